-- Generations of a site's outbox. A site's database restored from a copy numbers its next
-- commits as the original did after the copy was taken; the copy therefore uploads in a
-- generation of its own, and the centre keeps a stream per generation. `head_seq` is the newest
-- commit the generation has reported: it never goes back (a file restored without starting a
-- generation would), and no batch goes past it.

create table generations (
    site text not null references sites (site),
    generation text not null,
    -- the generation it descends from (null: the site's first)
    parent text,
    head_seq bigint,
    first_contact_ns bigint not null,
    last_contact_ns bigint not null,
    primary key (site, generation)
);

insert into generations (site, generation, parent, head_seq, first_contact_ns, last_contact_ns)
select site, outbox_id, null, null, first_contact_ns, last_contact_ns from sites;

-- The generation whose uploads the centre received last (what `GET /api/v1/sites` shows).
alter table sites add column generation text;
update sites set generation = outbox_id;

alter table streams add column generation text;
update streams set generation = (select outbox_id from sites where sites.site = streams.site);
alter table streams alter column generation set not null;
alter table streams drop constraint streams_pkey;
alter table streams add primary key (site, generation, tier);
alter table streams add foreign key (site, generation) references generations (site, generation);
