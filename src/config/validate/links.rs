//! `[[links]]`: the frame graph, calibrated links and measured links with their filter tuning.

use super::*;

impl Validator {
    pub(super) fn links(&mut self, raw: &RawFile) -> (Topology, Vec<LinkSpec>) {
        let mut topology = Topology::new();
        // Frames of cameras and markers exist even when no link touches them.
        for c in &raw.cameras {
            if is_valid_frame_name(&c.get_ref().frame) {
                topology.add_frame(&c.get_ref().frame);
            }
        }
        for m in &raw.markers {
            if is_valid_frame_name(&m.get_ref().frame) {
                topology.add_frame(&m.get_ref().frame);
            }
        }
        let mut specs = Vec::new();
        let empty_filter = raw::RawFilter::default();
        for spanned in &raw.links {
            let at = spanned.span().start;
            let l = spanned.get_ref();
            let Some((parent, child)) = split_link_name(&l.name) else {
                self.problem(
                    at,
                    format!(
                        "link name `{}` is not of the form <parent>_from_<child>",
                        l.name
                    ),
                );
                continue;
            };
            let mut ok = self.frame_name(at, parent) & self.frame_name(at, child);
            for (key, given, expected) in
                [("parent", &l.parent, parent), ("child", &l.child, child)]
            {
                if let Some(given) = given
                    && given != expected
                {
                    self.problem(
                            at,
                            format!(
                                "link `{}` does not match its frames: its name says {key} `{expected}` but {key} = `{given}`",
                                l.name
                            ),
                        );
                    ok = false;
                }
            }
            let kind = match l.kind.as_str() {
                "calibrated" => self.calibrated(at, l),
                "measured" => self.measured(
                    at,
                    l,
                    raw.filter.as_ref().map_or(&empty_filter, |f| f.get_ref()),
                ),
                other => {
                    self.problem(
                        at,
                        format!(
                            "link `{}`: kind `{other}` is not one of calibrated, measured",
                            l.name
                        ),
                    );
                    None
                }
            };
            let (Some(kind), true) = (kind, ok) else {
                continue;
            };
            match topology.add_link(&l.name, parent, child) {
                Ok(id) => specs.push(LinkSpec {
                    id,
                    name: l.name.clone(),
                    kind,
                }),
                Err(e) => self.problem(at, e.to_string()),
            }
        }
        (topology, specs)
    }

    pub(super) fn calibrated(&mut self, at: usize, l: &raw::RawLink) -> Option<LinkKind> {
        let what = format!("calibrated link `{}`", l.name);
        for (key, present) in [
            ("model", l.model.is_some()),
            ("expected_rate_hz", l.expected_rate_hz.is_some()),
            ("nominal", l.nominal.is_some()),
            ("random_walk", l.random_walk.is_some()),
            ("acceleration_noise", l.acceleration_noise.is_some()),
            ("oscillation", l.oscillation.is_some()),
        ] {
            if present {
                self.problem(
                    at,
                    format!("{what}: `{key}` applies to measured links only"),
                );
            }
        }
        let Some(raw_pose) = &l.pose else {
            self.problem(at, format!("{what} needs `pose`"));
            return None;
        };
        let Some(raw_sigma) = &l.sigma else {
            self.problem(
                at,
                format!("{what} needs `sigma` (its calibration uncertainty; a calibration is never exact)"),
            );
            return None;
        };
        let pose = self.pose(at, &format!("{what}: pose"), raw_pose)?;
        let sigmas = self.sigmas(at, &format!("{what}: sigma"), raw_sigma)?;
        Some(LinkKind::Calibrated {
            parent_from_child: PoseCov::from_reported_sigmas(pose, &sigmas),
        })
    }

    /// A motion model by its name.
    pub(super) fn motion_model(
        &mut self,
        at: usize,
        what: &str,
        name: &str,
    ) -> Option<MotionModel> {
        let model = MotionModel::parse(name);
        if model.is_none() {
            self.problem(
                at,
                format!(
                    "{what}: model `{name}` is not one of static, constant_velocity, oscillatory"
                ),
            );
        }
        model
    }

    /// A target's `[targets.filter]`: its filter's model and tuning instead of its links'.
    pub(super) fn target_filter(
        &mut self,
        at: usize,
        target: &str,
        f: &raw::RawTargetFilter,
        raw_filter: &raw::RawFilter,
    ) -> Option<crate::model::TargetFilter> {
        let what = format!("target `{target}` filter");
        let Some(name) = f.model.as_deref() else {
            self.problem(at, format!("{what} needs `model`"));
            return None;
        };
        let model = self.motion_model(at, &what, name)?;
        let fit_from_data = f.fit_from_data.unwrap_or(true);
        if fit_from_data && model != MotionModel::Oscillatory {
            self.problem(
                at,
                format!("{what}: `fit_from_data` applies to the oscillatory model (set it false, or leave it out)"),
            );
            return None;
        }
        let keys = TuningKeys {
            random_walk: f.random_walk,
            acceleration_noise: f.acceleration_noise,
            oscillation: f.oscillation,
        };
        let tuning = self.tuning(at, &what, model, keys, raw_filter)?;
        Some(crate::model::TargetFilter {
            tuning,
            fit_from_data: fit_from_data && model == MotionModel::Oscillatory,
        })
    }

    /// A motion model's tuning from its keys (`random_walk`, `acceleration_noise`,
    /// `oscillation`), each checked against the model it applies to.
    pub(super) fn tuning(
        &mut self,
        at: usize,
        what: &str,
        model: MotionModel,
        keys: TuningKeys,
        raw_filter: &raw::RawFilter,
    ) -> Option<FilterTuning> {
        let mut t = FilterTuning::default_for(model);
        let mut ok = true;
        if let Some(rw) = keys.random_walk {
            if model == MotionModel::ConstantVelocity {
                self.problem(
                    at,
                    format!("{what}: `random_walk` applies to the static and oscillatory models"),
                );
                ok = false;
            }
            ok &= self.plausible_rotation(
                at,
                &format!("{what}: random_walk.rotation_arcsec_per_sqrt_s"),
                rw.rotation_arcsec_per_sqrt_s,
            );
            ok &= self.plausible_translation(
                at,
                &format!("{what}: random_walk.translation_mm_per_sqrt_s"),
                rw.translation_mm_per_sqrt_s,
            );
            t.random_walk_rotation_arcsec_per_sqrt_s = rw.rotation_arcsec_per_sqrt_s;
            t.random_walk_translation_mm_per_sqrt_s = rw.translation_mm_per_sqrt_s;
        }
        if let Some(a) = keys.acceleration_noise {
            if model != MotionModel::ConstantVelocity {
                self.problem(
                    at,
                    format!("{what}: `acceleration_noise` applies to the constant_velocity model"),
                );
                ok = false;
            }
            ok &= self.plausible_rotation(
                at,
                &format!("{what}: acceleration_noise.rotation_arcsec_per_s_sqrt_s"),
                a.rotation_arcsec_per_s_sqrt_s,
            );
            ok &= self.plausible_translation(
                at,
                &format!("{what}: acceleration_noise.translation_mm_per_s_sqrt_s"),
                a.translation_mm_per_s_sqrt_s,
            );
            t.acceleration_rotation_arcsec_per_s_sqrt_s = a.rotation_arcsec_per_s_sqrt_s;
            t.acceleration_translation_mm_per_s_sqrt_s = a.translation_mm_per_s_sqrt_s;
        }
        if let Some(o) = keys.oscillation {
            if model != MotionModel::Oscillatory {
                self.problem(
                    at,
                    format!("{what}: `oscillation` applies to the oscillatory model"),
                );
                ok = false;
            }
            ok &= self.duration(
                at,
                &format!("{what}: oscillation.period_s"),
                o.period_s,
                1e-6,
                MAX_DURATION_S,
            );
            ok &= self.duration(
                at,
                &format!("{what}: oscillation.correlation_time_s"),
                o.correlation_time_s,
                1e-6,
                MAX_DURATION_S,
            );
            for v in o.rotation_arcsec.per_axis() {
                ok &=
                    self.plausible_rotation(at, &format!("{what}: oscillation.rotation_arcsec"), v);
            }
            for v in o.translation_mm.per_axis() {
                ok &= self.plausible_translation(
                    at,
                    &format!("{what}: oscillation.translation_mm"),
                    v,
                );
            }
            t.oscillation = crate::filter::OscillationTuning {
                period_s: o.period_s,
                correlation_time_s: o.correlation_time_s,
                rotation_arcsec: o.rotation_arcsec.per_axis(),
                translation_mm: o.translation_mm.per_axis(),
            };
        }
        if let Some(g) = raw_filter.gate_probability {
            t.gate_probability = g;
        }
        if let Some(n) = raw_filter.reinit_after_outliers {
            t.reinit_after_outliers = n.max(1);
        }
        ok.then_some(t)
    }

    pub(super) fn measured(
        &mut self,
        at: usize,
        l: &raw::RawLink,
        raw_filter: &raw::RawFilter,
    ) -> Option<LinkKind> {
        let what = format!("measured link `{}`", l.name);
        if l.pose.is_some() {
            self.problem(
                at,
                format!("{what}: `pose` is for calibrated links; a measured link's designed pose is `nominal`"),
            );
        }
        let model = self.motion_model(at, &what, l.model.as_deref().unwrap_or("static"))?;
        let Some(raw_sigma) = &l.sigma else {
            self.problem(
                at,
                format!("{what} needs `sigma` (the default measurement noise)"),
            );
            return None;
        };
        let sigmas = self.sigmas(at, &format!("{what}: sigma"), raw_sigma)?;
        let Some(rate) = l.expected_rate_hz else {
            self.problem(at, format!("{what} needs `expected_rate_hz`"));
            return None;
        };
        if !self.within(at, &format!("{what}: expected_rate_hz"), rate, 1e-4, 1e5) {
            return None;
        }
        let nominal = match &l.nominal {
            Some(p) => Some(self.pose(at, &format!("{what}: nominal"), p)?),
            None => None,
        };
        let keys = TuningKeys {
            random_walk: l.random_walk,
            acceleration_noise: l.acceleration_noise,
            oscillation: l.oscillation,
        };
        let tuning = self.tuning(at, &what, model, keys, raw_filter)?;
        Some(LinkKind::Measured(MeasuredLink {
            tuning,
            default_sigmas: sigmas,
            expected_rate_hz: rate,
            nominal,
        }))
    }
}

/// The tuning keys of a measured link or a target's filter.
#[derive(Debug, Clone, Copy)]
pub(super) struct TuningKeys {
    random_walk: Option<raw::RawRandomWalk>,
    acceleration_noise: Option<raw::RawAcceleration>,
    oscillation: Option<raw::RawOscillation>,
}
