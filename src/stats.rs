//! The statistics of the paper's Table 4 and 5 (`docs/interface.md`, "HTTP API": `/stats`).
//!
//! Per component of the Euler angles (degrees) and of the translation (mm) of `G_from_B`:
//! count, min, max, mean and rms, where rms is the **population standard deviation**
//! `sqrt(mean((x - mean)^2))`. Angles are unwrapped relative to the first sample before anything
//! is computed, so a series crossing +-180 degrees does not average to zero; min, max and mean
//! are reported in the unwrapped range, the mean wrapped back into (-180, 180].
//!
//! **Repeatability against the model.** Given each result's random covariance (the part of its
//! uncertainty that is noise: see [`crate::chain::ErrorTerms`]), the accumulator also gives the
//! rms per component the model expects from it, `sqrt(diag(J R J^T))` with `R` the mean random
//! covariance over the window and `J` the Euler angles' (or the translation's) Jacobian at the
//! first pose, and the chi-square statistic of the scatter, `tr(R^-1 S)` with
//! `S = sum (x_i - mean)(x_i - mean)^T` over the results' left perturbations from the first,
//! against its quantile with `6 (n - 1)` degrees of freedom. Independent results whose noise
//! the model describes stay under it with the quantile's probability; a scatter beyond it says
//! that a `pixel_sigma` or a link's sigma is set too small, or that something moves. Filtered
//! results are correlated in time and carry the motion the filter follows: the statistic
//! applies to raw results.

use crate::geometry::{Mat3, Mat6, Pose, PoseCov, Twist, euler_from_rotation, se3_log, so3_exp};
use statrs::distribution::{ChiSquared, ContinuousCDF};

/// Probability with which the scatter of results the model describes stays under the
/// chi-square quantile the repeatability is judged by.
pub const REPEATABILITY_PROBABILITY: f64 = 0.999;

/// Statistics of three components.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ComponentStats {
    /// Minimum per component.
    pub min: [f64; 3],
    /// Maximum per component.
    pub max: [f64; 3],
    /// Mean per component.
    pub mean: [f64; 3],
    /// Population standard deviation per component.
    pub rms: [f64; 3],
}

/// Table 4 and 5 over a set of poses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseStats {
    /// How many poses.
    pub count: usize,
    /// Euler angles `[Ax, Ay, Az]` (degrees).
    pub euler_deg: ComponentStats,
    /// Translation (mm).
    pub t_mm: ComponentStats,
    /// The scatter against the model's random part, when every pose came with it (and there
    /// were at least two).
    pub repeatability: Option<Repeatability>,
}

/// The scatter of a window of results against what their random covariances expect (see the
/// module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Repeatability {
    /// The rms of each Euler angle the model expects (degrees).
    pub expected_euler_rms_deg: [f64; 3],
    /// The rms of each translation component the model expects (mm).
    pub expected_t_rms_mm: [f64; 3],
    /// `tr(R^-1 S)`.
    pub chi2: f64,
    /// `6 (n - 1)`.
    pub dof: usize,
    /// The chi-square quantile at [`REPEATABILITY_PROBABILITY`].
    pub threshold: f64,
}

impl Repeatability {
    /// True when the scatter exceeds what chance allows for results the model describes.
    pub fn exceeded(&self) -> bool {
        self.chi2 > self.threshold
    }
}

/// Sums of the results' left perturbations from the first and of their random covariances.
#[derive(Debug, Clone, Copy)]
struct ScatterSums {
    first: Pose,
    n: usize,
    sum: Twist,
    sum_outer: Mat6,
    sum_cov: Mat6,
}

impl ScatterSums {
    fn push(&mut self, pose: &Pose, random_cov: &Mat6) {
        let x = se3_log(&(pose * self.first.inverse()));
        self.n += 1;
        self.sum += x;
        self.sum_outer += x * x.transpose();
        self.sum_cov += random_cov;
    }

    fn finish(&self) -> Option<Repeatability> {
        if self.n < 2 {
            return None;
        }
        let n = self.n as f64;
        let r = self.sum_cov / n;
        let scatter = self.sum_outer - self.sum * self.sum.transpose() / n;
        let info = r.cholesky()?.inverse();
        let chi2 = (info * scatter).trace();
        let dof = 6 * (self.n - 1);
        let threshold = ChiSquared::new(dof as f64)
            .map(|d| d.inverse_cdf(REPEATABILITY_PROBABILITY))
            .unwrap_or(f64::INFINITY);
        // The Euler angles' Jacobian with respect to the rotation's left perturbation, by
        // central differences at the first pose.
        let h = 1e-6;
        let mut j = Mat3::zeros();
        for k in 0..3 {
            let mut d = crate::geometry::Vec3::zeros();
            d[k] = h;
            let plus = euler_from_rotation(&(so3_exp(&d) * self.first.rotation)).to_degrees();
            let minus = euler_from_rotation(&(so3_exp(&(-d)) * self.first.rotation)).to_degrees();
            for i in 0..3 {
                j[(i, k)] = wrap_deg(plus[i] - minus[i]) / (2.0 * h);
            }
        }
        let rotation = j * r.fixed_view::<3, 3>(3, 3) * j.transpose();
        let translation = PoseCov {
            pose: self.first,
            cov: r,
        }
        .translation_covariance();
        Some(Repeatability {
            expected_euler_rms_deg: [0, 1, 2].map(|i| rotation[(i, i)].max(0.0).sqrt()),
            expected_t_rms_mm: [0, 1, 2].map(|i| translation[(i, i)].max(0.0).sqrt()),
            chi2,
            dof,
            threshold,
        })
    }
}

/// Wraps an angle difference (degrees) into (-180, 180].
fn wrap_deg(d: f64) -> f64 {
    let w = (d + 180.0).rem_euclid(360.0) - 180.0;
    if w <= -180.0 { w + 360.0 } else { w }
}

/// Streaming accumulator (Welford) of three components.
#[derive(Debug, Clone, Copy)]
struct Accumulator {
    n: usize,
    min: [f64; 3],
    max: [f64; 3],
    mean: [f64; 3],
    m2: [f64; 3],
}

impl Accumulator {
    fn new() -> Self {
        Self {
            n: 0,
            min: [f64::INFINITY; 3],
            max: [f64::NEG_INFINITY; 3],
            mean: [0.0; 3],
            m2: [0.0; 3],
        }
    }

    fn push(&mut self, x: [f64; 3]) {
        self.n += 1;
        let n = self.n as f64;
        for (i, &xi) in x.iter().enumerate() {
            self.min[i] = self.min[i].min(xi);
            self.max[i] = self.max[i].max(xi);
            let d = xi - self.mean[i];
            self.mean[i] += d / n;
            self.m2[i] += d * (xi - self.mean[i]);
        }
    }

    fn finish(&self) -> ComponentStats {
        let n = self.n.max(1) as f64;
        ComponentStats {
            min: self.min,
            max: self.max,
            mean: self.mean,
            rms: self.m2.map(|m| (m / n).sqrt()),
        }
    }
}

/// Table 4/5 statistics of a series of `G_from_B` poses; `None` for an empty series.
pub fn pose_stats<'a>(poses: impl IntoIterator<Item = &'a Pose>) -> Option<PoseStats> {
    let mut acc = PoseStatsAccumulator::default();
    for pose in poses {
        acc.push(pose);
    }
    acc.finish()
}

/// [`pose_stats`] one pose at a time, for a series read as a stream: constant memory.
#[derive(Debug, Clone, Copy)]
pub struct PoseStatsAccumulator {
    angles: Accumulator,
    translations: Accumulator,
    first: Option<[f64; 3]>,
    /// `None` once a pose came without its random covariance.
    scatter: Option<ScatterSums>,
    all_with_covariance: bool,
}

impl Default for PoseStatsAccumulator {
    fn default() -> Self {
        Self {
            angles: Accumulator::new(),
            translations: Accumulator::new(),
            first: None,
            scatter: None,
            all_with_covariance: true,
        }
    }
}

impl PoseStatsAccumulator {
    /// Adds one pose with its random covariance, for the repeatability.
    pub fn push_with_random(&mut self, pose: &Pose, random_cov: &Mat6) {
        if self.all_with_covariance {
            self.scatter
                .get_or_insert(ScatterSums {
                    first: *pose,
                    n: 0,
                    sum: Twist::zeros(),
                    sum_outer: Mat6::zeros(),
                    sum_cov: Mat6::zeros(),
                })
                .push(pose, random_cov);
        }
        self.push_pose(pose);
    }

    /// Adds one pose without a covariance: the window gets no repeatability.
    pub fn push(&mut self, pose: &Pose) {
        self.all_with_covariance = false;
        self.scatter = None;
        self.push_pose(pose);
    }

    fn push_pose(&mut self, pose: &Pose) {
        let e = euler_from_rotation(&pose.rotation).to_degrees();
        let reference = *self.first.get_or_insert(e);
        let unwrapped = [0, 1, 2].map(|i| reference[i] + wrap_deg(e[i] - reference[i]));
        self.angles.push(unwrapped);
        self.translations.push(pose.translation.vector.into());
    }

    /// The statistics of the poses added, `None` when there were none.
    pub fn finish(&self) -> Option<PoseStats> {
        if self.angles.n == 0 {
            return None;
        }
        let mut euler_deg = self.angles.finish();
        euler_deg.mean = euler_deg.mean.map(|m| {
            let w = wrap_deg(m);
            if w == -180.0 { 180.0 } else { w }
        });
        Some(PoseStats {
            count: self.angles.n,
            euler_deg,
            t_mm: self.translations.finish(),
            repeatability: self.scatter.as_ref().and_then(ScatterSums::finish),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rotation_from_euler;
    use approx::assert_relative_eq;
    use nalgebra::Translation3;

    #[test]
    fn angles_crossing_180_do_not_average_to_zero() {
        let poses: Vec<Pose> = [179.0_f64, -179.0, 179.5, -179.5]
            .iter()
            .map(|az| {
                Pose::from_parts(
                    Translation3::new(0.0, 0.0, 0.0),
                    rotation_from_euler([0.0, 0.0, az.to_radians()]).unwrap(),
                )
            })
            .collect();
        let s = pose_stats(&poses).unwrap();
        assert_relative_eq!(s.euler_deg.mean[2].abs(), 180.0, epsilon = 1e-9);
        // Spread of +-1 and +-0.5 degrees about 180: population sd = sqrt((1 + 1 + 0.25 + 0.25)/4).
        assert_relative_eq!(s.euler_deg.rms[2], (2.5f64 / 4.0).sqrt(), epsilon = 1e-9);
    }

    #[test]
    fn empty_series_has_no_statistics() {
        assert!(pose_stats(&[]).is_none());
    }
}
