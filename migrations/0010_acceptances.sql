-- Acceptances of the rig (`brokenray acceptance`, `/api/v1/acceptance`): who ran one, when
-- (ns, the server's clock), whether it passed, and its whole record as JSON (the steps'
-- windows and figures, the limits, the calibrations each target was measured with). Kept on
-- the site: a centre does not receive them.
create table acceptances (
    acceptance_id integer primary key,
    created_ns integer not null,
    by_name text not null,
    note text,
    passed integer not null,
    record text not null
);
