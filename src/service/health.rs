//! What `/healthz` says of the measurement beside the database and the writer: links whose
//! samples make no measurement group, targets whose filter no longer fits its data, and each
//! target's status and age now on the server's clock. Sentences for people; the HTTP layer
//! only places them.

use super::{Service, TargetNow};
use crate::model::TargetId;

impl Service {
    /// Measured links most of whose samples never made a measurement group with the other
    /// links of their targets, each named with its counts and what to do; none when every
    /// link groups.
    pub fn grouping_problem(&self) -> Option<String> {
        let snapshot = self.snapshot();
        let tolerance_ms = snapshot.bank.group_tolerance_ns() as f64 / 1e6;
        let problems: Vec<String> = (self.installation().model.links.iter())
            .filter_map(|l| {
                let (ungrouped, closed) = snapshot.bank.link_status(l.id).grouping_problem()?;
                Some(format!(
                    "link `{}`: {ungrouped} of its {closed} samples since the start made no \
                     measurement group (exposures more than {tolerance_ms:.1} ms from the other \
                     links'; set [filter] group_tolerance_ms or synchronise the cameras)",
                    l.name,
                ))
            })
            .collect();
        (!problems.is_empty()).then(|| problems.join("; "))
    }

    /// Targets whose filter no longer fits its data (the mean normalised innovation of its
    /// recent results outside the band a fitting filter stays in), each named with its
    /// figures; none when every judged filter fits.
    pub fn filter_problem(&self) -> Option<String> {
        let snapshot = self.snapshot();
        let problems: Vec<String> = (self.installation().model.target_ids())
            .filter_map(|(ti, t)| {
                let tuning = snapshot.bank.target_tuning(ti)?;
                let c = tuning.consistency;
                (c.samples >= crate::bank::CONSISTENCY_JUDGED_FROM && !c.fits()).then(|| {
                    format!(
                        "target `{}`: mean normalised innovation {:.1} over its last {} \
                         results, outside the {:.1} to {:.1} a filter that fits its data stays \
                         in (model `{}`)",
                        t.name,
                        c.mean_nis,
                        c.samples,
                        c.band.0,
                        c.band.1,
                        tuning.tuning.model.name()
                    )
                })
            })
            .collect();
        (!problems.is_empty()).then(|| problems.join("; "))
    }

    /// Each target, by name in installation order, with its status and age now on the
    /// server's clock.
    pub fn targets_now(&self) -> Vec<(String, TargetNow)> {
        let snapshot = self.snapshot();
        let now_ns = self.now_ns();
        let inst = self.installation();
        (inst.model.targets.iter().enumerate())
            .map(|(i, t)| {
                let now = snapshot.target_now(TargetId(i), now_ns, inst.server.clock_tolerance_s);
                (t.name.clone(), now)
            })
            .collect()
    }
}
