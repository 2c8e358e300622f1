//! Camera calibration: intrinsics and distortion from views of a plate of discs.
//!
//! 1. **Closed form** (Zhang): each view's homography from the plate to the image (normalized
//!    DLT, pixels scaled to the image size first for conditioning) gives two constraints on the
//!    image of the absolute conic; with zero skew, three views or more determine `fx, fy, cx,
//!    cy`. When that is ill-conditioned (a narrow lens, views of nearly the same tilt) the
//!    principal point is put at the image centre and the focal lengths solved alone, as
//!    OpenCV does. Each view's pose follows from its homography, refined by PnP's
//!    Levenberg-Marquardt.
//! 2. **Bundle adjustment**: Levenberg-Marquardt over the free intrinsics (`fx fy cx cy` and the
//!    distortion terms of the [`LensModel`] chosen, any of them fixed) and every view's pose on
//!    the pixel error, each point weighted by its detector's variance when known. A detected disc centre is the centre of the disc's
//!    image, not the image of its centre: each round predicts the perspective eccentricity of
//!    every disc ([`super::disc_image_offset`]) at the current estimate and the next round fits
//!    the detections with it, until it no longer moves the result.
//! 3. **Uncertainty**: the covariance of the free intrinsics is the block of `(J^T W J)^-1` at the
//!    solution, scaled by the residual variance factor `chi2 / (2 n - p)` (one when the detector's
//!    sigmas are right; the fit's own scatter otherwise). Correlations above 0.9 are listed.
//! 4. **Residual structure**: the residuals binned over the image, each bin's mean against its
//!    noise, say whether the lens model leaves an error it does not explain (see
//!    [`ResidualStructure`]).
//! 5. **Checks**: refused with the reason when fewer than three views, a view with too few
//!    points or unknown ids, views that do not determine the intrinsics, or a fit over the RMS
//!    limit (mislabelled points, a wrong plate description); warnings a user can act on (few
//!    views, little tilt, image corners never reached, a view fitting far worse than the rest).

mod adjust;
mod start;
mod structure;
mod warp;

pub use structure::{
    MIN_BIN_POINTS, PointResidual, ResidualBin, ResidualStructure, STRUCTURE_BINS_X,
    STRUCTURE_PROBABILITY, describe_residual_structure, residual_structure, structure_grid,
};
pub use warp::{PlateShape, PlateWarp, SAG_SIGNIFICANCE_CHI2, SagBasis, describe_plate_shape};

use super::{CameraModel, INTRINSICS, LensModel, Plate, VisionError};
use crate::geometry::Pose;
use adjust::Problem;
use nalgebra::Vector2;
use start::{initial_camera, initial_poses};

crate::words! {
    /// One intrinsic parameter of [`CameraModel`], in the order of covariances and sigmas.
    #[derive(PartialOrd, Ord)]
    pub enum Intrinsic("intrinsic parameter") {
        /// Focal length along x.
        Fx = "fx",
        /// Focal length along y.
        Fy = "fy",
        /// Principal point x.
        Cx = "cx",
        /// Principal point y.
        Cy = "cy",
        /// First radial term.
        K1 = "k1",
        /// Second radial term.
        K2 = "k2",
        /// First tangential term.
        P1 = "p1",
        /// Second tangential term.
        P2 = "p2",
        /// Third radial term.
        K3 = "k3",
        /// First radial term of the rational model's denominator.
        K4 = "k4",
        /// Second term of the denominator.
        K5 = "k5",
        /// Third term of the denominator.
        K6 = "k6",
        /// Thin prism along x, with `r^2`.
        S1 = "s1",
        /// Thin prism along x, with `r^4`.
        S2 = "s2",
        /// Thin prism along y, with `r^2`.
        S3 = "s3",
        /// Thin prism along y, with `r^4`.
        S4 = "s4",
    }
}

impl Intrinsic {
    /// Its position in [`Intrinsic::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }

    /// The intrinsics of a lens model, in order (`fx fy cx cy` and its distortion terms).
    pub fn of_model(model: LensModel) -> &'static [Intrinsic] {
        &Intrinsic::ALL[..model.intrinsics()]
    }
}

/// The intrinsics of a camera as a vector in [`Intrinsic::ALL`]'s order (every term, zero
/// beyond the camera's model).
pub fn intrinsics_of(camera: &CameraModel) -> [f64; INTRINSICS] {
    let mut out = [0.0; INTRINSICS];
    out[..4].copy_from_slice(&[camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px]);
    out[4..].copy_from_slice(&camera.distortion);
    out
}

/// The intrinsics (the first [`INTRINSICS`] of the adjustment's global parameters) and the
/// plate's two sags (mm, [`SAG_X`] and [`SAG_Y`]).
pub(super) type Globals = [f64; GLOBALS];
/// How many global parameters the adjustment has.
pub(super) const GLOBALS: usize = INTRINSICS + 2;
/// The position of the plate's sag along x among the global parameters.
pub(super) const SAG_X: usize = INTRINSICS;
/// The position of the plate's sag along y.
pub(super) const SAG_Y: usize = INTRINSICS + 1;

/// The camera of the first [`INTRINSICS`] of `p` (in [`Intrinsic::ALL`]'s order).
pub(super) fn from_params(p: &[f64], width_px: u32, height_px: u32) -> CameraModel {
    CameraModel::pinhole(p[0], p[1], p[2], p[3], width_px, height_px)
        .with_distortion(&p[4..INTRINSICS])
}

/// The plate's points seen in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationView {
    /// Detected centres (px).
    pub points_px: Vec<Vector2<f64>>,
    /// The plate point of each.
    pub ids: Vec<usize>,
    /// Each point's standard deviation from the detector (px); equal weights without.
    pub sigmas_px: Option<Vec<f64>>,
}

/// What to solve and when to refuse.
#[derive(Debug, Clone)]
pub struct CalibrationOptions {
    /// The lens model fitted: its terms are free (unless fixed), the others zero.
    pub model: LensModel,
    /// Parameters kept at their value: distortion terms at zero, the principal point at the
    /// image centre, focal lengths at `initial`'s (which must then be given), unless `initial`
    /// gives them.
    pub fixed: Vec<Intrinsic>,
    /// Known values (for fixed parameters), and a start if the closed form fails.
    pub initial: Option<CameraModel>,
    /// Correct each disc's perspective eccentricity.
    pub eccentricity: bool,
    /// The plate's shape: flat, warped, or warped when the views support it (the default).
    pub plate_shape: PlateShape,
    /// A fit with a larger RMS is refused (px).
    pub max_rms_px: f64,
    /// Levenberg-Marquardt iterations at most, per round.
    pub max_iterations: usize,
    /// Set by the caller to stop the work (its request is gone): checked every iteration.
    pub cancel: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
}

impl Default for CalibrationOptions {
    fn default() -> Self {
        Self {
            model: LensModel::Brown,
            fixed: Vec::new(),
            initial: None,
            eccentricity: true,
            plate_shape: PlateShape::Auto,
            max_rms_px: 1.0,
            max_iterations: 100,
            cancel: None,
        }
    }
}

/// One view's fit.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewFit {
    /// The plate's pose in the camera frame.
    pub camera_from_plate: Pose,
    /// Reprojection RMS of its points (px).
    pub rms_px: f64,
    /// Points used.
    pub points: usize,
    /// Angle between the plate's normal and the optical axis (degrees).
    pub tilt_deg: f64,
}

/// A pair of intrinsics whose estimates are strongly correlated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correlation {
    /// The first.
    pub a: Intrinsic,
    /// The second.
    pub b: Intrinsic,
    /// Their correlation coefficient.
    pub r: f64,
}

crate::words! {
    /// A corner of the image.
    pub enum ImageCorner("image corner") {
        /// Top left.
        TopLeft = "top_left",
        /// Top right.
        TopRight = "top_right",
        /// Bottom left.
        BottomLeft = "bottom_left",
        /// Bottom right.
        BottomRight = "bottom_right",
    }
}

/// Something about the views a user can improve.
#[derive(Debug, Clone, PartialEq)]
pub enum CalibrationWarning {
    /// Fewer views than distortion needs to be well determined.
    FewViews {
        /// Views given.
        views: usize,
        /// Views recommended.
        recommended: usize,
    },
    /// The plate was never tilted much: focal length and distance are then hard to separate.
    LittleTilt {
        /// The largest tilt of a view (degrees).
        max_tilt_deg: f64,
        /// Tilt recommended (degrees).
        recommended_deg: f64,
    },
    /// No plate point in these corners of the image (the outer third of each side), where
    /// distortion is largest.
    CornersNotReached {
        /// The corners.
        corners: Vec<ImageCorner>,
    },
    /// A view fits far worse than the others: a blurred or moving frame, or a bent plate.
    ViewFitsWorse {
        /// Its index.
        view: usize,
        /// Its RMS (px).
        rms_px: f64,
        /// The median view's RMS (px).
        median_rms_px: f64,
    },
}

/// Fewer views than this draws a warning.
pub const RECOMMENDED_VIEWS: usize = 10;
/// A largest tilt under this draws a warning (degrees).
pub const RECOMMENDED_TILT_DEG: f64 = 20.0;
/// Fewest views accepted.
pub const MIN_VIEWS: usize = 3;
/// Fewest points of a view accepted.
pub const MIN_VIEW_POINTS: usize = 6;
/// Most views accepted: the adjustment's normal equations grow with the cube of the views.
pub const MAX_VIEWS: usize = 200;
/// Most points accepted over all views: each iteration's work grows with them.
pub(super) const MAX_POINTS: usize = 40_000;

crate::words! {
    /// The kind of a [`CalibrationWarning`].
    pub enum WarningKind("calibration warning kind") {
        /// Fewer views than recommended.
        FewViews = "few_views",
        /// The plate is not tilted enough.
        LittleTilt = "little_tilt",
        /// Image corners without a plate point.
        CornersNotReached = "corners_not_reached",
        /// A view fits much worse than the others.
        ViewFitsWorse = "view_fits_worse",
        /// Views that came as JPEG, whose compression moves disc edges (`calibrate-camera`
        /// reads files; the calibration itself never makes this one).
        LossyFrames = "lossy_frames",
    }
}

impl CalibrationWarning {
    /// The kind of warning.
    pub fn kind(&self) -> WarningKind {
        match self {
            CalibrationWarning::FewViews { .. } => WarningKind::FewViews,
            CalibrationWarning::LittleTilt { .. } => WarningKind::LittleTilt,
            CalibrationWarning::CornersNotReached { .. } => WarningKind::CornersNotReached,
            CalibrationWarning::ViewFitsWorse { .. } => WarningKind::ViewFitsWorse,
        }
    }
}

impl std::fmt::Display for CalibrationWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CalibrationWarning::FewViews { views, recommended } => write!(
                f,
                "{views} views: {recommended} or more determine the distortion better"
            ),
            CalibrationWarning::LittleTilt {
                max_tilt_deg,
                recommended_deg,
            } => write!(
                f,
                "the plate is tilted at most {max_tilt_deg:.1} deg: tilt it by {recommended_deg:.0} to 45 deg about different axes, or focal length and distance mix"
            ),
            CalibrationWarning::CornersNotReached { corners } => {
                let names: Vec<&str> = corners.iter().map(|c| c.name()).collect();
                write!(
                    f,
                    "no plate point in the image's {} corner(s): distortion there is extrapolated; add views with the plate in them",
                    names.join(", ")
                )
            }
            CalibrationWarning::ViewFitsWorse {
                view,
                rms_px,
                median_rms_px,
            } => write!(
                f,
                "view {view} fits with {rms_px:.4} px RMS, against {median_rms_px:.4} px for the median view: a blurred or moving frame? leave it out and calibrate again"
            ),
        }
    }
}

/// A calibrated camera with its uncertainty and the fit.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraCalibration {
    /// The calibrated camera.
    pub camera: CameraModel,
    /// The lens model fitted.
    pub model: LensModel,
    /// Standard deviation of each intrinsic (0 for fixed ones and those beyond the model), in
    /// [`Intrinsic::ALL`]'s order.
    pub sigma: [f64; INTRINSICS],
    /// Their covariance (rows and columns of fixed ones and those beyond the model zero).
    pub covariance: [[f64; INTRINSICS]; INTRINSICS],
    /// Reprojection RMS over every point (px).
    pub rms_px: f64,
    /// `chi2 / (2 n - p)`: the factor the covariance was scaled by.
    pub variance_factor: f64,
    /// Each view's fit, in input order.
    pub views: Vec<ViewFit>,
    /// Pairs of free intrinsics correlated by more than 0.9.
    pub correlations: Vec<Correlation>,
    /// What could be better.
    pub warnings: Vec<CalibrationWarning>,
    /// The parameters kept fixed.
    pub fixed: Vec<Intrinsic>,
    /// Levenberg-Marquardt iterations, over all rounds.
    pub iterations: usize,
    /// The covariance's cross-validation, when it was checked ([`super::calibrate_camera_checked`]):
    /// `covariance` and `sigma` are then the formal ones scaled by its inflation.
    pub cross_validation: Option<super::CrossValidation>,
    /// The shape the plate was fitted with: [`PlateShape::Flat`] or [`PlateShape::Warped`].
    pub plate_shape: PlateShape,
    /// The plate's sag: fitted when warped; with [`PlateShape::Auto`] choosing flat, the sag
    /// that was tested and found not significant (none when the views did not determine it).
    pub plate_warp: Option<PlateWarp>,
    /// The residuals binned over the image and judged for structure the lens model does not
    /// explain (none when no bin has enough points).
    pub residual_structure: Option<ResidualStructure>,
    /// Each view's points' residuals at the solution, in input order.
    pub residuals: Vec<Vec<PointResidual>>,
}

impl CameraCalibration {
    /// The error of a point predicted with this calibration, per image axis (px): its RMS
    /// reprojection error spread over the two axes, at least 0.001 px. It is what an
    /// installation's `pixel_sigma` for this camera should say.
    pub fn pixel_sigma(&self) -> f64 {
        (self.rms_px / std::f64::consts::SQRT_2).max(0.001)
    }
}

/// A wider lens model's fit whose RMS is over this many times the Brown-Conrady fit it started
/// from is refused.
const WIDER_MODEL_RMS_RATIO: f64 = 1.05;

/// Eccentricity rounds at most (the correction changes by a small fraction each round).
const ECCENTRICITY_ROUNDS: usize = 4;

pub(super) fn refuse(reason: impl Into<String>) -> VisionError {
    VisionError::CalibrationRefused {
        reason: reason.into(),
    }
}

/// Calibrates a camera of `width_px` x `height_px` from views of `plate`.
pub fn calibrate_camera(
    plate: &Plate,
    width_px: u32,
    height_px: u32,
    views: &[CalibrationView],
    options: &CalibrationOptions,
) -> Result<CameraCalibration, VisionError> {
    if width_px == 0 || height_px == 0 {
        return Err(refuse("the image size must not be zero"));
    }
    check_views(plate, views)?;
    let size = (width_px, height_px);
    match options.plate_shape {
        PlateShape::Flat | PlateShape::Warped => {
            fit_shape(plate, size, views, options, options.plate_shape)
        }
        PlateShape::Auto => {
            match fit_shape(plate, size, views, options, PlateShape::Warped) {
                Ok(warped) if warped.plate_warp.is_some_and(|w| w.significant) => Ok(warped),
                // Not significant, or not determined by these views: flat, with the sag
                // that was tested when there is one.
                tried => {
                    let mut flat = fit_shape(plate, size, views, options, PlateShape::Flat)?;
                    flat.plate_warp = tried.ok().and_then(|c| c.plate_warp);
                    Ok(flat)
                }
            }
        }
    }
}

/// The calibration with the plate fitted as `shape` (flat or warped).
fn fit_shape(
    plate: &Plate,
    (width_px, height_px): (u32, u32),
    views: &[CalibrationView],
    options: &CalibrationOptions,
    shape: PlateShape,
) -> Result<CameraCalibration, VisionError> {
    let problem = Problem::new(plate, views, shape);
    let mut free: Vec<usize> = Intrinsic::of_model(options.model)
        .iter()
        .filter(|p| !options.fixed.contains(p))
        .map(|p| p.index())
        .collect();
    if shape == PlateShape::Warped {
        free.extend([SAG_X, SAG_Y]);
    }
    // A wider lens model starts from Brown-Conrady's fit (its own terms at zero): a point of
    // its space whose cost the adjustment can only lower, where a start with every term at
    // zero can lead its many correlated terms into a poor minimum.
    let mut brown_rms_px = None;
    let start = match options.model {
        LensModel::Brown => initial_camera(&problem, width_px, height_px, options)?,
        _ => {
            let brown = CalibrationOptions {
                model: LensModel::Brown,
                ..options.clone()
            };
            match fit_shape(plate, (width_px, height_px), views, &brown, shape) {
                Ok(c) => {
                    brown_rms_px = Some(c.rms_px);
                    // The wider terms start at zero, or at `initial`'s value when fixed.
                    let mut camera = c.camera;
                    let known = options.initial.as_ref().map(intrinsics_of);
                    for p in &Intrinsic::of_model(options.model)[LensModel::Brown.intrinsics()..] {
                        if let (true, Some(known)) = (options.fixed.contains(p), known) {
                            camera.distortion[p.index() - 4] = known[p.index()];
                        }
                    }
                    camera
                }
                Err(_) => initial_camera(&problem, width_px, height_px, options)?,
            }
        }
    };
    let mut params: Globals = [0.0; GLOBALS];
    params[..INTRINSICS].copy_from_slice(&intrinsics_of(&start));
    let mut poses = initial_poses(&problem, &start)?;
    let mut offsets: Vec<Vec<Vector2<f64>>> = views
        .iter()
        .map(|v| vec![Vector2::zeros(); v.ids.len()])
        .collect();
    let mut iterations = 0;
    // Without the correction one adjustment; with it, one per round until the correction
    // settles (then once more with it) or the rounds run out.
    let mut settled = !options.eccentricity;
    let mut round = 0;
    // One adjustment from the current estimate, with the given eccentricity offsets.
    let adjust = |problem: &Problem,
                  params: &mut Globals,
                  poses: &mut [Pose],
                  offsets: &[Vec<Vector2<f64>>]| {
        problem.adjust(
            params,
            poses,
            offsets,
            &free,
            width_px,
            height_px,
            options.max_iterations,
            options.cancel.as_deref(),
        )
    };
    let fit = loop {
        let result = adjust(&problem, &mut params, &mut poses, &offsets)?;
        iterations += result.iterations;
        round += 1;
        if settled || round == ECCENTRICITY_ROUNDS {
            break result.fit;
        }
        let camera = from_params(&params, width_px, height_px);
        let next = problem.offsets(&camera, [params[SAG_X], params[SAG_Y]], &poses);
        let change = next
            .iter()
            .flatten()
            .zip(offsets.iter().flatten())
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        offsets = next;
        settled = change < 1e-5;
    };
    // The detector's sigmas are its pixel noise only. On real frames the residuals are
    // usually larger (the print, compression, what the lens model leaves): weighting by those
    // sigmas alone would let the sharpest discs decide the fit. When the residuals exceed them
    // clearly, the error beyond them is estimated from the residuals (the same for every
    // point), added to every point's variance, and the fit run again.
    let mut problem = problem;
    let mut fit = fit;
    let n_points: usize = views.iter().map(|v| v.ids.len()).sum();
    let dof = (2 * n_points).saturating_sub(free.len() + 6 * poses.len());
    if views.iter().any(|v| v.sigmas_px.is_some()) && dof > 0 && fit.chi2 / dof as f64 > 2.0 {
        let residual_var = fit.view_cost_px2.iter().sum::<f64>() / dof as f64;
        let detector_var = problem
            .weights
            .iter()
            .flatten()
            .map(|w| 1.0 / w)
            .sum::<f64>()
            / n_points as f64;
        let extra_var = (residual_var - detector_var).max(0.0);
        problem.add_variance(extra_var);
        let result = adjust(&problem, &mut params, &mut poses, &offsets)?;
        iterations += result.iterations;
        fit = result.fit;
    }
    // A wider model that ends worse than the Brown-Conrady fit it started from has wandered
    // where the views do not hold it (its terms trading with the principal point, the discs'
    // eccentricity chasing the estimate): its terms are not determined.
    let rms_px = (fit.view_cost_px2.iter().sum::<f64>() / n_points as f64).sqrt();
    if let Some(brown) = brown_rms_px
        && rms_px > WIDER_MODEL_RMS_RATIO * brown
    {
        return Err(refuse(format!(
            "the {} lens model fits these views worse than Brown-Conrady's ({rms_px:.3} px RMS \
             against {brown:.3} px): the views do not determine its terms; add views that reach \
             the image's corners, fix some of its terms, or choose a model with fewer",
            options.model
        )));
    }
    let mut calibration = problem.report(
        &params,
        (width_px, height_px),
        &poses,
        &offsets,
        fit,
        &free,
        options,
    )?;
    calibration.iterations = iterations;
    Ok(calibration)
}

fn check_views(plate: &Plate, views: &[CalibrationView]) -> Result<(), VisionError> {
    if views.len() < MIN_VIEWS {
        return Err(refuse(format!(
            "{} view(s): at least {MIN_VIEWS} are needed ({RECOMMENDED_VIEWS} or more recommended)",
            views.len()
        )));
    }
    if views.len() > MAX_VIEWS {
        return Err(refuse(format!(
            "{} views: at most {MAX_VIEWS} are taken (a few dozen determine a camera well)",
            views.len()
        )));
    }
    let points: usize = views.iter().map(|v| v.points_px.len()).sum();
    if points > MAX_POINTS {
        return Err(refuse(format!(
            "{points} points over the views: at most {MAX_POINTS} are taken (a few thousand \
             determine a camera well)"
        )));
    }
    for (v, view) in views.iter().enumerate() {
        if view.ids.len() != view.points_px.len() {
            return Err(refuse(format!(
                "view {v}: {} point(s) but {} id(s)",
                view.points_px.len(),
                view.ids.len()
            )));
        }
        if view.points_px.len() < MIN_VIEW_POINTS {
            return Err(refuse(format!(
                "view {v}: {} point(s), at least {MIN_VIEW_POINTS} are needed",
                view.points_px.len()
            )));
        }
        let mut seen = vec![false; plate.len()];
        for &id in &view.ids {
            if id >= plate.len() {
                return Err(refuse(format!(
                    "view {v}: id {id} is not a point of the {}-point plate",
                    plate.len()
                )));
            }
            if std::mem::replace(&mut seen[id], true) {
                return Err(refuse(format!("view {v}: id {id} appears twice")));
            }
        }
        if let Some(p) = view
            .points_px
            .iter()
            .position(|p| !p.iter().all(|c| c.is_finite()))
        {
            return Err(refuse(format!(
                "view {v}: point {p} is not a finite number"
            )));
        }
        if let Some(sigmas) = &view.sigmas_px {
            if sigmas.len() != view.ids.len() {
                return Err(refuse(format!(
                    "view {v}: {} sigma(s) for {} point(s)",
                    sigmas.len(),
                    view.ids.len()
                )));
            }
            if let Some(p) = sigmas.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
                return Err(refuse(format!(
                    "view {v}: the sigma of point {p} must be a positive number"
                )));
            }
        }
    }
    Ok(())
}
