-- Alarm transitions of targets: deformation (warn / alarm with hysteresis and dwell), rate of
-- change, and stale data. One row per change of level, in measurement time.
create table alarms (
    target_id integer not null references targets (target_id),
    time_ns integer not null,
    -- deformation | rate | stale
    kind text not null,
    -- none | warn | alarm
    from_level text not null,
    to_level text not null,
    -- arc-seconds (deformation), arc-seconds per second (rate), 0 (stale)
    value real not null,
    message text not null,
    created_ns integer not null,
    primary key (target_id, time_ns, kind)
) without rowid;

create index alarms_by_time on alarms (time_ns);
