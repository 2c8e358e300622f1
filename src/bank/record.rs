//! The bank's state as plain records, saved with every commit and restored at start.

use super::*;

/// The bank's state as plain records, for persistence.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BankRecord {
    /// Per measured link, by name: its filter state.
    pub filters: Vec<(String, LinkFilterRecord)>,
    /// Per link, by name: sample, outlier and restart counts and the newest sample time.
    pub counters: Vec<(String, u64, u64, u64, Option<i64>)>,
    /// Per target, by name: the time of the newest filtered result.
    pub frontiers: Vec<(String, i64)>,
    /// Per target, by name: its own filter's state.
    #[serde(default)]
    pub targets: Vec<(String, LinkFilterRecord)>,
}

impl FilterBank {
    /// The bank's state as plain records (filters, counters, frontiers), for persistence.
    pub fn record(&self) -> BankRecord {
        let links = &self.model.links;
        BankRecord {
            filters: self
                .measured
                .iter()
                .enumerate()
                .filter_map(|(i, s)| {
                    s.as_ref()
                        .and_then(|s| s.filter.record())
                        .map(|r| (links[i].name.clone(), r))
                })
                .collect(),
            counters: self
                .status
                .iter()
                .enumerate()
                .filter(|(_, s)| s.n_samples > 0)
                .map(|(i, s)| {
                    (
                        links[i].name.clone(),
                        s.n_samples,
                        s.n_outliers,
                        s.n_reinitializations,
                        s.last_time_ns,
                    )
                })
                .collect(),
            frontiers: self
                .frontier_ns
                .iter()
                .enumerate()
                .filter_map(|(i, f)| f.map(|f| (self.model.targets[i].name.clone(), f)))
                .collect(),
            targets: self
                .tracks
                .iter()
                .enumerate()
                .filter_map(|(i, t)| {
                    t.filter
                        .record()
                        .map(|r| (self.model.targets[i].name.clone(), r))
                })
                .collect(),
        }
    }

    /// Restores a recorded state into this (fresh) bank. Entries for links or targets the
    /// installation no longer has, or whose model changed, are skipped and listed in the answer.
    pub fn restore(&mut self, record: &BankRecord) -> Vec<String> {
        let mut skipped = Vec::new();
        for (name, r) in &record.filters {
            let Some(id) = self.model.topology.link_id(name) else {
                skipped.push(format!("link `{name}` is no longer in the installation"));
                continue;
            };
            let Some(slot) = self.measured[id.0].as_mut() else {
                skipped.push(format!("link `{name}` is no longer measured"));
                continue;
            };
            match LinkFilter::restore(*slot.filter.tuning(), r) {
                Ok(f) => {
                    slot.history.clear();
                    slot.history.push_back(f.clone());
                    slot.filter = f;
                }
                Err(e) => skipped.push(format!("link `{name}`: {e}")),
            }
        }
        for (name, n, o, re, last) in &record.counters {
            if let Some(id) = self.model.topology.link_id(name) {
                self.status[id.0] = LinkStatus {
                    n_samples: *n,
                    n_outliers: *o,
                    n_reinitializations: *re,
                    last_time_ns: *last,
                    // Counted since start: groups are not kept across restarts.
                    ..LinkStatus::default()
                };
            }
        }
        for (name, f) in &record.frontiers {
            if let Some(i) = self.model.targets.iter().position(|t| &t.name == name) {
                self.frontier_ns[i] = Some(*f);
            }
        }
        for (name, r) in &record.targets {
            let Some(ti) = self.model.target_id(name) else {
                skipped.push(format!("target `{name}` is no longer in the installation"));
                continue;
            };
            let track = &mut self.tracks[ti.0];
            match LinkFilter::restore(track.base_tuning, r) {
                Ok(f) => {
                    track.history.clear();
                    track.history.push_back(f.clone());
                    track.filter = f;
                }
                Err(e) => skipped.push(format!("target `{name}`: {e}")),
            }
        }
        skipped
    }

    /// Returns every filter, counter and frontier to a recorded state (the last commit), as if
    /// nothing since had happened. Calibrations are kept. Returns what could not be restored.
    pub fn rollback(&mut self, record: &BankRecord) -> Vec<String> {
        for slot in self.measured.iter_mut().flatten() {
            slot.filter = LinkFilter::new(*slot.filter.tuning());
            slot.history.clear();
            slot.recent_times.clear();
        }
        for s in &mut self.status {
            *s = LinkStatus::default();
        }
        self.frontier_ns.iter_mut().for_each(|f| *f = None);
        self.tracks.iter_mut().for_each(TargetTrack::reset);
        self.groups.clear();
        self.restore(record)
    }
}
