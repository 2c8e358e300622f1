//! How often a marker that stays lost is searched for in the whole frame.
//!
//! Searching a whole frame for a marker's layout costs about ten milliseconds a frame where the
//! search near a prediction costs a few hundred microseconds. A marker that is covered, knocked
//! off or out of view would otherwise pay the whole search in every frame of its camera and take
//! a core. So a marker is searched for in the whole frame when it was found in its previous
//! frame (or was never searched for), and after a whole-frame search that did not find it, again
//! only once `interval_ns` of frame time has passed; near its prediction it is looked for in
//! every frame. The time is the frames' own (their measurement times), so a backlog of frames
//! sent faster than real time is paced the same: at 25 frames a second and an interval of one
//! second, a lost marker costs one whole search in 25 frames.

use crate::chain::LinkId;

/// The pace of each measured link's whole-frame searches.
#[derive(Debug, Clone)]
pub struct SearchPacer {
    interval_ns: i64,
    /// Per link (by id): the frame time of the last whole-frame search that did not find the
    /// marker, while it stays lost.
    failed_at_ns: Vec<Option<i64>>,
}

impl SearchPacer {
    /// A pacer of `links` links, each lost marker searched in the whole frame at most once every
    /// `interval_ns` of frame time (0: in every frame).
    pub fn new(links: usize, interval_ns: i64) -> Self {
        Self {
            interval_ns: interval_ns.max(0),
            failed_at_ns: vec![None; links],
        }
    }

    /// Whether `link`'s marker may be searched for in the whole frame of `time_ns`; otherwise
    /// how long (s of frame time) until it may. A frame older than the last failed search (sent
    /// out of order, or a replay) may.
    pub fn whole_frame(&self, link: LinkId, time_ns: i64) -> Result<(), f64> {
        match self.failed_at_ns.get(link.0).copied().flatten() {
            Some(at) if time_ns >= at && time_ns - at < self.interval_ns => {
                Err((at + self.interval_ns - time_ns) as f64 / 1e9)
            }
            _ => Ok(()),
        }
    }

    /// Records what the frame of `time_ns` showed of `link`'s marker: `found`, and whether the
    /// whole frame was searched for it (`whole_frame` as [`Self::whole_frame`] allowed).
    pub fn record(&mut self, link: LinkId, time_ns: i64, found: bool, whole_frame: bool) {
        if let Some(slot) = self.failed_at_ns.get_mut(link.0) {
            if found {
                *slot = None;
            } else if whole_frame {
                *slot = Some(time_ns);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;

    #[test]
    fn a_lost_marker_is_searched_once_an_interval_and_at_once_when_lost_again() {
        let link = LinkId(1);
        let mut pacer = SearchPacer::new(2, 1000 * MS);
        // 25 frames a second; the marker is lost from frame 10 to frame 80, then found.
        let mut searched = Vec::new();
        for k in 0..120 {
            let t = k * 40 * MS;
            let lost = (10..80).contains(&k);
            let allowed = pacer.whole_frame(link, t).is_ok();
            if allowed && lost {
                searched.push(k);
            }
            pacer.record(link, t, !lost, allowed);
        }
        // At once when lost, then every 25 frames (a second) while it stays lost.
        assert_eq!(searched, [10, 35, 60]);
        assert_eq!(
            pacer.whole_frame(link, 120 * 40 * MS),
            Ok(()),
            "found again"
        );
        // The wait is told in frame time.
        pacer.record(link, 0, false, true);
        assert_eq!(pacer.whole_frame(link, 400 * MS), Err(0.6));
        // An older frame (out of order) may be searched; another link is its own.
        assert_eq!(pacer.whole_frame(link, -40 * MS), Ok(()));
        assert_eq!(pacer.whole_frame(LinkId(0), 400 * MS), Ok(()));
        // A search not allowed leaves the pace as it was.
        pacer.record(link, 400 * MS, false, false);
        assert_eq!(pacer.whole_frame(link, 1000 * MS), Ok(()));
    }

    #[test]
    fn an_interval_of_zero_searches_every_frame() {
        let mut pacer = SearchPacer::new(1, 0);
        pacer.record(LinkId(0), 0, false, true);
        assert_eq!(pacer.whole_frame(LinkId(0), 0), Ok(()));
        assert_eq!(pacer.whole_frame(LinkId(0), 40 * MS), Ok(()));
    }
}
