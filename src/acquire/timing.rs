//! A frame's time in UTC, the middle of its exposure, from what the camera and the host say:
//! the camera's stamp (its own clock, or PTP's TAI), the host's clock at the frame's arrival, and
//! the trigger that exposed it. Pure: every time is handed in.

use crate::config::{CameraSource, TimestampMode};
use std::collections::VecDeque;

/// Pairs of the device's clock and the host's, and the line through them: the device clock's
/// offset from the host's and its drift.
///
/// Latched pairs (the host's time read half-way through a latch of the device's clock) are
/// fitted by least squares. Arrival pairs (a frame's stamp and its arrival) carry the transfer's
/// latency, which only adds: each second keeps its smallest offset (the lower envelope), and the
/// line goes through those, so the fit sits on the fastest transfers. Pairs older than the
/// window leave; a pair that misses the line by more than [`ClockFit::RESET_NS`] (a camera that
/// restarted its clock) starts the fit again.
#[derive(Debug, Clone)]
pub struct ClockFit {
    /// `(device_ns, host_ns - device_ns)`, oldest first; for arrival pairs one per second.
    points: VecDeque<(i64, i64)>,
    latched: bool,
    window_ns: i64,
    line: Option<Line>,
}

/// `host - device = offset_ns + drift * (device - device_ref_ns)`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Line {
    device_ref_ns: i64,
    offset_ns: f64,
    drift: f64,
    residual_rms_ns: f64,
}

/// What a fit says, for reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitReport {
    /// Host minus device clock at the newest pair (ns).
    pub offset_ns: f64,
    /// How much faster the host's clock runs than the device's (parts per million).
    pub drift_ppm: f64,
    /// RMS of the pairs kept about the line (ns).
    pub residual_rms_ns: f64,
    /// Pairs the line goes through.
    pub pairs: usize,
    /// Latched pairs (true) or arrival pairs.
    pub latched: bool,
}

impl ClockFit {
    /// A pair this far off the line restarts the fit (the device's clock was reset).
    pub const RESET_NS: i64 = 1_000_000_000;
    /// No drift is fitted over a span shorter than this: the lower envelope of arrivals moves by
    /// a fraction of a millisecond, which over a minute is a few ppm.
    const MIN_DRIFT_SPAN_NS: i64 = 60_000_000_000;
    /// Before a drift is fitted, the offset comes from this much of the newest pairs.
    const RECENT_NS: i64 = 5_000_000_000;

    /// An empty fit over `window_s` seconds of pairs.
    pub fn new(latched: bool, window_s: f64) -> Self {
        Self {
            points: VecDeque::new(),
            latched,
            window_ns: (window_s * 1e9) as i64,
            line: None,
        }
    }

    /// Whether the pairs are latched.
    pub fn latched(&self) -> bool {
        self.latched
    }

    /// Adds a pair: the device's clock and the host's at the same instant (latched), or a
    /// frame's stamp and its arrival.
    pub fn add(&mut self, device_ns: i64, host_ns: i64) {
        let offset = host_ns - device_ns;
        if let Some(predicted) = self.map(device_ns)
            && (host_ns - predicted).abs() > Self::RESET_NS
        {
            self.points.clear();
        }
        match self.points.back_mut() {
            // Arrival pairs: one a second, the smallest offset of the second.
            Some(last)
                if !self.latched
                    && device_ns.div_euclid(1_000_000_000) == last.0.div_euclid(1_000_000_000) =>
            {
                if offset >= last.1 {
                    // Not this second's lowest: the line stays as it is.
                    return;
                }
                *last = (device_ns, offset);
            }
            Some(last) if device_ns <= last.0 => return,
            _ => self.points.push_back((device_ns, offset)),
        }
        while let (Some(first), Some(last)) = (self.points.front(), self.points.back())
            && last.0 - first.0 > self.window_ns
        {
            self.points.pop_front();
        }
        self.line = Some(self.fit());
    }

    fn fit(&self) -> Line {
        let (device_ref_ns, _) = *self.points.back().unwrap_or(&(0, 0));
        let n = self.points.len() as f64;
        let span = self.points.back().map_or(0, |b| b.0) - self.points.front().map_or(0, |f| f.0);
        let xs = || self.points.iter().map(|&(d, _)| (d - device_ref_ns) as f64);
        let ys = || self.points.iter().map(|&(_, o)| o as f64);
        let (offset_ns, drift) = if span < Self::MIN_DRIFT_SPAN_NS {
            // Too short for a drift: the offset alone, from the newest seconds only, so that an
            // unfitted drift (tens of ppm) moves it by a fraction of a millisecond at most.
            let recent = || {
                self.points
                    .iter()
                    .filter(|&&(d, _)| device_ref_ns - d <= Self::RECENT_NS)
                    .map(|&(_, o)| o as f64)
            };
            let offset = if self.latched {
                recent().sum::<f64>() / recent().count() as f64
            } else {
                recent().fold(f64::INFINITY, f64::min)
            };
            (offset, 0.0)
        } else {
            let mx = xs().sum::<f64>() / n;
            let my = ys().sum::<f64>() / n;
            let sxy: f64 = xs().zip(ys()).map(|(x, y)| (x - mx) * (y - my)).sum();
            let sxx: f64 = xs().map(|x| (x - mx) * (x - mx)).sum();
            let drift = sxy / sxx;
            let mut offset = my - drift * mx;
            if !self.latched {
                // The line's slope from all the seconds, its height from the lowest of them:
                // the minima scatter above the fastest transfer, never below it.
                offset += xs()
                    .zip(ys())
                    .map(|(x, y)| y - offset - drift * x)
                    .fold(f64::INFINITY, f64::min);
            }
            (offset, drift)
        };
        let residual_rms_ns = (xs()
            .zip(ys())
            .map(|(x, y)| (y - offset_ns - drift * x).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
        Line {
            device_ref_ns,
            offset_ns,
            drift,
            residual_rms_ns,
        }
    }

    /// The host's time of a device time, once there is a pair.
    pub fn map(&self, device_ns: i64) -> Option<i64> {
        let l = self.line?;
        let dx = (device_ns - l.device_ref_ns) as f64;
        Some(device_ns + (l.offset_ns + l.drift * dx).round() as i64)
    }

    /// The fit, once there is a pair.
    pub fn report(&self) -> Option<FitReport> {
        self.line.map(|l| FitReport {
            offset_ns: l.offset_ns,
            drift_ppm: l.drift * 1e6,
            residual_rms_ns: l.residual_rms_ns,
            pairs: self.points.len(),
            latched: self.latched,
        })
    }

    /// Whether the fit has settled: latched pairs from three latches, arrival pairs from
    /// three distinct seconds (a first transfer that came late no longer sets the offset).
    pub fn settled(&self) -> bool {
        self.points.len() >= 3
    }

    /// Forgets every pair (a new connection: the device's clock may have restarted).
    pub fn clear(&mut self) {
        self.points.clear();
        self.line = None;
    }
}

/// Why a frame's time was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TimeRefusal {
    /// `host_fit` has too few pairs yet to know the device's clock.
    #[error("the device clock's fit has not settled yet (three seconds of pairs)")]
    Settling,
    /// PTP is not synchronised.
    #[error("the camera's PTP clock is not synchronised (status `{0}`)")]
    PtpNotLocked(String),
    /// The frame's time and its arrival on the host disagree.
    #[error(
        "the frame's time ({time}) is {off_ms:.1} ms from its arrival on the host's clock, beyond the tolerance of {tolerance_ms} ms (a clock in another timescale, a device clock not fitted, or a host clock that jumped)"
    )]
    Disagrees {
        /// The time the frame would have had (RFC 3339).
        time: String,
        /// Arrival minus the frame's time, less half the exposure (ms).
        off_ms: f64,
        /// The tolerance (ms).
        tolerance_ms: f64,
    },
}

/// Turns a camera's stamps into UTC times of the middle of the exposure, per `timestamp`.
#[derive(Debug, Clone)]
pub struct FrameClock {
    mode: TimestampMode,
    stamp_offset_ns: i64,
    latency_ns: i64,
    half_exposure_ns: i64,
    tai_offset_ns: i64,
    tolerance_ns: i64,
    /// `host_fit`: the device clock against the host's.
    pub fit: ClockFit,
    /// `ptp`: the camera's PTP status, and whether it is synchronised.
    ptp: Option<(String, bool)>,
}

impl FrameClock {
    /// The clock of a camera configured by `source`, exposing for `exposure_us`; `latched`
    /// when the camera can latch its clock for `host_fit`.
    pub fn new(source: &CameraSource, exposure_us: f64, latched: bool) -> Self {
        Self {
            mode: source.timestamp,
            stamp_offset_ns: source.stamp_offset_ns(exposure_us),
            latency_ns: source.latency_ns(exposure_us),
            half_exposure_ns: (exposure_us * 500.0).round() as i64,
            tai_offset_ns: (source.tai_offset_s * 1e9).round() as i64,
            tolerance_ns: (source.tolerance_ms * 1e6).round() as i64,
            fit: ClockFit::new(latched, 600.0),
            ptp: None,
        }
    }

    /// The camera's PTP status as it reads, and whether it is synchronised (`Slave`).
    pub fn set_ptp_status(&mut self, status: &str) {
        self.ptp = Some((status.to_owned(), ptp_locked(status)));
    }

    /// The PTP status last read.
    pub fn ptp_status(&self) -> Option<&str> {
        self.ptp.as_ref().map(|(s, _)| s.as_str())
    }

    /// The frame's time (UTC ns, the middle of its exposure) from its stamp and its arrival on
    /// the host's clock; refused when PTP is not synchronised or the time disagrees with the
    /// arrival.
    pub fn frame_time(&mut self, device_ns: i64, arrival_ns: i64) -> Result<i64, TimeRefusal> {
        let t = match self.mode {
            TimestampMode::Ptp => {
                match &self.ptp {
                    Some((_, true)) => {}
                    Some((status, false)) => return Err(TimeRefusal::PtpNotLocked(status.clone())),
                    None => return Err(TimeRefusal::PtpNotLocked("not read yet".into())),
                }
                device_ns - self.tai_offset_ns + self.stamp_offset_ns
            }
            TimestampMode::HostFit => {
                if !self.fit.latched() {
                    self.fit.add(device_ns, arrival_ns);
                }
                match self.fit.map(device_ns) {
                    Some(host) if self.fit.settled() => host + self.stamp_offset_ns,
                    _ => return Err(TimeRefusal::Settling),
                }
            }
            TimestampMode::Host => arrival_ns - self.latency_ns,
        };
        self.check(t, arrival_ns)?;
        Ok(t)
    }

    /// Refuses a time whose distance to the arrival, less half the exposure, is beyond the
    /// tolerance.
    pub fn check(&self, t: i64, arrival_ns: i64) -> Result<(), TimeRefusal> {
        let off = arrival_ns - t - self.half_exposure_ns;
        if off.abs() > self.tolerance_ns {
            return Err(TimeRefusal::Disagrees {
                time: crate::clock::format_ns(t),
                off_ms: off as f64 / 1e6,
                tolerance_ms: self.tolerance_ns as f64 / 1e6,
            });
        }
        Ok(())
    }

    /// Half the exposure (ns).
    pub fn half_exposure_ns(&self) -> i64 {
        self.half_exposure_ns
    }
}

/// Whether a PTP status (`PtpStatus` or `GevIEEE1588Status`) is synchronised to a grandmaster.
pub fn ptp_locked(status: &str) -> bool {
    status.eq_ignore_ascii_case("slave")
}

/// The next instant of a software trigger's schedule after `now_ns`: whole multiples of the
/// period since the epoch, so every camera of a group fires at the same instants without
/// talking to the others.
pub fn next_tick_ns(now_ns: i64, period_ns: i64) -> i64 {
    (now_ns.div_euclid(period_ns) + 1) * period_ns
}

/// The tick of a software trigger that exposed a frame whose own time is `t` (the latest tick
/// at or before it, less a margin for the exposure's middle).
pub fn tick_of(t_ns: i64, half_exposure_ns: i64, period_ns: i64) -> i64 {
    (t_ns - half_exposure_ns).div_euclid(period_ns) * period_ns
}

/// The trigger instants a group of cameras has seen lately, so that frames of one trigger
/// carry one time: the first frame of a trigger gives it its time, and every frame of the
/// group within `window_ns` of it takes that time.
#[derive(Debug, Default)]
pub struct TriggerInstants {
    recent: VecDeque<i64>,
}

impl TriggerInstants {
    /// The group's time for a frame whose own time is `t_ns`.
    pub fn instant(&mut self, t_ns: i64, window_ns: i64) -> i64 {
        if let Some(&known) = self
            .recent
            .iter()
            .filter(|&&k| (k - t_ns).abs() <= window_ns)
            .min_by_key(|&&k| (k - t_ns).abs())
        {
            return known;
        }
        self.recent.push_back(t_ns);
        if self.recent.len() > 64 {
            self.recent.pop_front();
        }
        t_ns
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A device clock 40 ppm slow, 1234 s behind, frames at 25 Hz arriving 2 to 9 ms after
    /// their stamp (the latency only adds): over ten minutes the mapping stays within the
    /// smallest latency plus a little of the truth, and the drift is found.
    #[test]
    fn arrival_pairs_find_the_offset_and_the_drift() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let mut fit = ClockFit::new(false, 600.0);
        let host0 = 1_800_000_000_000_000_000_i64;
        let drift = -40e-6;
        let device_of = |host: i64| ((host - host0) as f64 * (1.0 + drift)) as i64 + 5_000_000_000;
        let mut worst = 0_i64;
        for k in 0..(25 * 600) {
            let exposed = host0 + k * 40_000_000;
            let arrival = exposed + 2_000_000 + rng.random_range(0..7_000_000);
            fit.add(device_of(exposed), arrival);
            if k > 25 * 10 {
                let err = fit.map(device_of(exposed)).unwrap() - exposed;
                // The lower envelope sits on the fastest transfers (2 ms); before the drift is
                // fitted (a minute), 40 ppm over the newest 5 s may take 0.2 ms off.
                assert!(err >= 1_750_000, "{err} ns at frame {k}");
                worst = worst.max(err - 2_000_000);
            }
        }
        assert!(
            worst < 300_000,
            "worst error above the 2 ms latency floor: {worst} ns"
        );
        let r = fit.report().unwrap();
        assert!((r.drift_ppm - 40.0).abs() < 0.5, "{r:?}");
        assert!(!r.latched);
    }

    /// Latched pairs with ±50 µs of read noise: the least-squares line maps to within 20 µs.
    #[test]
    fn latched_pairs_fit_by_least_squares() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let mut fit = ClockFit::new(true, 600.0);
        for k in 0..600_i64 {
            let host = 1_000_000_000_000 + k * 1_000_000_000;
            let device = (host as f64 * (1.0 + 25e-6)) as i64 - 77_000_000_000;
            fit.add(device, host + rng.random_range(-50_000..50_000));
        }
        let host = 1_000_000_000_000 + 600 * 1_000_000_000_i64;
        let device = (host as f64 * (1.0 + 25e-6)) as i64 - 77_000_000_000;
        let err = fit.map(device).unwrap() - host;
        assert!(err.abs() < 20_000, "{err} ns");
    }

    /// A device clock that restarts (a camera power-cycled) starts the fit again.
    #[test]
    fn a_clock_that_restarts_restarts_the_fit() {
        let mut fit = ClockFit::new(false, 600.0);
        for k in 0..20_i64 {
            fit.add(
                500_000_000_000 + k * 1_000_000_000,
                9_000_000_000_000 + k * 1_000_000_000,
            );
        }
        fit.add(3_000_000_000, 9_021_000_000_000);
        assert_eq!(fit.report().unwrap().pairs, 1);
        assert_eq!(fit.map(3_000_000_000), Some(9_021_000_000_000));
    }

    fn source(mode: TimestampMode) -> CameraSource {
        let installation = crate::config::parse(
            "t",
            &crate::config::DEFAULT_INSTALLATION_TOML.replacen(
                "[[cameras]]",
                &format!(
                    "[[cameras]]\nsource = {{ address = \"127.0.0.2\", timestamp = \"{mode}\", exposure_us = 2000, rate_hz = 25 }}"
                ),
                1,
            ),
        )
        .unwrap();
        installation.sources[0].clone()
    }

    /// PTP's TAI stamps become UTC, 37 s earlier, at the exposure's middle; an unsynchronised
    /// clock and a camera in UTC already (37 s off) are refused.
    #[test]
    fn ptp_stamps_are_tai() {
        let s = source(TimestampMode::Ptp);
        let mut clock = FrameClock::new(&s, 2000.0, false);
        let utc_start = 1_900_000_000_000_000_000_i64;
        let tai = utc_start + 37_000_000_000;
        assert!(matches!(
            clock.frame_time(tai, utc_start + 3_000_000),
            Err(TimeRefusal::PtpNotLocked(_))
        ));
        clock.set_ptp_status("Listening");
        assert!(clock.frame_time(tai, utc_start + 3_000_000).is_err());
        clock.set_ptp_status("Slave");
        assert_eq!(
            clock.frame_time(tai, utc_start + 3_000_000),
            Ok(utc_start + 1_000_000)
        );
        let refused = clock
            .frame_time(utc_start, utc_start + 3_000_000)
            .unwrap_err();
        assert!(
            matches!(refused, TimeRefusal::Disagrees { off_ms, .. } if (off_ms - 37_001.0).abs() < 1.0),
            "{refused:?}"
        );
    }

    /// `host_fit` from arrivals: nothing is timed before three seconds of pairs; then the
    /// lowest offset of each second sets the time, not a first transfer that came late.
    #[test]
    fn host_fit_waits_for_three_seconds_of_pairs() {
        let s = source(TimestampMode::HostFit);
        let mut clock = FrameClock::new(&s, 2000.0, false);
        let device0 = 5_000_000_000_i64;
        let host0 = 1_900_000_000_000_000_000_i64;
        // The first frame arrives 70 ms late, the others 4 ms after their stamp.
        assert_eq!(
            clock.frame_time(device0, host0 + 70_000_000),
            Err(TimeRefusal::Settling)
        );
        let mut timed = Vec::new();
        for k in 1..40_i64 {
            let t = clock.frame_time(
                device0 + k * 100_000_000,
                host0 + k * 100_000_000 + 4_000_000,
            );
            if k < 20 {
                assert_eq!(t, Err(TimeRefusal::Settling), "frame {k}");
            } else {
                timed.push(t.unwrap() - (host0 + k * 100_000_000));
            }
        }
        // Stamp plus half the exposure, plus the 4 ms floor of the arrivals.
        assert!(timed.iter().all(|&e| e == 5_000_000), "{timed:?}");
    }

    /// `host`: the arrival less the latency (half the exposure by default).
    #[test]
    fn host_mode_is_the_arrival_less_the_latency() {
        let s = source(TimestampMode::Host);
        let mut clock = FrameClock::new(&s, 2000.0, false);
        assert_eq!(clock.frame_time(0, 10_000_000), Ok(9_000_000));
    }

    #[test]
    fn software_ticks_fall_on_one_grid() {
        let period = 40_000_000;
        assert_eq!(next_tick_ns(1_000_000_013, period), 1_040_000_000);
        assert_eq!(next_tick_ns(1_040_000_000, period), 1_080_000_000);
        assert_eq!(
            tick_of(1_041_000_000 + 7_000_000, 1_000_000, period),
            1_040_000_000
        );
    }

    #[test]
    fn frames_of_one_trigger_take_the_first_ones_time() {
        let mut g = TriggerInstants::default();
        assert_eq!(g.instant(1_000_000_000, 5_000_000), 1_000_000_000);
        assert_eq!(g.instant(1_000_300_000, 5_000_000), 1_000_000_000);
        assert_eq!(g.instant(1_100_000_000, 5_000_000), 1_100_000_000);
        assert_eq!(g.instant(999_000_000, 5_000_000), 1_000_000_000);
    }
}
