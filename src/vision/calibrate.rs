//! Camera calibration: intrinsics and distortion from views of a plate of discs.
//!
//! 1. **Closed form** (Zhang): each view's homography from the plate to the image (normalized
//!    DLT, pixels scaled to the image size first for conditioning) gives two constraints on the
//!    image of the absolute conic; with zero skew, three views or more determine `fx, fy, cx,
//!    cy`. When that is ill-conditioned (a narrow lens, views of nearly the same tilt) the
//!    principal point is put at the image centre and the focal lengths solved alone, as
//!    OpenCV does. Each view's pose follows from its homography, refined by PnP's
//!    Levenberg-Marquardt.
//! 2. **Bundle adjustment**: Levenberg-Marquardt over the free intrinsics (`fx fy cx cy k1 k2 p1
//!    p2 k3`, any of them fixed) and every view's pose on the pixel error, each point weighted
//!    by its detector's variance when known. A detected disc centre is the centre of the disc's
//!    image, not the image of its centre: each round predicts the perspective eccentricity of
//!    every disc ([`super::disc_image_offset`]) at the current estimate and the next round fits
//!    the detections with it, until it no longer moves the result.
//! 3. **Uncertainty**: the covariance of the free intrinsics is the block of `(J^T W J)^-1` at the
//!    solution, scaled by the residual variance factor `chi2 / (2 n - p)` (one when the detector's
//!    sigmas are right; the fit's own scatter otherwise). Correlations above 0.9 are listed.
//! 4. **Checks**: refused with the reason when fewer than three views, a view with too few
//!    points or unknown ids, views that do not determine the intrinsics, or a fit over the RMS
//!    limit (mislabelled points, a wrong plate description); warnings a user can act on (few
//!    views, little tilt, image corners never reached, a view fitting far worse than the rest).

use super::{CameraModel, Plate, VisionError, disc_image_offset, ippe::homography, pnp};
use crate::geometry::{Mat3, Pose, Rotation, Vec3, se3_exp, skew};
use nalgebra::{DMatrix, DVector, Matrix2x3, SMatrix, Translation3, Vector2, Vector6};

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
    }
}

impl Intrinsic {
    /// Its position in [`Intrinsic::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

/// The intrinsics of a camera as a vector in [`Intrinsic::ALL`]'s order.
pub fn intrinsics_of(camera: &CameraModel) -> [f64; 9] {
    let [k1, k2, p1, p2, k3] = camera.distortion;
    [
        camera.fx_px,
        camera.fy_px,
        camera.cx_px,
        camera.cy_px,
        k1,
        k2,
        p1,
        p2,
        k3,
    ]
}

fn from_params(p: &[f64; 9], width_px: u32, height_px: u32) -> CameraModel {
    CameraModel {
        fx_px: p[0],
        fy_px: p[1],
        cx_px: p[2],
        cy_px: p[3],
        distortion: [p[4], p[5], p[6], p[7], p[8]],
        width_px,
        height_px,
    }
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
    /// Parameters kept at their value: distortion terms at zero, the principal point at the
    /// image centre, focal lengths at `initial`'s (which must then be given), unless `initial`
    /// gives them.
    pub fixed: Vec<Intrinsic>,
    /// Known values (for fixed parameters), and a start if the closed form fails.
    pub initial: Option<CameraModel>,
    /// Correct each disc's perspective eccentricity.
    pub eccentricity: bool,
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
            fixed: Vec::new(),
            initial: None,
            eccentricity: true,
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
    /// Standard deviation of each intrinsic (0 for fixed ones), in [`Intrinsic::ALL`]'s order.
    pub sigma: [f64; 9],
    /// Their covariance (rows and columns of fixed ones zero).
    pub covariance: [[f64; 9]; 9],
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
}

impl CameraCalibration {
    /// The error of a point predicted with this calibration, per image axis (px): its RMS
    /// reprojection error spread over the two axes, at least 0.001 px. It is what an
    /// installation's `pixel_sigma` for this camera should say.
    pub fn pixel_sigma(&self) -> f64 {
        (self.rms_px / std::f64::consts::SQRT_2).max(0.001)
    }
}

/// Eccentricity rounds at most (the correction changes by a small fraction each round).
const ECCENTRICITY_ROUNDS: usize = 4;

fn refuse(reason: impl Into<String>) -> VisionError {
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
    let problem = Problem::new(plate, views);
    let free: Vec<usize> = Intrinsic::ALL
        .iter()
        .filter(|p| !options.fixed.contains(p))
        .map(|p| p.index())
        .collect();
    let start = initial_camera(&problem, width_px, height_px, options)?;
    let mut params = intrinsics_of(&start);
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
                  params: &mut [f64; 9],
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
        let next = problem.offsets(&camera, &poses);
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
    let camera = from_params(&params, width_px, height_px);
    problem.report(camera, &poses, fit, &free, options, iterations)
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

/// The views prepared for adjustment.
struct Problem<'a> {
    views: &'a [CalibrationView],
    /// Per view: its points in the plate frame, relative to their centroid.
    centred_mm: Vec<Vec<Vec3>>,
    /// Per view: the centroid of its plate points (mm).
    centroids_mm: Vec<Vec3>,
    /// Per view: each point's weight (1 / variance).
    weights: Vec<Vec<f64>>,
    /// Each plate point's disc diameter (mm).
    diameters_mm: Vec<f64>,
    plate_points_mm: Vec<Vec3>,
}

/// The fit at one estimate.
struct Evaluation {
    /// Sum of squared residuals over their variances (what is minimised).
    chi2: f64,
    /// Sum of squared residuals (px^2), per view.
    view_cost_px2: Vec<f64>,
    /// `J^T W J` over the free intrinsics and the poses.
    information: DMatrix<f64>,
    /// `J^T W r`.
    gradient: DVector<f64>,
}

struct Adjusted {
    fit: Evaluation,
    iterations: usize,
}

impl<'a> Problem<'a> {
    fn new(plate: &Plate, views: &'a [CalibrationView]) -> Self {
        let plate_points_mm = plate.points_mm();
        let mut centred_mm = Vec::with_capacity(views.len());
        let mut centroids_mm = Vec::with_capacity(views.len());
        let mut weights = Vec::with_capacity(views.len());
        for view in views {
            let points: Vec<Vec3> = view.ids.iter().map(|&i| plate_points_mm[i]).collect();
            let c = points.iter().fold(Vec3::zeros(), |a, p| a + p) / points.len() as f64;
            centred_mm.push(points.iter().map(|p| p - c).collect());
            centroids_mm.push(c);
            weights.push(match &view.sigmas_px {
                Some(s) => s.iter().map(|s| 1.0 / (s * s)).collect(),
                None => vec![1.0; view.ids.len()],
            });
        }
        Self {
            views,
            centred_mm,
            centroids_mm,
            weights,
            diameters_mm: (0..plate.len())
                .map(|i| plate.disc_diameter_mm(i))
                .collect(),
            plate_points_mm,
        }
    }

    /// Adds `var_px2` to every point's variance (per axis).
    fn add_variance(&mut self, var_px2: f64) {
        for w in self.weights.iter_mut().flatten() {
            *w = 1.0 / (1.0 / *w + var_px2);
        }
    }

    fn plate_xy(&self, v: usize) -> Vec<Vector2<f64>> {
        self.views[v]
            .ids
            .iter()
            .map(|&i| self.plate_points_mm[i].xy())
            .collect()
    }

    /// Each disc's eccentricity at the estimate (px).
    fn offsets(&self, camera: &CameraModel, poses: &[Pose]) -> Vec<Vec<Vector2<f64>>> {
        poses
            .iter()
            .enumerate()
            .map(|(v, pose)| {
                let normal = pose.rotation * Vec3::z();
                self.centred_mm[v]
                    .iter()
                    .zip(&self.views[v].ids)
                    .map(|(x, &id)| {
                        let centre = (pose * nalgebra::Point3::from(*x)).coords;
                        disc_image_offset(camera, &centre, &normal, self.diameters_mm[id])
                            .unwrap_or_else(Vector2::zeros)
                    })
                    .collect()
            })
            .collect()
    }

    /// The fit over the free intrinsics and the poses (`camera_from_centred`, right
    /// perturbation); `None` when a point is behind the camera.
    fn evaluate(
        &self,
        params: &[f64; 9],
        poses: &[Pose],
        offsets: &[Vec<Vector2<f64>>],
        free: &[usize],
        size: (u32, u32),
    ) -> Option<Evaluation> {
        let camera = from_params(params, size.0, size.1);
        let nf = free.len();
        let n = nf + 6 * poses.len();
        let mut jtj = DMatrix::<f64>::zeros(n, n);
        let mut jtr = DVector::<f64>::zeros(n);
        let mut chi2 = 0.0;
        let mut view_cost_px2 = vec![0.0; poses.len()];
        for (v, pose) in poses.iter().enumerate() {
            let r_mat = pose.rotation.to_rotation_matrix().into_inner();
            let mut jii = DMatrix::<f64>::zeros(nf, nf);
            let mut jip = DMatrix::<f64>::zeros(nf, 6);
            let mut jpp = SMatrix::<f64, 6, 6>::zeros();
            let mut gi = DVector::<f64>::zeros(nf);
            let mut gp = Vector6::<f64>::zeros();
            for (k, x) in self.centred_mm[v].iter().enumerate() {
                let p = r_mat * x + pose.translation.vector;
                let (uv, dp) = camera.project_with_jacobian(&p)?;
                let r = uv + offsets[v][k] - self.views[v].points_px[k];
                let w = self.weights[v][k];
                view_cost_px2[v] += r.norm_squared();
                chi2 += w * r.norm_squared();
                let intrinsic = camera.intrinsics_jacobian(&p);
                let ji = DMatrix::<f64>::from_fn(2, nf, |row, col| intrinsic[(row, free[col])]);
                let dpr: Matrix2x3<f64> = dp * r_mat;
                let mut jp = SMatrix::<f64, 2, 6>::zeros();
                jp.fixed_view_mut::<2, 3>(0, 0).copy_from(&dpr);
                jp.fixed_view_mut::<2, 3>(0, 3)
                    .copy_from(&(-(dpr * skew(x))));
                let rv = DVector::from_column_slice(r.as_slice());
                jii += ji.transpose() * &ji * w;
                jip += ji.transpose() * DMatrix::from_column_slice(2, 6, jp.as_slice()) * w;
                jpp += jp.transpose() * jp * w;
                gi += ji.transpose() * &rv * w;
                gp += jp.transpose() * r * w;
            }
            let o = nf + 6 * v;
            let mut top = jtj.view_mut((0, 0), (nf, nf));
            top += &jii;
            jtj.view_mut((0, o), (nf, 6)).copy_from(&jip);
            jtj.view_mut((o, 0), (6, nf)).copy_from(&jip.transpose());
            jtj.view_mut((o, o), (6, 6))
                .copy_from(&DMatrix::from_column_slice(6, 6, jpp.as_slice()));
            let mut head = jtr.rows_mut(0, nf);
            head += &gi;
            jtr.rows_mut(o, 6)
                .copy_from(&DVector::from_column_slice(gp.as_slice()));
        }
        Some(Evaluation {
            chi2,
            view_cost_px2,
            information: jtj,
            gradient: jtr,
        })
    }

    /// Levenberg-Marquardt with the eccentricities fixed.
    #[allow(clippy::too_many_arguments)]
    fn adjust(
        &self,
        params: &mut [f64; 9],
        poses: &mut [Pose],
        offsets: &[Vec<Vector2<f64>>],
        free: &[usize],
        width_px: u32,
        height_px: u32,
        max_iterations: usize,
        cancel: Option<&std::sync::atomic::AtomicBool>,
    ) -> Result<Adjusted, VisionError> {
        let size = (width_px, height_px);
        let behind = || {
            refuse(
                "the estimate puts plate points behind the camera: the views or their labels are inconsistent",
            )
        };
        let mut fit = self
            .evaluate(params, poses, offsets, free, size)
            .ok_or_else(behind)?;
        let nf = free.len();
        let mut lambda = 1e-4;
        let mut iterations = 0;
        while iterations < max_iterations {
            if cancel.is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed)) {
                return Err(refuse("stopped: the request was withdrawn"));
            }
            iterations += 1;
            let mut a = fit.information.clone();
            for i in 0..a.nrows() {
                a[(i, i)] += lambda * fit.information[(i, i)].max(1e-12);
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                if lambda > 1e10 {
                    break;
                }
                continue;
            };
            let delta = chol.solve(&(-&fit.gradient));
            let predicted = -delta.dot(&fit.gradient);
            if !predicted.is_finite() || predicted <= 1e-12 * fit.chi2.max(1e-300) {
                break;
            }
            let mut next_params = *params;
            for (k, &i) in free.iter().enumerate() {
                next_params[i] += delta[k];
            }
            let next_poses: Vec<Pose> = poses
                .iter()
                .enumerate()
                .map(|(v, pose)| {
                    let d = delta.rows(nf + 6 * v, 6);
                    pose * se3_exp(&Vector6::from_column_slice(d.as_slice()))
                })
                .collect();
            match self
                .evaluate(&next_params, &next_poses, offsets, free, size)
                .filter(|e| e.chi2.is_finite() && e.chi2 <= fit.chi2)
            {
                Some(better) => {
                    *params = next_params;
                    poses.copy_from_slice(&next_poses);
                    fit = better;
                    lambda = (lambda * 0.1).max(1e-12);
                }
                None => {
                    lambda *= 10.0;
                    if lambda > 1e10 {
                        break;
                    }
                }
            }
        }
        if !params.iter().all(|p| p.is_finite()) {
            return Err(refuse("the adjustment diverged"));
        }
        Ok(Adjusted { fit, iterations })
    }

    fn report(
        &self,
        camera: CameraModel,
        poses: &[Pose],
        fit: Evaluation,
        free: &[usize],
        options: &CalibrationOptions,
        iterations: usize,
    ) -> Result<CameraCalibration, VisionError> {
        let n_points: usize = self.views.iter().map(|v| v.ids.len()).sum();
        let dof = (2 * n_points).saturating_sub(free.len() + 6 * poses.len());
        if dof == 0 {
            return Err(refuse("as many unknowns as measurements: add views"));
        }
        let rms_px = (fit.view_cost_px2.iter().sum::<f64>() / n_points as f64).sqrt();
        if rms_px > options.max_rms_px {
            return Err(refuse(format!(
                "the fit's RMS is {rms_px:.3} px, over the limit of {} px: points are mislabelled, the plate's description (spacing, rows, cols, asymmetric) is wrong, or the lens is not of the distortion model",
                options.max_rms_px
            )));
        }
        let variance_factor = fit.chi2 / dof as f64;
        let nf = free.len();
        let inverse = invert_information(&fit.information, nf, free)?;
        let mut covariance = [[0.0; 9]; 9];
        let mut sigma = [0.0; 9];
        for (a, &i) in free.iter().enumerate() {
            for (b, &j) in free.iter().enumerate() {
                covariance[i][j] = inverse[(a, b)] * variance_factor;
            }
            sigma[i] = covariance[i][i].max(0.0).sqrt();
        }
        let mut correlations = Vec::new();
        for (a, &i) in free.iter().enumerate() {
            for &j in &free[a + 1..] {
                let r = covariance[i][j] / (sigma[i] * sigma[j]);
                if r.abs() > 0.9 {
                    correlations.push(Correlation {
                        a: Intrinsic::ALL[i],
                        b: Intrinsic::ALL[j],
                        r,
                    });
                }
            }
        }
        // Each view's RMS from the costs the fit ended on: the same residuals as `rms_px`.
        let views: Vec<ViewFit> = poses
            .iter()
            .enumerate()
            .map(|(v, pose)| {
                let normal = pose.rotation * Vec3::z();
                ViewFit {
                    camera_from_plate: pose * Translation3::from(-self.centroids_mm[v]),
                    rms_px: (fit.view_cost_px2[v] / self.centred_mm[v].len() as f64).sqrt(),
                    points: self.centred_mm[v].len(),
                    tilt_deg: normal.z.abs().clamp(0.0, 1.0).acos().to_degrees(),
                }
            })
            .collect();
        let warnings = self.warnings(&camera, &views);
        let mut fixed = options.fixed.clone();
        fixed.sort();
        fixed.dedup();
        Ok(CameraCalibration {
            camera,
            sigma,
            covariance,
            rms_px,
            variance_factor,
            views,
            correlations,
            warnings,
            fixed,
            iterations,
            cross_validation: None,
        })
    }

    fn warnings(&self, camera: &CameraModel, views: &[ViewFit]) -> Vec<CalibrationWarning> {
        let mut warnings = Vec::new();
        if views.len() < RECOMMENDED_VIEWS {
            warnings.push(CalibrationWarning::FewViews {
                views: views.len(),
                recommended: RECOMMENDED_VIEWS,
            });
        }
        let max_tilt_deg = views.iter().map(|v| v.tilt_deg).fold(0.0, f64::max);
        if max_tilt_deg < RECOMMENDED_TILT_DEG {
            warnings.push(CalibrationWarning::LittleTilt {
                max_tilt_deg,
                recommended_deg: RECOMMENDED_TILT_DEG,
            });
        }
        let (w, h) = (f64::from(camera.width_px), f64::from(camera.height_px));
        let mut reached = [false; 4];
        for p in self.views.iter().flat_map(|v| &v.points_px) {
            let left = p.x < w / 3.0;
            let right = p.x > 2.0 * w / 3.0;
            let top = p.y < h / 3.0;
            let bottom = p.y > 2.0 * h / 3.0;
            reached[0] |= left && top;
            reached[1] |= right && top;
            reached[2] |= left && bottom;
            reached[3] |= right && bottom;
        }
        let corners: Vec<ImageCorner> = [
            ImageCorner::TopLeft,
            ImageCorner::TopRight,
            ImageCorner::BottomLeft,
            ImageCorner::BottomRight,
        ]
        .into_iter()
        .zip(reached)
        .filter(|(_, r)| !r)
        .map(|(c, _)| c)
        .collect();
        if !corners.is_empty() {
            warnings.push(CalibrationWarning::CornersNotReached { corners });
        }
        let mut rms: Vec<f64> = views.iter().map(|v| v.rms_px).collect();
        rms.sort_by(f64::total_cmp);
        let median_rms_px = rms[rms.len() / 2];
        for (view, fit) in views.iter().enumerate() {
            if fit.rms_px > 3.0 * median_rms_px && fit.rms_px > 0.02 {
                warnings.push(CalibrationWarning::ViewFitsWorse {
                    view,
                    rms_px: fit.rms_px,
                    median_rms_px,
                });
            }
        }
        warnings
    }
}

/// The free intrinsics' block of the inverse information, or a refusal naming the parameter
/// the views do not determine.
fn invert_information(
    information: &DMatrix<f64>,
    nf: usize,
    free: &[usize],
) -> Result<DMatrix<f64>, VisionError> {
    // Scale to unit diagonal so that the test of determination does not depend on units.
    let d: Vec<f64> = (0..information.nrows())
        .map(|i| information[(i, i)].max(1e-300).sqrt())
        .collect();
    let scaled = DMatrix::from_fn(information.nrows(), information.ncols(), |i, j| {
        information[(i, j)] / (d[i] * d[j])
    });
    let eigen = scaled.clone().symmetric_eigen();
    let (weakest, smallest) = eigen
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .map(|(k, v)| (k, *v))
        .unwrap_or((0, 0.0));
    if smallest < 1e-12 {
        let vector = eigen.eigenvectors.column(weakest);
        let (param, _) = (0..nf)
            .map(|k| (k, vector[k].abs()))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, 0.0));
        let name = free
            .get(param)
            .map_or("a view's pose", |&i| Intrinsic::ALL[i].name());
        return Err(refuse(format!(
            "the views do not determine {name}: tilt the plate more and about different axes, or fix it"
        )));
    }
    let Some(inverse) = scaled.cholesky().map(|c| c.inverse()) else {
        return Err(refuse("the views do not determine the intrinsics"));
    };
    Ok(DMatrix::from_fn(nf, nf, |i, j| {
        inverse[(i, j)] / (d[i] * d[j])
    }))
}

/// The starting camera: Zhang's closed form (or the focal lengths alone with the principal
/// point at the centre), then the fixed parameters at their values.
fn initial_camera(
    problem: &Problem,
    width_px: u32,
    height_px: u32,
    options: &CalibrationOptions,
) -> Result<CameraModel, VisionError> {
    let (w, h) = (f64::from(width_px), f64::from(height_px));
    // Pixels to a unit scale about the image centre, for conditioning.
    let s = w.max(h);
    let (ccx, ccy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let n = Mat3::new(
        1.0 / s,
        0.0,
        -ccx / s,
        0.0,
        1.0 / s,
        -ccy / s,
        0.0,
        0.0,
        1.0,
    );
    let mut homographies = Vec::with_capacity(problem.views.len());
    for (v, view) in problem.views.iter().enumerate() {
        let normalized: Vec<Vector2<f64>> = view
            .points_px
            .iter()
            .map(|p| {
                let q = n * Vec3::new(p.x, p.y, 1.0);
                Vector2::new(q.x, q.y)
            })
            .collect();
        let hv = homography(&problem.plate_xy(v), &normalized).ok_or_else(|| {
            refuse(format!(
                "view {v}: its points do not determine a homography (collinear?)"
            ))
        })?;
        homographies.push(hv);
    }
    let k_normalized = zhang(&homographies)
        .filter(plausible)
        .or_else(|| centred_focal(&homographies))
        .or_else(|| {
            options.initial.map(|c| {
                n * Mat3::new(c.fx_px, 0.0, c.cx_px, 0.0, c.fy_px, c.cy_px, 0.0, 0.0, 1.0)
            })
        })
        .ok_or_else(|| {
            refuse("the views do not determine the focal length: they are nearly parallel; tilt the plate by 20 to 45 degrees about different axes")
        })?;
    let k = n.try_inverse().unwrap_or_else(Mat3::identity) * k_normalized;
    let mut params = [
        k[(0, 0)],
        k[(1, 1)],
        k[(0, 2)],
        k[(1, 2)],
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
    ];
    for p in &options.fixed {
        let i = p.index();
        params[i] = match (options.initial, p) {
            (Some(c), _) => intrinsics_of(&c)[i],
            (None, Intrinsic::Cx) => ccx,
            (None, Intrinsic::Cy) => ccy,
            (None, Intrinsic::Fx | Intrinsic::Fy) => {
                return Err(refuse(format!(
                    "{} can be fixed only at a known value: give the initial camera",
                    p.name()
                )));
            }
            (None, _) => 0.0,
        };
    }
    Ok(from_params(&params, width_px, height_px))
}

/// A camera matrix (normalized pixels) with positive focal lengths and its principal point
/// inside the image.
fn plausible(k: &Mat3) -> bool {
    k.iter().all(|v| v.is_finite())
        && k[(0, 0)] > 0.0
        && k[(1, 1)] > 0.0
        && k[(0, 2)].abs() < 0.5
        && k[(1, 2)].abs() < 0.5
        && (k[(0, 0)] / k[(1, 1)] - 1.0).abs() < 0.5
}

/// `v_ij` of Zhang's method: `h_i^T B h_j = v_ij . b`.
fn v_ij(h: &Mat3, i: usize, j: usize) -> SMatrix<f64, 6, 1> {
    let (hi, hj) = (h.column(i), h.column(j));
    SMatrix::<f64, 6, 1>::from_column_slice(&[
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    ])
}

/// Zhang's closed form with zero skew; `None` when the views do not determine it.
fn zhang(homographies: &[Mat3]) -> Option<Mat3> {
    let mut vtv = SMatrix::<f64, 6, 6>::zeros();
    for h in homographies {
        let h = h / h.norm();
        let rows = [v_ij(&h, 0, 1), v_ij(&h, 0, 0) - v_ij(&h, 1, 1)];
        for r in rows {
            vtv += r * r.transpose();
        }
    }
    // Zero skew: B12 = 0, weighted like a view.
    let skew_row = SMatrix::<f64, 6, 1>::from_column_slice(&[0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    vtv += skew_row * skew_row.transpose() * (vtv.trace() / 6.0).max(1e-12);
    let eigen = vtv.symmetric_eigen();
    let mut order: Vec<usize> = (0..6).collect();
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    // The null vector must be clearly the smallest, or the views leave a family of solutions.
    if eigen.eigenvalues[order[0]] > 1e-3 * eigen.eigenvalues[order[1]] {
        return None;
    }
    let b = eigen.eigenvectors.column(order[0]);
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    if den.abs() < 1e-300 {
        return None;
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha2 = lambda / b11;
    let beta2 = lambda * b11 / den;
    if alpha2 <= 0.0 || beta2 <= 0.0 {
        return None;
    }
    let (alpha, beta) = (alpha2.sqrt(), beta2.sqrt());
    let u0 = -b13 * alpha2 / lambda;
    Some(Mat3::new(alpha, 0.0, u0, 0.0, beta, v0, 0.0, 0.0, 1.0))
}

/// Focal lengths alone, the principal point at the centre (normalized pixels' origin).
fn centred_focal(homographies: &[Mat3]) -> Option<Mat3> {
    // With omega = diag(a, b, 1): h1' omega h2 = 0 and h1' omega h1 = h2' omega h2.
    let mut ata = nalgebra::Matrix2::<f64>::zeros();
    let mut atb = Vector2::<f64>::zeros();
    for h in homographies {
        let h = h / h.norm();
        let rows = [
            (
                [h[(0, 0)] * h[(0, 1)], h[(1, 0)] * h[(1, 1)]],
                -h[(2, 0)] * h[(2, 1)],
            ),
            (
                [
                    h[(0, 0)].powi(2) - h[(0, 1)].powi(2),
                    h[(1, 0)].powi(2) - h[(1, 1)].powi(2),
                ],
                -(h[(2, 0)].powi(2) - h[(2, 1)].powi(2)),
            ),
        ];
        for (r, rhs) in rows {
            let r = Vector2::new(r[0], r[1]);
            ata += r * r.transpose();
            atb += r * rhs;
        }
    }
    let ab = ata.try_inverse()? * atb;
    if !(ab.x > 0.0 && ab.y > 0.0) {
        return None;
    }
    Some(Mat3::new(
        1.0 / ab.x.sqrt(),
        0.0,
        0.0,
        0.0,
        1.0 / ab.y.sqrt(),
        0.0,
        0.0,
        0.0,
        1.0,
    ))
}

/// Each view's `camera_from_centred` at the start: from its homography and the camera, then
/// refined by PnP's Levenberg-Marquardt.
fn initial_poses(problem: &Problem, camera: &CameraModel) -> Result<Vec<Pose>, VisionError> {
    let k = Mat3::new(
        camera.fx_px,
        0.0,
        camera.cx_px,
        0.0,
        camera.fy_px,
        camera.cy_px,
        0.0,
        0.0,
        1.0,
    );
    let k_inv = k
        .try_inverse()
        .ok_or_else(|| refuse("the starting camera is singular"))?;
    let mut poses = Vec::with_capacity(problem.views.len());
    for (v, view) in problem.views.iter().enumerate() {
        let start_failed = || refuse(format!("view {v}: no pose of the plate explains it"));
        let h = homography(&problem.plate_xy(v), &view.points_px).ok_or_else(start_failed)?;
        let a = k_inv * h;
        let scale = 2.0 / (a.column(0).norm() + a.column(1).norm());
        let sign = if a[(2, 2)] * scale < 0.0 { -1.0 } else { 1.0 };
        let r1 = a.column(0) * scale * sign;
        let r2 = a.column(1) * scale * sign;
        let t = a.column(2) * scale * sign;
        let r3 = r1.cross(&r2);
        let rotation = super::sqpnp::nearest_rotation(&Mat3::from_columns(&[r1, r2, r3]));
        let camera_from_plate = Pose::from_parts(
            Translation3::from(Vec3::from(t)),
            Rotation::from_matrix_eps(&rotation, 1e-15, 100, Rotation::identity()),
        );
        let plate_mm: Vec<Vec3> = view
            .ids
            .iter()
            .map(|&i| problem.plate_points_mm[i])
            .collect();
        let refined = pnp::refine(
            camera,
            &plate_mm,
            &view.points_px,
            &problem.weights[v],
            &camera_from_plate,
            50,
        )
        .ok_or_else(start_failed)?;
        poses.push(refined.camera_from_marker * Translation3::from(problem.centroids_mm[v]));
    }
    Ok(poses)
}
