//! The statistics of the paper's Table 4 and 5 (`docs/interface.md`, "HTTP API": `/stats`).
//!
//! Per component of the Euler angles (degrees) and of the translation (mm) of `G_from_B`:
//! count, min, max, mean and rms, where rms is the **population standard deviation**
//! `sqrt(mean((x - mean)^2))`. Angles are unwrapped relative to the first sample before anything
//! is computed, so a series crossing +-180 degrees does not average to zero; min, max and mean
//! are reported in the unwrapped range, the mean wrapped back into (-180, 180].

use crate::geometry::{Pose, euler_from_rotation};

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
}

impl Default for PoseStatsAccumulator {
    fn default() -> Self {
        Self {
            angles: Accumulator::new(),
            translations: Accumulator::new(),
            first: None,
        }
    }
}

impl PoseStatsAccumulator {
    /// Adds one pose.
    pub fn push(&mut self, pose: &Pose) {
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
