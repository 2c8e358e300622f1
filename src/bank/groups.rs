//! Measurement groups: the samples of one instant within the group tolerance, each brought to
//! the group's time by its link's filter, composed along each target's paths into raw results.

use super::*;

/// The samples of one instant, within the group tolerance: each link's measurement and its own
/// exposure time.
#[derive(Debug, Clone, Default)]
pub(super) struct Group {
    pub(super) samples: HashMap<LinkId, (i64, PoseCov)>,
    pub(super) emitted: Vec<bool>,
}

impl FilterBank {
    /// How far apart (ns) the exposures of one measurement group may be.
    pub fn group_tolerance_ns(&self) -> i64 {
        self.group_tolerance_ns
    }

    /// Adds a sample to its measurement group and returns the raw results it completes, or
    /// `None` when the sample is older than every group kept in memory.
    ///
    /// A sample joins the group nearest its time within the group tolerance that has no sample
    /// of its link yet, else starts one at its own time: the group's time is its first
    /// sample's. Each sample is brought to the group's time by its link's filter (see
    /// [`Self::at_group_time`]) when the group is composed.
    pub(super) fn add_to_group(
        &mut self,
        link: LinkId,
        time_ns: i64,
        z: PoseCov,
    ) -> Option<Vec<(RawResult, SourcedPose)>> {
        let n_targets = self.model.targets.len();
        let tolerance = self.group_tolerance_ns;
        let oldest_kept = self.groups.keys().next().copied();
        if self.groups.len() >= self.settings.group_window
            && oldest_kept.is_some_and(|o| time_ns < o.saturating_sub(tolerance))
        {
            // Older than every group still assembled: only the store can complete it.
            return None;
        }
        let key = self
            .groups
            .range(time_ns.saturating_sub(tolerance)..=time_ns.saturating_add(tolerance))
            .filter(|(_, g)| !g.samples.contains_key(&link))
            .min_by_key(|(k, _)| (**k - time_ns).unsigned_abs())
            .map_or(time_ns, |(k, _)| *k);
        let group = self.groups.entry(key).or_insert_with(|| Group {
            samples: HashMap::new(),
            emitted: vec![false; n_targets],
        });
        group.samples.insert(link, (time_ns, z));
        let group = &self.groups[&key];
        // Most samples leave their group incomplete: compose only when a target of the link
        // has a sample of every measured link on its paths.
        let completes = self.targets_of_link[link.0].iter().any(|t| {
            !group.emitted[t.0]
                && self.model.targets[t.0].resolution.paths.iter().all(|p| {
                    p.links()
                        .all(|l| self.measured[l.0].is_none() || group.samples.contains_key(&l))
                })
        });
        let out = if completes {
            let samples = self.at_group_time(key, &group.samples);
            self.compose_group(link, key, &samples, &group.emitted)
        } else {
            Vec::new()
        };
        if let Some(g) = self.groups.get_mut(&key) {
            for (r, _) in &out {
                g.emitted[r.target.0] = true;
            }
        }
        while self.groups.len() > self.settings.group_window {
            if let Some((_, gone)) = self.groups.pop_first() {
                self.count_ungrouped(&gone);
            }
        }
        Some(out)
    }

    /// Counts, for each sample of a group leaving memory, whether the group completed nothing
    /// its link serves.
    pub(super) fn count_ungrouped(&mut self, group: &Group) {
        for l in group.samples.keys() {
            self.status[l.0].n_grouped_closed += 1;
            if !self.targets_of_link[l.0]
                .iter()
                .any(|t| group.emitted.get(t.0).copied().unwrap_or(false))
            {
                self.status[l.0].n_ungrouped += 1;
            }
        }
    }

    /// The samples of a group brought to the group's time `group_ns`: a sample exposed at
    /// another time is moved by its link's motion between the two times as the link's filter
    /// predicts it from its state before both, its covariance widened by what the prediction
    /// adds over that interval (per axis), so that a raw result composes one instant.
    /// Without a filter state before both times (a link's first samples) a sample is taken as
    /// it is.
    pub(super) fn at_group_time(
        &self,
        group_ns: i64,
        samples: &HashMap<LinkId, (i64, PoseCov)>,
    ) -> HashMap<LinkId, PoseCov> {
        samples
            .iter()
            .map(|(&l, &(t, z))| (l, self.moved(l, t, group_ns, z)))
            .collect()
    }

    /// Sample `z` of link `l` exposed at `from_ns`, moved to `to_ns` (see
    /// [`Self::at_group_time`]).
    pub(super) fn moved(&self, l: LinkId, from_ns: i64, to_ns: i64, z: PoseCov) -> PoseCov {
        if from_ns == to_ns {
            return z;
        }
        let Some(slot) = self.measured.get(l.0).and_then(Option::as_ref) else {
            return z;
        };
        let state = state_at(&slot.filter, &slot.history, from_ns.min(to_ns));
        let predicted = |t: i64| state.and_then(|f| f.predict(t)).and_then(Result::ok);
        let (Some(at_from), Some(at_to)) = (predicted(from_ns), predicted(to_ns)) else {
            return z;
        };
        let delta = at_to.pose * at_from.pose.inverse();
        let (earlier, later) = if from_ns < to_ns {
            (&at_from.cov, &at_to.cov)
        } else {
            (&at_to.cov, &at_from.cov)
        };
        let added = Mat6::from_diagonal(&(later - earlier).diagonal().map(|v| v.max(0.0)));
        let ad = adjoint(&delta);
        PoseCov {
            pose: delta * z.pose,
            cov: ad * z.cov * ad.transpose() + added,
        }
    }

    /// The raw results of a measurement group at `time_ns` given all its samples (`samples`:
    /// each link's measurement, as [`Self::measurement`] makes it, with its own exposure time
    /// within the group tolerance), for the targets on `link`'s paths that the group
    /// completes. For groups too old for memory ([`SampleOutcome::needs_stored_group`]): the
    /// caller reads the other links' samples of that instant from the store.
    pub fn raw_results_of_group(
        &self,
        link: LinkId,
        time_ns: i64,
        samples: &HashMap<LinkId, (i64, PoseCov)>,
    ) -> Vec<RawResult> {
        let none = vec![false; self.model.targets.len()];
        let moved = self.at_group_time(time_ns, samples);
        self.compose_group(link, time_ns, &moved, &none)
            .into_iter()
            .map(|(r, _)| r)
            .collect()
    }

    /// A link's pose with its error terms: a calibrated link's calibration in force at
    /// `time_ns` (its covariance systematic), or a measured link's `measured` pose (a sample or
    /// a filtered estimate; its covariance the link's noise) with its camera's intrinsics
    /// error. `None` for a measured link without `measured`.
    pub(super) fn sourced_link(
        &self,
        link: LinkId,
        time_ns: i64,
        measured: Option<&PoseCov>,
    ) -> Option<SourcedPose> {
        if let Some(c) = self.calibration_entry_at(link, time_ns) {
            return Some(SourcedPose {
                pose: c.parent_from_child.pose,
                terms: ErrorTerms::of(Contributor::Calibration(link), c.factor),
            });
        }
        let z = measured?;
        let mut terms = ErrorTerms::of(Contributor::Noise(link), factor_of_covariance(&z.cov));
        if let Some((_, camera, f)) = self
            .measured
            .get(link.0)
            .and_then(Option::as_ref)
            .and_then(|s| s.intrinsics.as_ref())
        {
            terms.add(Contributor::Intrinsics(*camera), *f);
        }
        Some(SourcedPose {
            pose: z.pose,
            terms,
        })
    }

    /// Composes, for each target on `link`'s paths not yet `emitted`, the raw result of a
    /// group whose every path is complete in `samples`.
    pub(super) fn compose_group(
        &self,
        link: LinkId,
        time_ns: i64,
        samples: &HashMap<LinkId, PoseCov>,
        emitted: &[bool],
    ) -> Vec<(RawResult, SourcedPose)> {
        let mut out = Vec::new();
        for &ti in &self.targets_of_link[link.0] {
            if emitted[ti.0] {
                continue;
            }
            let target = &self.model.targets[ti.0];
            let mut estimates = Vec::new();
            let mut complete = true;
            for path in &target.resolution.paths {
                let mut missing = false;
                let composed = compose_path_terms(path, |l| {
                    self.sourced_link(l, time_ns, samples.get(&l))
                        .unwrap_or_else(|| {
                            missing = true;
                            SourcedPose::identity()
                        })
                });
                if missing {
                    complete = false;
                    break;
                }
                estimates.push(composed);
            }
            if !complete {
                continue;
            }
            if let Ok((sourced, f)) = fuse_terms(estimates, self.settings.consistency_probability) {
                let (random, systematic) = sourced.terms.parts();
                out.push((
                    RawResult {
                        target: ti,
                        time_ns,
                        target_from_base: MeasuredPose {
                            whole: PoseCov {
                                pose: sourced.pose,
                                cov: random + systematic,
                            },
                            systematic_cov: systematic,
                            calibration: Some(self.calibration_stamp(ti, time_ns)),
                        },
                        consistency: f.consistency,
                    },
                    sourced,
                ));
            }
        }
        out
    }
}
