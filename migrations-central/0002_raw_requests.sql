-- Raw samples of a period, asked of a site by the office. A site whose raw tier is not
-- streamed (or is behind) uploads the samples and raw results measured in `[from_ns, to_ns)`
-- in slices of measurement time, in order; `delivered_to_ns` is how far they arrived.

create table raw_requests (
    request_id bigint generated always as identity primary key,
    site text not null references sites (site),
    from_ns bigint not null,
    to_ns bigint not null check (to_ns > from_ns),
    -- every raw row measured before this time (from `from_ns`) has been applied
    delivered_to_ns bigint not null,
    rows_applied bigint not null default 0,
    requested_by text,
    created_ns bigint not null,
    done_ns bigint
);

create index raw_requests_pending on raw_requests (site) where done_ns is null;
