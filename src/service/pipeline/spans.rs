//! Where each link may hold samples that are stored or on their way to the store: per link,
//! a few disjoint time intervals that cover every such sample. The pipeline asks it whether
//! an ingest request can repeat or contradict one. When no interval of a link meets the span
//! of the request's samples of that link, a read of the store over that span would find
//! nothing, so the request needs none.
//!
//! The cover only ever errs on the side of "may hold": a failed commit, a pruned sample or a
//! merge of two intervals (memory is bounded) leave a time covered that holds nothing, and a
//! request there is read for first, as any other that may repeat.

use super::IngestItem;
use crate::chain::LinkId;

/// At most this many intervals a link: past it, the two oldest merge into one (the gap
/// between them becomes "may hold": the oldest gaps are the least likely to be filled late).
const INTERVALS_PER_LINK: usize = 64;

/// Per link, sorted disjoint closed intervals of time (ns) covering every sample of the link
/// stored or on its way.
#[derive(Debug, Clone)]
pub(super) struct StoredSpans {
    links: Vec<Vec<(i64, i64)>>,
}

impl StoredSpans {
    /// At start: each link may hold samples up to its newest stored one (`newest_ns`, by link;
    /// `None` for a link with nothing stored).
    pub(super) fn new(newest_ns: &[Option<i64>]) -> Self {
        let links = newest_ns
            .iter()
            .map(|n| n.map(|t| vec![(i64::MIN, t)]).unwrap_or_default())
            .collect();
        Self { links }
    }

    /// Whether `link` may hold a sample at a time in `from..=to`.
    pub(super) fn may_hold(&self, link: LinkId, from_ns: i64, to_ns: i64) -> bool {
        let Some(intervals) = self.links.get(link.0) else {
            return false;
        };
        // The first interval that ends at or after `from`: it meets the span if it starts
        // no later than `to`; every later one starts later still.
        let i = intervals.partition_point(|&(_, end)| end < from_ns);
        intervals.get(i).is_some_and(|&(start, _)| start <= to_ns)
    }

    /// Covers `from..=to` of `link`.
    pub(super) fn add(&mut self, link: LinkId, from_ns: i64, to_ns: i64) {
        let Some(intervals) = self.links.get_mut(link.0) else {
            return;
        };
        // The intervals that meet or touch the new one merge with it.
        let first = intervals.partition_point(|&(_, end)| end.saturating_add(1) < from_ns);
        let last = intervals.partition_point(|&(start, _)| start <= to_ns.saturating_add(1));
        let (mut start, mut end) = (from_ns, to_ns);
        if first < last {
            start = start.min(intervals[first].0);
            end = end.max(intervals[last - 1].1);
        }
        intervals.splice(first..last, std::iter::once((start, end)));
        if intervals.len() > INTERVALS_PER_LINK {
            let (_, second_end) = intervals.remove(1);
            intervals[0].1 = second_end;
        }
    }

    /// Whether a request's samples may repeat or contradict one covered: some link's span of
    /// them (first to last time) meets that link's cover.
    pub(super) fn may_repeat(&self, items: &[IngestItem]) -> bool {
        super::spans_of(items)
            .into_iter()
            .any(|(link, (from, to))| self.may_hold(link, from, to))
    }

    /// Covers a request's samples: each link's span of them.
    pub(super) fn add_all(&mut self, items: &[IngestItem]) {
        for (link, (from, to)) in super::spans_of(items) {
            self.add(link, from, to);
        }
    }

    #[cfg(test)]
    fn intervals(&self, link: LinkId) -> &[(i64, i64)] {
        &self.links[link.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn well_formed(intervals: &[(i64, i64)]) -> bool {
        intervals.iter().all(|&(s, e)| s <= e)
            && intervals
                .windows(2)
                .all(|w| w[0].1.saturating_add(1) < w[1].0)
            && intervals.len() <= INTERVALS_PER_LINK
    }

    proptest! {
        /// Every time added stays covered, whatever merged; a span that meets no added
        /// time and no merge's gap is not covered; the intervals stay sorted, disjoint, apart
        /// and bounded.
        #[test]
        fn the_cover_holds_every_added_time_and_answers_spans_exactly(
            spans in proptest::collection::vec((0i64..10_000, 0i64..50), 1..300),
            probes in proptest::collection::vec((0i64..10_050, 0i64..60), 50),
        ) {
            let mut cover = StoredSpans::new(&[None, Some(-5)]);
            let link = LinkId(0);
            let mut added: Vec<(i64, i64)> = Vec::new();
            let mut ever_full = false;
            for &(from, len) in &spans {
                cover.add(link, from, from + len);
                added.push((from, from + len));
                prop_assert!(well_formed(cover.intervals(link)), "{:?}", cover.intervals(link));
                ever_full |= cover.intervals(link).len() == INTERVALS_PER_LINK;
            }
            for &(from, to) in &added {
                prop_assert!(cover.may_hold(link, from, to));
                prop_assert!(cover.may_hold(link, to, to));
            }
            // Against a brute-force cover: exact unless the bound was ever reached (a merge
            // of the two oldest may then cover a gap).
            for &(from, len) in &probes {
                let to = from + len;
                let meets = added.iter().any(|&(s, e)| s <= to && from <= e);
                if meets {
                    prop_assert!(cover.may_hold(link, from, to));
                } else if !ever_full {
                    prop_assert!(!cover.may_hold(link, from, to), "{from}..={to}");
                }
                // Either way the answer agrees with the intervals themselves.
                let by_scan = cover.intervals(link).iter().any(|&(s, e)| s <= to && from <= e);
                prop_assert_eq!(cover.may_hold(link, from, to), by_scan);
            }
            // The other link: nothing after what was stored at start.
            prop_assert!(cover.may_hold(LinkId(1), i64::MIN, -5));
            prop_assert!(!cover.may_hold(LinkId(1), -4, i64::MAX));
        }
    }

    #[test]
    fn a_link_with_nothing_stored_holds_nothing_until_a_sample_comes() {
        let mut cover = StoredSpans::new(&[None]);
        assert!(!cover.may_hold(LinkId(0), i64::MIN, i64::MAX));
        cover.add(LinkId(0), 100, 200);
        assert!(cover.may_hold(LinkId(0), 200, 300));
        assert!(!cover.may_hold(LinkId(0), 201, 300));
        assert!(!cover.may_hold(LinkId(0), 0, 99));
        // Touching spans become one; a span between two fills the gap.
        cover.add(LinkId(0), 201, 250);
        cover.add(LinkId(0), 300, 400);
        assert_eq!(cover.intervals(LinkId(0)), &[(100, 250), (300, 400)]);
        cover.add(LinkId(0), 240, 310);
        assert_eq!(cover.intervals(LinkId(0)), &[(100, 400)]);
        // An unknown link holds nothing and takes nothing.
        cover.add(LinkId(7), 0, 1);
        assert!(!cover.may_hold(LinkId(7), 0, 1));
    }

    #[test]
    fn past_the_bound_the_two_oldest_intervals_merge() {
        let mut cover = StoredSpans::new(&[None]);
        for k in 0..=INTERVALS_PER_LINK as i64 {
            cover.add(LinkId(0), 10 * k, 10 * k + 1);
        }
        let intervals = cover.intervals(LinkId(0));
        assert_eq!(intervals.len(), INTERVALS_PER_LINK);
        assert_eq!(intervals[0], (0, 11));
        // The gap 2..=9 is now covered (may hold), the next one is not.
        assert!(cover.may_hold(LinkId(0), 5, 5));
        assert!(!cover.may_hold(LinkId(0), 15, 15));
    }
}
