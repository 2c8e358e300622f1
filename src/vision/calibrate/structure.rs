//! Whether a calibration's residuals have structure its lens model does not explain.
//!
//! A lens model that fits leaves residuals that are noise: their mean over any patch of the
//! image is zero within the noise of a mean. A model that lacks a term (a rational lens fitted
//! with Brown-Conrady's five, a prism fitted without one) leaves the same error wherever the
//! image is seen again, in every view: the mean residual of a patch then stands out of its
//! noise, and coherently over neighbouring patches.
//!
//! The image is cut into [`STRUCTURE_BINS_X`] columns and as many rows as keep the bins square.
//! In each bin with [`MIN_BIN_POINTS`] points or more, the mean residual vector `m` (px) has,
//! per axis, the variance `sum_i s_i^2 / n^2`, `s_i^2` each point's variance as the fit weighed
//! it (its detector's, scaled by the fit's variance factor), so `z^2 = |m|^2 / var` is
//! chi-square with two degrees of freedom when the model fits. Their sum over the bins is
//! judged against the chi-square quantile of `2 B` degrees of freedom at
//! [`STRUCTURE_PROBABILITY`]: one calibration in a thousand that fits is flagged by chance.
//! (The fit takes a little from every residual, so the statistic errs low: it never flags
//! more often than that.)

use super::LensModel;
use crate::chain::chi_square_quantile;
use nalgebra::Vector2;

/// Columns of the grid the residuals are binned on.
pub const STRUCTURE_BINS_X: usize = 8;
/// Fewest points of a bin whose mean is judged.
pub const MIN_BIN_POINTS: usize = 5;
/// The probability of the quantile the statistic is judged by.
pub const STRUCTURE_PROBABILITY: f64 = 0.999;

/// One bin of the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualBin {
    /// Its column and row.
    pub cell: (usize, usize),
    /// Its centre in the image (px).
    pub centre_px: Vector2<f64>,
    /// Points in it.
    pub points: usize,
    /// The mean residual, detected minus predicted (px).
    pub mean_px: Vector2<f64>,
    /// The standard deviation of that mean, per axis (px).
    pub sigma_px: f64,
    /// `|mean|^2 / sigma^2`: chi-square with two degrees of freedom when the model fits.
    pub z2: f64,
}

/// The residuals binned over the image and judged.
#[derive(Debug, Clone, PartialEq)]
pub struct ResidualStructure {
    /// Columns of the grid.
    pub bins_x: usize,
    /// Rows of the grid.
    pub bins_y: usize,
    /// The bins judged (those with [`MIN_BIN_POINTS`] points or more), row by row.
    pub bins: Vec<ResidualBin>,
    /// The sum of their `z2`.
    pub chi2: f64,
    /// Its degrees of freedom: two per bin judged.
    pub dof: usize,
    /// The chi-square quantile at [`STRUCTURE_PROBABILITY`] for `dof`.
    pub threshold: f64,
    /// Whether `chi2` is over it: the residuals have structure the model does not explain.
    pub significant: bool,
}

/// One point's residual: where it was seen (px), detected minus predicted (px), and its
/// variance per axis as the fit weighed it (px^2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointResidual {
    /// Where it was detected (px).
    pub at_px: Vector2<f64>,
    /// Detected minus predicted (px).
    pub residual_px: Vector2<f64>,
    /// Its variance per axis (px^2).
    pub variance_px2: f64,
}

/// The grid over a `width_px` x `height_px` image: `(columns, rows, cell width, cell height)`
/// (px), [`STRUCTURE_BINS_X`] columns and as many rows as keep the cells square.
pub fn structure_grid(width_px: u32, height_px: u32) -> (usize, usize, f64, f64) {
    let (w, h) = (f64::from(width_px), f64::from(height_px));
    let bins_x = STRUCTURE_BINS_X;
    let bins_y = ((bins_x as f64 * h / w).round() as usize).max(1);
    (bins_x, bins_y, w / bins_x as f64, h / bins_y as f64)
}

/// The residuals of a `width_px` x `height_px` image binned and judged; `None` when no bin
/// has enough points.
pub fn residual_structure(
    width_px: u32,
    height_px: u32,
    residuals: &[PointResidual],
) -> Option<ResidualStructure> {
    let (bins_x, bins_y, cell_w, cell_h) = structure_grid(width_px, height_px);
    // Per cell: points, sum of residuals, sum of variances.
    let mut sums = vec![(0usize, Vector2::<f64>::zeros(), 0.0f64); bins_x * bins_y];
    for r in residuals {
        let col = ((r.at_px.x / cell_w).floor().max(0.0) as usize).min(bins_x - 1);
        let row = ((r.at_px.y / cell_h).floor().max(0.0) as usize).min(bins_y - 1);
        let cell = &mut sums[row * bins_x + col];
        cell.0 += 1;
        cell.1 += r.residual_px;
        cell.2 += r.variance_px2;
    }
    let bins: Vec<ResidualBin> = sums
        .iter()
        .enumerate()
        .filter(|(_, (n, _, var))| *n >= MIN_BIN_POINTS && *var > 0.0)
        .map(|(i, &(n, sum, var))| {
            let (col, row) = (i % bins_x, i / bins_x);
            let nf = n as f64;
            let mean_px = sum / nf;
            let variance = var / (nf * nf);
            ResidualBin {
                cell: (col, row),
                centre_px: Vector2::new((col as f64 + 0.5) * cell_w, (row as f64 + 0.5) * cell_h),
                points: n,
                mean_px,
                sigma_px: variance.sqrt(),
                z2: mean_px.norm_squared() / variance,
            }
        })
        .collect();
    if bins.is_empty() {
        return None;
    }
    let chi2 = bins.iter().map(|b| b.z2).sum();
    let dof = 2 * bins.len();
    let threshold = chi_square_quantile(dof, STRUCTURE_PROBABILITY);
    Some(ResidualStructure {
        bins_x,
        bins_y,
        bins,
        chi2,
        dof,
        threshold,
        significant: chi2 > threshold,
    })
}

/// The judgement in a sentence, for reports.
pub fn describe_residual_structure(s: &ResidualStructure, model: LensModel) -> String {
    let worst = s
        .bins
        .iter()
        .max_by(|a, b| a.z2.total_cmp(&b.z2))
        .map(|b| {
            format!(
                "the largest mean ({:.3}, {:.3}) px +- {:.3} near ({:.0}, {:.0}) px",
                b.mean_px.x, b.mean_px.y, b.sigma_px, b.centre_px.x, b.centre_px.y
            )
        })
        .unwrap_or_default();
    if s.significant {
        let next = match model {
            LensModel::Brown => {
                "; try the rational lens model, or look for a plate that is not flat"
            }
            LensModel::Rational => {
                "; try the thin prism (rational_prism), or look for a plate that is not flat"
            }
            LensModel::RationalPrism => {
                "; look for a plate that is not flat or a lens no model here describes"
            }
        };
        format!(
            "the residuals have structure the {model} lens model does not explain: binned over \
             the image, their means give chi-square {:.1} over {} bins (at most {:.1} when the \
             model fits); {worst}{next}",
            s.chi2,
            s.bins.len(),
            s.threshold
        )
    } else {
        format!(
            "the residuals have no structure the {model} lens model leaves: binned over the \
             image, their means give chi-square {:.1} over {} bins (at most {:.1}); {worst}",
            s.chi2,
            s.bins.len(),
            s.threshold
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    fn noise(
        n: usize,
        sigma: f64,
        seed: u64,
        shift: impl Fn(Vector2<f64>) -> Vector2<f64>,
    ) -> Vec<PointResidual> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let normal = Normal::new(0.0, sigma).expect("sigma");
        (0..n)
            .map(|_| {
                let at = Vector2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
                PointResidual {
                    at_px: at,
                    residual_px: Vector2::new(normal.sample(&mut rng), normal.sample(&mut rng))
                        + shift(at),
                    variance_px2: sigma * sigma,
                }
            })
            .collect()
    }

    #[test]
    fn noise_is_flagged_about_as_often_as_the_quantile_says() {
        // 400 sets of pure noise: at 99.9 % none is expected; two would be a 1-in-16 event.
        let flagged = (0..400)
            .filter(|&seed| {
                residual_structure(640, 480, &noise(1500, 0.05, seed, |_| Vector2::zeros()))
                    .expect("bins")
                    .significant
            })
            .count();
        assert!(flagged <= 2, "{flagged} of 400 noise sets flagged");
        // The statistic's mean is its degrees of freedom.
        let mean: f64 = (0..200)
            .map(|seed| {
                let s = residual_structure(
                    640,
                    480,
                    &noise(1500, 0.05, 1000 + seed, |_| Vector2::zeros()),
                )
                .expect("bins");
                s.chi2 / s.dof as f64
            })
            .sum::<f64>()
            / 200.0;
        assert!((mean - 1.0).abs() < 0.03, "mean chi2/dof {mean}");
    }

    #[test]
    fn a_radial_error_under_the_noise_is_flagged() {
        // A radial error growing as r^3 to 0.02 px at the corners, under 0.05 px of noise per
        // point: no point shows it, the bins' means do.
        let radial = |at: Vector2<f64>| {
            let d = (at - Vector2::new(320.0, 240.0)) / 400.0;
            d * d.norm_squared() * 0.02
        };
        let s = residual_structure(640, 480, &noise(6000, 0.05, 7, radial)).expect("bins");
        assert!(s.significant, "chi2 {} threshold {}", s.chi2, s.threshold);
        assert_eq!((s.bins_x, s.bins_y), (8, 6));
        let text = describe_residual_structure(&s, LensModel::Brown);
        assert!(text.contains("rational"), "{text}");
    }

    #[test]
    fn sparse_bins_are_left_out() {
        let few = noise(3, 0.05, 1, |_| Vector2::zeros());
        assert!(residual_structure(640, 480, &few).is_none());
    }
}
