//! Cross-validation of a camera calibration's covariance: does it cover the spread of
//! calibrations made from other views?
//!
//! The formal covariance (`(J^T W J)^-1`, scaled by the residual variance factor) treats every
//! point's error as independent of every other's. Errors shared by the points of one view (the
//! print and the shape of the plate, its light, a lens the distortion model does not fit)
//! break that, and the formal covariance is then too small by a factor nothing within the fit
//! shows: a low residual says nothing of it. The views are the independent units, so they are
//! what is left out.
//!
//! The leave-one-view-out jackknife: the camera is calibrated `n` times, each time without one
//! view, and `J = (n-1)/n sum_i (theta_i - mean)(theta_i - mean)^T` estimates the covariance of
//! the estimate from all `n` views with views as the units. The check compares `J` with the
//! formal covariance `F` on the focal lengths and the principal point: `r`, the mean of
//! `J_kk / F_kk`. When `F` is honest, `r` is 1 within the jackknife's own noise, a relative
//! spread of about `sqrt(2 / (n - 1))`; beyond twice that, `F` is too small and the whole
//! covariance is scaled by `r` (its shape, the correlations, kept). mrcal's rule reads the same
//! numbers: a spread beyond twice the predicted uncertainty (`r > 4`) means the model does not
//! fit (a plate that is not flat, a lens of another model), and the report says so.

use super::INTRINSICS;
use super::calibrate::intrinsics_of;
use super::{
    CalibrationOptions, CalibrationView, CameraCalibration, Plate, PlateShape, calibrate_camera,
};

/// Fewest views the check runs with: three calibrations of three views each, the fewest that
/// calibrate; the noise bound grows as the views get fewer, so few views inflate only a large
/// spread.
pub const MIN_CROSS_VALIDATION_VIEWS: usize = 4;

/// The parameters compared (fx, fy, cx, cy: positions in [`super::Intrinsic::ALL`]).
const COMPARED: [usize; 4] = [0, 1, 2, 3];

crate::words! {
    /// What the cross-validation found.
    pub enum CrossValidationVerdict("cross-validation verdict") {
        /// The spread of the calibrations is within the formal covariance and its noise: the
        /// formal covariance is reported.
        Honest = "honest",
        /// The spread exceeds the formal covariance: the covariance reported is the formal one
        /// scaled by the ratio.
        Inflated = "inflated",
        /// Too few views to tell: the formal covariance is reported unchecked.
        TooFewViews = "too_few_views",
    }
}

/// The spread of leave-one-view-out calibrations against the formal covariance.
#[derive(Debug, Clone, PartialEq)]
pub struct CrossValidation {
    /// What it found.
    pub verdict: CrossValidationVerdict,
    /// Calibrations made, one view left out of each (those a subset could not calibrate are
    /// not counted).
    pub calibrations: usize,
    /// For fx, fy, cx, cy: the jackknife's variance over the formal one.
    pub ratios: [f64; 4],
    /// Their mean, `r`.
    pub ratio: f64,
    /// The largest `r` that is the jackknife's noise about 1: `1 + 2 sqrt(2 / (n - 1))`.
    pub noise_bound: f64,
    /// What the formal covariance was multiplied by (1 unless inflated).
    pub inflation: f64,
    /// True when the spread is over twice the formal sigmas (`r > 4`): the model (the plate's
    /// shape, the lens model) does not fit these views, whatever the inflation covers.
    pub model_misfit: bool,
}

/// Cross-validates `full`, the calibration from all of `views` with `options`.
pub fn cross_validate(
    plate: &Plate,
    width_px: u32,
    height_px: u32,
    views: &[CalibrationView],
    options: &CalibrationOptions,
    full: &CameraCalibration,
) -> CrossValidation {
    let too_few = |calibrations: usize| CrossValidation {
        verdict: CrossValidationVerdict::TooFewViews,
        calibrations,
        ratios: [f64::NAN; 4],
        ratio: f64::NAN,
        noise_bound: f64::NAN,
        inflation: 1.0,
        model_misfit: false,
    };
    if views.len() < MIN_CROSS_VALIDATION_VIEWS {
        return too_few(0);
    }
    // Each subset is fitted with the plate's shape the whole set chose.
    let options = &CalibrationOptions {
        plate_shape: full.plate_shape,
        ..options.clone()
    };
    let mut estimates: Vec<[f64; INTRINSICS]> = Vec::with_capacity(views.len());
    for left_out in 0..views.len() {
        let subset: Vec<CalibrationView> = views
            .iter()
            .enumerate()
            .filter(|(i, _)| *i != left_out)
            .map(|(_, v)| v.clone())
            .collect();
        if let Ok(c) = calibrate_camera(plate, width_px, height_px, &subset, options) {
            estimates.push(intrinsics_of(&c.camera));
        }
    }
    let n = estimates.len();
    if n < MIN_CROSS_VALIDATION_VIEWS {
        return too_few(n);
    }
    let nf = n as f64;
    let mut ratios = [f64::NAN; 4];
    for (slot, &k) in COMPARED.iter().enumerate() {
        let formal = full.covariance[k][k];
        if formal <= 0.0 {
            continue;
        }
        let mean = estimates.iter().map(|e| e[k]).sum::<f64>() / nf;
        let jackknife =
            (nf - 1.0) / nf * estimates.iter().map(|e| (e[k] - mean).powi(2)).sum::<f64>();
        ratios[slot] = jackknife / formal;
    }
    let compared: Vec<f64> = ratios.iter().copied().filter(|r| r.is_finite()).collect();
    if compared.is_empty() {
        return too_few(n);
    }
    let ratio = compared.iter().sum::<f64>() / compared.len() as f64;
    let noise_bound = 1.0 + 2.0 * (2.0 / (nf - 1.0)).sqrt();
    let inflated = ratio > noise_bound;
    CrossValidation {
        verdict: if inflated {
            CrossValidationVerdict::Inflated
        } else {
            CrossValidationVerdict::Honest
        },
        calibrations: n,
        ratios,
        ratio,
        noise_bound,
        inflation: if inflated { ratio } else { 1.0 },
        model_misfit: ratio > 4.0,
    }
}

/// Calibrates a camera and cross-validates its covariance: the covariance and sigmas reported
/// are the formal ones scaled by the check's inflation (the plate's sag's too: its
/// significance is judged again against the inflated sigmas), and the check travels with
/// them. With [`PlateShape::Auto`], a sag that was significant against the formal covariance
/// but is not against the cross-validated one is not supported by the data: the plate is then
/// fitted flat (and that calibration checked), with the sag tested reported.
pub fn calibrate_camera_checked(
    plate: &Plate,
    width_px: u32,
    height_px: u32,
    views: &[CalibrationView],
    options: &CalibrationOptions,
) -> Result<CameraCalibration, super::VisionError> {
    let checked = |options: &CalibrationOptions| {
        let mut calibration = calibrate_camera(plate, width_px, height_px, views, options)?;
        let check = cross_validate(plate, width_px, height_px, views, options, &calibration);
        for row in &mut calibration.covariance {
            for v in row.iter_mut() {
                *v *= check.inflation;
            }
        }
        for s in &mut calibration.sigma {
            *s *= check.inflation.sqrt();
        }
        calibration.plate_warp = calibration.plate_warp.map(|w| w.inflated(check.inflation));
        calibration.cross_validation = Some(check);
        Ok::<_, super::VisionError>(calibration)
    };
    let first = checked(options)?;
    let unsupported = options.plate_shape == PlateShape::Auto
        && first.plate_shape == PlateShape::Warped
        && first.plate_warp.is_some_and(|w| !w.significant);
    if unsupported {
        let flat = CalibrationOptions {
            plate_shape: PlateShape::Flat,
            ..options.clone()
        };
        if let Ok(mut calibration) = checked(&flat) {
            calibration.plate_warp = first.plate_warp;
            return Ok(calibration);
        }
    }
    Ok(first)
}

/// The check in a sentence, for reports.
pub fn describe_cross_validation(c: &CrossValidation) -> String {
    match c.verdict {
        CrossValidationVerdict::TooFewViews => format!(
            "not cross-validated: {} calibrations without a view each, at least {} are needed; \
             the covariance is the fit's own, unchecked (add views)",
            c.calibrations, MIN_CROSS_VALIDATION_VIEWS
        ),
        CrossValidationVerdict::Honest => format!(
            "cross-validated over {} calibrations without a view each: their spread is {:.2} \
             times the formal variance, within its noise (up to {:.2}); the formal covariance \
             is reported",
            c.calibrations, c.ratio, c.noise_bound
        ),
        CrossValidationVerdict::Inflated => format!(
            "cross-validated over {} calibrations without a view each: their spread is {:.2} \
             times the formal variance (beyond its noise, {:.2}): errors shared within views \
             (the plate's print or shape, light, the lens model); the covariance reported is \
             the formal one times {:.2}{}",
            c.calibrations,
            c.ratio,
            c.noise_bound,
            c.inflation,
            if c.model_misfit {
                ", and a spread over twice the formal sigmas says the model does not fit these \
                 views (a plate that is not flat, a lens of another model)"
            } else {
                ""
            }
        ),
    }
}
