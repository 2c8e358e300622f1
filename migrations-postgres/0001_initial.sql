-- The brokenray schema on PostgreSQL: the same tables, keys and conflict rules as the SQLite
-- schema (`migrations/`), in PostgreSQL's own types. Times are integer nanoseconds since the
-- Unix epoch (UTC), lengths millimetres, rotations unit quaternions, covariances 36
-- little-endian f64 (column-major) in a bytea.
--
-- Samples, results and rollups are partitioned by time (declarative range partitions of one
-- day, kept by pg_partman; rows outside the made partitions go to a default partition until
-- maintenance moves them), so retention drops whole days instead of deleting rows. The primary
-- keys (B-tree, time last) serve every query: each reads one link or target over a time range.
-- The partitioned tables carry no foreign keys: checking one per inserted row took about half
-- of an ingest commit (measured), and only the store writes their link and target ids, which
-- it reads from `links` and `targets` at start-up.
--
-- pg_partman is created here when the role may (a superuser, or a database owner once an
-- administrator has run `create extension pg_partman schema partman`).

create schema if not exists partman;
create extension if not exists pg_partman schema partman;

create table links (
    link_id bigint generated always as identity primary key,
    name text not null unique,
    created_ns bigint not null
);

create table targets (
    target_id bigint generated always as identity primary key,
    name text not null unique,
    created_ns bigint not null
);

create table samples (
    link_id bigint not null,
    time_ns bigint not null,
    tx_mm double precision not null,
    ty_mm double precision not null,
    tz_mm double precision not null,
    qw double precision not null,
    qx double precision not null,
    qy double precision not null,
    qz double precision not null,
    -- 0: the link's default sigmas; 1: per-axis sigmas (6 f64: rotation arcsec x y z,
    -- translation mm x y z); 2: a full covariance (36 f64).
    uncertainty_kind bigint not null check (uncertainty_kind in (0, 1, 2)),
    uncertainty bytea,
    reprojection_rms_px double precision,
    points bigint,
    disposition text not null
        check (disposition in ('initialized', 'fused', 'outlier', 'reinitialized', 'out_of_order')),
    outlier boolean not null,
    nis double precision,
    received_ns bigint not null,
    primary key (link_id, time_ns)
) partition by range (time_ns);

create table results (
    target_id bigint not null,
    -- 0: raw, 1: filtered
    source bigint not null check (source in (0, 1)),
    time_ns bigint not null,
    tx_mm double precision not null,
    ty_mm double precision not null,
    tz_mm double precision not null,
    qw double precision not null,
    qx double precision not null,
    qy double precision not null,
    qz double precision not null,
    cov bytea not null,
    sigma_rx_arcsec double precision not null,
    sigma_ry_arcsec double precision not null,
    sigma_rz_arcsec double precision not null,
    sigma_tx_mm double precision not null,
    sigma_ty_mm double precision not null,
    sigma_tz_mm double precision not null,
    status text not null,
    age_s double precision not null,
    chi2 double precision,
    -- The deformation against the reference in force when the result was computed (null
    -- while the target has none): rotation vector (arcsec) and translation (mm).
    reference_version bigint,
    def_rx_arcsec double precision,
    def_ry_arcsec double precision,
    def_rz_arcsec double precision,
    def_tx_mm double precision,
    def_ty_mm double precision,
    def_tz_mm double precision,
    primary key (target_id, source, time_ns)
) partition by range (time_ns);

-- Per bucket of each width: count, count with a deformation, and min, sum, max of every
-- component (432 bytes).
create table rollups (
    target_id bigint not null,
    source bigint not null check (source in (0, 1)),
    width_s bigint not null,
    bucket_ns bigint not null,
    n bigint not null,
    n_def bigint not null,
    stats bytea not null,
    primary key (target_id, source, width_s, bucket_ns)
) partition by range (bucket_ns);

create table target_references (
    target_id bigint not null references targets (target_id),
    version bigint not null,
    tx_mm double precision not null,
    ty_mm double precision not null,
    tz_mm double precision not null,
    qw double precision not null,
    qx double precision not null,
    qy double precision not null,
    qz double precision not null,
    cov bytea not null,
    origin text not null check (origin in ('explicit', 'window')),
    window_from_ns bigint,
    window_to_ns bigint,
    window_count bigint,
    created_ns bigint not null,
    primary key (target_id, version)
);

create table calibrations (
    link_id bigint not null references links (link_id),
    version bigint not null,
    valid_from_ns bigint not null,
    tx_mm double precision not null,
    ty_mm double precision not null,
    tz_mm double precision not null,
    qw double precision not null,
    qx double precision not null,
    qy double precision not null,
    qz double precision not null,
    cov bytea not null,
    created_ns bigint not null,
    primary key (link_id, version)
);

create table filter_state (
    id bigint primary key check (id = 1),
    installation_digest text not null,
    state text not null,
    updated_ns bigint not null
);

create table alarms (
    alarm_id bigint generated always as identity primary key,
    target_id bigint not null references targets (target_id),
    time_ns bigint not null,
    kind text not null check (kind in ('deformation', 'rate', 'stale')),
    from_level text not null check (from_level in ('none', 'warn', 'alarm')),
    to_level text not null check (to_level in ('none', 'warn', 'alarm')),
    -- the deciding value, in `unit`
    value double precision not null,
    message text not null,
    created_ns bigint not null,
    unit text,
    -- the acknowledgement: all three null until one is given
    acknowledged_by text,
    acknowledged_ns bigint,
    ack_note text,
    unique (target_id, time_ns, kind)
);
create index alarms_by_time on alarms (time_ns);

create table link_resets (
    link_id bigint not null references links (link_id),
    created_ns bigint not null,
    by_name text,
    note text,
    primary key (link_id, created_ns)
);

-- Day partitions (86 400 s in ns) from today, 30 days made ahead; maintenance (at start-up and
-- with each retention pass) makes the next ones and moves stray rows out of the default.
select partman.create_parent(
    p_parent_table => format('%I.%s', current_schema(), t),
    p_control => c,
    p_type => 'native',
    p_interval => '86400000000000',
    p_premake => 30,
    p_start_partition => ((extract(epoch from now())::bigint / 86400) * 86400000000000)::text,
    p_jobmon => false
)
from (values ('samples', 'time_ns'), ('results', 'time_ns'), ('rollups', 'bucket_ns')) as p (t, c);
