//! Markers found with no prior: from the marker's layout and the detected discs alone, wherever
//! the marker is in the view and at any pose from which its discs image.
//!
//! **Hypotheses.** A disc's image is an ellipse whose size gives its distance (the major
//! semi-axis is `f r / d` for a disc of radius `r` at distance `d`) and whose shape gives its
//! plane's normal up to the sign of the tilt (the normal leans from the viewing ray by
//! `acos(minor / major)` along the minor axis). So one blob taken as one marker point fixes
//! the marker's position and the normal of its discs, leaving one angle about that normal; a
//! second blob taken as a second point fixes that angle in closed form (the ray to the second
//! blob must pass through the second point: two linear equations in `cos` and `sin` of the
//! angle) and tells how far the first blob's distance was off (the length of `(cos, sin)`).
//! Every anchor blob is paired with its nearest blobs of a similar size, as every pair of
//! marker points, both tilt signs and both faces of the discs (only the face the camera sees
//! at the link's nominal pose, when it has one: an opaque disc is not seen from behind): some
//! thousands of hypotheses of a few tens of operations each.
//!
//! **Verification.** A hypothesis predicts every marker point; it survives when its points find
//! blobs near their predictions, and the first four so found fit one pose (their RMS residual
//! within two of the tight gates below: most wrong hypotheses end here, cheaply). The blobs so
//! matched are refined by PnP (Levenberg-Marquardt
//! from the hypothesis), every point is predicted again at the refined pose and takes the one
//! blob within a tight gate (a point with two is left out), twice. That gives an
//! *identification*: which blob is which point, the points it uses, and the points that should
//! image inside the frame (the visible ones).
//!
//! **Acceptance** (the stated test). An identification *fits* when the chi-square of its
//! reprojection residuals (centroids corrected for the discs' eccentricity, each over the
//! detector's variance plus `pixel_sigma`'s) is below its 99.9 % quantile for `2 n - 6`
//! degrees of freedom. The best identification (most points, then smallest chi-square) is
//! accepted only when
//! * it fits, uses at least [`MIN_POINTS`] points, and uses every visible point;
//! * no *rival* exists: an identification that contradicts it (a point on another blob, or a
//!   blob on another point), fits, and either uses every visible point and at most one point
//!   fewer (a point is within what the frame's edge does) or uses as many points. A rival that
//!   leaves a visible point unexplained and uses fewer points has against it a disc missing
//!   where it needs one and one present that it cannot place, which the best explains.
//! * PnP with the eccentricity correction accepts it (its RMS limit).
//!
//! Otherwise the marker is not found and the reason says which rule failed. A symmetric
//! layout (one that maps onto itself under a motion the camera could see), or a marker whose
//! visible points alone are symmetric, is ambiguous from the frame alone; a *hint* (the last
//! pose the marker was seen at, or its nominal pose) settles such a turn when exactly one of
//! the rivals is within 30 degrees of it and every other beyond 60, and nothing else.
//! [`layout_symmetries`] finds symmetric layouts for `check-config`.

use super::identify::{Found, NotFound, solve_matched};
use super::observation::ObservedLink;
use crate::chain::chi_square_quantile;
use crate::geometry::{Mat3, Pose, Vec3};
use crate::vision::{Blob, MIN_POINTS, disc_image_offset, refine};
use nalgebra::{Point3, Rotation3, Translation3, UnitQuaternion, Vector2};
use std::collections::HashSet;

/// Blobs each anchor is paired with: its nearest of a similar size.
const PARTNERS: usize = 6;
/// A partner's area is within this factor of the anchor's (the marker's depth range and
/// foreshortening).
const AREA_RATIO: f64 = 2.5;
/// The anchor's distance, as its disc size gives it, may be off by this factor.
const DISTANCE_FACTOR: f64 = 1.4;
/// A hypothesis's point takes its nearest blob within this fraction of the distance to the
/// nearest other predicted point.
const FIRST_GATE_FRACTION: f64 = 0.3;
/// A hypothesis is given up after this many points with no blob near their prediction.
const FIRST_MISSES: usize = 2;
/// Levenberg-Marquardt iterations on the first four points matched: enough to place the rest
/// (a right match converges in two or three from the hypothesis), few for a wrong one.
const FIRST_ITERATIONS: usize = 4;
/// The first four points matched are refused when their fit's RMS residual exceeds this many
/// tight gates.
const FIRST_FIT_GATES: f64 = 2.0;
/// After refinement a point takes a blob within this many pixels ...
const TIGHT_GATE_PX: f64 = 3.0;
/// ... or this fraction of its disc's imaged radius, if larger.
const TIGHT_GATE_OF_RADIUS: f64 = 0.25;
/// A point is visible when its disc images wholly inside the frame with this margin (px).
const EDGE_MARGIN_PX: f64 = 2.0;
/// A hint settles a symmetric layout's turn for the identification within this angle of it ...
pub const HINT_ACCEPT_DEG: f64 = 30.0;
/// ... when every other is turned further than this from it.
pub const HINT_REFUSE_DEG: f64 = 60.0;
/// An identification fits when its chi-square is below this quantile.
const FIT_PROBABILITY: f64 = 0.999;

/// One identification: per marker point, its blob.
#[derive(Debug, Clone)]
struct Identification {
    blobs: Vec<Option<usize>>,
    used: usize,
    visible: usize,
    missing_visible: usize,
    /// The reprojection residuals over their variances (detector and `pixel_sigma`), after
    /// the eccentricity correction.
    chi2: f64,
    /// The refined pose (`camera_from_marker`).
    pose: Pose,
}

impl Identification {
    /// Whether the residuals are within what noise gives (the chi-square bound at
    /// [`FIT_PROBABILITY`]).
    fn fits(&self) -> bool {
        let dof = (2 * self.used).saturating_sub(6).max(1);
        self.chi2 <= chi_square_quantile(dof, FIT_PROBABILITY)
    }
}

impl Identification {
    /// Whether `other` labels some blob differently (the same blob as another point, or the
    /// same point on another blob).
    fn contradicts(&self, other: &Identification) -> bool {
        self.blobs.iter().zip(&other.blobs).any(|pair| match pair {
            (Some(a), Some(b)) => a != b,
            _ => false,
        }) || self.blobs.iter().enumerate().any(|(i, a)| {
            a.is_some()
                && other
                    .blobs
                    .iter()
                    .enumerate()
                    .any(|(j, b)| j != i && b == a)
        })
    }
}

/// A blob seen as a disc: its ray and how far along it.
struct Seen {
    centre: Vector2<f64>,
    ray: Vec3,
    distance_mm: f64,
    /// Unit, perpendicular to the ray: the minor axis' direction lifted into space.
    minor_dir: Vec3,
    cos_tilt: f64,
    sin_tilt: f64,
    area_px: f64,
}

/// The side of a [`Grid`]'s cells (px): about the widest gate, so a look spans a few cells.
const GRID_CELL_PX: f64 = 48.0;

/// Blobs by position, for the nearest within a gate.
struct Grid {
    cell_px: f64,
    columns: usize,
    rows: usize,
    cells: Vec<Vec<usize>>,
}

impl Grid {
    fn new(centres: &[Vector2<f64>], width_px: u32, height_px: u32) -> Self {
        let cell_px = GRID_CELL_PX;
        let columns = (f64::from(width_px) / cell_px).ceil().max(1.0) as usize;
        let rows = (f64::from(height_px) / cell_px).ceil().max(1.0) as usize;
        let mut cells = vec![Vec::new(); columns * rows];
        for (k, c) in centres.iter().enumerate() {
            let (x, y) = Self::cell(c, cell_px, columns, rows);
            cells[y * columns + x].push(k);
        }
        Self {
            cell_px,
            columns,
            rows,
            cells,
        }
    }

    fn cell(c: &Vector2<f64>, cell_px: f64, columns: usize, rows: usize) -> (usize, usize) {
        let x = (c.x / cell_px).floor().clamp(0.0, (columns - 1) as f64) as usize;
        let y = (c.y / cell_px).floor().clamp(0.0, (rows - 1) as f64) as usize;
        (x, y)
    }

    /// The nearest blob within `gate` of `p` and whether a second one is within it too.
    fn nearest(&self, centres: &[Vector2<f64>], p: &Vector2<f64>, gate: f64) -> Nearest {
        let lo = Vector2::new(p.x - gate, p.y - gate);
        let hi = Vector2::new(p.x + gate, p.y + gate);
        let (x0, y0) = Self::cell(&lo, self.cell_px, self.columns, self.rows);
        let (x1, y1) = Self::cell(&hi, self.cell_px, self.columns, self.rows);
        // Squared distances: no square root per blob looked at.
        let gate2 = gate * gate;
        let mut best: Option<(f64, usize)> = None;
        let mut within = 0;
        for y in y0..=y1 {
            for x in x0..=x1 {
                for &k in &self.cells[y * self.columns + x] {
                    let d = (centres[k] - p).norm_squared();
                    if d <= gate2 {
                        within += 1;
                        if best.is_none_or(|(b, _)| d < b) {
                            best = Some((d, k));
                        }
                    }
                }
            }
        }
        match best {
            None => Nearest::None,
            Some((_, k)) if within == 1 => Nearest::One(k),
            Some(_) => Nearest::Several,
        }
    }
}

enum Nearest {
    None,
    One(usize),
    Several,
}

/// Finds `link`'s marker among `blobs` (the discs detected in the whole frame) with no prior.
///
/// `hint`, when there is one (the last pose the marker was seen at, or its nominal pose),
/// settles a turn of a symmetric layout and nothing else: among identifications that are
/// otherwise rivals, the one whose rotation is within [`HINT_ACCEPT_DEG`] of the hint's is
/// taken when every other is beyond [`HINT_REFUSE_DEG`].
pub fn find_without_prior(
    link: &ObservedLink,
    blobs: &[Blob],
    hint: Option<&Pose>,
) -> Result<Found, NotFound> {
    let target = link.target.ok_or(NotFound::NoTarget)?;
    let n = link.points_mm.len();
    let camera = &link.camera;
    let radius_mm = 0.5 * target.diameter_mm;
    let focal_px = (camera.fx_px * camera.fy_px).sqrt();
    let centres: Vec<Vector2<f64>> = blobs
        .iter()
        .map(|b| Vector2::new(b.centre_px[0], b.centre_px[1]))
        .collect();
    let seen: Vec<Option<Seen>> = blobs
        .iter()
        .zip(&centres)
        .map(|(b, c)| see(link, b, c, radius_mm, focal_px))
        .collect();
    let grid = Grid::new(&centres, camera.width_px, camera.height_px);
    let extent_mm = link
        .points_mm
        .iter()
        .flat_map(|p| link.points_mm.iter().map(move |q| (p - q).norm()))
        .fold(0.0, f64::max);

    // Per pair of points: the offset along the anchor's normal and its in-plane part.
    struct PairGeometry {
        along_mm: f64,
        across_mm: f64,
        across_dir: Vec3,
    }
    let pairs: Vec<Vec<Option<PairGeometry>>> = (0..n)
        .map(|i| {
            (0..n)
                .map(|j| {
                    let d = link.points_mm[j] - link.points_mm[i];
                    let normal = link.normals[i].normalize();
                    let along_mm = d.dot(&normal);
                    let across = d - along_mm * normal;
                    let across_mm = across.norm();
                    (j != i && across_mm > 1e-6 * extent_mm.max(1.0)).then(|| PairGeometry {
                        along_mm,
                        across_mm,
                        across_dir: across / across_mm,
                    })
                })
                .collect()
        })
        .collect();

    // Per anchor point, the others nearest first.
    let orders: Vec<Vec<usize>> = (0..n)
        .map(|i| {
            let mut order: Vec<usize> = (0..n).filter(|k| *k != i).collect();
            order.sort_by(|x, y| {
                let d = |k: &usize| (link.points_mm[*k] - link.points_mm[i]).norm();
                d(x).total_cmp(&d(y))
            });
            order
        })
        .collect();
    // The face each disc shows the camera at the nominal pose: an opaque disc is seen from that
    // side or not at all, so a hypothesis that shows its other face is not formed.
    let front_faces_camera: Vec<Option<bool>> = (0..n)
        .map(|i| {
            link.nominal.map(|nominal| {
                let centre = nominal * Point3::from(link.points_mm[i]);
                (nominal.rotation * link.normals[i]).dot(&centre.coords) < 0.0
            })
        })
        .collect();
    let mut tried: HashSet<Vec<Option<usize>>> = HashSet::new();
    let mut identifications: Vec<Identification> = Vec::new();
    for (a, anchor) in seen.iter().enumerate() {
        let Some(anchor) = anchor else { continue };
        let reach_px = DISTANCE_FACTOR * 1.2 * focal_px * extent_mm / anchor.distance_mm;
        let tight_gate_px =
            TIGHT_GATE_PX.max(TIGHT_GATE_OF_RADIUS * radius_mm * focal_px / anchor.distance_mm);
        let mut partners: Vec<(f64, usize)> = seen
            .iter()
            .enumerate()
            .filter(|(b, s)| {
                *b != a
                    && s.as_ref().is_some_and(|s| {
                        let ratio = s.area_px / anchor.area_px;
                        (1.0 / AREA_RATIO..=AREA_RATIO).contains(&ratio)
                    })
            })
            .map(|(b, _)| ((centres[b] - anchor.centre).norm(), b))
            .filter(|(d, _)| *d <= reach_px)
            .collect();
        partners.sort_by(|x, y| x.0.total_cmp(&y.0));
        partners.truncate(PARTNERS);
        for normal_c in normal_candidates(anchor) {
            // A basis of the discs' plane in the camera frame.
            let e1 = normal_c
                .cross(&anchor.ray)
                .try_normalize(1e-9)
                .unwrap_or_else(|| {
                    normal_c
                        .cross(&Vec3::x())
                        .try_normalize(1e-9)
                        .unwrap_or_else(Vec3::y)
                });
            let e2 = normal_c.cross(&e1);
            let x_a = anchor.distance_mm * anchor.ray;
            for &(_, b) in &partners {
                let Some(partner) = &seen[b] else { continue };
                let ray_b = partner.ray;
                let u1 = ray_b.cross(&e1);
                let u2 = ray_b.cross(&e2);
                let (g11, g12, g22) = (u1.dot(&u1), u1.dot(&u2), u2.dot(&u2));
                let det = g11 * g22 - g12 * g12;
                if det.abs() < 1e-12 {
                    continue;
                }
                let bx = ray_b.cross(&x_a);
                let bn = ray_b.cross(&normal_c);
                let (p1, q1, p2, q2) = (u1.dot(&bx), u1.dot(&bn), u2.dot(&bx), u2.dot(&bn));
                let solve = |scale: f64, g: &PairGeometry| {
                    let r1 = -(scale * p1 + g.along_mm * q1) / g.across_mm;
                    let r2 = -(scale * p2 + g.along_mm * q2) / g.across_mm;
                    ((g22 * r1 - g12 * r2) / det, (g11 * r2 - g12 * r1) / det)
                };
                let faces_camera = normal_c.dot(&anchor.ray) < 0.0;
                for i in 0..n {
                    if front_faces_camera[i].is_some_and(|f| f != faces_camera) {
                        continue;
                    }
                    for (j, g) in pairs[i].iter().enumerate() {
                        let Some(g) = g else { continue };
                        let (c, s) = solve(1.0, g);
                        // Most pairs fail here: the square root only for those that pass.
                        let rho2 = c * c + s * s;
                        if !(DISTANCE_FACTOR.powi(-2)..=DISTANCE_FACTOR.powi(2)).contains(&rho2) {
                            continue;
                        }
                        let rho = rho2.sqrt();
                        // The anchor's distance off by about rho: solved again at rho times it.
                        let (c, s) = solve(rho, g);
                        let Some(u) = (c * e1 + s * e2).try_normalize(1e-12) else {
                            continue;
                        };
                        let normal_m = link.normals[i].normalize();
                        let m = Mat3::from_columns(&[
                            normal_m,
                            g.across_dir,
                            normal_m.cross(&g.across_dir),
                        ]);
                        let c_frame = Mat3::from_columns(&[normal_c, u, normal_c.cross(&u)]);
                        let rotation = c_frame * m.transpose();
                        let t = rho * x_a - rotation * link.points_mm[i];
                        // The partner's disc images at the size its place in this pose gives
                        // it, within the anchor's own tolerance (the anchor's fits by
                        // construction): a pair whose sizes cannot fit is refused before the
                        // costlier match.
                        let partner_ratio =
                            (rotation * link.points_mm[j] + t).norm() / partner.distance_mm;
                        if !(1.0 / DISTANCE_FACTOR..=DISTANCE_FACTOR).contains(&partner_ratio) {
                            continue;
                        }
                        let pose = Pose::from_parts(
                            Translation3::from(t),
                            UnitQuaternion::from_rotation_matrix(
                                &Rotation3::from_matrix_unchecked(rotation),
                            ),
                        );
                        let Some(first) = first_match(
                            link,
                            &centres,
                            &grid,
                            &pose,
                            &orders[i],
                            a,
                            i,
                            b,
                            j,
                            tight_gate_px,
                        ) else {
                            continue;
                        };
                        if !tried.insert(first.assignment.clone()) {
                            continue;
                        }
                        if let Some(found) = verify(link, blobs, &centres, &grid, first)
                            && !identifications.iter().any(|k| k.blobs == found.blobs)
                        {
                            identifications.push(found);
                        }
                    }
                }
            }
        }
    }
    choose(link, blobs, identifications, hint)
}

/// A blob as a disc of the marker: its ray, distance and tilt.
fn see(
    link: &ObservedLink,
    blob: &Blob,
    centre: &Vector2<f64>,
    radius_mm: f64,
    focal_px: f64,
) -> Option<Seen> {
    let [major_px, minor_px, angle] = blob.ellipse;
    if major_px.is_nan() || major_px <= 0.5 || !minor_px.is_finite() {
        return None;
    }
    let xy = link.camera.undistort(*centre).ok()?;
    let ray = Vec3::new(xy.x, xy.y, 1.0).normalize();
    let minor_image = Vec3::new(-angle.sin(), angle.cos(), 0.0);
    let minor_dir = (minor_image - minor_image.dot(&ray) * ray).try_normalize(1e-9)?;
    let cos_tilt = (minor_px / major_px).clamp(0.0, 1.0);
    Some(Seen {
        centre: *centre,
        ray,
        distance_mm: radius_mm * focal_px / major_px,
        minor_dir,
        cos_tilt,
        sin_tilt: (1.0 - cos_tilt * cos_tilt).sqrt(),
        area_px: blob.area_px,
    })
}

/// The normals the anchor's ellipse allows (camera frame): both tilt signs (one when it is
/// seen face-on), both faces.
fn normal_candidates(anchor: &Seen) -> Vec<Vec3> {
    let facing = -anchor.cos_tilt * anchor.ray;
    let lean = anchor.sin_tilt * anchor.minor_dir;
    let mut normals = vec![facing + lean];
    if anchor.sin_tilt > 0.05 {
        normals.push(facing - lean);
    }
    let back: Vec<Vec3> = normals.iter().map(|n| -n).collect();
    normals.extend(back);
    normals
}

/// A hypothesis's first matches: each point's blob, and the pose refined on them.
struct FirstMatch {
    /// Each point's blob, `None` where none matched.
    assignment: Vec<Option<usize>>,
    pose: Pose,
}

/// Each point's nearest blob under a hypothesis, grown outwards from the anchor: the points
/// nearest the anchor in the layout first (where an error of the anchor's tilt or distance
/// moves the prediction least), each within a gate of a fraction of the predicted spacing, the
/// pose refined by PnP once four points are matched. `None` when more than [`FIRST_MISSES`]
/// points in the frame find no blob, or too few match. The anchor pair keeps its blobs.
#[allow(clippy::too_many_arguments)]
fn first_match(
    link: &ObservedLink,
    centres: &[Vector2<f64>],
    grid: &Grid,
    pose: &Pose,
    order: &[usize],
    a: usize,
    i: usize,
    b: usize,
    j: usize,
    tight_gate_px: f64,
) -> Option<FirstMatch> {
    let spacing_of = predict_all(link, pose);
    let mut pose = *pose;
    let mut assignment = vec![None; link.points_mm.len()];
    assignment[i] = Some(a);
    assignment[j] = Some(b);
    let (mut matched, mut misses, mut refined) = (2, 0, false);
    for &k in order {
        if k == j {
            continue;
        }
        // Until the fit, the pose is the hypothesis's: its images are already predicted.
        let predicted = if refined {
            link.camera
                .project(&(pose * Point3::from(link.points_mm[k])).coords)
        } else {
            spacing_of[k]
        };
        let Some(p) = predicted else {
            continue;
        };
        if !link.camera.in_image(&p) {
            continue;
        }
        let gate = (FIRST_GATE_FRACTION * nearest_other(&spacing_of, k)).max(TIGHT_GATE_PX);
        match grid.nearest(centres, &p, gate) {
            Nearest::One(blob) if !assignment.contains(&Some(blob)) => {
                assignment[k] = Some(blob);
                matched += 1;
            }
            _ => {
                misses += 1;
                if misses > FIRST_MISSES {
                    return None;
                }
            }
        }
        if matched == MIN_POINTS && !refined {
            refined = true;
            let (object, image): (Vec<Vec3>, Vec<Vector2<f64>>) = assignment
                .iter()
                .enumerate()
                .filter_map(|(m, x)| x.map(|x| (link.points_mm[m], centres[x])))
                .unzip();
            let weights = vec![1.0; object.len()];
            let refined = refine(
                &link.camera,
                &object,
                &image,
                &weights,
                &pose,
                FIRST_ITERATIONS,
            )?;
            // Four points no pose places near their blobs are not this marker's (the tight
            // match would leave them out): refused before the costlier verification.
            if refined.cost_px2 / MIN_POINTS as f64 > (FIRST_FIT_GATES * tight_gate_px).powi(2) {
                return None;
            }
            pose = refined.camera_from_marker;
        }
    }
    (matched >= MIN_POINTS).then_some(FirstMatch { assignment, pose })
}

/// Every point's image at `pose` (`None` behind the camera).
fn predict_all(link: &ObservedLink, pose: &Pose) -> Vec<Option<Vector2<f64>>> {
    link.points_mm
        .iter()
        .map(|p| link.camera.project(&(pose * Point3::from(*p)).coords))
        .collect()
}

/// The distance from point `k`'s image to the nearest other point's.
fn nearest_other(predicted: &[Option<Vector2<f64>>], k: usize) -> f64 {
    let Some(p) = predicted[k] else {
        return f64::INFINITY;
    };
    predicted
        .iter()
        .enumerate()
        .filter(|(m, _)| *m != k)
        .filter_map(|(_, q)| q.map(|q| (q - p).norm_squared()))
        .fold(f64::INFINITY, f64::min)
        .sqrt()
}

/// Refines a hypothesis's matches by PnP and matches every point again at the refined pose
/// (twice): the identification it leads to.
fn verify(
    link: &ObservedLink,
    blobs: &[Blob],
    centres: &[Vector2<f64>],
    grid: &Grid,
    first: FirstMatch,
) -> Option<Identification> {
    let FirstMatch {
        mut assignment,
        mut pose,
    } = first;
    let mut visible = Vec::new();
    for _ in 0..2 {
        let (object, image): (Vec<Vec3>, Vec<Vector2<f64>>) = assignment
            .iter()
            .enumerate()
            .filter_map(|(k, b)| b.map(|b| (link.points_mm[k], centres[b])))
            .unzip();
        if object.len() < MIN_POINTS {
            return None;
        }
        let weights = vec![1.0; object.len()];
        let refined = refine(&link.camera, &object, &image, &weights, &pose, 20)?;
        pose = refined.camera_from_marker;
        (assignment, visible) = tight_match(link, centres, grid, &pose);
    }
    let blobs_of = assignment;
    let used = blobs_of.iter().flatten().count();
    if used < MIN_POINTS {
        return None;
    }
    // The residuals of the centroids corrected for their discs' eccentricity, refined once
    // more: what the final solution will see.
    let diameter_mm = link.target.map_or(0.0, |t| t.diameter_mm);
    let (mut object, mut image, mut weights) = (Vec::new(), Vec::new(), Vec::new());
    for (k, b) in blobs_of.iter().enumerate() {
        let Some(b) = *b else { continue };
        let centre = (pose * Point3::from(link.points_mm[k])).coords;
        let normal = pose.rotation * link.normals[k];
        let offset = disc_image_offset(&link.camera, &centre, &normal, diameter_mm)
            .unwrap_or_else(Vector2::zeros);
        object.push(link.points_mm[k]);
        image.push(centres[b] - offset);
        let sigma2 = blobs[b].sigma_px().powi(2) + link.options.pixel_sigma_px.powi(2);
        weights.push(1.0 / sigma2.max(1e-12));
    }
    let refined = refine(&link.camera, &object, &image, &weights, &pose, 20)?;
    let missing_visible = visible
        .iter()
        .zip(&blobs_of)
        .filter(|(v, b)| **v && b.is_none())
        .count();
    Some(Identification {
        used,
        visible: visible.iter().filter(|v| **v).count(),
        missing_visible,
        blobs: blobs_of,
        chi2: refined.chi2,
        pose: refined.camera_from_marker,
    })
}

/// Each point's one blob within the tight gate at `pose`, and whether the point is visible
/// (its disc images wholly inside the frame, in front of the camera).
pub(super) fn tight_match_at(
    link: &ObservedLink,
    blobs: &[Blob],
    pose: &Pose,
) -> (Vec<Option<usize>>, Vec<bool>) {
    let centres: Vec<Vector2<f64>> = blobs
        .iter()
        .map(|b| Vector2::new(b.centre_px[0], b.centre_px[1]))
        .collect();
    let grid = Grid::new(&centres, link.camera.width_px, link.camera.height_px);
    tight_match(link, &centres, &grid, pose)
}

fn tight_match(
    link: &ObservedLink,
    centres: &[Vector2<f64>],
    grid: &Grid,
    pose: &Pose,
) -> (Vec<Option<usize>>, Vec<bool>) {
    let predicted = predict_all(link, pose);
    let focal_px = link.camera.fx_px.max(link.camera.fy_px);
    let diameter_mm = link.target.map_or(0.0, |t| t.diameter_mm);
    let (w, h) = (
        f64::from(link.camera.width_px),
        f64::from(link.camera.height_px),
    );
    let mut assignment = vec![None; predicted.len()];
    let mut visible = vec![false; predicted.len()];
    for (k, p) in predicted.iter().enumerate() {
        let Some(p) = p else { continue };
        let depth_mm = (pose * Point3::from(link.points_mm[k])).z.max(1.0);
        let radius_px = 0.5 * diameter_mm * focal_px / depth_mm;
        let margin = radius_px + EDGE_MARGIN_PX;
        // Two discs that image together are one blob, which the detector refuses.
        let apart = nearest_other(&predicted, k) > 2.0 * radius_px + EDGE_MARGIN_PX;
        visible[k] = apart
            && p.x >= margin - 0.5
            && p.y >= margin - 0.5
            && p.x <= w - 0.5 - margin
            && p.y <= h - 0.5 - margin;
        let gate = (TIGHT_GATE_PX.max(TIGHT_GATE_OF_RADIUS * radius_px))
            .min(0.45 * nearest_other(&predicted, k));
        // A disc that images against another is not measured cleanly: left out.
        if !apart {
            continue;
        }
        if let Nearest::One(blob) = grid.nearest(centres, p, gate) {
            assignment[k] = Some(blob);
        }
    }
    // A blob taken by two points belongs to neither.
    for k in 0..assignment.len() {
        if let Some(b) = assignment[k]
            && assignment.iter().filter(|x| **x == Some(b)).count() > 1
        {
            for x in assignment.iter_mut().filter(|x| **x == Some(b)) {
                *x = None;
            }
        }
    }
    (assignment, visible)
}

/// The accepted identification's pose, or why there is none.
fn choose(
    link: &ObservedLink,
    blobs: &[Blob],
    mut identifications: Vec<Identification>,
    hint: Option<&Pose>,
) -> Result<Found, NotFound> {
    identifications.sort_by(|x, y| y.used.cmp(&x.used).then(x.chi2.total_cmp(&y.chi2)));
    let Some(best) = identifications
        .iter()
        .find(|k| k.missing_visible == 0 && k.used >= MIN_POINTS && k.fits())
    else {
        let most = identifications.first();
        return Err(NotFound::NotIdentified {
            used: most.map_or(0, |k| k.used),
            visible: most.map_or(0, |k| k.visible),
        });
    };
    // A rival is an identification that contradicts the best, fits within noise itself, and
    // explains nearly as much: every visible point and at most one point fewer than the best,
    // or as many points as the best.
    let rivals: Vec<&Identification> = identifications
        .iter()
        .filter(|k| {
            best.contradicts(k)
                && k.fits()
                && ((k.missing_visible == 0 && k.used + 1 >= best.used) || k.used >= best.used)
        })
        .collect();
    let mut best = best;
    if let Some(rival) = rivals.first() {
        let turn =
            |k: &Identification| hint.map(|h| k.pose.rotation.angle_to(&h.rotation).to_degrees());
        let near: Vec<&Identification> = std::iter::once(best)
            .chain(rivals.iter().copied())
            .filter(|k| turn(k).is_some_and(|d| d <= HINT_ACCEPT_DEG))
            .collect();
        let far_enough = std::iter::once(best)
            .chain(rivals.iter().copied())
            .all(|k| turn(k).is_some_and(|d| d <= HINT_ACCEPT_DEG || d > HINT_REFUSE_DEG));
        match (near.as_slice(), far_enough) {
            ([one], true) => best = one,
            _ => {
                return Err(NotFound::Ambiguous {
                    used: best.used,
                    rival_used: rival.used,
                });
            }
        }
    }
    let matched: Vec<(usize, usize)> = best
        .blobs
        .iter()
        .enumerate()
        .filter_map(|(k, b)| b.map(|b| (k, b)))
        .collect();
    solve_matched(link, blobs, &matched)
}

/// Motions under which the layout maps onto itself, or nearly: for each pair of distinct
/// point labellings that a rigid motion relates (every point onto another point within
/// `tolerance_mm`), one. Empty for a layout a camera identifies unambiguously.
pub fn layout_symmetries(points_mm: &[Vec3], tolerance_mm: f64) -> Vec<Vec<usize>> {
    let n = points_mm.len();
    let mut found = Vec::new();
    if n < 3 {
        return found;
    }
    // Three non-collinear points as the basis; every image of them under a permutation of
    // the layout that keeps distances is a candidate motion.
    let Some((i0, i1, i2)) = basis(points_mm) else {
        return found;
    };
    let frame_of = |a: &Vec3, b: &Vec3, c: &Vec3| -> Option<(Mat3, Vec3)> {
        let x = (b - a).try_normalize(1e-9)?;
        let z = x.cross(&(c - a)).try_normalize(1e-9)?;
        Some((Mat3::from_columns(&[x, z.cross(&x), z]), *a))
    };
    let Some((r0, o0)) = frame_of(&points_mm[i0], &points_mm[i1], &points_mm[i2]) else {
        return found;
    };
    let d = |a: usize, b: usize| (points_mm[a] - points_mm[b]).norm();
    for j0 in 0..n {
        for j1 in 0..n {
            if j1 == j0 || (d(j0, j1) - d(i0, i1)).abs() > tolerance_mm {
                continue;
            }
            for j2 in 0..n {
                if j2 == j0
                    || j2 == j1
                    || (d(j0, j2) - d(i0, i2)).abs() > tolerance_mm
                    || (d(j1, j2) - d(i1, i2)).abs() > tolerance_mm
                {
                    continue;
                }
                if (j0, j1, j2) == (i0, i1, i2) {
                    continue;
                }
                let Some((r1, o1)) = frame_of(&points_mm[j0], &points_mm[j1], &points_mm[j2])
                else {
                    continue;
                };
                // The motion taking (i0, i1, i2) onto (j0, j1, j2).
                let rotation = r1 * r0.transpose();
                let map: Option<Vec<usize>> = points_mm
                    .iter()
                    .map(|p| {
                        let q = rotation * (p - o0) + o1;
                        points_mm
                            .iter()
                            .position(|r| (r - q).norm() <= tolerance_mm)
                    })
                    .collect();
                if let Some(map) = map
                    && map.iter().enumerate().any(|(k, m)| *m != k)
                    && !found.contains(&map)
                {
                    found.push(map);
                }
            }
        }
    }
    found
}

/// Three points of the layout far apart and not on a line.
fn basis(points_mm: &[Vec3]) -> Option<(usize, usize, usize)> {
    let n = points_mm.len();
    let (mut i0, mut i1, mut far) = (0, 0, 0.0);
    for a in 0..n {
        for b in a + 1..n {
            let d = (points_mm[a] - points_mm[b]).norm();
            if d > far {
                (i0, i1, far) = (a, b, d);
            }
        }
    }
    let line = (points_mm[i1] - points_mm[i0]).try_normalize(1e-12)?;
    let (i2, off) = (0..n)
        .map(|k| {
            let v = points_mm[k] - points_mm[i0];
            (k, (v - v.dot(&line) * line).norm())
        })
        .max_by(|x, y| x.1.total_cmp(&y.1))?;
    (off > 1e-6 * far).then_some((i0, i1, i2))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Twist, se3_exp};
    use proptest::prelude::*;

    fn square() -> Vec<Vec3> {
        vec![
            Vec3::new(-200.0, -200.0, 0.0),
            Vec3::new(200.0, -200.0, 0.0),
            Vec3::new(200.0, 200.0, 0.0),
            Vec3::new(-200.0, 200.0, 0.0),
        ]
    }

    #[test]
    fn a_square_has_its_turns_and_a_point_off_the_symmetry_removes_them() {
        // Four quarter turns about the normal, and half turns about the two axes and the two
        // diagonals (the square seen from behind): seven labellings besides the identity.
        assert_eq!(layout_symmetries(&square(), 1.0).len(), 7);
        let mut off = square();
        off.push(Vec3::new(60.0, 20.0, 100.0));
        assert!(layout_symmetries(&off, 1.0).is_empty());
        // Nearly symmetric: within the tolerance it is, beyond it it is not.
        let mut nearly = square();
        nearly[2].x += 3.0;
        assert!(!layout_symmetries(&nearly, 5.0).is_empty());
        assert!(layout_symmetries(&nearly, 1.0).is_empty());
    }

    proptest! {
        /// Symmetries belong to the layout, not to where it is: moving every point by one
        /// rigid motion changes none of them.
        #[test]
        fn symmetries_do_not_depend_on_the_layouts_placement(
            t in prop::array::uniform3(-500.0f64..500.0),
            r in prop::array::uniform3(-3.0f64..3.0),
            raised in any::<bool>(),
        ) {
            let motion = se3_exp(&Twist::new(t[0], t[1], t[2], r[0], r[1], r[2]));
            let mut layout = square();
            if raised {
                layout.push(Vec3::new(0.0, 0.0, 150.0));
            }
            let moved: Vec<Vec3> = layout
                .iter()
                .map(|p| (motion * nalgebra::Point3::from(*p)).coords)
                .collect();
            let mut a = layout_symmetries(&layout, 1.0);
            let mut b = layout_symmetries(&moved, 1.0);
            a.sort();
            b.sort();
            prop_assert_eq!(a, b);
        }
    }
}
