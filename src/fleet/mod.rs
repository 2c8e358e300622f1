//! A fleet: sites that push their history to a centre, store-and-forward, exactly once.
//!
//! A site (`[site] name`, `[upstream] url`) keeps working alone; its SQLite file is its outbox
//! (see [`crate::store::outbox`]): every commit numbered, every row marked with the commit that
//! last wrote it, and per tier the number the centre acknowledged. The [`uploader`] pushes the
//! tiers in priority order (events, then results, then raw samples under a bandwidth budget),
//! compressed with zstd; retention at the site never prunes what the centre has not
//! acknowledged. The centre (`[central] enabled`, on PostgreSQL) applies each upload in one
//! transaction exactly once ([`crate::store::Central`]) and serves the fleet
//! (`GET /api/v1/sites`). The wire format is in [`protocol`], what a centre checks of an upload in [`checks`].

pub mod checks;
pub mod protocol;
pub mod upkeep;
pub mod uploader;

pub use uploader::{TierProgress, Upstream};
