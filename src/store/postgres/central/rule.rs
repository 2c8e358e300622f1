//! The centre's exactly-once rule, as pure functions of what it holds: whether an upload from a
//! generation of a site's outbox may go on, what a tier's batch does (nothing, a gap, or applied
//! and acknowledged to which commit), and the same for a slice of a period the centre asked
//! for. The SQL module reads what they need, in the upload's transaction, and does what they
//! say; their tests need no database.

use super::SyncOutcome;

/// What the centre holds of the generation an upload comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum GenerationHeld<'a> {
    /// Known to the centre.
    Known {
        /// The newest commit a batch of it proved (`None`: none yet).
        head_seq: Option<i64>,
        /// A generation that descends from it and has uploaded, if one has.
        child: Option<String>,
    },
    /// New to the centre, which knows these generations of the site.
    New {
        /// Every generation of the site the centre knows.
        known: &'a [String],
    },
}

/// What the rule says of an upload's generation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum GenerationRuling<'a> {
    /// A known generation: go on.
    GoOn,
    /// A new generation: registered under `parent`, the nearest of its lineage the centre
    /// knows (`None`: the site's first), then go on.
    Register {
        /// Its parent.
        parent: Option<&'a str>,
    },
    /// Refused; nothing of the upload is applied.
    Refused(SyncOutcome),
}

/// The rule on an upload from `generation` (descending from `lineage`, the nearest first) whose
/// site's newest commit is `head_seq`:
/// * a generation a later one descends from is superseded (the site's database was replaced
///   by a copy, and the old one still uploads beside it);
/// * a known generation's newest commit never goes back (an older copy that did not start a
///   generation of its own);
/// * a new generation descends from one the centre knows, unless it knows none of the site.
pub(super) fn rule_generation<'a>(
    generation: &str,
    lineage: &'a [String],
    head_seq: Option<i64>,
    held: GenerationHeld<'_>,
) -> GenerationRuling<'a> {
    match held {
        GenerationHeld::Known {
            head_seq: known_head_seq,
            child,
        } => {
            if let Some(by) = child {
                return GenerationRuling::Refused(SyncOutcome::GenerationSuperseded {
                    generation: generation.to_owned(),
                    by,
                });
            }
            match (head_seq, known_head_seq) {
                (Some(head_seq), Some(known_head_seq)) if head_seq < known_head_seq => {
                    GenerationRuling::Refused(SyncOutcome::CommitsWentBack {
                        generation: generation.to_owned(),
                        head_seq,
                        known_head_seq,
                    })
                }
                _ => GenerationRuling::GoOn,
            }
        }
        GenerationHeld::New { known } => {
            let parent = lineage.iter().find(|g| known.contains(g));
            if parent.is_none() && !known.is_empty() {
                return GenerationRuling::Refused(SyncOutcome::GenerationUnknown {
                    generation: generation.to_owned(),
                });
            }
            GenerationRuling::Register {
                parent: parent.map(String::as_str),
            }
        }
    }
}

/// A tier's acknowledgement: its last applied commit and when the site made it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Acked {
    /// The commit (`None`: nothing yet).
    pub seq: Option<i64>,
    /// When the site made it, as its batch said (`None`: not known).
    pub stamp_ns: Option<i64>,
}

/// A tier's batch, as far as the rule reads it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct BatchSpan {
    /// The last commit the site knew acknowledged when it read the batch (`None`: nothing).
    pub after_seq: Option<i64>,
    /// The last commit it covers.
    pub upto_seq: i64,
    /// When that commit was made.
    pub upto_stamp_ns: Option<i64>,
    /// Only a part of that commit's rows, more parts following.
    pub partial: bool,
}

/// What a tier's batch does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum BatchRuling {
    /// It ends at or before what was applied: nothing to apply (a replay, or one a later
    /// upload overtook).
    Duplicate,
    /// It starts after what was applied: refused, the site resumes from the acknowledgement.
    Gap,
    /// Applied (its rows replacing those at the same keys), the tier then acknowledged so.
    Apply(Acked),
}

/// The rule on a tier's batch, given the tier's acknowledgement in this generation and, when it
/// has none yet, `inherited`: the nearest ancestor generation's acknowledged commit for the tier
/// (a restored copy recorded the acknowledgements it had, so it holds nothing the centre lacks
/// below them). A part of a commit is applied but acknowledges nothing new until the last.
pub(super) fn rule_batch(stored: Acked, inherited: Option<i64>, batch: BatchSpan) -> BatchRuling {
    if stored.seq.is_some_and(|acked| batch.upto_seq <= acked) {
        return BatchRuling::Duplicate;
    }
    // `None` is before every commit: a batch from the start continues anything.
    let start = stored.seq.or(inherited);
    if batch.after_seq > start {
        return BatchRuling::Gap;
    }
    BatchRuling::Apply(if batch.partial {
        stored
    } else {
        Acked {
            seq: Some(batch.upto_seq),
            stamp_ns: batch.upto_stamp_ns,
        }
    })
}

/// What a slice of a requested period does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum SliceRuling {
    /// The request is done (delivered or cancelled), or the slice ends within what was
    /// delivered: nothing to apply.
    Duplicate,
    /// It starts after what was delivered: the site resumes from `delivered_to_ns`.
    Gap,
    /// Applied; the request then delivered to this time.
    Apply {
        /// The request's new `delivered_to_ns`.
        delivered_to_ns: i64,
    },
}

/// The rule on a slice `[from_ns, slice_to_ns)` of a request for `[.., to_ns)` delivered to
/// `delivered_to_ns`, `done` when finished or cancelled.
pub(super) fn rule_slice(
    to_ns: i64,
    delivered_to_ns: i64,
    done: bool,
    from_ns: i64,
    slice_to_ns: i64,
) -> SliceRuling {
    if done || slice_to_ns <= delivered_to_ns {
        SliceRuling::Duplicate
    } else if from_ns > delivered_to_ns {
        SliceRuling::Gap
    } else {
        SliceRuling::Apply {
            delivered_to_ns: slice_to_ns.min(to_ns),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn span(after_seq: Option<i64>, upto_seq: i64, partial: bool) -> BatchSpan {
        BatchSpan {
            after_seq,
            upto_seq,
            upto_stamp_ns: Some(upto_seq * 1000),
            partial,
        }
    }

    fn acked(seq: i64) -> Acked {
        Acked {
            seq: Some(seq),
            stamp_ns: Some(seq * 1000),
        }
    }

    const NONE: Acked = Acked {
        seq: None,
        stamp_ns: None,
    };

    #[test]
    fn a_batch_that_continues_is_applied_and_acknowledged_at_its_end() {
        // The first batch of a stream, from the start.
        assert_eq!(
            rule_batch(NONE, None, span(None, 5, false)),
            BatchRuling::Apply(acked(5))
        );
        // Continuing exactly, and overlapping what was applied (the site read before the last
        // acknowledgement arrived): the overlap is applied again, the same rows.
        assert_eq!(
            rule_batch(acked(5), None, span(Some(5), 9, false)),
            BatchRuling::Apply(acked(9))
        );
        assert_eq!(
            rule_batch(acked(5), None, span(Some(3), 9, false)),
            BatchRuling::Apply(acked(9))
        );
    }

    #[test]
    fn a_replay_changes_nothing_and_a_gap_is_refused() {
        for upto in [3, 5] {
            assert_eq!(
                rule_batch(acked(5), None, span(Some(1), upto, false)),
                BatchRuling::Duplicate,
                "ends at {upto}, applied to 5"
            );
        }
        assert_eq!(
            rule_batch(acked(5), None, span(Some(6), 9, false)),
            BatchRuling::Gap
        );
        // Nothing applied: only a batch from the start continues.
        assert_eq!(
            rule_batch(NONE, None, span(Some(2), 9, false)),
            BatchRuling::Gap
        );
    }

    #[test]
    fn a_part_of_a_commit_is_applied_without_a_new_acknowledgement() {
        assert_eq!(
            rule_batch(acked(5), None, span(Some(5), 6, true)),
            BatchRuling::Apply(acked(5))
        );
        assert_eq!(
            rule_batch(NONE, None, span(None, 1, true)),
            BatchRuling::Apply(NONE)
        );
        // Its last part acknowledges it.
        assert_eq!(
            rule_batch(acked(5), None, span(Some(5), 6, false)),
            BatchRuling::Apply(acked(6))
        );
    }

    #[test]
    fn a_new_generation_continues_its_ancestor_s_acknowledgement() {
        // A restored copy acknowledged to 7 by its parent may start anywhere up to 7.
        for after in [None, Some(4), Some(7)] {
            assert_eq!(
                rule_batch(NONE, Some(7), span(after, 10, false)),
                BatchRuling::Apply(acked(10)),
                "after {after:?}"
            );
        }
        assert_eq!(
            rule_batch(NONE, Some(7), span(Some(8), 10, false)),
            BatchRuling::Gap
        );
        // Once it has its own acknowledgement, the ancestor's no longer counts.
        assert_eq!(
            rule_batch(acked(2), Some(7), span(Some(7), 10, false)),
            BatchRuling::Gap
        );
    }

    #[test]
    fn generations_are_superseded_unknown_or_gone_back_as_the_rule_says() {
        let lineage = vec!["g1".to_owned(), "g0".to_owned()];
        let known = vec!["g0".to_owned(), "other".to_owned()];
        // New: registered under the nearest ancestor the centre knows.
        assert_eq!(
            rule_generation(
                "g2",
                &lineage,
                Some(3),
                GenerationHeld::New { known: &known }
            ),
            GenerationRuling::Register { parent: Some("g0") }
        );
        // A site's first generation has no parent.
        assert_eq!(
            rule_generation("g2", &lineage, None, GenerationHeld::New { known: &[] }),
            GenerationRuling::Register { parent: None }
        );
        // New, descending from none the centre knows of a site it knows.
        assert_eq!(
            rule_generation("g2", &[], None, GenerationHeld::New { known: &known }),
            GenerationRuling::Refused(SyncOutcome::GenerationUnknown {
                generation: "g2".to_owned()
            })
        );
        // Known and superseded, even with commits ahead.
        assert_eq!(
            rule_generation(
                "g0",
                &[],
                Some(99),
                GenerationHeld::Known {
                    head_seq: Some(5),
                    child: Some("g1".to_owned())
                }
            ),
            GenerationRuling::Refused(SyncOutcome::GenerationSuperseded {
                generation: "g0".to_owned(),
                by: "g1".to_owned()
            })
        );
        // Known: commits never go back; equal or ahead, or not stated, go on.
        let held = |head_seq| GenerationHeld::Known {
            head_seq,
            child: None,
        };
        assert_eq!(
            rule_generation("g0", &[], Some(4), held(Some(5))),
            GenerationRuling::Refused(SyncOutcome::CommitsWentBack {
                generation: "g0".to_owned(),
                head_seq: 4,
                known_head_seq: 5
            })
        );
        for (head, known_head) in [(Some(5), Some(5)), (Some(6), Some(5)), (None, Some(5))] {
            assert_eq!(
                rule_generation("g0", &[], head, held(known_head)),
                GenerationRuling::GoOn
            );
        }
        assert_eq!(
            rule_generation("g0", &[], Some(1), held(None)),
            GenerationRuling::GoOn
        );
    }

    #[test]
    fn a_slice_of_a_request_is_applied_once_and_in_order() {
        // A request for [0, 100) delivered to 40.
        assert_eq!(
            rule_slice(100, 40, false, 40, 70),
            SliceRuling::Apply {
                delivered_to_ns: 70
            }
        );
        assert_eq!(
            rule_slice(100, 40, false, 20, 130),
            SliceRuling::Apply {
                delivered_to_ns: 100
            }
        );
        assert_eq!(rule_slice(100, 40, false, 10, 40), SliceRuling::Duplicate);
        assert_eq!(rule_slice(100, 40, true, 40, 70), SliceRuling::Duplicate);
        assert_eq!(rule_slice(100, 40, false, 41, 70), SliceRuling::Gap);
    }
}
