-- The initial schema: links, raw samples, raw and filtered target results, references,
-- calibrations and the persisted filter state.
--
-- Times are integer nanoseconds since the Unix epoch (UTC). Lengths are millimetres; rotations
-- are unit quaternions (w, x, y, z); sigmas are arc-seconds and millimetres; covariances are 36
-- little-endian f64 (column-major, [rho (mm); phi (rad)]) in a blob.

-- Links and targets get small integer ids so that the time-series tables stay narrow.
create table links (
    link_id integer primary key,
    name text not null unique,
    created_ns integer not null
);

create table targets (
    target_id integer primary key,
    name text not null unique,
    created_ns integer not null
);

-- Raw samples of measured links. One row per (link, time): a retry of the same sample is
-- recognised by its key and values, never stored twice.
create table samples (
    link_id integer not null references links (link_id),
    time_ns integer not null,
    tx_mm real not null,
    ty_mm real not null,
    tz_mm real not null,
    qw real not null,
    qx real not null,
    qy real not null,
    qz real not null,
    -- 0: the link's default sigmas; 1: per-axis sigmas (6 f64: rotation arcsec x y z,
    -- translation mm x y z); 2: a full covariance (36 f64).
    uncertainty_kind integer not null,
    uncertainty blob,
    reprojection_rms_px real,
    points integer,
    -- initialized | fused | outlier | reinitialized | out_of_order
    disposition text not null,
    outlier integer not null,
    nis real,
    received_ns integer not null,
    primary key (link_id, time_ns)
) without rowid;

-- Target results: raw (source 0, one per measurement group) and filtered (source 1).
create table results (
    target_id integer not null references targets (target_id),
    source integer not null,
    time_ns integer not null,
    tx_mm real not null,
    ty_mm real not null,
    tz_mm real not null,
    qw real not null,
    qx real not null,
    qy real not null,
    qz real not null,
    cov blob not null,
    sigma_rx_arcsec real not null,
    sigma_ry_arcsec real not null,
    sigma_rz_arcsec real not null,
    sigma_tx_mm real not null,
    sigma_ty_mm real not null,
    sigma_tz_mm real not null,
    -- ok | stale | degraded | initializing | predicted
    status text not null,
    age_s real not null,
    chi2 real,
    -- The deformation against the reference in force when the result was computed (null
    -- while the target has none): rotation vector (arcsec) and translation (mm).
    reference_version integer,
    def_rx_arcsec real,
    def_ry_arcsec real,
    def_rz_arcsec real,
    def_tx_mm real,
    def_ty_mm real,
    def_tz_mm real,
    primary key (target_id, source, time_ns)
) without rowid;

-- References (zero readings) of targets, versioned: results name the version they used.
create table target_references (
    target_id integer not null references targets (target_id),
    version integer not null,
    tx_mm real not null,
    ty_mm real not null,
    tz_mm real not null,
    qw real not null,
    qx real not null,
    qy real not null,
    qz real not null,
    cov blob not null,
    -- explicit | window
    origin text not null,
    window_from_ns integer,
    window_to_ns integer,
    window_count integer,
    created_ns integer not null,
    primary key (target_id, version)
) without rowid;

-- Calibrations of calibrated links, versioned, each valid from a time until a later one.
create table calibrations (
    link_id integer not null references links (link_id),
    version integer not null,
    valid_from_ns integer not null,
    tx_mm real not null,
    ty_mm real not null,
    tz_mm real not null,
    qw real not null,
    qx real not null,
    qy real not null,
    qz real not null,
    cov blob not null,
    created_ns integer not null,
    primary key (link_id, version)
) without rowid;

-- The filter bank's state after the last commit (one row), so that a restart continues
-- exactly where the service stopped.
create table filter_state (
    id integer primary key check (id = 1),
    installation_digest text not null,
    state text not null,
    updated_ns integer not null
);
