//! Alarms of a target: deformation levels with hysteresis and dwell, a rate-of-change limit,
//! and stale data. Pure: fed with results in measurement-time order, it returns transitions.
//!
//! * Deformation: the magnitudes of the deformation rotation (arc-seconds) and translation (mm)
//!   against the warn and alarm thresholds. A level is entered when a magnitude reaches its
//!   threshold, and left only when the magnitude falls below `(1 - hysteresis)` of it.
//! * Rate: the change of `target_from_base` between consecutive results (rotation angle per
//!   second, translation per second) against its limits: level `alarm` or `none`.
//! * Stale: `alarm` while a link on the target's paths has delivered nothing for longer than
//!   its staleness limit, judged on the server's clock by [`AlarmMonitor::liveness`] (results
//!   stop coming exactly when it matters, so this track cannot wait for them). It is entered when
//!   the age reaches the limit and left when it falls below `(1 - hysteresis)` of it.
//!
//! A new level must hold for `dwell_s` before it becomes a transition (measurement time for
//! the deformation and rate, the server's clock for staleness), so noise around a threshold
//! does not flap.

use crate::geometry::{ARCSEC_PER_RAD, Pose, so3_log};

/// Deformation thresholds of a target (absent ones are not checked).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlarmThresholds {
    /// Warn above this rotation magnitude (arc-seconds).
    pub warn_rotation_arcsec: Option<f64>,
    /// Alarm above this rotation magnitude (arc-seconds).
    pub alarm_rotation_arcsec: Option<f64>,
    /// Warn above this translation magnitude (mm).
    pub warn_translation_mm: Option<f64>,
    /// Alarm above this translation magnitude (mm).
    pub alarm_translation_mm: Option<f64>,
    /// A level is left only below `(1 - hysteresis)` of its threshold.
    pub hysteresis: f64,
    /// A new level must hold this long (s, measurement time) to become a transition.
    pub dwell_s: f64,
    /// Alarm above this rate of rotation of the target (arc-seconds per second).
    pub rate_rotation_arcsec_per_s: Option<f64>,
    /// Alarm above this rate of translation of the target (mm per second).
    pub rate_translation_mm_per_s: Option<f64>,
}

crate::words! {
    /// An alarm level.
    #[derive(PartialOrd, Ord)]
    pub enum Level("alarm level") {
        /// Nothing to report.
        None = "none",
        /// Over the warn threshold.
        Warn = "warn",
        /// Over the alarm threshold.
        Alarm = "alarm",
    }
}

crate::words! {
    /// What an alarm is about.
    pub enum AlarmKind("alarm kind") {
        /// The deformation's magnitude.
        Deformation = "deformation",
        /// The rate of change of the target's pose.
        Rate = "rate",
        /// Data stopped arriving.
        Stale = "stale",
    }
}

crate::words! {
    /// The unit of a transition's deciding value.
    pub enum ValueUnit("alarm unit") {
        /// Arc-seconds (a deformation rotation).
        Arcsec = "arcsec",
        /// Millimetres (a deformation translation).
        Mm = "mm",
        /// Arc-seconds per second (a rotation rate).
        ArcsecPerS = "arcsec_per_s",
        /// Millimetres per second (a translation rate).
        MmPerS = "mm_per_s",
        /// Seconds (the age of a link's newest sample).
        S = "s",
        /// No value (stale transitions stored before ages were recorded).
        None = "none",
    }
}

/// Of a rotation and a translation measure against their thresholds, the one that decides: the
/// larger fraction of its nearest threshold (a component without thresholds never decides
/// unless neither has any).
fn deciding(
    rotation: (f64, Option<f64>, Option<f64>, ValueUnit),
    translation: (f64, Option<f64>, Option<f64>, ValueUnit),
) -> (f64, ValueUnit) {
    let fraction = |(v, warn, alarm, _): (f64, Option<f64>, Option<f64>, ValueUnit)| {
        warn.or(alarm).map_or(f64::NEG_INFINITY, |t| v / t)
    };
    if fraction(translation) > fraction(rotation) {
        (translation.0, translation.3)
    } else {
        (rotation.0, rotation.3)
    }
}

/// A change of level.
#[derive(Debug, Clone, PartialEq)]
pub struct Transition {
    /// What it is about.
    pub kind: AlarmKind,
    /// When (ns): measurement time for deformation and rate, the server's clock for stale.
    pub time_ns: i64,
    /// The level before.
    pub from: Level,
    /// The level after.
    pub to: Level,
    /// The value that decided it, in `unit`: the rotation or the translation, whichever is the
    /// larger fraction of its threshold; for stale, the age of the oldest link (s).
    pub value: f64,
    /// The unit of `value`.
    pub unit: ValueUnit,
    /// A sentence for people.
    pub message: String,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Track {
    level: Level,
    pending: Option<(Level, i64)>,
}

impl Track {
    fn new(level: Level) -> Self {
        Self {
            level,
            pending: None,
        }
    }

    /// Moves towards `candidate`; a change becomes a transition after `dwell_ns`.
    fn step(&mut self, candidate: Level, time_ns: i64, dwell_ns: i64) -> Option<(Level, Level)> {
        if candidate == self.level {
            self.pending = None;
            return None;
        }
        let since = match self.pending {
            Some((level, since)) if level == candidate => since,
            _ => {
                self.pending = Some((candidate, time_ns));
                time_ns
            }
        };
        if time_ns - since >= dwell_ns {
            let from = self.level;
            self.level = candidate;
            self.pending = None;
            Some((from, candidate))
        } else {
            None
        }
    }
}

/// The level of `value` against `warn` and `alarm`, holding the `current` level down to
/// `(1 - hysteresis)` of its threshold.
fn level_of(
    value: f64,
    warn: Option<f64>,
    alarm: Option<f64>,
    current: Level,
    hysteresis: f64,
) -> Level {
    let keep = 1.0 - hysteresis;
    let over = |limit: Option<f64>, level: Level| {
        limit.is_some_and(|l| value >= l || (current >= level && value >= l * keep))
    };
    if over(alarm, Level::Alarm) {
        Level::Alarm
    } else if over(warn, Level::Warn) {
        Level::Warn
    } else {
        Level::None
    }
}

/// The level of deformation magnitudes against the thresholds alone (no hysteresis, no dwell):
/// what a single result at another time than the live one shows.
pub fn threshold_level(
    thresholds: &AlarmThresholds,
    rotation_arcsec: f64,
    translation_mm: f64,
) -> Level {
    let t = thresholds;
    level_of(
        rotation_arcsec,
        t.warn_rotation_arcsec,
        t.alarm_rotation_arcsec,
        Level::None,
        0.0,
    )
    .max(level_of(
        translation_mm,
        t.warn_translation_mm,
        t.alarm_translation_mm,
        Level::None,
        0.0,
    ))
}

/// The alarm state of one target.
#[derive(Debug, Clone, PartialEq)]
pub struct AlarmMonitor {
    thresholds: AlarmThresholds,
    deformation: Track,
    rate: Track,
    stale: Track,
    last_pose: Option<(i64, Pose)>,
}

impl AlarmMonitor {
    /// A monitor starting from known levels (the last stored transition of each kind).
    pub fn new(thresholds: AlarmThresholds, deformation: Level, rate: Level, stale: Level) -> Self {
        Self {
            thresholds,
            deformation: Track::new(deformation),
            rate: Track::new(rate),
            stale: Track::new(stale),
            last_pose: None,
        }
    }

    /// The overall level: the highest of the three.
    pub fn level(&self) -> Level {
        self.deformation
            .level
            .max(self.rate.level)
            .max(self.stale.level)
    }

    /// Feeds one result: its time, `target_from_base`, and the deformation magnitudes (rotation
    /// arcsec, translation mm) when the target has a reference.
    pub fn update(
        &mut self,
        time_ns: i64,
        target_from_base: &Pose,
        deformation: Option<(f64, f64)>,
    ) -> Vec<Transition> {
        let t = self.thresholds;
        let dwell_ns = (t.dwell_s * 1e9) as i64;
        let mut out = Vec::new();
        if let Some((rot, tr)) = deformation {
            let current = self.deformation.level;
            let candidate = level_of(
                rot,
                t.warn_rotation_arcsec,
                t.alarm_rotation_arcsec,
                current,
                t.hysteresis,
            )
            .max(level_of(
                tr,
                t.warn_translation_mm,
                t.alarm_translation_mm,
                current,
                t.hysteresis,
            ));
            if let Some((from, to)) = self.deformation.step(candidate, time_ns, dwell_ns) {
                let (value, unit) = deciding(
                    (
                        rot,
                        t.warn_rotation_arcsec,
                        t.alarm_rotation_arcsec,
                        ValueUnit::Arcsec,
                    ),
                    (
                        tr,
                        t.warn_translation_mm,
                        t.alarm_translation_mm,
                        ValueUnit::Mm,
                    ),
                );
                out.push(Transition {
                    kind: AlarmKind::Deformation,
                    time_ns,
                    from,
                    to,
                    value,
                    unit,
                    message: format!(
                        "deformation {} -> {}: {rot:.1} arcsec, {tr:.3} mm",
                        from.name(),
                        to.name()
                    ),
                });
            }
        }
        if let Some((t0, p0)) = self.last_pose
            && time_ns > t0
        {
            let dt_s = (time_ns - t0) as f64 / 1e9;
            let d = target_from_base * p0.inverse();
            let rot_rate = so3_log(&d.rotation).norm() * ARCSEC_PER_RAD / dt_s;
            let tr_rate =
                (target_from_base.translation.vector - p0.translation.vector).norm() / dt_s;
            let current = self.rate.level;
            let candidate = level_of(
                rot_rate,
                None,
                t.rate_rotation_arcsec_per_s,
                current,
                t.hysteresis,
            )
            .max(level_of(
                tr_rate,
                None,
                t.rate_translation_mm_per_s,
                current,
                t.hysteresis,
            ));
            if let Some((from, to)) = self.rate.step(candidate, time_ns, dwell_ns) {
                let (value, unit) = deciding(
                    (
                        rot_rate,
                        None,
                        t.rate_rotation_arcsec_per_s,
                        ValueUnit::ArcsecPerS,
                    ),
                    (
                        tr_rate,
                        None,
                        t.rate_translation_mm_per_s,
                        ValueUnit::MmPerS,
                    ),
                );
                out.push(Transition {
                    kind: AlarmKind::Rate,
                    time_ns,
                    from,
                    to,
                    value,
                    unit,
                    message: format!(
                        "rate of change {} -> {}: {rot_rate:.1} arcsec/s, {tr_rate:.3} mm/s",
                        from.name(),
                        to.name()
                    ),
                });
            }
        }
        self.last_pose = Some((time_ns, *target_from_base));
        out
    }

    /// Judges staleness at `now_ns` on the server's clock: `age_s` is how long the link that is
    /// furthest behind (`link`, relative to its limit) has delivered nothing, `limit_s` its
    /// staleness limit. Called periodically, whether results come or not.
    pub fn liveness(
        &mut self,
        now_ns: i64,
        link: &str,
        age_s: f64,
        limit_s: f64,
    ) -> Option<Transition> {
        let t = self.thresholds;
        let candidate = level_of(
            age_s / limit_s,
            None,
            Some(1.0),
            self.stale.level,
            t.hysteresis,
        );
        let (from, to) = self
            .stale
            .step(candidate, now_ns, (t.dwell_s * 1e9) as i64)?;
        Some(Transition {
            kind: AlarmKind::Stale,
            time_ns: now_ns,
            from,
            to,
            value: age_s,
            unit: ValueUnit::S,
            message: if to > Level::None {
                format!("no sample from link {link} for {age_s:.1} s (limit {limit_s:.1} s)")
            } else {
                format!("every link delivers again ({link}: last sample {age_s:.1} s ago)")
            },
        })
    }
}

/// What acknowledging a stored transition does.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Acknowledging {
    /// Record the acknowledgement.
    Record,
    /// The same person already acknowledged it with the same note: nothing to write (a
    /// retried request).
    AlreadyRecorded,
}

/// Why a transition cannot be acknowledged.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AckRefusal {
    /// A return to `none`: there is nothing to acknowledge.
    ReturnToNone,
    /// Someone else (or the same person with another note) acknowledged it already.
    AlreadyAcknowledged {
        /// Who did.
        by: String,
    },
}

/// Whether a transition to `to` whose acknowledgement so far is `previous` (`(by, note)`)
/// takes the acknowledgement of `by` with `note`.
pub fn acknowledging(
    to: Level,
    previous: Option<(&str, Option<&str>)>,
    by: &str,
    note: Option<&str>,
) -> Result<Acknowledging, AckRefusal> {
    if to == Level::None {
        return Err(AckRefusal::ReturnToNone);
    }
    match previous {
        None => Ok(Acknowledging::Record),
        Some((prev_by, prev_note)) if prev_by == by && prev_note == note => {
            Ok(Acknowledging::AlreadyRecorded)
        }
        Some((prev_by, _)) => Err(AckRefusal::AlreadyAcknowledged {
            by: prev_by.to_owned(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_acknowledgement_is_recorded_once_and_refused_to_another() {
        assert_eq!(
            acknowledging(Level::Alarm, None, "ana", Some("seen")),
            Ok(Acknowledging::Record)
        );
        assert_eq!(
            acknowledging(
                Level::Warn,
                Some(("ana", Some("seen"))),
                "ana",
                Some("seen")
            ),
            Ok(Acknowledging::AlreadyRecorded),
            "a retry is no conflict"
        );
        assert_eq!(
            acknowledging(Level::Warn, Some(("ana", Some("seen"))), "ana", None),
            Err(AckRefusal::AlreadyAcknowledged { by: "ana".into() }),
            "another note is a conflict"
        );
        assert_eq!(
            acknowledging(Level::Alarm, Some(("ana", None)), "bo", None),
            Err(AckRefusal::AlreadyAcknowledged { by: "ana".into() })
        );
        assert_eq!(
            acknowledging(Level::None, None, "ana", None),
            Err(AckRefusal::ReturnToNone)
        );
    }

    fn thresholds() -> AlarmThresholds {
        AlarmThresholds {
            warn_rotation_arcsec: Some(60.0),
            alarm_rotation_arcsec: Some(120.0),
            warn_translation_mm: None,
            alarm_translation_mm: None,
            hysteresis: 0.1,
            dwell_s: 1.0,
            rate_rotation_arcsec_per_s: None,
            rate_translation_mm_per_s: None,
        }
    }

    /// Feeds a deformation series at 25 Hz; returns the transitions as (second, from, to).
    fn run(values: impl Iterator<Item = f64>) -> Vec<(f64, Level, Level)> {
        let mut m = AlarmMonitor::new(thresholds(), Level::None, Level::None, Level::None);
        let mut out = Vec::new();
        for (k, v) in values.enumerate() {
            let t = k as i64 * 40_000_000;
            for tr in m.update(t, &Pose::identity(), Some((v, 0.0))) {
                out.push((t as f64 / 1e9, tr.from, tr.to));
            }
        }
        out
    }

    /// A deterministic jitter in [-1, 1).
    fn jitter(k: usize) -> f64 {
        ((k as f64 * 12.9898).sin() * 43758.5453).fract() * 2.0 - 1.0
    }

    #[test]
    fn a_ramp_up_and_down_crosses_each_level_once_each_way() {
        // 0 to 150 arcsec in 30 s, 10 s at 150, back to 0 in 30 s, with 3 arcsec of noise.
        let series = (0..(70 * 25)).map(|k| {
            let t = k as f64 / 25.0;
            let v = if t < 30.0 {
                t * 5.0
            } else if t < 40.0 {
                150.0
            } else {
                150.0 - (t - 40.0) * 5.0
            };
            v.max(0.0) + 3.0 * jitter(k)
        });
        let levels: Vec<(Level, Level)> = run(series).into_iter().map(|(_, f, t)| (f, t)).collect();
        use Level::*;
        assert_eq!(
            levels,
            [(None, Warn), (Warn, Alarm), (Alarm, Warn), (Warn, None)]
        );
    }

    #[test]
    fn noise_hovering_at_a_threshold_does_not_flap() {
        // 60 +- 5 arcsec for a minute: one entry into warn at most, never back and forth.
        let out = run((0..(60 * 25)).map(|k| 60.0 + 5.0 * jitter(k)));
        assert!(out.len() <= 1, "{out:?}");
    }

    #[test]
    fn a_short_excursion_shorter_than_the_dwell_is_not_an_alarm() {
        let out = run((0..(10 * 25)).map(|k| if (100..110).contains(&k) { 200.0 } else { 0.0 }));
        assert!(out.is_empty(), "{out:?}");
    }

    #[test]
    fn a_transition_decided_by_translation_reports_the_translation() {
        let mut t = thresholds();
        t.warn_translation_mm = Some(1.0);
        t.alarm_translation_mm = Some(2.0);
        t.dwell_s = 0.0;
        let mut m = AlarmMonitor::new(t, Level::None, Level::None, Level::None);
        let pose = Pose::identity();
        // 10 arcsec (a sixth of the rotation's warn) and 1.5 mm (over the translation's warn).
        let out = m.update(0, &pose, Some((10.0, 1.5)));
        assert_eq!(out.len(), 1);
        assert_eq!(out[0].to, Level::Warn);
        assert_eq!((out[0].value, out[0].unit), (1.5, ValueUnit::Mm));
        // Rotation over its alarm threshold decides the next one.
        let out = m.update(40_000_000, &pose, Some((130.0, 1.5)));
        assert_eq!(
            (out[0].to, out[0].value, out[0].unit),
            (Level::Alarm, 130.0, ValueUnit::Arcsec)
        );
    }

    #[test]
    fn a_fast_change_raises_the_rate_alarm() {
        let mut t = thresholds();
        t.rate_rotation_arcsec_per_s = Some(30.0);
        t.dwell_s = 0.0;
        let mut m = AlarmMonitor::new(t, Level::None, Level::None, Level::None);
        let turn = |arcsec: f64| {
            Pose::from_parts(
                nalgebra::Translation3::new(0.0, 0.0, 0.0),
                crate::geometry::rotation_from_euler([(arcsec / 3600.0f64).to_radians(), 0.0, 0.0])
                    .unwrap(),
            )
        };
        assert!(m.update(0, &turn(0.0), None).is_empty());
        // 10 arcsec in 40 ms is 250 arcsec/s.
        let out = m.update(40_000_000, &turn(10.0), None);
        assert_eq!(out.len(), 1);
        assert_eq!((out[0].kind, out[0].to), (AlarmKind::Rate, Level::Alarm));
        assert_eq!(m.level(), Level::Alarm);
        let out = m.update(80_000_000, &turn(10.0), None);
        assert_eq!((out[0].kind, out[0].to), (AlarmKind::Rate, Level::None));
    }

    #[test]
    fn staleness_holds_for_the_dwell_and_clears_below_the_hysteresis() {
        // Dwell 1 s, hysteresis 0.1, limit 2 s: checked every 0.25 s of the server's clock.
        let mut m = AlarmMonitor::new(thresholds(), Level::None, Level::None, Level::None);
        let s = |x: f64| (x * 1e9) as i64;
        let mut at = |now: f64, age: f64| m.liveness(s(now), "C1_from_B", age, 2.0);
        // The feed stops at 0: the age passes the limit at 2 s, the alarm comes after the dwell.
        for k in 0..12 {
            let now = k as f64 * 0.25;
            assert_eq!(at(now, now), None, "at {now} s");
        }
        let on = at(3.0, 3.0).expect("stale after the limit and the dwell");
        assert_eq!(
            (on.kind, on.from, on.to),
            (AlarmKind::Stale, Level::None, Level::Alarm)
        );
        assert_eq!((on.value, on.unit, on.time_ns), (3.0, ValueUnit::S, s(3.0)));
        assert!(on.message.contains("C1_from_B"), "{}", on.message);
        // Samples again: an age of 1.9 s is under the limit but within the hysteresis band.
        assert_eq!(at(10.0, 1.9), None);
        assert_eq!(at(12.0, 1.9), None);
        // Well under it: cleared once the dwell has passed.
        assert_eq!(at(13.0, 0.1), None);
        let off = at(14.0, 0.1).expect("cleared after the dwell");
        assert_eq!((off.from, off.to), (Level::Alarm, Level::None));
        // A single late check that crosses the limit briefly does not raise it.
        assert_eq!(at(20.0, 2.5), None);
        assert_eq!(at(20.5, 0.1), None);
        assert_eq!(at(22.0, 0.1), None);
    }
}
