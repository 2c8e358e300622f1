-- Rollups of target results for history at any scale: per target, source and bucket width
-- (1 s, 10 s, 1 min, 10 min, 1 h), the count and, per component, min, sum and max, so a spike
-- survives any downsampling and a mean is sum / count. Maintained in the same transaction as
-- the results they summarise (the one writer merges them), and kept when old results are pruned.
--
-- `stats` holds, for each of the 18 components in order, min, sum and max as little-endian f64
-- (432 bytes): Euler angles of target_from_base x y z (degrees), its translation x y z (mm), the
-- deformation rotation vector x y z (arcsec) and translation x y z (mm) against the reference in
-- force (counted by n_def; absent ones are min +inf, max -inf), and the reported sigmas of
-- rotation x y z (arcsec) and translation x y z (mm). One blob rather than 54 columns: a history
-- query reads thousands of buckets, and per-column decoding would dominate it.
create table rollups (
    target_id integer not null references targets (target_id),
    source integer not null,
    width_s integer not null,
    bucket_ns integer not null,
    n integer not null,
    n_def integer not null,
    stats blob not null,
    primary key (target_id, source, width_s, bucket_ns)
) without rowid;
