-- The systematic part of a result's covariance (cameras' intrinsics and calibrations: the same
-- error in every result of that geometry), 36 little-endian f64 column-major like `cov`; the
-- random part is `cov` minus it. Null in rows written before it was kept: read as zero.
-- `calibration_stamp`: the calibrations the result (or the reference's window) was measured
-- with, as one number; the systematic part cancels in a deformation whose reference has the
-- same. Null in older rows: not known (the parts add). Added to the partitioned parent, the
-- columns reach every partition.
alter table results add column cov_systematic bytea;
alter table results add column calibration_stamp bigint;
alter table target_references add column cov_systematic bytea;
alter table target_references add column calibration_stamp bigint;
