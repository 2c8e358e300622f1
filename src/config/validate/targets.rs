//! `[[targets]]`: targets, their paths, filters and alarm thresholds.

use super::*;

impl Validator {
    pub(super) fn targets(&mut self, raw: &RawFile, topology: &Topology) -> Vec<TargetSpec> {
        let mut out: Vec<TargetSpec> = Vec::new();
        if raw.targets.is_empty() {
            // An empty or mistaken file would otherwise run a service that measures nothing.
            self.problems.push(ConfigProblem {
                line: None,
                column: None,
                message: "the installation has no [[targets]]: nothing would be measured \
                          (see `brokenray default-config` for a complete file)"
                    .to_owned(),
            });
        }
        for spanned in &raw.targets {
            let at = spanned.span().start;
            let t = spanned.get_ref();
            if out.iter().any(|o| o.name == t.name) {
                self.problem(at, format!("duplicate target `{}`", t.name));
                continue;
            }
            let alarms = self.alarms(at, &t.name, &t.alarms);
            let filter = match &t.filter {
                Some(f) => match self.target_filter(
                    at,
                    &t.name,
                    f,
                    raw.filter
                        .as_ref()
                        .map_or(&raw::RawFilter::default(), |f| f.get_ref()),
                ) {
                    Some(f) => Some(f),
                    None => continue,
                },
                None => None,
            };
            let resolution = match topology.resolve(&t.base, &t.name) {
                Ok(r) => r,
                Err(ChainError::UnknownFrame(f)) => {
                    self.problem(
                        at,
                        format!("target `{}`: frame `{f}` is not introduced by any link, camera or marker", t.name),
                    );
                    continue;
                }
                Err(e) => {
                    self.problem(at, e.to_string());
                    continue;
                }
            };
            out.push(TargetSpec {
                name: t.name.clone(),
                frame: resolution.target,
                base: resolution.base,
                resolution,
                alarms,
                filter,
            });
        }
        out
    }

    pub(super) fn alarms(
        &mut self,
        at: usize,
        target: &str,
        a: &raw::RawAlarms,
    ) -> AlarmThresholds {
        let what = format!("target `{target}` alarms");
        for (name, v) in [
            ("warn_rotation_arcsec", a.warn_rotation_arcsec),
            ("alarm_rotation_arcsec", a.alarm_rotation_arcsec),
            ("warn_translation_mm", a.warn_translation_mm),
            ("alarm_translation_mm", a.alarm_translation_mm),
        ] {
            if let Some(v) = v {
                self.positive(at, &format!("{what}: {name}"), v);
            }
        }
        for (kind, warn, alarm) in [
            ("rotation", a.warn_rotation_arcsec, a.alarm_rotation_arcsec),
            ("translation", a.warn_translation_mm, a.alarm_translation_mm),
        ] {
            if let (Some(w), Some(al)) = (warn, alarm)
                && w >= al
            {
                self.problem(
                    at,
                    format!(
                        "{what}: the {kind} warn level ({w}) must be below the alarm level ({al})"
                    ),
                );
            }
        }
        let hysteresis = a.hysteresis.unwrap_or(0.1);
        if !(0.0..0.5).contains(&hysteresis) {
            self.problem(
                at,
                format!("{what}: hysteresis must be a fraction from 0 up to 0.5, not {hysteresis}"),
            );
        }
        let dwell_s = a.dwell_s.unwrap_or(1.0);
        self.duration(
            at,
            &format!("{what}: dwell_s"),
            dwell_s,
            0.0,
            MAX_DURATION_S,
        );
        for (name, v) in [
            ("rate_rotation_arcsec_per_s", a.rate_rotation_arcsec_per_s),
            ("rate_translation_mm_per_s", a.rate_translation_mm_per_s),
        ] {
            if let Some(v) = v {
                self.positive(at, &format!("{what}: {name}"), v);
            }
        }
        AlarmThresholds {
            warn_rotation_arcsec: a.warn_rotation_arcsec,
            alarm_rotation_arcsec: a.alarm_rotation_arcsec,
            warn_translation_mm: a.warn_translation_mm,
            alarm_translation_mm: a.alarm_translation_mm,
            hysteresis,
            dwell_s,
            rate_rotation_arcsec_per_s: a.rate_rotation_arcsec_per_s,
            rate_translation_mm_per_s: a.rate_translation_mm_per_s,
        }
    }
}
