-- Manual restarts of measured links' filters (`POST /api/v1/links/{name}/reset`): the filter
-- starts again from the link's next sample, for recovery from a bad time or a moved station.
create table link_resets (
    link_id integer not null references links (link_id),
    created_ns integer not null,
    -- who asked, and why (optional)
    by_name text,
    note text,
    primary key (link_id, created_ns)
) without rowid;
