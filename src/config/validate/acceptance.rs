//! `[acceptance]`: the procedure's windows, its known moves and its limits.

use super::*;
use crate::acceptance::{Displacement, Limits, Plan, PlannedMove};

/// The largest move a step may state: a stage's travel, not a structure's (mm).
const MAX_MOVE_MM: f64 = 1000.0;
/// The largest rotation a step may state (arc-seconds; 10 degrees).
const MAX_MOVE_ARCSEC: f64 = 36_000.0;

impl Validator {
    /// `[acceptance]`: `Some(None)` without the section.
    pub(super) fn acceptance(
        &mut self,
        raw: &RawFile,
        targets: &[TargetSpec],
    ) -> Option<Option<AcceptanceSettings>> {
        let Some(section) = &raw.acceptance else {
            return Some(None);
        };
        let (at, r) = (section.span().start, section.get_ref());
        let reverify_days = r.reverify_every_days.unwrap_or(365.0);
        let still_s = r.still_s.unwrap_or(30.0);
        let settle_s = r.settle_s.unwrap_or(2.0);
        let step_s = r.step_s.unwrap_or(10.0);
        let mut ok = true;
        if !(reverify_days.is_finite() && (1.0..=3660.0).contains(&reverify_days)) {
            self.problem(
                at,
                format!(
                    "acceptance.reverify_every_days must lie in [1, 3660] days, not {reverify_days}"
                ),
            );
            ok = false;
        }
        ok &= self.duration(at, "acceptance.still_s", still_s, 1.0, 3600.0);
        ok &= self.duration(at, "acceptance.settle_s", settle_s, 0.0, 600.0);
        ok &= self.duration(at, "acceptance.step_s", step_s, 1.0, 3600.0);
        for (key, value) in [
            ("acceptance.still_rms_arcsec", r.still_rms_arcsec),
            ("acceptance.still_rms_mm", r.still_rms_mm),
            ("acceptance.move_arcsec", r.move_arcsec),
            ("acceptance.move_mm", r.move_mm),
        ] {
            ok &= self.positive(at, key, value);
        }
        if r.moves.is_empty() {
            self.problem(
                at,
                "[acceptance] states no [[acceptance.moves]]: the procedure needs at least one known move".into(),
            );
            ok = false;
        }
        let mut moves = Vec::new();
        let mut names = std::collections::HashSet::new();
        for m in &r.moves {
            let (at, m) = (m.span().start, m.get_ref());
            if m.name.trim().is_empty() || m.name.len() > 64 {
                self.problem(
                    at,
                    "acceptance.moves.name must be 1 to 64 characters".into(),
                );
                ok = false;
            } else if !names.insert(m.name.clone()) || m.name == "still" {
                self.problem(
                    at,
                    format!(
                        "acceptance.moves.name `{}` is taken (by another move, or `still`, the first step's)",
                        m.name
                    ),
                );
                ok = false;
            }
            let target = match (&m.target, targets) {
                (Some(name), _) => targets.iter().position(|t| &t.name == name),
                (None, [_]) => Some(0),
                (None, _) => None,
            };
            let Some(target) = target else {
                let known: Vec<&str> = targets.iter().map(|t| t.name.as_str()).collect();
                self.problem(
                    at,
                    match &m.target {
                        Some(name) => format!(
                            "acceptance.moves.target `{name}` is not a target (targets: {})",
                            known.join(", ")
                        ),
                        None => format!(
                            "acceptance.moves `{}` must name its target: the installation has {} (targets: {})",
                            m.name,
                            known.len(),
                            known.join(", ")
                        ),
                    },
                );
                ok = false;
                continue;
            };
            for (key, values, max) in [
                ("rotation_arcsec", m.rotation_arcsec, MAX_MOVE_ARCSEC),
                ("translation_mm", m.translation_mm, MAX_MOVE_MM),
            ] {
                if let Some(v) = values.iter().find(|v| !(v.is_finite() && v.abs() <= max)) {
                    self.problem(
                        at,
                        format!(
                            "acceptance.moves.{key} of `{}` must lie in [-{max}, {max}], not {v}",
                            m.name
                        ),
                    );
                    ok = false;
                }
            }
            if m.rotation_arcsec == [0.0; 3] && m.translation_mm == [0.0; 3] {
                self.warning(
                    at,
                    format!(
                        "acceptance.moves `{}` moves nothing: it repeats the still window",
                        m.name
                    ),
                );
            }
            moves.push(PlannedMove {
                name: m.name.clone(),
                target,
                displacement: Displacement {
                    rotation_arcsec: m.rotation_arcsec,
                    translation_mm: m.translation_mm,
                },
            });
        }
        let ns = |s: f64| (s * 1e9).round() as i64;
        ok.then(|| {
            Some(AcceptanceSettings {
                plan: Plan {
                    targets: targets.len(),
                    still_ns: ns(still_s),
                    step_ns: ns(step_s),
                    settle_ns: ns(settle_s),
                    moves,
                    limits: Limits {
                        still_rms_arcsec: r.still_rms_arcsec,
                        still_rms_mm: r.still_rms_mm,
                        move_arcsec: r.move_arcsec,
                        move_mm: r.move_mm,
                    },
                },
                reverify_every_ns: ns(reverify_days * 86_400.0),
            })
        })
    }
}
