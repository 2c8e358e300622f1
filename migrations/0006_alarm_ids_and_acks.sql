-- Alarm transitions get an id (for `POST /api/v1/alarms/{id}/ack`) and an acknowledgement:
-- who, when (server clock), and a note. The table is rebuilt with an integer primary key; the
-- old key stays unique. Existing rows keep their values and get ids in time order.
create table alarms_with_ids (
    alarm_id integer primary key,
    target_id integer not null references targets (target_id),
    time_ns integer not null,
    -- deformation | rate | stale
    kind text not null,
    -- none | warn | alarm
    from_level text not null,
    to_level text not null,
    -- the deciding value, in `unit`
    value real not null,
    message text not null,
    created_ns integer not null,
    -- arcsec | mm | arcsec_per_s | mm_per_s | s | none; null in rows from before units
    unit text,
    -- the acknowledgement: all three null until one is given
    acknowledged_by text,
    acknowledged_ns integer,
    ack_note text,
    unique (target_id, time_ns, kind)
);

insert into alarms_with_ids
    (target_id, time_ns, kind, from_level, to_level, value, message, created_ns, unit)
select target_id, time_ns, kind, from_level, to_level, value, message, created_ns, unit
from alarms
order by time_ns, target_id, kind;

drop table alarms;
alter table alarms_with_ids rename to alarms;
create index alarms_by_time on alarms (time_ns);
