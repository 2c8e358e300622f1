-- The outbox of a site in a fleet. Every write transaction gets the next commit sequence number
-- (`commits`), and every row a transaction writes carries it (`commit_seq`): a row that changes
-- later (a result recomputed, a rollup merged, an alarm acknowledged) carries the later
-- number. What the centre has acknowledged is one number per tier (`upstream_acks`): every
-- row with a `commit_seq` above it is still to send, in its current version.
--
-- Rows from before this migration get negative numbers, one per minute of their time, in time
-- order, so that a site that starts pushing sends its whole history in batches of bounded size.

create table commits (
    seq integer primary key,
    -- the server's clock when the transaction began
    created_ns integer not null
);

-- What the centre has acknowledged, per tier (events | results | raw).
create table upstream_acks (
    tier text primary key,
    acked_seq integer not null,
    updated_ns integer not null
);

-- The outbox's identity: the centre refuses uploads of another outbox under the same site
-- name (a replaced or re-created file would restart its numbers).
create table outbox (
    id integer primary key check (id = 1),
    outbox_id text not null
);
insert into outbox (id, outbox_id) values (1, lower(hex(randomblob(16))));

alter table samples add column commit_seq integer not null default 0;
alter table results add column commit_seq integer not null default 0;
alter table rollups add column commit_seq integer not null default 0;
alter table alarms add column commit_seq integer not null default 0;
alter table target_references add column commit_seq integer not null default 0;
alter table calibrations add column commit_seq integer not null default 0;
alter table link_resets add column commit_seq integer not null default 0;

update samples set commit_seq = time_ns / 60000000000 - 1000000000;
update results set commit_seq = time_ns / 60000000000 - 1000000000;
update rollups set commit_seq = bucket_ns / 60000000000 - 1000000000;
update alarms set commit_seq = time_ns / 60000000000 - 1000000000;
update target_references set commit_seq = created_ns / 60000000000 - 1000000000;
update calibrations set commit_seq = created_ns / 60000000000 - 1000000000;
update link_resets set commit_seq = created_ns / 60000000000 - 1000000000;

-- The uploader reads each table in commit order from the last acknowledged number.
create index samples_by_commit on samples (commit_seq);
create index results_by_commit on results (source, commit_seq);
create index rollups_by_commit on rollups (commit_seq);
create index alarms_by_commit on alarms (commit_seq);
create index target_references_by_commit on target_references (commit_seq);
create index calibrations_by_commit on calibrations (commit_seq);
create index link_resets_by_commit on link_resets (commit_seq);
