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

use crate::config::CentralSettings;
use crate::store::Central;
use std::sync::{Arc, Mutex};

/// Uploads a centre reads at once (decompressed, parsed and applied): each may take up to
/// `[central] max_sync_mb` of memory, so a burst of them cannot take the host's.
pub const SYNC_SLOTS: usize = 2;

/// A centre's side of the fleet: its record of the sites, its settings, the uploads it reads
/// at once and what its last upkeep found.
#[derive(Debug)]
pub struct Centre {
    /// The record of the sites (PostgreSQL).
    pub store: Central,
    /// `[central]`.
    pub settings: CentralSettings,
    /// Uploads read and applied at once ([`SYNC_SLOTS`]).
    pub sync_slots: Arc<tokio::sync::Semaphore>,
    /// Why the last upkeep failed, for some site or for all; `None` when it went through.
    upkeep_problem: Mutex<Option<String>>,
}

impl Centre {
    /// A centre over its record of the sites.
    pub fn new(store: Central, settings: CentralSettings) -> Self {
        Self {
            store,
            settings,
            sync_slots: Arc::new(tokio::sync::Semaphore::new(SYNC_SLOTS)),
            upkeep_problem: Mutex::new(None),
        }
    }

    /// Why the last upkeep failed (`/healthz` `centre_problem`), if it did.
    pub fn upkeep_problem(&self) -> Option<String> {
        self.upkeep_problem
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    fn set_upkeep_problem(&self, problem: Option<String>) {
        *self
            .upkeep_problem
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = problem;
    }
}
