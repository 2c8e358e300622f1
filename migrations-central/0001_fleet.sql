-- The centre's record of its fleet, in the schema `fleet`. Each site's rows live in a schema of
-- their own (`site_<site_id>`, the tables of `migrations-postgres/`); these tables say which
-- sites exist, which outbox each one uploads from, and how far each tier of each site has
-- been applied.

create table sites (
    site text primary key,
    -- names the site's schema: `site_<site_id>`
    site_id bigint generated always as identity unique,
    -- the site's outbox (random, made with its file): uploads from another are refused
    outbox_id text not null,
    first_contact_ns bigint not null,
    last_contact_ns bigint not null,
    -- the site's last report of its state and backlog (JSON, as the site sent it)
    status text,
    backlog text
);

create table streams (
    site text not null references sites (site),
    -- events | results | raw
    tier text not null check (tier in ('events', 'results', 'raw')),
    -- every row of the site's commits up to this number has been applied
    acked_seq bigint not null,
    rows_applied bigint not null default 0,
    bytes_received bigint not null default 0,
    batches_applied bigint not null default 0,
    updated_ns bigint not null,
    primary key (site, tier)
);
