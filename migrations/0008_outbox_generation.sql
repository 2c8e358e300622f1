-- Outbox generations. A site's database replaced by an older copy of itself (a restore from
-- `brokenray backup`) would number its next commits as the original did after the copy was
-- taken, numbers the centre already holds under other rows. A copy therefore starts a new
-- generation of the outbox: a stream of its own at the centre, which begins where the copy's
-- acknowledged numbers say and never confuses the two lives' numbers.
--
-- `generation` names the current generation (random); `lineage` lists the generations it
-- descends from, the nearest first, separated by commas (empty for the first one). The first
-- generation of an existing file is named by its outbox id.

alter table outbox add column generation text not null default '';
alter table outbox add column lineage text not null default '';
update outbox set generation = outbox_id;
