-- When the site made the commit a stream is acknowledged up to (the site's clock, ns), as the
-- batch that brought it said. With the number it names the commit: a site whose database was
-- replaced by an older copy reuses numbers for other commits, and tells from this stamp that
-- the centre's acknowledgement is not of its own commit. Null: not known (an earlier version's
-- batch).
alter table streams add column acked_stamp_ns bigint;
