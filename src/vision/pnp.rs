//! Perspective-n-point: `camera_from_marker` from a marker's known points and their pixels.
//!
//! 1. Undistort the pixels to normalized rays ([`CameraModel::undistort`]).
//! 2. Initialise: IPPE for planar markers (both solutions kept), SQPnP otherwise.
//! 3. Refine each candidate by Levenberg-Marquardt on the reprojection error in pixels, with the
//!    full distortion model, perturbing the pose about the marker points' centroid; keep the best.
//! 4. Check: every point in front of the camera, the RMS under the limit, a well-conditioned
//!    information matrix. The covariance is `(J^T W J)^-1` with `W = diag(1 / sigma_i^2)`, of
//!    the left perturbation `[rho (mm); phi (rad)]` (`docs/interface.md`, "Conventions"), so it
//!    feeds the filter as is.
//!
//! A point's standard deviation `sigma_i` is the camera's `pixel_sigma` when the pixels come
//! without their own uncertainty ([`solve_pnp`]); when a detector measured each point's
//! ([`solve_pnp_weighted`]) it is `sqrt(sigma_detected^2 + pixel_sigma^2)`: the camera's
//! `pixel_sigma` then stands for what the detector cannot see (calibration residuals, the air).
//! The fit minimises `sum |r_i|^2 / sigma_i^2`; the reported RMS is in pixels, unweighted.
//!
//! In robust mode an observation that fails the RMS check is solved again by RANSAC over
//! four-point subsets (a fixed pseudo-random sequence: the same input gives the same answer),
//! and the points off the consensus are reported.

use super::camera::{CameraModel, INTRINSICS};
use super::{VisionError, ippe, sqpnp};
use crate::geometry::{Mat3, Mat6, Pose, Rotation, Twist, Vec3, adjoint, se3_exp, skew};
use nalgebra::{Matrix2x3, SMatrix, Translation3, Vector2};

/// Fewest points accepted (a unique pose needs four in general position).
pub const MIN_POINTS: usize = 4;

/// How a pose is estimated and when it is refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PnpOptions {
    /// Standard deviation of a measured image point (px), or with per-point sigmas the part
    /// of it the detector does not see (added in quadrature).
    pub pixel_sigma_px: f64,
    /// A solution with a larger reprojection RMS is refused (px).
    pub max_rms_px: f64,
    /// Retry a refused observation by RANSAC, dropping points off the consensus.
    pub robust: bool,
    /// RANSAC: a point within this reprojection error supports a pose (px).
    pub inlier_threshold_px: f64,
    /// Levenberg-Marquardt iterations at most.
    pub max_iterations: usize,
}

impl Default for PnpOptions {
    fn default() -> Self {
        Self {
            pixel_sigma_px: 0.1,
            max_rms_px: 1.0,
            robust: false,
            inlier_threshold_px: 2.0,
            max_iterations: 50,
        }
    }
}

/// An estimated pose with its quality.
#[derive(Debug, Clone, PartialEq)]
pub struct PnpSolution {
    /// The pose of the marker in the camera frame.
    pub camera_from_marker: Pose,
    /// Covariance of the left perturbation `[rho (mm); phi (rad)]`: `(J^T W J)^-1`.
    pub covariance: Mat6,
    /// Root mean square of the reprojection error over the points used (px).
    pub rms_px: f64,
    /// Points used.
    pub points: usize,
    /// The RMS of the best solution over that of the runner-up local minimum (0 when there is
    /// none): near 1 the view is ambiguous (a planar marker seen nearly face-on, small in the
    /// image), near 0 it is not.
    pub ambiguity_ratio: f64,
    /// Indices of points left out in robust mode (empty otherwise).
    pub rejected_points: Vec<usize>,
    /// Levenberg-Marquardt iterations of the kept solution.
    pub iterations: usize,
}

/// The result of refining one start.
#[derive(Debug, Clone, Copy)]
pub struct Refinement {
    /// The refined pose.
    pub camera_from_marker: Pose,
    /// Sum of squared reprojection errors (px^2).
    pub cost_px2: f64,
    /// Sum of squared reprojection errors over their variances (what is minimised).
    pub chi2: f64,
    /// The solution with the marker frame moved to the points' centroid.
    pub camera_from_centred: Pose,
    /// `J^T W J` at the solution, of the right perturbation of `camera_from_centred`.
    pub information_centred: Mat6,
    /// Iterations taken.
    pub iterations: usize,
}

/// Estimates `camera_from_marker` from marker points (mm) and their measured pixels, every
/// pixel with the camera's `pixel_sigma`.
pub fn solve_pnp(
    camera: &CameraModel,
    marker_points_mm: &[Vec3],
    image_points_px: &[Vector2<f64>],
    options: &PnpOptions,
) -> Result<PnpSolution, VisionError> {
    check_input(marker_points_mm, image_points_px)?;
    let weights = vec![1.0 / options.pixel_sigma_px.powi(2); marker_points_mm.len()];
    solve_checked(camera, marker_points_mm, image_points_px, &weights, options)
}

/// Estimates `camera_from_marker` from marker points (mm), their measured pixels and each
/// pixel's own standard deviation (px, from the detector), the camera's `pixel_sigma` added in
/// quadrature.
pub fn solve_pnp_weighted(
    camera: &CameraModel,
    marker_points_mm: &[Vec3],
    image_points_px: &[Vector2<f64>],
    point_sigmas_px: &[f64],
    options: &PnpOptions,
) -> Result<PnpSolution, VisionError> {
    check_input(marker_points_mm, image_points_px)?;
    if point_sigmas_px.len() != image_points_px.len() {
        return Err(VisionError::MismatchedPoints {
            marker_points: marker_points_mm.len(),
            image_points: point_sigmas_px.len(),
        });
    }
    let mut weights = Vec::with_capacity(point_sigmas_px.len());
    for (i, s) in point_sigmas_px.iter().enumerate() {
        let variance = s * s + options.pixel_sigma_px * options.pixel_sigma_px;
        if !s.is_finite() || *s < 0.0 || variance <= 0.0 {
            return Err(VisionError::NonFinite {
                what: format!("the standard deviation of image point {i} ({s})"),
            });
        }
        weights.push(1.0 / variance);
    }
    solve_checked(camera, marker_points_mm, image_points_px, &weights, options)
}

fn solve_checked(
    camera: &CameraModel,
    marker_points_mm: &[Vec3],
    image_points_px: &[Vector2<f64>],
    weights: &[f64],
    options: &PnpOptions,
) -> Result<PnpSolution, VisionError> {
    let normalized = undistort_all(camera, image_points_px)?;
    let first = solve_all(
        camera,
        marker_points_mm,
        image_points_px,
        &normalized,
        weights,
        options,
    );
    match first {
        Err(VisionError::ReprojectionTooLarge { .. }) if options.robust => solve_ransac(
            camera,
            marker_points_mm,
            image_points_px,
            &normalized,
            weights,
            options,
        ),
        other => other,
    }
}

fn check_input(marker: &[Vec3], image: &[Vector2<f64>]) -> Result<(), VisionError> {
    if marker.len() != image.len() {
        return Err(VisionError::MismatchedPoints {
            marker_points: marker.len(),
            image_points: image.len(),
        });
    }
    if marker.len() < MIN_POINTS {
        return Err(VisionError::NotEnoughPoints {
            given: marker.len(),
            needed: MIN_POINTS,
        });
    }
    for (i, p) in marker.iter().enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(VisionError::NonFinite {
                what: format!("marker point {i}"),
            });
        }
    }
    for (i, p) in image.iter().enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(VisionError::NonFinite {
                what: format!("image point {i}"),
            });
        }
    }
    Ok(())
}

/// The shape of a marker: centroid and principal axes (rows of `plane_from_marker`).
struct Shape {
    centroid: Vec3,
    /// Rows: the principal axes, largest spread first; the last is the plane normal.
    axes: Mat3,
    planar: bool,
}

fn shape(points: &[Vec3]) -> Result<Shape, VisionError> {
    let n = points.len() as f64;
    let centroid = points.iter().fold(Vec3::zeros(), |a, p| a + p) / n;
    let scatter = points.iter().fold(Mat3::zeros(), |a, p| {
        a + (p - centroid) * (p - centroid).transpose()
    }) / n;
    let eigen = nalgebra::SymmetricEigen::new(scatter);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
    let [l0, l1, l2] = order.map(|k| eigen.eigenvalues[k].max(0.0));
    if l0.is_nan() || l0 <= 0.0 || l1 < 1e-10 * l0 {
        return Err(VisionError::Degenerate {
            reason: "the marker points are collinear (or coincide)".to_owned(),
        });
    }
    let e0: Vec3 = eigen.eigenvectors.column(order[0]).into_owned();
    let e1: Vec3 = eigen.eigenvectors.column(order[1]).into_owned();
    let e2 = e0.cross(&e1);
    Ok(Shape {
        centroid,
        axes: Mat3::from_rows(&[e0.transpose(), e1.transpose(), e2.transpose()]),
        planar: l2 < 1e-10 * l0,
    })
}

/// Initial `camera_from_marker` candidates, best first (by the initialiser's own cost): the
/// first stage of [`solve_pnp`], public for benchmarks.
pub fn initial_poses(
    camera: &CameraModel,
    marker_points_mm: &[Vec3],
    image_points_px: &[Vector2<f64>],
) -> Result<Vec<Pose>, VisionError> {
    check_input(marker_points_mm, image_points_px)?;
    initial_from_normalized(marker_points_mm, &undistort_all(camera, image_points_px)?)
}

/// The normalized rays `(X/Z, Y/Z)` of measured pixels.
fn undistort_all(
    camera: &CameraModel,
    image: &[Vector2<f64>],
) -> Result<Vec<Vector2<f64>>, VisionError> {
    image.iter().map(|p| camera.undistort(*p)).collect()
}

fn initial_from_normalized(
    marker: &[Vec3],
    normalized: &[Vector2<f64>],
) -> Result<Vec<Pose>, VisionError> {
    let shape = shape(marker)?;
    let mut poses = Vec::with_capacity(2);
    if shape.planar {
        let plane_xy: Vec<Vector2<f64>> = marker
            .iter()
            .map(|p| {
                let q = shape.axes * (p - shape.centroid);
                Vector2::new(q.x, q.y)
            })
            .collect();
        for (r_camera_from_plane, t) in ippe::candidates(&plane_xy, normalized) {
            // camera_from_marker = camera_from_plane * plane_from_marker.
            let rotation = r_camera_from_plane * shape.axes;
            let t_mm = t - rotation * shape.centroid;
            poses.push(pose_of(&rotation, &t_mm));
        }
    } else {
        let centred: Vec<Vec3> = marker.iter().map(|p| p - shape.centroid).collect();
        for m in sqpnp::minima(&centred, normalized) {
            let t_mm = m.t_mm - m.rotation * shape.centroid;
            poses.push(pose_of(&m.rotation, &t_mm));
        }
    }
    if poses.is_empty() {
        return Err(VisionError::Degenerate {
            reason: "the image points do not determine a pose".to_owned(),
        });
    }
    Ok(poses)
}

fn pose_of(rotation: &Mat3, t_mm: &Vec3) -> Pose {
    let r = Rotation::from_matrix_eps(rotation, 1e-15, 100, Rotation::identity());
    Pose::from_parts(Translation3::from(*t_mm), r)
}

/// Weighted cost, unweighted cost (px^2), `J^T W J` and `J^T W r` of the reprojection error at `camera_from_centred` (the marker
/// frame moved to the points' centroid `c`), over a right perturbation
/// `camera_from_centred * Exp(delta)`; `None` if a point is behind the camera. About the
/// centroid, rotation and translation are nearly decoupled, which keeps Gauss-Newton quadratic
/// for the narrow fields of view of measurement cameras.
fn evaluate(
    camera: &CameraModel,
    marker: &[Vec3],
    c: &Vec3,
    image: &[Vector2<f64>],
    weights: &[f64],
    camera_from_centred: &Pose,
) -> Option<(f64, f64, Mat6, SMatrix<f64, 6, 1>)> {
    let r_mat = camera_from_centred
        .rotation
        .to_rotation_matrix()
        .into_inner();
    let mut chi2 = 0.0;
    let mut cost = 0.0;
    let mut jtj = Mat6::zeros();
    let mut jtr = SMatrix::<f64, 6, 1>::zeros();
    for ((x, uv), w) in marker.iter().zip(image).zip(weights) {
        let xc = x - c;
        let p = r_mat * xc + camera_from_centred.translation.vector;
        let (proj, dp) = camera.project_with_jacobian(&p)?;
        let r = proj - uv;
        cost += r.norm_squared();
        chi2 += w * r.norm_squared();
        // p = R (x + rho + phi x x) + t: dp/drho = R, dp/dphi = -R [x]x.
        let dpr: Matrix2x3<f64> = dp * r_mat;
        let mut j = SMatrix::<f64, 2, 6>::zeros();
        j.fixed_view_mut::<2, 3>(0, 0).copy_from(&dpr);
        j.fixed_view_mut::<2, 3>(0, 3)
            .copy_from(&(-(dpr * skew(&xc))));
        jtj += j.transpose() * j * *w;
        jtr += j.transpose() * r * *w;
    }
    Some((chi2, cost, jtj, jtr))
}

/// Levenberg-Marquardt on the reprojection error from `start`, each point weighted by
/// `weights` (`1 / sigma_i^2`): the second stage of [`solve_pnp`], public for benchmarks.
/// `None` if the start puts a point behind the camera.
pub fn refine(
    camera: &CameraModel,
    marker_points_mm: &[Vec3],
    image_points_px: &[Vector2<f64>],
    weights: &[f64],
    start: &Pose,
    max_iterations: usize,
) -> Option<Refinement> {
    let c = marker_points_mm.iter().fold(Vec3::zeros(), |a, p| a + p)
        / marker_points_mm.len().max(1) as f64;
    let mut pose = start * Translation3::from(c);
    let eval = |pose: &Pose| evaluate(camera, marker_points_mm, &c, image_points_px, weights, pose);
    let (mut chi2, mut cost, mut jtj, mut jtr) = eval(&pose)?;
    // The initialisers start close: begin as Gauss-Newton, damp only when a step fails.
    let mut lambda = 1e-6;
    let mut iterations = 0;
    while iterations < max_iterations {
        iterations += 1;
        let mut a = jtj;
        for i in 0..6 {
            a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
        }
        let Some(chol) = a.cholesky() else {
            lambda *= 10.0;
            continue;
        };
        let delta: Twist = chol.solve(&(-jtr));
        // Converged: the step would lower the cost by less than its rounding, or no longer
        // moves the pose by anything that matters (1e-10 of the distance, 1e-12 rad).
        let predicted = -delta.dot(&jtr);
        let small = delta.fixed_rows::<3>(0).norm()
            < 1e-10 * (1.0 + pose.translation.vector.norm())
            && delta.fixed_rows::<3>(3).norm() < 1e-12;
        if small || predicted <= 1e-15 * chi2 {
            break;
        }
        let candidate = pose * se3_exp(&delta);
        match eval(&candidate).filter(|(x, _, _, _)| *x <= chi2) {
            Some((x, c, j, g)) => {
                pose = candidate;
                (chi2, cost, jtj, jtr) = (x, c, j, g);
                lambda = (lambda * 0.1).max(1e-12);
            }
            None => {
                lambda *= 10.0;
                if lambda > 1e8 {
                    break;
                }
            }
        }
    }
    Some(Refinement {
        camera_from_marker: pose * Translation3::from(-c),
        camera_from_centred: pose,
        cost_px2: cost,
        chi2,
        information_centred: jtj,
        iterations,
    })
}

/// How `camera_from_marker`'s estimate moves with the camera's intrinsics: `d xi / d theta`,
/// `xi` the left perturbation `[rho (mm); phi (rad)]` of the pose (as its covariance) and
/// `theta = (fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4)` (as the calibration's
/// covariance).
///
/// The estimate minimises `sum w_i |uv_i - pi(xi, theta; p_i)|^2`; at its minimum the
/// gradient vanishes, and differentiating that condition with respect to `theta` (the
/// Gauss-Newton approximation, residuals' second derivatives left out) gives
/// `d xi / d theta = -(J^T W J)^-1 J^T W J_theta`, with `J = d pi / d xi` and
/// `J_theta = d pi / d theta` at the solution. The weights are `1 / sigma_i^2` (uniform when
/// `None`); they scale out but for their ratios. A camera's intrinsics error `d theta` then
/// moves the pose by `S d theta` in every frame: the error that does not average down.
/// `None` when a point lies behind the camera or the points do not determine the pose.
pub fn intrinsics_sensitivity(
    camera: &CameraModel,
    marker_points_mm: &[Vec3],
    camera_from_marker: &Pose,
    weights: Option<&[f64]>,
) -> Option<SMatrix<f64, 6, INTRINSICS>> {
    let mut information = Mat6::zeros();
    let mut cross = SMatrix::<f64, 6, INTRINSICS>::zeros();
    for (i, m) in marker_points_mm.iter().enumerate() {
        let w = weights.map_or(1.0, |w| w.get(i).copied().unwrap_or(1.0));
        let p = camera_from_marker * nalgebra::Point3::from(*m);
        let (_, dp) = camera.project_with_jacobian(&p.coords)?;
        // Left perturbation: p' = Exp(xi) p, so dp/dxi = [I, -[p]x].
        let mut j = SMatrix::<f64, 2, 6>::zeros();
        j.fixed_view_mut::<2, 3>(0, 0).copy_from(&dp);
        j.fixed_view_mut::<2, 3>(0, 3)
            .copy_from(&(-(dp * skew(&p.coords))));
        let jt_w = j.transpose() * w;
        information += jt_w * j;
        cross += jt_w * camera.intrinsics_jacobian(&p.coords);
    }
    let chol = information.cholesky()?;
    Some(-chol.solve(&cross))
}

fn rms(cost_px2: f64, n: usize) -> f64 {
    (cost_px2 / n as f64).sqrt()
}

/// Solves with every point (`normalized`: the pixels undistorted).
fn solve_all(
    camera: &CameraModel,
    marker: &[Vec3],
    image: &[Vector2<f64>],
    normalized: &[Vector2<f64>],
    weights: &[f64],
    options: &PnpOptions,
) -> Result<PnpSolution, VisionError> {
    let starts = initial_from_normalized(marker, normalized)?;
    // Refine the two best starts that put the marker in front of the camera.
    let refine_starts = |starts: &[Pose]| -> Vec<Refinement> {
        starts
            .iter()
            .filter(|s| count_behind(s, marker) == 0)
            .take(2)
            .filter_map(|s| refine(camera, marker, image, weights, s, options.max_iterations))
            .collect()
    };
    let mut refined = refine_starts(&starts);
    refined.sort_by(|a, b| a.chi2.total_cmp(&b.chi2));
    // A planar marker of few points, some nearly in line, can give IPPE a homography too poor
    // to start from: when its best is over the limit, SQPnP's minima are tried as well.
    let over_limit = |r: &[Refinement]| {
        r.first()
            .is_none_or(|b| rms(b.cost_px2, marker.len()) > options.max_rms_px)
    };
    if over_limit(&refined) && shape(marker).is_ok_and(|s| s.planar) {
        let centroid = marker.iter().fold(Vec3::zeros(), |a, p| a + p) / marker.len() as f64;
        let centred: Vec<Vec3> = marker.iter().map(|p| p - centroid).collect();
        let more: Vec<Pose> = sqpnp::minima(&centred, normalized)
            .iter()
            .map(|m| pose_of(&m.rotation, &(m.t_mm - m.rotation * centroid)))
            .collect();
        refined.extend(refine_starts(&more));
        refined.sort_by(|a, b| a.chi2.total_cmp(&b.chi2));
    }
    let Some(best) = refined.first().copied() else {
        let behind = starts
            .first()
            .map_or(marker.len(), |s| count_behind(s, marker));
        return Err(VisionError::BehindCamera { count: behind });
    };
    let ambiguity_ratio = match refined.get(1) {
        Some(second) if !same_pose(&second.camera_from_marker, &best.camera_from_marker) => {
            if second.cost_px2 > 0.0 {
                (best.cost_px2 / second.cost_px2).sqrt()
            } else {
                1.0
            }
        }
        _ => 0.0,
    };
    // The initialiser's best fit lies behind the camera and explains the pixels within the
    // limit: whatever fits in front is a poorer explanation, and a refusal should say why.
    let behind_best = starts
        .first()
        .filter(|s| rms_through_the_centre(camera, marker, image, s) <= options.max_rms_px)
        .map_or(0, |s| count_behind(s, marker));
    finish(best, marker, options, ambiguity_ratio, behind_best)
}

/// The reprojection RMS of a pose by the projection equations alone, which hold for points
/// behind the camera too (a central projection does not know which side it looks at).
fn rms_through_the_centre(
    camera: &CameraModel,
    marker: &[Vec3],
    image: &[Vector2<f64>],
    pose: &Pose,
) -> f64 {
    let mut sum = 0.0;
    for (x, uv) in marker.iter().zip(image) {
        let p = pose * nalgebra::Point3::from(*x);
        if p.z == 0.0 {
            return f64::INFINITY;
        }
        let proj = camera.pixel_of_normalized(Vector2::new(p.x / p.z, p.y / p.z));
        sum += (proj - uv).norm_squared();
    }
    (sum / marker.len() as f64).sqrt()
}

fn same_pose(a: &Pose, b: &Pose) -> bool {
    a.rotation.angle_to(&b.rotation) < 1e-9
        && (a.translation.vector - b.translation.vector).norm() < 1e-6
}

fn count_behind(pose: &Pose, marker: &[Vec3]) -> usize {
    marker
        .iter()
        .filter(|x| (pose * nalgebra::Point3::from(**x)).z <= 0.0)
        .count()
}

/// Checks a refined solution and derives its covariance.
fn finish(
    best: Refinement,
    marker_used: &[Vec3],
    options: &PnpOptions,
    ambiguity_ratio: f64,
    behind_best_start: usize,
) -> Result<PnpSolution, VisionError> {
    let behind = count_behind(&best.camera_from_marker, marker_used);
    if behind > 0 {
        return Err(VisionError::BehindCamera { count: behind });
    }
    let rms_px = rms(best.cost_px2, marker_used.len());
    if rms_px.is_nan() || rms_px > options.max_rms_px {
        if behind_best_start > 0 {
            return Err(VisionError::BehindCamera {
                count: behind_best_start,
            });
        }
        return Err(VisionError::ReprojectionTooLarge {
            rms_px,
            limit_px: options.max_rms_px,
        });
    }
    let covariance = covariance_of(&best)?;
    Ok(PnpSolution {
        camera_from_marker: best.camera_from_marker,
        covariance,
        rms_px,
        points: marker_used.len(),
        ambiguity_ratio,
        rejected_points: Vec::new(),
        iterations: best.iterations,
    })
}

/// `(J^T W J)^-1` in the left perturbation of `camera_from_marker`, refused when the
/// information is (numerically) singular: the view does not determine some direction of the
/// pose. The right perturbation of `camera_from_centred` moves to the left one of
/// `camera_from_marker = camera_from_centred * const` by its adjoint.
fn covariance_of(refinement: &Refinement) -> Result<Mat6, VisionError> {
    let information = &refinement.information_centred;
    let d = information.diagonal().map(|v| v.max(0.0).sqrt());
    if d.iter().any(|v| v.is_nan() || *v <= 0.0) {
        return Err(degenerate_view());
    }
    let scale = Mat6::from_diagonal(&d.map(|v| 1.0 / v));
    let normalized = scale * information * scale;
    // With a unit diagonal, the largest diagonal entry of the inverse bounds 1/lambda_min
    // from below within a factor of 6: a cheap condition check.
    let inv = normalized.cholesky().ok_or_else(degenerate_view)?.inverse();
    if inv.diagonal().max() > 1e12 {
        return Err(degenerate_view());
    }
    let right = scale * inv * scale;
    let ad = adjoint(&refinement.camera_from_centred);
    let cov = ad * right * ad.transpose();
    Ok((cov + cov.transpose()) * 0.5)
}

fn degenerate_view() -> VisionError {
    VisionError::Degenerate {
        reason: "the view does not determine the pose (points nearly collinear in the image)"
            .to_owned(),
    }
}

/// A small, fixed pseudo-random sequence (xorshift64*): RANSAC is reproducible.
struct Sequence(u64);

impl Sequence {
    fn below(&mut self, n: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let v = self.0.wrapping_mul(0x2545_F491_4F6C_DD1D);
        ((v >> 33) % n as u64) as usize
    }
}

fn solve_ransac(
    camera: &CameraModel,
    marker: &[Vec3],
    image: &[Vector2<f64>],
    normalized: &[Vector2<f64>],
    weights: &[f64],
    options: &PnpOptions,
) -> Result<PnpSolution, VisionError> {
    let n = marker.len();
    let needed = MIN_POINTS.max(n.div_ceil(2) + 1).min(n);
    let no_consensus = || VisionError::NoConsensus {
        given: n,
        needed,
        threshold_px: options.inlier_threshold_px,
    };
    if n <= MIN_POINTS {
        return Err(no_consensus());
    }
    let threshold2 = options.inlier_threshold_px * options.inlier_threshold_px;
    let inliers_of = |pose: &Pose| -> Vec<usize> {
        (0..n)
            .filter(|&i| {
                let p = pose * nalgebra::Point3::from(marker[i]);
                camera
                    .project(&p.coords)
                    .is_some_and(|uv| (uv - image[i]).norm_squared() <= threshold2)
            })
            .collect()
    };
    let mut rng = Sequence(0x9E37_79B9_7F4A_7C15 ^ n as u64);
    let mut best: Vec<usize> = Vec::new();
    for _ in 0..200 {
        let mut subset: Vec<usize> = Vec::with_capacity(MIN_POINTS);
        while subset.len() < MIN_POINTS {
            let k = rng.below(n);
            if !subset.contains(&k) {
                subset.push(k);
            }
        }
        let m: Vec<Vec3> = subset.iter().map(|&i| marker[i]).collect();
        let v: Vec<Vector2<f64>> = subset.iter().map(|&i| normalized[i]).collect();
        let Ok(poses) = initial_from_normalized(&m, &v) else {
            continue;
        };
        for pose in poses {
            let inliers = inliers_of(&pose);
            if inliers.len() > best.len() {
                best = inliers;
            }
        }
        if best.len() == n {
            break;
        }
    }
    if best.len() < needed {
        return Err(no_consensus());
    }
    // Refine on the consensus, then take the consensus of the refined pose and refine again,
    // until it settles (three rounds at most).
    let mut kept = best;
    for round in 0..3 {
        let m: Vec<Vec3> = kept.iter().map(|&i| marker[i]).collect();
        let px: Vec<Vector2<f64>> = kept.iter().map(|&i| image[i]).collect();
        let rays: Vec<Vector2<f64>> = kept.iter().map(|&i| normalized[i]).collect();
        let w: Vec<f64> = kept.iter().map(|&i| weights[i]).collect();
        let solution = solve_all(camera, &m, &px, &rays, &w, options)?;
        let again = inliers_of(&solution.camera_from_marker);
        if round == 2 || again == kept || again.len() < needed {
            return Ok(PnpSolution {
                rejected_points: (0..n).filter(|i| !kept.contains(i)).collect(),
                ..solution
            });
        }
        kept = again;
    }
    Err(no_consensus())
}
