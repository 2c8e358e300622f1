//! The plate's shape: a printed plate is not flat.
//!
//! A plate glued or printed on board sags or bows by a fraction of a millimetre, and a fit that
//! takes it as flat moves the focal length to explain it (a plate 250 mm wide bowed by 0.5 mm
//! shifts a 540 px focal length by several pixels) while its residual barely changes. The
//! shape fitted here is mrcal's `calobject_warp`: a parabolic cylinder along each of the
//! plate's axes,
//!
//! ```text
//! dz = sag_x (1 - xn^2) + sag_y (1 - yn^2)
//! ```
//!
//! along the plate's z axis, with `xn` and `yn` running from -1 to 1 across the span of the
//! plate's points. `sag_x` is the height of the plate's middle above its two edges along x
//! (mm), `sag_y` the same along y. Their constant part moves the whole plate along its
//! normal, which each view's pose takes; the views determine the rest.
//!
//! [`PlateShape::Auto`] fits the sag and keeps it when the data support it: when its Wald
//! statistic `s^T C^-1 s` (the two sags against their covariance) exceeds the chi-square
//! quantile of two degrees of freedom at 99 % ([`SAG_SIGNIFICANCE_CHI2`]), otherwise the
//! plate is fitted flat, so an honest flat plate keeps its smaller covariance.

use crate::geometry::Vec3;

crate::words! {
    /// The shape a plate is fitted with.
    pub enum PlateShape("plate shape") {
        /// The sag is fitted, and kept when it is significant; otherwise the plate is flat.
        Auto = "auto",
        /// Flat, as described.
        Flat = "flat",
        /// The sag along each axis is fitted and kept.
        Warped = "warped",
    }
}

/// The chi-square quantile of two degrees of freedom at 99 %: a sag whose Wald statistic is
/// over it is significant.
pub const SAG_SIGNIFICANCE_CHI2: f64 = 9.21;

/// The plate's fitted sag.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlateWarp {
    /// The height of the plate's middle above its edges along x and along y (mm), along the
    /// plate's z axis.
    pub sag_mm: [f64; 2],
    /// Their standard deviations (mm).
    pub sigma_mm: [f64; 2],
    /// Their correlation.
    pub correlation: f64,
    /// The Wald statistic of the two sags against zero (chi-square, two degrees of freedom).
    pub chi2: f64,
    /// Whether it is over [`SAG_SIGNIFICANCE_CHI2`].
    pub significant: bool,
}

impl PlateWarp {
    /// The sag and its statistic from the two values and their 2x2 covariance.
    pub(super) fn new(sag_mm: [f64; 2], covariance: [[f64; 2]; 2]) -> Self {
        let sigma_mm = [
            covariance[0][0].max(0.0).sqrt(),
            covariance[1][1].max(0.0).sqrt(),
        ];
        let det = covariance[0][0] * covariance[1][1] - covariance[0][1] * covariance[1][0];
        let chi2 = if det > 0.0 {
            (covariance[1][1] * sag_mm[0] * sag_mm[0]
                - 2.0 * covariance[0][1] * sag_mm[0] * sag_mm[1]
                + covariance[0][0] * sag_mm[1] * sag_mm[1])
                / det
        } else {
            f64::INFINITY
        };
        Self {
            sag_mm,
            sigma_mm,
            correlation: if sigma_mm[0] > 0.0 && sigma_mm[1] > 0.0 {
                covariance[0][1] / (sigma_mm[0] * sigma_mm[1])
            } else {
                0.0
            },
            chi2,
            significant: chi2 > SAG_SIGNIFICANCE_CHI2,
        }
    }

    /// The sag's standard deviations scaled by `sqrt(inflation)`, and its statistic by
    /// `1 / inflation`: the sag's share of a covariance scaled by `inflation`.
    pub(crate) fn inflated(self, inflation: f64) -> Self {
        Self {
            sigma_mm: self.sigma_mm.map(|s| s * inflation.sqrt()),
            chi2: self.chi2 / inflation,
            significant: self.chi2 / inflation > SAG_SIGNIFICANCE_CHI2,
            ..self
        }
    }
}

/// The plate's shape in a sentence, for reports: what it was fitted with and why.
pub fn describe_plate_shape(shape: PlateShape, warp: Option<&PlateWarp>) -> String {
    let Some(w) = warp else {
        return "plate fitted flat; its sag was not fitted (asked flat, or these views do not \
                determine it)"
            .to_owned();
    };
    let sag = format!(
        "sag along x {:+.3} +- {:.3} mm, along y {:+.3} +- {:.3} mm (the middle above the \
         edges, along the plate's z), chi-square {:.1} of 2 degrees of freedom",
        w.sag_mm[0], w.sigma_mm[0], w.sag_mm[1], w.sigma_mm[1], w.chi2
    );
    match (shape, w.significant) {
        (PlateShape::Warped, true) => {
            format!("plate fitted warped: {sag}, significant (over {SAG_SIGNIFICANCE_CHI2})")
        }
        (PlateShape::Warped, false) => format!(
            "plate fitted warped: {sag}, not significant against these sigmas (at most \
             {SAG_SIGNIFICANCE_CHI2})"
        ),
        _ => format!(
            "plate fitted flat: its {sag} is not significant (at most {SAG_SIGNIFICANCE_CHI2})"
        ),
    }
}

/// Where each plate point lies on the sag's two shapes.
#[derive(Debug, Clone, Copy)]
pub struct SagBasis {
    centre: [f64; 2],
    half_span: [f64; 2],
}

impl SagBasis {
    /// The basis over the span of `points` (plate frame, mm); `None` when they span no width
    /// or no height.
    pub fn of(points: &[Vec3]) -> Option<Self> {
        let mut low = [f64::INFINITY; 2];
        let mut high = [f64::NEG_INFINITY; 2];
        for p in points {
            for a in 0..2 {
                low[a] = low[a].min(p[a]);
                high[a] = high[a].max(p[a]);
            }
        }
        let half_span = [(high[0] - low[0]) / 2.0, (high[1] - low[1]) / 2.0];
        (half_span[0] > 0.0 && half_span[1] > 0.0).then_some(Self {
            centre: [(high[0] + low[0]) / 2.0, (high[1] + low[1]) / 2.0],
            half_span,
        })
    }

    /// `(1 - xn^2, 1 - yn^2)` at a plate point: the height of that point per mm of each sag.
    pub fn at(&self, p: &Vec3) -> [f64; 2] {
        let n = |a: usize| (p[a] - self.centre[a]) / self.half_span[a];
        [1.0 - n(0).powi(2), 1.0 - n(1).powi(2)]
    }

    /// The span's lowest and highest corner `([x, y], [x, y])` (mm).
    pub fn bounds(&self) -> ([f64; 2], [f64; 2]) {
        let [cx, cy] = self.centre;
        let [hx, hy] = self.half_span;
        ([cx - hx, cy - hy], [cx + hx, cy + hy])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_basis_is_one_in_the_middle_and_zero_at_the_edges() {
        let points: Vec<Vec3> = (0..5)
            .flat_map(|r| (0..4).map(move |c| Vec3::new(25.0 * c as f64, 25.0 * r as f64, 0.0)))
            .collect();
        let basis = SagBasis::of(&points).unwrap();
        assert_eq!(basis.at(&Vec3::new(37.5, 50.0, 0.0)), [1.0, 1.0]);
        assert_eq!(basis.at(&Vec3::new(0.0, 0.0, 0.0)), [0.0, 0.0]);
        assert_eq!(basis.at(&Vec3::new(75.0, 100.0, 0.0)), [0.0, 0.0]);
        let quarter = basis.at(&Vec3::new(37.5 + 18.75, 75.0, 0.0));
        assert!((quarter[0] - 0.75).abs() < 1e-12 && (quarter[1] - 0.75).abs() < 1e-12);
        assert!(
            SagBasis::of(&points[..4]).is_none(),
            "one row spans no height"
        );
    }

    #[test]
    fn the_wald_statistic_matches_an_independent_computation() {
        // Covariance [[4, 1], [1, 9]], sag (3, -2): the statistic is s^T C^-1 s.
        let warp = PlateWarp::new([3.0, -2.0], [[4.0, 1.0], [1.0, 9.0]]);
        let inverse = nalgebra::Matrix2::new(4.0, 1.0, 1.0, 9.0)
            .try_inverse()
            .unwrap();
        let s = nalgebra::Vector2::new(3.0, -2.0);
        let expected = (s.transpose() * inverse * s)[0];
        assert!((warp.chi2 - expected).abs() < 1e-12);
        assert_eq!(warp.sigma_mm, [2.0, 3.0]);
        assert!((warp.correlation - 1.0 / 6.0).abs() < 1e-12);
        assert!(warp.significant == (expected > SAG_SIGNIFICANCE_CHI2));
        let wider = warp.inflated(4.0);
        assert_eq!(wider.sigma_mm, [4.0, 6.0]);
        assert!((wider.chi2 - expected / 4.0).abs() < 1e-12);
    }
}
