//! `[[cameras]]` and `[cameras.source]`: the camera models, their intrinsics' covariance, and
//! the cameras the service takes frames from itself.

use super::*;
use crate::vision::{Intrinsic, LensModel};

impl Validator {
    pub(super) fn cameras(&mut self, raw: &RawFile) -> Vec<Camera> {
        let mut out = Vec::new();
        for spanned in &raw.cameras {
            let at = spanned.span().start;
            let c = spanned.get_ref();
            let what = format!("camera `{}`", c.frame);
            let mut ok = self.frame_name(at, &c.frame);
            if c.width == 0 || c.height == 0 {
                self.problem(at, format!("{what}: width and height must be positive"));
                ok = false;
            }
            ok &= self.positive(at, &format!("{what}: fx"), c.fx);
            ok &= self.positive(at, &format!("{what}: fy"), c.fy);
            ok &= self.finite(at, &format!("{what}: principal point"), &[c.cx, c.cy]);
            ok &= self.finite(at, &format!("{what}: distortion"), &c.distortion);
            // OpenCV's lengths: four (no k3) counts as Brown-Conrady's five.
            let model = match c.distortion.len() {
                0 | 4 => Some(LensModel::Brown),
                n => LensModel::with_terms(n),
            };
            let Some(model) = model else {
                self.problem(
                    at,
                    format!(
                        "{what}: distortion has {} numbers; it takes OpenCV's 4, 5, 8 or 12 (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]])",
                        c.distortion.len()
                    ),
                );
                continue;
            };
            ok &= self.positive(at, &format!("{what}: pixel_sigma"), c.pixel_sigma);
            if let Some(gain) = c.gain_e_per_dn {
                ok &= self.positive(at, &format!("{what}: gain_e_per_dn"), gain);
            }
            let intrinsics_covariance = match &c.intrinsics_covariance {
                Some(values) => match intrinsics_covariance(values, model) {
                    Ok(cov) => Some(cov),
                    Err(reason) => {
                        self.problem(at, format!("{what}: intrinsics_covariance {reason}"));
                        ok = false;
                        None
                    }
                },
                None => {
                    self.warning(at, format!(
                            "{what}: no intrinsics_covariance, so its calibration is taken as exact and no sigma includes its error (`brokenray calibrate-camera --out` writes it)"
                        ));
                    None
                }
            };
            if ok {
                out.push(Camera {
                    frame: c.frame.clone(),
                    intrinsics: CameraModel::pinhole(c.fx, c.fy, c.cx, c.cy, c.width, c.height)
                        .with_distortion(&c.distortion),
                    pixel_sigma_px: c.pixel_sigma,
                    gain_e_per_dn: c.gain_e_per_dn,
                    intrinsics_covariance,
                });
            }
        }
        out
    }

    /// Every camera's `calibration_report`. A page that is not there is a warning, not a
    /// problem: the installation may be checked on another machine, or the page written after
    /// it; the dashboard's link then says the page cannot be read.
    pub(super) fn calibration_reports(&mut self, raw: &RawFile) -> Vec<CalibrationReportFile> {
        let mut out = Vec::new();
        for spanned in &raw.cameras {
            let at = spanned.span().start;
            let c = spanned.get_ref();
            let Some(path) = &c.calibration_report else {
                continue;
            };
            let what = format!("camera `{}`: calibration_report", c.frame);
            if path.trim().is_empty() {
                self.problem(at, format!("{what} is empty; name the HTML page `brokenray calibrate-camera --report DIR` wrote (DIR/calibration.html)"));
                continue;
            }
            let path = PathBuf::from(path);
            if !path.is_file() {
                self.warning(
                    at,
                    format!(
                        "{what} `{}` is not a file here, so the dashboard's link to it will say it cannot be read",
                        path.display()
                    ),
                );
            }
            out.push(CalibrationReportFile {
                camera: c.frame.clone(),
                path,
            });
        }
        out
    }

    /// Every camera's `[cameras.source]`; `None` when one has a problem.
    pub(super) fn sources(&mut self, raw: &RawFile) -> Option<Vec<CameraSource>> {
        let mut out = Vec::new();
        let mut ok = true;
        let mut addresses = std::collections::HashMap::new();
        for spanned in &raw.cameras {
            let c = spanned.get_ref();
            let Some(s) = &c.source else { continue };
            // Problems point at the source's own table.
            let at = s.span().start;
            match self.source(at, &c.frame, s.get_ref()) {
                Some(source) => {
                    if let Some(other) =
                        addresses.insert(source.address.to_string(), c.frame.clone())
                    {
                        self.problem(
                            at,
                            format!(
                                "camera `{}`: source.address `{}` is camera `{other}`'s already",
                                c.frame, source.address
                            ),
                        );
                        ok = false;
                    }
                    out.push(source);
                }
                None => ok = false,
            }
        }
        // The cameras of a trigger group share its rate and its trigger.
        for (i, a) in out.iter().enumerate() {
            if a.trigger == TriggerMode::FreeRun {
                continue;
            }
            if let Some(b) = out[..i]
                .iter()
                .find(|b| b.trigger != TriggerMode::FreeRun && b.trigger_group == a.trigger_group)
                && (b.trigger != a.trigger || b.rate_hz != a.rate_hz)
            {
                let at = raw
                    .cameras
                    .iter()
                    .find(|c| c.get_ref().frame == a.camera)
                    .and_then(|c| c.get_ref().source.as_ref())
                    .map_or(0, |s| s.span().start);
                self.problem(
                    at,
                    format!(
                        "camera `{}`: source.trigger_group `{}` has camera `{}` with trigger `{}` at {} Hz; a group's cameras share one trigger and one rate",
                        a.camera, a.trigger_group, b.camera, b.trigger, b.rate_hz
                    ),
                );
                ok = false;
            }
        }
        ok.then_some(out)
    }

    /// One camera's `[cameras.source]`.
    pub(super) fn source(
        &mut self,
        at: usize,
        camera: &str,
        s: &super::raw::RawSource,
    ) -> Option<CameraSource> {
        let what = format!("camera `{camera}`: source");
        let mut ok = true;
        let address = CameraAddress::parse(&s.address)
            .map_err(|e| self.problem(at, format!("{what}.address {e}")))
            .ok();
        let pixel_format = self.word(
            at,
            &format!("{what}.pixel_format"),
            s.pixel_format.as_deref(),
            PixelFormat::Mono8,
        );
        let trigger = self.word(
            at,
            &format!("{what}.trigger"),
            s.trigger.as_deref(),
            TriggerMode::FreeRun,
        );
        let timestamp = self.word(
            at,
            &format!("{what}.timestamp"),
            s.timestamp.as_deref(),
            TimestampMode::HostFit,
        );
        let rate_hz = s.rate_hz.unwrap_or(10.0);
        ok &= self.within(at, &format!("{what}.rate_hz"), rate_hz, 0.01, 1000.0);
        if let Some(e) = s.exposure_us {
            ok &= self.within(at, &format!("{what}.exposure_us"), e, 1.0, 10e6);
            if e * 1e-6 >= 1.0 / rate_hz {
                self.problem(
                    at,
                    format!(
                        "{what}.exposure_us {e} does not fit in a frame period at rate_hz {rate_hz}"
                    ),
                );
                ok = false;
            }
        }
        if let Some(g) = s.gain_db {
            ok &= self.within(at, &format!("{what}.gain_db"), g, -20.0, 60.0);
        }
        if let Some(o) = s.stamp_offset_us {
            ok &= self.within(at, &format!("{what}.stamp_offset_us"), o, -10e6, 10e6);
        }
        if let Some(l) = s.latency_us {
            ok &= self.within(at, &format!("{what}.latency_us"), l, 0.0, 10e6);
        }
        let tai_offset_s = s.tai_offset_s.unwrap_or(37.0);
        ok &= self.within(at, &format!("{what}.tai_offset_s"), tai_offset_s, -1e9, 1e9);
        let tolerance_ms = s.tolerance_ms.unwrap_or(100.0);
        ok &= self.within(
            at,
            &format!("{what}.tolerance_ms"),
            tolerance_ms,
            0.1,
            60_000.0,
        );
        if let Some(p) = s.packet_size_bytes
            && !(576..=16_384).contains(&p)
        {
            self.problem(
                at,
                format!("{what}.packet_size_bytes {p} is outside 576 to 16384"),
            );
            ok = false;
        }
        let mut features = Vec::new();
        for f in &s.features {
            match FeatureSetting::parse(f) {
                Ok(f) => features.push(f),
                Err(e) => {
                    self.problem(at, format!("{what}.features {e}"));
                    ok = false;
                }
            }
        }
        let group = s
            .trigger_group
            .clone()
            .unwrap_or_else(|| "default".to_owned());
        if group.is_empty() || group.len() > 64 {
            self.problem(
                at,
                format!("{what}.trigger_group must be 1 to 64 characters"),
            );
            ok = false;
        }
        if trigger == Some(TriggerMode::Line) && s.trigger_line.is_none() {
            self.warning(
                at,
                format!("{what}: trigger `line` with no trigger_line: Line0 is taken"),
            );
        }
        if timestamp == Some(TimestampMode::Host) {
            self.warning(at, format!(
                    "{what}: timestamp `host` takes a frame's arrival minus latency_us as its time: the transfer's jitter (milliseconds) moves every result of a moving structure; `ptp` or `host_fit` do not"
                ));
        }
        Some(CameraSource {
            camera: camera.to_owned(),
            address: address?,
            pixel_format: pixel_format?,
            trigger: trigger?,
            trigger_group: group,
            trigger_line: s.trigger_line.clone().unwrap_or_else(|| "Line0".to_owned()),
            rate_hz,
            exposure_us: s.exposure_us,
            gain_db: s.gain_db,
            timestamp: timestamp?,
            stamp_offset_us: s.stamp_offset_us,
            latency_us: s.latency_us,
            tai_offset_s,
            tolerance_ms,
            packet_size_bytes: s.packet_size_bytes,
            features,
        })
        .filter(|_| ok)
    }
}

/// A camera's `intrinsics_covariance` (`n x n` numbers, row-major, `fx fy cx cy` and the
/// distortion terms of the camera's lens `model`) checked: finite, symmetric, positive
/// semi-definite (a calibration's fixed parameters leave zero rows); otherwise what is wrong
/// with it. The terms beyond the model have zero rows and columns.
fn intrinsics_covariance(
    values: &[f64],
    model: LensModel,
) -> Result<crate::chain::IntrinsicsCovariance, String> {
    let names = Intrinsic::of_model(model);
    let n = names.len();
    if values.len() != n * n {
        let words: Vec<&str> = names.iter().map(|p| p.name()).collect();
        return Err(format!(
            "must have {} numbers ({n} x {n}, row-major, in the order {}: the {} lens model of the camera's {} distortion coefficients), not {}",
            n * n,
            words.join(" "),
            model.name(),
            model.distortion_terms(),
            values.len()
        ));
    }
    if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(format!("entry {i} is not a finite number ({v})"));
    }
    let mut cov = crate::chain::IntrinsicsCovariance::zeros();
    cov.view_mut((0, 0), (n, n))
        .copy_from(&nalgebra::DMatrix::from_row_slice(n, n, values));
    // Plausible variances: a focal length or principal point known to 10 000 px, a
    // distortion term to 100, is no calibration at all; beyond, the sigmas it feeds are huge
    // or not finite.
    for (i, name) in names.iter().enumerate() {
        let max = if i < 4 { 1e8 } else { 1e4 };
        let v = cov[(i, i)];
        if v > max {
            return Err(format!(
                "has a variance of {v:e} for {name} (entry {}), beyond the plausible {max:e}",
                i * (n + 1)
            ));
        }
    }
    let scale = cov.amax().max(f64::MIN_POSITIVE);
    for i in 0..n {
        for j in 0..i {
            if (cov[(i, j)] - cov[(j, i)]).abs() > 1e-9 * scale {
                return Err(format!(
                    "is not symmetric (row {i}, column {j}: {} against {})",
                    cov[(i, j)],
                    cov[(j, i)]
                ));
            }
        }
    }
    let smallest = nalgebra::SymmetricEigen::new((cov + cov.transpose()) * 0.5)
        .eigenvalues
        .min();
    // The file's numbers are rounded, so a tiny negative eigenvalue is rounding: at most a
    // billionth of the largest entry, and never more than 1e-9 whatever the entries.
    if smallest < -1e-9 * scale.min(1.0) {
        return Err(format!(
            "is not positive semi-definite (an eigenvalue of {smallest:e})"
        ));
    }
    Ok(cov)
}
