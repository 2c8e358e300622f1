//! The bundle adjustment of a camera calibration: the views prepared as a problem, its
//! Levenberg-Marquardt over the free intrinsics and every view's pose, and the report of the
//! fit (covariance, correlations, per-view fits, warnings).

use super::structure::{PointResidual, residual_structure};
use super::warp::{PlateShape, PlateWarp, SagBasis};
use super::{
    CalibrationOptions, CalibrationView, CalibrationWarning, CameraCalibration, Correlation,
    GLOBALS, Globals, ImageCorner, Intrinsic, RECOMMENDED_TILT_DEG, RECOMMENDED_VIEWS, SAG_X,
    SAG_Y, ViewFit, from_params, refuse,
};
use crate::geometry::{Pose, Vec3, se3_exp, skew};
use crate::vision::{CameraModel, INTRINSICS, Plate, VisionError, disc_image_offset};
use nalgebra::{DMatrix, DVector, Matrix2x3, SMatrix, Translation3, Vector2, Vector6};

/// The standard deviation of the weak prior on a global parameter, if it has one: the rational
/// model's `k4 k5 k6` about zero with 10, the thin prism's `s1..s4` with 0.1. Where distortion
/// is small, a numerator and a denominator that cancel leave the rational terms free to wander
/// along a valley the data do not see (to tens or hundreds, and to a pole in the field); the
/// prior bounds that valley at sizes lenses do not reach (a wide lens's rational terms stay
/// within a few units, a prism within a few thousandths) and moves nothing the data determine.
/// The covariance is the posterior's: along the valley it says the prior's width. The prior is
/// weighed against the data by their variance factor (see [`Problem::adjust`]).
pub(super) fn prior_sigma(i: usize) -> Option<f64> {
    use Intrinsic::{K4, K5, K6, S1, S2, S3, S4};
    let term = Intrinsic::ALL.get(i)?;
    match term {
        K4 | K5 | K6 => Some(10.0),
        S1 | S2 | S3 | S4 => Some(0.1),
        _ => None,
    }
}

/// The views prepared for adjustment.
pub(super) struct Problem<'a> {
    pub(super) views: &'a [CalibrationView],
    /// Per view: its points in the plate frame, relative to their centroid.
    pub(super) centred_mm: Vec<Vec<Vec3>>,
    /// Per view: the centroid of its plate points (mm).
    pub(super) centroids_mm: Vec<Vec3>,
    /// Per view: each point's weight (1 / variance).
    pub(super) weights: Vec<Vec<f64>>,
    /// Each plate point's disc diameter (mm).
    pub(super) diameters_mm: Vec<f64>,
    pub(super) plate_points_mm: Vec<Vec3>,
    /// Per view: each point's height per mm of the two sags (zeros for a flat plate).
    pub(super) sag_basis: Vec<Vec<[f64; 2]>>,
}

/// The fit at one estimate.
pub(super) struct Evaluation {
    /// Sum of squared residuals over their variances (what is minimised).
    pub(super) chi2: f64,
    /// Sum of squared residuals (px^2), per view.
    pub(super) view_cost_px2: Vec<f64>,
    /// `J^T W J` over the free intrinsics and the poses.
    pub(super) information: DMatrix<f64>,
    /// `J^T W r`.
    pub(super) gradient: DVector<f64>,
}

pub(super) struct Adjusted {
    pub(super) fit: Evaluation,
    pub(super) iterations: usize,
}

impl<'a> Problem<'a> {
    /// The views of `plate`; with `shape` [`PlateShape::Flat`] the sag stays out of the
    /// points' positions (its basis zero).
    pub(super) fn new(plate: &Plate, views: &'a [CalibrationView], shape: PlateShape) -> Self {
        let plate_points_mm = plate.points_mm();
        let basis = match shape {
            PlateShape::Flat => None,
            PlateShape::Auto | PlateShape::Warped => SagBasis::of(&plate_points_mm),
        };
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
        let sag_basis = views
            .iter()
            .map(|view| {
                view.ids
                    .iter()
                    .map(|&i| basis.map_or([0.0; 2], |b| b.at(&plate_points_mm[i])))
                    .collect()
            })
            .collect();
        Self {
            views,
            centred_mm,
            centroids_mm,
            weights,
            diameters_mm: (0..plate.len())
                .map(|i| plate.disc_diameter_mm(i))
                .collect(),
            plate_points_mm,
            sag_basis,
        }
    }

    /// Point `k` of view `v` relative to the view's centroid, on the plate sagging by `sag_mm`.
    fn point(&self, v: usize, k: usize, sag_mm: [f64; 2]) -> Vec3 {
        let b = self.sag_basis[v][k];
        let mut x = self.centred_mm[v][k];
        x.z += sag_mm[0] * b[0] + sag_mm[1] * b[1];
        x
    }

    /// Adds `var_px2` to every point's variance (per axis).
    pub(super) fn add_variance(&mut self, var_px2: f64) {
        for w in self.weights.iter_mut().flatten() {
            *w = 1.0 / (1.0 / *w + var_px2);
        }
    }

    pub(super) fn plate_xy(&self, v: usize) -> Vec<Vector2<f64>> {
        self.views[v]
            .ids
            .iter()
            .map(|&i| self.plate_points_mm[i].xy())
            .collect()
    }

    /// Each disc's eccentricity at the estimate (px).
    ///
    /// Each disc lies in the plate's plane: the sag's slope (a few thousandths of a radian)
    /// tilts it by less than the eccentricity notices.
    pub(super) fn offsets(
        &self,
        camera: &CameraModel,
        sag_mm: [f64; 2],
        poses: &[Pose],
    ) -> Vec<Vec<Vector2<f64>>> {
        poses
            .iter()
            .enumerate()
            .map(|(v, pose)| {
                let normal = pose.rotation * Vec3::z();
                self.views[v]
                    .ids
                    .iter()
                    .enumerate()
                    .map(|(k, &id)| {
                        let x = self.point(v, k, sag_mm);
                        let centre = (pose * nalgebra::Point3::from(x)).coords;
                        disc_image_offset(camera, &centre, &normal, self.diameters_mm[id])
                            .unwrap_or_else(Vector2::zeros)
                    })
                    .collect()
            })
            .collect()
    }

    /// The fit over the free intrinsics and the poses (`camera_from_centred`, right
    /// perturbation); `None` when a point is behind the camera.
    #[allow(clippy::too_many_arguments)]
    fn evaluate(
        &self,
        params: &Globals,
        poses: &[Pose],
        offsets: &[Vec<Vector2<f64>>],
        free: &[usize],
        size: (u32, u32),
        prior_scale: f64,
    ) -> Option<Evaluation> {
        let camera = from_params(params, size.0, size.1);
        let sag_mm = [params[SAG_X], params[SAG_Y]];
        let nf = free.len();
        let n = nf + 6 * poses.len();
        let mut jtj = DMatrix::<f64>::zeros(n, n);
        let mut jtr = DVector::<f64>::zeros(n);
        let mut chi2 = 0.0;
        let mut view_cost_px2 = vec![0.0; poses.len()];
        // Per point, on the stack: the Jacobian over the free globals (two rows, `nf` of the
        // columns used) and over the pose, their products accumulated by hand. A heap
        // matrix a point cost more than the arithmetic.
        let mut ji = [[0.0_f64; GLOBALS]; 2];
        for (v, pose) in poses.iter().enumerate() {
            let r_mat = pose.rotation.to_rotation_matrix().into_inner();
            let mut jii = DMatrix::<f64>::zeros(nf, nf);
            let mut jip = [[0.0_f64; 6]; GLOBALS];
            let mut jpp = SMatrix::<f64, 6, 6>::zeros();
            let mut gi = [0.0_f64; GLOBALS];
            let mut gp = Vector6::<f64>::zeros();
            for (k, offset) in offsets[v].iter().enumerate() {
                let x = self.point(v, k, sag_mm);
                let p = r_mat * x + pose.translation.vector;
                let (uv, dp) = camera.project_with_jacobian(&p)?;
                let r = uv + offset - self.views[v].points_px[k];
                let w = self.weights[v][k];
                view_cost_px2[v] += r.norm_squared();
                chi2 += w * r.norm_squared();
                let intrinsic = camera.intrinsics_jacobian(&p);
                let dpr: Matrix2x3<f64> = dp * r_mat;
                // A sag moves the point along the plate's z axis by its basis.
                let b = self.sag_basis[v][k];
                for (col, &i) in free.iter().enumerate() {
                    for (row, out) in ji.iter_mut().enumerate() {
                        out[col] = match i {
                            SAG_X => dpr[(row, 2)] * b[0],
                            SAG_Y => dpr[(row, 2)] * b[1],
                            i => intrinsic[(row, i)],
                        };
                    }
                }
                let mut jp = SMatrix::<f64, 2, 6>::zeros();
                jp.fixed_view_mut::<2, 3>(0, 0).copy_from(&dpr);
                jp.fixed_view_mut::<2, 3>(0, 3)
                    .copy_from(&(-(dpr * skew(&x))));
                for a in 0..nf {
                    let (wa0, wa1) = (w * ji[0][a], w * ji[1][a]);
                    for bcol in a..nf {
                        jii[(a, bcol)] += wa0 * ji[0][bcol] + wa1 * ji[1][bcol];
                    }
                    for (c, out) in jip[a].iter_mut().enumerate() {
                        *out += wa0 * jp[(0, c)] + wa1 * jp[(1, c)];
                    }
                    gi[a] += wa0 * r.x + wa1 * r.y;
                }
                jpp += jp.transpose() * jp * w;
                gp += jp.transpose() * r * w;
            }
            // The upper triangle was summed.
            for a in 0..nf {
                for bcol in 0..a {
                    jii[(a, bcol)] = jii[(bcol, a)];
                }
            }
            let o = nf + 6 * v;
            let mut top = jtj.view_mut((0, 0), (nf, nf));
            top += &jii;
            for a in 0..nf {
                for c in 0..6 {
                    jtj[(a, o + c)] = jip[a][c];
                    jtj[(o + c, a)] = jip[a][c];
                }
                jtr[a] += gi[a];
            }
            jtj.view_mut((o, o), (6, 6))
                .copy_from(&DMatrix::from_column_slice(6, 6, jpp.as_slice()));
            jtr.rows_mut(o, 6)
                .copy_from(&DVector::from_column_slice(gp.as_slice()));
        }
        // The wider models' weak prior: each of their terms about zero with its sigma.
        for (col, &i) in free.iter().enumerate() {
            if let Some(sigma) = prior_sigma(i) {
                let w = prior_scale / (sigma * sigma);
                chi2 += w * params[i] * params[i];
                jtj[(col, col)] += w;
                jtr[col] += w * params[i];
            }
        }
        Some(Evaluation {
            chi2,
            view_cost_px2,
            information: jtj,
            gradient: jtr,
        })
    }

    /// Each view's points' residuals at the estimate (detected minus predicted), with their
    /// variance as the fit weighs them scaled by `variance_factor`; `None` when a point is
    /// behind the camera.
    pub(super) fn residuals(
        &self,
        params: &Globals,
        poses: &[Pose],
        offsets: &[Vec<Vector2<f64>>],
        size: (u32, u32),
        variance_factor: f64,
    ) -> Option<Vec<Vec<PointResidual>>> {
        let camera = from_params(params, size.0, size.1);
        let sag_mm = [params[SAG_X], params[SAG_Y]];
        poses
            .iter()
            .enumerate()
            .map(|(v, pose)| {
                offsets[v]
                    .iter()
                    .enumerate()
                    .map(|(k, offset)| {
                        let p = pose * nalgebra::Point3::from(self.point(v, k, sag_mm));
                        let predicted = camera.project(&p.coords)? + offset;
                        let at_px = self.views[v].points_px[k];
                        Some(PointResidual {
                            at_px,
                            residual_px: at_px - predicted,
                            variance_px2: variance_factor / self.weights[v][k],
                        })
                    })
                    .collect()
            })
            .collect()
    }

    /// The largest `r^2 = (X^2 + Y^2) / Z^2` of a plate point in the camera frame.
    fn largest_r2(&self, params: &Globals, poses: &[Pose]) -> f64 {
        let sag_mm = [params[SAG_X], params[SAG_Y]];
        poses
            .iter()
            .enumerate()
            .flat_map(|(v, pose)| {
                (0..self.centred_mm[v].len()).map(move |k| {
                    let p = pose * nalgebra::Point3::from(self.point(v, k, sag_mm));
                    (p.x * p.x + p.y * p.y) / (p.z * p.z).max(1e-300)
                })
            })
            .fold(0.0, f64::max)
    }

    /// Levenberg-Marquardt with the eccentricities fixed.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn adjust(
        &self,
        params: &mut Globals,
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
        // The prior is weighed as the data are: by their variance factor at the start, so that
        // it keeps its width whatever the points' sigmas say of their noise.
        let points: usize = self.centred_mm.iter().map(Vec::len).sum();
        let dof = (2 * points)
            .saturating_sub(free.len() + 6 * poses.len())
            .max(1);
        let unscaled = self
            .evaluate(params, poses, offsets, free, size, 1.0)
            .ok_or_else(behind)?;
        let prior_scale = (unscaled.chi2 / dof as f64).max(1.0);
        let mut fit = self
            .evaluate(params, poses, offsets, free, size, prior_scale)
            .ok_or_else(behind)?;
        // The field the views cover (the largest normalized radius of a point, with a margin):
        // a step whose distortion folds or has a pole inside it is refused like a worse one.
        // A start that is not monotonic so far (it cannot be left by a monotonic step) is held
        // to the field it is monotonic in.
        let largest = self.largest_r2(params, poses);
        let here = from_params(params, width_px, height_px);
        let r2_max = [1.25 * largest, largest]
            .into_iter()
            .find(|&r2| here.radially_monotonic_to(r2))
            .unwrap_or(0.0);
        let monotonic =
            |p: &Globals| from_params(p, width_px, height_px).radially_monotonic_to(r2_max);
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
                .evaluate(&next_params, &next_poses, offsets, free, size, prior_scale)
                .filter(|e| e.chi2.is_finite() && e.chi2 <= fit.chi2 && monotonic(&next_params))
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

    /// The calibration at the solution, refused over the RMS limit or where the views do not
    /// determine a parameter; its `iterations` are the caller's to set.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn report(
        &self,
        params: &Globals,
        size: (u32, u32),
        poses: &[Pose],
        offsets: &[Vec<Vector2<f64>>],
        fit: Evaluation,
        free: &[usize],
        options: &CalibrationOptions,
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
        let mut globals = [[0.0; GLOBALS]; GLOBALS];
        for (a, &i) in free.iter().enumerate() {
            for (b, &j) in free.iter().enumerate() {
                globals[i][j] = inverse[(a, b)] * variance_factor;
            }
        }
        let mut covariance = [[0.0_f64; INTRINSICS]; INTRINSICS];
        let mut sigma = [0.0_f64; INTRINSICS];
        for i in 0..INTRINSICS {
            covariance[i].copy_from_slice(&globals[i][..INTRINSICS]);
            sigma[i] = covariance[i][i].max(0.0).sqrt();
        }
        let warped = free.contains(&SAG_X);
        let plate_warp = warped.then(|| {
            PlateWarp::new(
                [params[SAG_X], params[SAG_Y]],
                [
                    [globals[SAG_X][SAG_X], globals[SAG_X][SAG_Y]],
                    [globals[SAG_Y][SAG_X], globals[SAG_Y][SAG_Y]],
                ],
            )
        });
        let camera = from_params(params, size.0, size.1);
        let intrinsics: Vec<usize> = free.iter().copied().filter(|&i| i < INTRINSICS).collect();
        let mut correlations = Vec::new();
        for (a, &i) in intrinsics.iter().enumerate() {
            for &j in &intrinsics[a + 1..] {
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
        let residuals = self
            .residuals(params, poses, offsets, size, variance_factor)
            .unwrap_or_default();
        let all: Vec<PointResidual> = residuals.iter().flatten().copied().collect();
        let residual_structure = residual_structure(size.0, size.1, &all);
        let mut fixed = options.fixed.clone();
        fixed.sort();
        fixed.dedup();
        Ok(CameraCalibration {
            camera,
            model: options.model,
            sigma,
            covariance,
            rms_px,
            variance_factor,
            views,
            correlations,
            warnings,
            fixed,
            iterations: 0,
            cross_validation: None,
            plate_shape: if warped {
                PlateShape::Warped
            } else {
                PlateShape::Flat
            },
            plate_warp,
            residual_structure,
            residuals,
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
        let name = free.get(param).map_or("a view's pose", |&i| match i {
            SAG_X => "the plate's sag along x",
            SAG_Y => "the plate's sag along y",
            i => Intrinsic::ALL[i].name(),
        });
        let rational = free.contains(&Intrinsic::K4.index());
        let distortion = free
            .get(param)
            .is_some_and(|&i| (Intrinsic::K1.index()..SAG_X).contains(&i));
        return Err(refuse(if rational && distortion {
            format!(
                "the views do not determine {name}: the rational model's numerator and \
                 denominator trade against each other unless the lens distorts strongly out to \
                 the image's corners; fix k3 and k6, or choose a model with fewer terms"
            )
        } else {
            format!(
                "the views do not determine {name}: tilt the plate more and about different axes, or fix it"
            )
        }));
    }
    let Some(inverse) = scaled.cholesky().map(|c| c.inverse()) else {
        return Err(refuse("the views do not determine the intrinsics"));
    };
    Ok(DMatrix::from_fn(nf, nf, |i, j| {
        inverse[(i, j)] / (d[i] * d[j])
    }))
}
