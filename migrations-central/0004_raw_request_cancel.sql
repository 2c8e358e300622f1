-- A raw request the office no longer wants: cancelled (who, when). A cancelled request is
-- done: no site delivers it any more.
alter table raw_requests add column cancelled_by text;
alter table raw_requests add column cancelled_ns bigint;
