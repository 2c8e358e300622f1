//! Calibration plates: disc targets in a regular grid, and finding one in a frame.
//!
//! Point `i` of a plate is row `i / cols`, column `i % cols`, at `(col * spacing, row * spacing,
//! 0)` in the plate frame. An asymmetric plate is OpenCV's asymmetric circle grid, the one
//! people print: `rows` rows of `cols` discs, disc `(row, col)` at
//! `((2 col + row mod 2) * spacing, row * spacing, 0)`, so the pitch along a row is twice the
//! spacing and each disc's nearest neighbours lie diagonally, `sqrt(2)` spacings away. The plate is seen from the side its grid reads normally (x to the right, y down,
//! as the image's `u` and `v`), so its +z points away from the camera.
//!
//! Finding the plate ([`Plate::find`]) needs no pose: the grid is grown from the detected discs.
//! From a seed disc near the middle, its nearest neighbour and the nearest one in another
//! direction give two lattice steps; neighbours are then predicted one step out from every
//! disc placed so far, through the homography of all of them (so perspective and moderate
//! distortion bend the prediction with the grid), and taken when one disc lies within a third
//! of a step of the prediction. The lattice found is matched to the plate's: among the integer
//! changes of basis, those mapping the found points onto the plate's exactly and seeing the
//! plate from the front (the homography keeps orientation). A plate
//! of which fewer discs than it has form the grid (cut by the frame's edge, covered, too
//! tilted) is refused with what was found, never labelled in part.
//!
//! A symmetric plate (and an asymmetric one with an even number of rows) looks the same turned
//! by half a turn: its labelling is then fixed by convention (the plate's +x towards the
//! image's right) and [`PlateView::symmetric`] says so; fine for intrinsics, but a station's
//! hand-eye calibration needs an unambiguous plate.

use super::{Blob, Polarity, VisionError, ippe::homography};
use crate::geometry::{Mat3, Vec3};
use nalgebra::{Matrix2, Vector2, Vector3};
use std::collections::HashMap;

/// A plate of disc targets in a grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plate {
    rows: usize,
    cols: usize,
    spacing_mm: f64,
    diameter_mm: f64,
    asymmetric: bool,
    polarity: Polarity,
    /// The diameter of the disc at point 0 when it is larger than the others (mm).
    origin_diameter_mm: Option<f64>,
    /// It looks the same after a turn in its plane (a property of the layout, found once).
    symmetric: bool,
}

/// Where a plate's points were found in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct PlateView {
    /// The plate points found, ascending: every id when the whole plate was found; all but
    /// 0 when the plate's larger origin disc is out of view (cut by the frame's edge,
    /// covered) and the other corners placed it.
    pub ids: Vec<usize>,
    /// Each found point's detected centre (px), in the order of `ids`.
    pub points_px: Vec<Vector2<f64>>,
    /// Each found point's standard deviation from the detector (px).
    pub sigmas_px: Vec<f64>,
    /// The plate looks the same after a turn, so the labelling follows a convention.
    pub symmetric: bool,
}

/// Smallest plate side accepted (points).
const MIN_SIDE: usize = 3;

impl Plate {
    /// A plate; refuses sizes under 3 x 3, non-finite or non-positive lengths, and discs that
    /// would touch.
    pub fn new(
        rows: usize,
        cols: usize,
        spacing_mm: f64,
        diameter_mm: f64,
        asymmetric: bool,
        polarity: Polarity,
    ) -> Result<Self, VisionError> {
        let refuse = |reason: String| Err(VisionError::PlateInvalid { reason });
        if rows < MIN_SIDE || cols < MIN_SIDE {
            return refuse(format!(
                "a plate of {rows} x {cols} points: at least {MIN_SIDE} rows and {MIN_SIDE} columns are needed"
            ));
        }
        if rows * cols > 10_000 {
            return refuse(format!(
                "a plate of {rows} x {cols} points: at most 10000 points"
            ));
        }
        if !(spacing_mm.is_finite() && spacing_mm > 0.0) {
            return refuse(format!("spacing_mm must be positive (got {spacing_mm})"));
        }
        if !(diameter_mm.is_finite() && diameter_mm > 0.0) {
            return refuse(format!("diameter_mm must be positive (got {diameter_mm})"));
        }
        let neighbour_mm = if asymmetric {
            spacing_mm * std::f64::consts::SQRT_2
        } else {
            spacing_mm
        };
        if diameter_mm >= neighbour_mm {
            return refuse(format!(
                "discs of {diameter_mm} mm {neighbour_mm:.3} mm apart (a spacing of {spacing_mm} mm) would touch"
            ));
        }
        let mut plate = Self {
            rows,
            cols,
            spacing_mm,
            diameter_mm,
            asymmetric,
            polarity,
            origin_diameter_mm: None,
            symmetric: false,
        };
        plate.symmetric = plate.has_turn_symmetry();
        Ok(plate)
    }

    /// The plate with a larger disc at point 0 (the "modified circle grid"), which makes its
    /// labelling unambiguous whatever the layout. Refuses a diameter not larger than the other
    /// discs' or one that would touch its neighbours.
    pub fn with_origin_diameter(mut self, origin_diameter_mm: f64) -> Result<Self, VisionError> {
        let refuse = |reason: String| Err(VisionError::PlateInvalid { reason });
        if !(origin_diameter_mm.is_finite() && origin_diameter_mm > self.diameter_mm) {
            return refuse(format!(
                "origin_diameter_mm must be larger than diameter_mm ({}), got {origin_diameter_mm}",
                self.diameter_mm
            ));
        }
        if (origin_diameter_mm + self.diameter_mm) / 2.0 >= self.neighbour_mm() {
            return refuse(format!(
                "an origin disc of {origin_diameter_mm} mm would touch its neighbours {:.3} mm away",
                self.neighbour_mm()
            ));
        }
        self.origin_diameter_mm = Some(origin_diameter_mm);
        self.symmetric = false;
        Ok(self)
    }

    /// The origin disc's diameter when it is larger than the others (mm).
    pub fn origin_diameter_mm(&self) -> Option<f64> {
        self.origin_diameter_mm
    }

    /// The diameter of point `i`'s disc (mm).
    pub fn disc_diameter_mm(&self, i: usize) -> f64 {
        match self.origin_diameter_mm {
            Some(d) if i == 0 => d,
            _ => self.diameter_mm,
        }
    }

    /// Rows of points.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Points per row.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Distance between neighbouring points of a row, and between rows (mm).
    pub fn spacing_mm(&self) -> f64 {
        self.spacing_mm
    }

    /// Disc diameter (mm).
    pub fn diameter_mm(&self) -> f64 {
        self.diameter_mm
    }

    /// Whether odd rows are shifted by half a spacing.
    pub fn asymmetric(&self) -> bool {
        self.asymmetric
    }

    /// Dark discs on a light plate, or bright ones.
    pub fn polarity(&self) -> Polarity {
        self.polarity
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.rows * self.cols
    }

    /// Always false: a plate has at least nine points.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// Point `i` in the plate frame (mm): row `i / cols`, column `i % cols` at
    /// `(col s, row s, 0)`; on an asymmetric plate (OpenCV's asymmetric circle grid) at
    /// `((2 col + row mod 2) s, row s, 0)`, with `s` the spacing.
    pub fn point_mm(&self, i: usize) -> Vec3 {
        let (row, col) = (i / self.cols, i % self.cols);
        let x = if self.asymmetric {
            (2 * col + row % 2) as f64
        } else {
            col as f64
        };
        Vec3::new(x * self.spacing_mm, row as f64 * self.spacing_mm, 0.0)
    }

    /// Distance between a disc's centre and its nearest neighbour's (mm): the spacing, or on
    /// an asymmetric plate `sqrt(2)` times it (its neighbours lie diagonally).
    pub fn neighbour_mm(&self) -> f64 {
        if self.asymmetric {
            self.spacing_mm * std::f64::consts::SQRT_2
        } else {
            self.spacing_mm
        }
    }

    /// Every point in the plate frame (mm), in order.
    pub fn points_mm(&self) -> Vec<Vec3> {
        (0..self.len()).map(|i| self.point_mm(i)).collect()
    }

    /// Point `i`'s integer coordinates in the lattice basis: `(col, row)`, or on an asymmetric
    /// plate in the basis of its diagonal neighbours `(s, s)` and `(s, -s)`.
    fn lattice(&self, i: usize) -> [i64; 2] {
        let (row, col) = ((i / self.cols) as i64, (i % self.cols) as i64);
        if self.asymmetric {
            let x = 2 * col + row % 2;
            [(x + row) / 2, (x - row) / 2]
        } else {
            [col, row]
        }
    }

    /// The integer changes of lattice basis (small entries, determinant +-1), with whether they
    /// keep orientation. The two steps a grid is grown from are short lattice vectors, so the
    /// change from them to the plate's basis has small entries.
    fn lattice_maps() -> Vec<(Matrix2<i64>, bool)> {
        let mut out = Vec::new();
        for a in -2i64..=2 {
            for b in -2i64..=2 {
                for c in -2i64..=2 {
                    for d in -2i64..=2 {
                        let det = a * d - b * c;
                        if det.abs() == 1 {
                            out.push((Matrix2::new(a, b, c, d), det == 1));
                        }
                    }
                }
            }
        }
        out
    }

    /// Whether the plate looks the same after a turn in its plane (so a frame cannot tell its
    /// point 0 from another).
    pub fn is_symmetric(&self) -> bool {
        self.symmetric
    }

    fn has_turn_symmetry(&self) -> bool {
        let own: HashMap<[i64; 2], usize> = (0..self.len()).map(|i| (self.lattice(i), i)).collect();
        Self::lattice_maps()
            .iter()
            .filter(|(u, keeps)| *keeps && *u != Matrix2::identity())
            .any(|(u, _)| {
                self.offset_onto(u, own.keys().copied(), &own, None)
                    .is_some()
            })
    }

    /// The offset `t` with `u * p + t` a plate point for every `p`, and every plate point but
    /// `without` (a point id) so reached, when there is one.
    fn offset_onto(
        &self,
        u: &Matrix2<i64>,
        points: impl Iterator<Item = [i64; 2]> + Clone,
        own: &HashMap<[i64; 2], usize>,
        without: Option<usize>,
    ) -> Option<[i64; 2]> {
        let turned = |p: [i64; 2]| {
            [
                u[(0, 0)] * p[0] + u[(0, 1)] * p[1],
                u[(1, 0)] * p[0] + u[(1, 1)] * p[1],
            ]
        };
        let min_of = |it: &mut dyn Iterator<Item = [i64; 2]>| {
            it.fold([i64::MAX, i64::MAX], |m, p| {
                [m[0].min(p[0]), m[1].min(p[1])]
            })
        };
        let kept = || {
            own.iter()
                .filter(|&(_, &id)| Some(id) != without)
                .map(|(p, _)| *p)
        };
        let mine = min_of(&mut kept());
        let theirs = min_of(&mut points.clone().map(turned));
        let t = [mine[0] - theirs[0], mine[1] - theirs[1]];
        let mut count = 0;
        for p in points {
            let q = turned(p);
            let id = own.get(&[q[0] + t[0], q[1] + t[1]])?;
            if Some(*id) == without {
                return None;
            }
            count += 1;
        }
        (count == own.len() - usize::from(without.is_some())).then_some(t)
    }

    /// Finds the plate among the discs detected in a frame.
    pub fn find(&self, blobs: &[Blob]) -> Result<PlateView, VisionError> {
        let n = self.len();
        // One fewer when a larger origin disc may be out of view.
        if blobs.len() + usize::from(self.origin_area_ratio() > 1.0) < n {
            return Err(not_found(format!(
                "{} disc(s) detected, the plate has {n}: part of it is outside the frame, covered or out of focus",
                blobs.len()
            )));
        }
        let candidates = similar_in_size(blobs, self.origin_area_ratio());
        let positions: Vec<Vector2<f64>> = candidates
            .iter()
            .map(|&k| Vector2::new(blobs[k].centre_px[0], blobs[k].centre_px[1]))
            .collect();
        let centroid =
            positions.iter().fold(Vector2::zeros(), |a, p| a + p) / positions.len().max(1) as f64;
        let mut seeds: Vec<usize> = (0..positions.len()).collect();
        seeds.sort_by(|&a, &b| {
            (positions[a] - centroid)
                .norm_squared()
                .total_cmp(&(positions[b] - centroid).norm_squared())
        });
        let own: HashMap<[i64; 2], usize> = (0..n).map(|i| (self.lattice(i), i)).collect();
        let mut best_found = 0;
        let mut last_reason = None;
        for &seed in seeds.iter().take(6) {
            let Some(grid) = grow(&positions, seed, n) else {
                continue;
            };
            best_found = best_found.max(grid.len());
            if grid.len() > n {
                last_reason = Some(format!(
                    "more discs form a regular grid than the plate's {n}: check rows and cols"
                ));
                continue;
            }
            // A plate with a larger origin disc is found without it (cut by the frame's edge,
            // covered): the other corners, small, say which corner it was.
            let origin_missing = grid.len() + 1 == n && self.origin_area_ratio() > 1.0;
            if grid.len() < n && !origin_missing {
                continue;
            }
            let areas: Vec<f64> = candidates.iter().map(|&k| blobs[k].area_px).collect();
            match self.label(&grid, &positions, &areas, &own, origin_missing) {
                Ok(mut labels) => {
                    labels.sort_by_key(|&(_, id)| id);
                    return Ok(PlateView {
                        ids: labels.iter().map(|&(_, id)| id).collect(),
                        points_px: labels.iter().map(|&(k, _)| positions[k]).collect(),
                        sigmas_px: labels
                            .iter()
                            .map(|&(k, _)| blobs[candidates[k]].sigma_px())
                            .collect(),
                        symmetric: self.symmetric,
                    });
                }
                Err(reason) => last_reason = Some(reason),
            }
        }
        Err(not_found(last_reason.unwrap_or_else(|| {
            format!(
                "{best_found} of the plate's {n} discs found in a grid: part of it is outside the frame, covered, or too tilted"
            )
        })))
    }

    /// The origin disc's image area over the others' (1 without a larger origin disc).
    fn origin_area_ratio(&self) -> f64 {
        self.origin_diameter_mm
            .map_or(1.0, |d| (d / self.diameter_mm).powi(2))
    }

    /// Plate point ids for the grid's discs (`grid`: lattice coordinates to disc index);
    /// `origin_missing`: the grid is the plate but its origin disc.
    fn label(
        &self,
        grid: &HashMap<[i64; 2], usize>,
        positions: &[Vector2<f64>],
        areas: &[f64],
        own: &HashMap<[i64; 2], usize>,
        origin_missing: bool,
    ) -> Result<Vec<(usize, usize)>, String> {
        let mut best: Option<(f64, Vec<(usize, usize)>)> = None;
        // Without the origin disc, the labellings that leave point 0 out: one, unless the
        // plate's corners cannot tell.
        let mut without_origin = 0;
        let n = self.len();
        let corners = [0, self.cols - 1, n - self.cols, n - 1];
        // With a larger origin disc, the labelling puts point 0 on it: on the disc that stands
        // out most from its neighbours, by more than halfway (in proportion) to the ratio
        // expected.
        let origin_ratio = self.origin_area_ratio();
        let median_area = {
            let mut a: Vec<f64> = grid.values().map(|&k| areas[k]).collect();
            a.sort_by(f64::total_cmp);
            a[a.len() / 2]
        };
        for (u, _) in Self::lattice_maps() {
            let Some(t) =
                self.offset_onto(&u, grid.keys().copied(), own, origin_missing.then_some(0))
            else {
                continue;
            };
            let labels: Vec<(usize, usize)> = grid
                .iter()
                .map(|(p, &k)| {
                    let q = [
                        u[(0, 0)] * p[0] + u[(0, 1)] * p[1] + t[0],
                        u[(1, 0)] * p[0] + u[(1, 1)] * p[1] + t[1],
                    ];
                    (k, own[&q])
                })
                .collect();
            let plate_xy: Vec<Vector2<f64>> = labels
                .iter()
                .map(|&(_, id)| self.point_mm(id).xy())
                .collect();
            let image: Vec<Vector2<f64>> = labels.iter().map(|&(k, _)| positions[k]).collect();
            let Some(h) = homography(&plate_xy, &image) else {
                continue;
            };
            let centre =
                plate_xy.iter().fold(Vector2::zeros(), |a, p| a + p) / plate_xy.len() as f64;
            let jac = homography_jacobian(&h, &centre);
            if jac.determinant() <= 0.0 {
                // A mirrored labelling: every grid has a mirror symmetry, so the labelling
                // that sees the plate from the front is among the others.
                continue;
            }
            // The convention among equivalent labellings: the plate's +x towards the image's
            // right (+u), then its +y downwards; with a larger origin disc, the one that puts
            // point 0 on the largest disc.
            let x_dir = jac.column(0).normalize();
            let y_dir = jac.column(1).normalize();
            let score = if origin_missing {
                // The corners in view are not the origin's size.
                if labels.iter().any(|&(k, id)| {
                    corners.contains(&id) && areas[k] >= median_area * origin_ratio.sqrt()
                }) {
                    continue;
                }
                without_origin += 1;
                0.0
            } else if origin_ratio > 1.0 {
                let Some(&(k0, _)) = labels.iter().find(|&&(_, id)| id == 0) else {
                    continue;
                };
                if areas[k0] < median_area * origin_ratio.sqrt() {
                    continue;
                }
                areas[k0]
            } else {
                x_dir.x + 1e-3 * y_dir.y
            };
            if best.as_ref().is_none_or(|(s, _)| score > *s + 1e-12) {
                best = Some((score, labels));
            }
        }
        match best {
            Some(_) if without_origin > 1 => Err(format!(
                "the plate's origin disc is not in view, and its other corners do not tell which corner it was ({without_origin} labellings fit)"
            )),
            Some((_, labels)) => Ok(labels),
            None if origin_missing => Err(
                "the discs found form the plate's grid but for one corner, and no labelling puts the origin disc there with the other corners the size of the rest".to_owned(),
            ),
            None if origin_ratio > 1.0 => Err(format!(
                "the discs found form the plate's grid, but none of its corners holds a disc larger than the others by the origin disc's {} mm: check origin_diameter_mm, or the origin disc is hidden",
                self.origin_diameter_mm.unwrap_or_default()
            )),
            None => Err(format!(
                "the discs found form a grid, but not the plate's {} x {}{}: check rows, cols and asymmetric",
                self.rows,
                self.cols,
                if self.asymmetric { " (asymmetric)" } else { "" }
            )),
        }
    }
}

fn not_found(reason: String) -> VisionError {
    VisionError::PlateNotFound { reason }
}

/// `d(u, v) / d(x, y)` of the homography at a plate point.
fn homography_jacobian(h: &Mat3, p: &Vector2<f64>) -> Matrix2<f64> {
    let q = h * Vector3::new(p.x, p.y, 1.0);
    let w = q.z;
    let (u, v) = (q.x / w, q.y / w);
    Matrix2::new(
        (h[(0, 0)] - u * h[(2, 0)]) / w,
        (h[(0, 1)] - u * h[(2, 1)]) / w,
        (h[(1, 0)] - v * h[(2, 0)]) / w,
        (h[(1, 1)] - v * h[(2, 1)]) / w,
    )
}

/// Indices of the blobs whose area is within a factor of four of the median (the upper bound
/// times `larger`, the origin disc's area over the others'): a plate's discs vary with tilt
/// and distance, specks and large reflections stand out.
fn similar_in_size(blobs: &[Blob], larger: f64) -> Vec<usize> {
    let mut areas: Vec<f64> = blobs.iter().map(|b| b.area_px).collect();
    areas.sort_by(f64::total_cmp);
    let median = areas[areas.len() / 2];
    (0..blobs.len())
        .filter(|&k| {
            let a = blobs[k].area_px;
            a >= median / 4.0 && a <= median * 4.0 * larger
        })
        .collect()
}

/// Predicts image positions of lattice points.
enum Predictor {
    /// Before enough points for a homography: the seed and two steps.
    Affine {
        origin: Vector2<f64>,
        steps: Matrix2<f64>,
    },
    /// Lattice coordinates to pixels.
    Projective(Mat3),
}

impl Predictor {
    fn at(&self, p: [i64; 2]) -> Vector2<f64> {
        let l = Vector2::new(p[0] as f64, p[1] as f64);
        match self {
            Predictor::Affine { origin, steps } => origin + steps * l,
            Predictor::Projective(h) => {
                let q = h * Vector3::new(l.x, l.y, 1.0);
                Vector2::new(q.x / q.z, q.y / q.z)
            }
        }
    }
}

/// Grows a lattice from `seed`: lattice coordinates to indices into `positions`. `None` when
/// the seed has no two neighbours that span a lattice; stops past `limit + 1` points.
fn grow(positions: &[Vector2<f64>], seed: usize, limit: usize) -> Option<HashMap<[i64; 2], usize>> {
    let origin = positions[seed];
    let mut by_distance: Vec<usize> = (0..positions.len()).filter(|&k| k != seed).collect();
    by_distance.sort_by(|&a, &b| {
        (positions[a] - origin)
            .norm_squared()
            .total_cmp(&(positions[b] - origin).norm_squared())
    });
    let first = *by_distance.first()?;
    let a = positions[first] - origin;
    let second = by_distance.iter().copied().skip(1).find(|&k| {
        let b = positions[k] - origin;
        let cos = (a.dot(&b) / (a.norm() * b.norm())).abs();
        cos < 0.82 // more than 35 degrees from the first step's line
    })?;
    let b = positions[second] - origin;
    if b.norm() > 2.5 * a.norm() {
        return None;
    }
    let mut grid: HashMap<[i64; 2], usize> = HashMap::new();
    let mut taken = vec![false; positions.len()];
    for (p, k) in [([0, 0], seed), ([1, 0], first), ([0, 1], second)] {
        grid.insert(p, k);
        taken[k] = true;
    }
    let mut predictor = Predictor::Affine {
        origin,
        steps: Matrix2::from_columns(&[a, b]),
    };
    loop {
        let mut added = Vec::new();
        let mut wanted: Vec<[i64; 2]> = Vec::new();
        for p in grid.keys() {
            for d in [[1, 0], [-1, 0], [0, 1], [0, -1]] {
                let q = [p[0] + d[0], p[1] + d[1]];
                if !grid.contains_key(&q) && !wanted.contains(&q) {
                    wanted.push(q);
                }
            }
        }
        wanted.sort_unstable();
        for q in wanted {
            let at = predictor.at(q);
            let step = (predictor.at([q[0] + 1, q[1]]) - at)
                .norm()
                .min((predictor.at([q[0], q[1] + 1]) - at).norm());
            let tolerance = step / 3.0;
            let nearest = (0..positions.len()).min_by(|&x, &y| {
                (positions[x] - at)
                    .norm_squared()
                    .total_cmp(&(positions[y] - at).norm_squared())
            })?;
            if (positions[nearest] - at).norm() < tolerance && !taken[nearest] {
                taken[nearest] = true;
                added.push((q, nearest));
            }
        }
        if added.is_empty() {
            return Some(grid);
        }
        grid.extend(added);
        if grid.len() > limit {
            return Some(grid);
        }
        if grid.len() >= 5 {
            let (lattice, image): (Vec<Vector2<f64>>, Vec<Vector2<f64>>) = grid
                .iter()
                .map(|(p, &k)| (Vector2::new(p[0] as f64, p[1] as f64), positions[k]))
                .unzip();
            if let Some(h) = homography(&lattice, &image) {
                predictor = Predictor::Projective(h);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand::rngs::StdRng;
    use rand::seq::SliceRandom;

    fn blob_at(u: f64, v: f64) -> Blob {
        Blob {
            centre_px: [u, v],
            covariance_px2: [[1e-4, 0.0], [0.0, 1e-4]],
            area_px: 80.0,
            ellipse: [5.0, 5.0, 0.0],
            contrast_dn: 100.0,
            background_dn: 40.0,
        }
    }

    /// The plate's points through a homography, as blobs, in a shuffled order.
    fn seen(plate: &Plate, h: &Mat3) -> Vec<Blob> {
        let mut blobs: Vec<Blob> = plate
            .points_mm()
            .iter()
            .map(|p| {
                let q = h * Vector3::new(p.x, p.y, 1.0);
                blob_at(q.x / q.z, q.y / q.z)
            })
            .collect();
        blobs.shuffle(&mut StdRng::seed_from_u64(7));
        blobs
    }

    fn tilted() -> Mat3 {
        // Plate mm to pixels: about 5 px per mm, some perspective and rotation.
        Mat3::new(4.6, -1.2, 300.0, 0.9, 4.8, 200.0, 0.0004, -0.0003, 1.0)
    }

    /// Every point of `view` where `h` puts its plate point.
    fn check_labels(plate: &Plate, h: &Mat3, view: &PlateView) {
        assert_eq!(view.ids.len(), view.points_px.len());
        assert_eq!(view.ids.len(), view.sigmas_px.len());
        for (&i, found) in view.ids.iter().zip(&view.points_px) {
            let p = plate.point_mm(i);
            let q = h * Vector3::new(p.x, p.y, 1.0);
            let expected = Vector2::new(q.x / q.z, q.y / q.z);
            assert!((found - expected).norm() < 1e-9, "point {i}");
        }
    }

    /// The plate's points through `h` with the origin's disc four times the others' area.
    fn seen_with_origin(plate: &Plate, h: &Mat3) -> (Vec<Blob>, Vector2<f64>) {
        let mut blobs = seen(plate, h);
        let q = h * Vector3::new(0.0, 0.0, 1.0);
        let origin = Vector2::new(q.x / q.z, q.y / q.z);
        for b in &mut blobs {
            if (Vector2::new(b.centre_px[0], b.centre_px[1]) - origin).norm() < 1e-9 {
                b.area_px = 320.0;
            }
        }
        (blobs, origin)
    }

    fn near(b: &Blob, p: Vector2<f64>) -> bool {
        (Vector2::new(b.centre_px[0], b.centre_px[1]) - p).norm() < 1e-9
    }

    #[test]
    fn a_plate_whose_origin_disc_is_out_of_view_is_placed_by_its_other_corners() {
        let plate = Plate::new(6, 6, 20.0, 10.0, false, Polarity::Dark)
            .and_then(|p| p.with_origin_diameter(20.0))
            .expect("valid");
        let n = plate.len();
        for turn_deg in [0.0f64, 90.0, 180.0, 270.0, 35.0] {
            let t = turn_deg.to_radians();
            let turn = Mat3::new(t.cos(), -t.sin(), 0.0, t.sin(), t.cos(), 0.0, 0.0, 0.0, 1.0);
            let h = tilted() * turn;
            let (mut blobs, origin) = seen_with_origin(&plate, &h);
            blobs.retain(|b| !near(b, origin));
            let view = plate.find(&blobs).expect("found without its origin disc");
            assert_eq!(view.ids, (1..n).collect::<Vec<_>>(), "turned {turn_deg}");
            check_labels(&plate, &h, &view);
            // Whole, it is found whole.
            let (whole, _) = seen_with_origin(&plate, &h);
            let view = plate.find(&whole).expect("found");
            assert_eq!(view.ids, (0..n).collect::<Vec<_>>());
            check_labels(&plate, &h, &view);
        }
        // Another corner missing too: the corners cannot place the origin.
        let h = tilted();
        let (blobs, origin) = seen_with_origin(&plate, &h);
        let corner = {
            let p = plate.point_mm(n - 1);
            let q = h * Vector3::new(p.x, p.y, 1.0);
            Vector2::new(q.x / q.z, q.y / q.z)
        };
        let two_gone: Vec<Blob> = blobs
            .iter()
            .filter(|b| !near(b, origin) && !near(b, corner))
            .cloned()
            .collect();
        assert!(plate.find(&two_gone).is_err());
        // The origin's corner empty but another corner of the origin's size: not this plate's
        // picture, refused rather than guessed.
        let mut odd: Vec<Blob> = blobs.iter().filter(|b| !near(b, origin)).cloned().collect();
        for b in &mut odd {
            if near(b, corner) {
                b.area_px = 320.0;
            }
        }
        let err = plate.find(&odd).expect_err("refused");
        assert!(err.to_string().contains("origin disc"), "{err}");
        // A plate without a larger origin disc is found whole or not at all.
        let even = Plate::new(6, 6, 20.0, 10.0, false, Polarity::Dark).expect("valid");
        let mut blobs = seen(&even, &h);
        blobs.retain(|b| !near(b, origin));
        assert!(even.find(&blobs).is_err());
    }

    #[test]
    fn points_follow_the_documented_layout() {
        // OpenCV's asymmetric circle grid: x = (2 col + row mod 2) s, y = row s.
        let plate = Plate::new(4, 5, 30.0, 15.0, true, Polarity::Dark).expect("valid");
        assert_eq!(plate.point_mm(0), Vec3::new(0.0, 0.0, 0.0));
        assert_eq!(plate.point_mm(7), Vec3::new(150.0, 30.0, 0.0)); // row 1 (odd), col 2
        assert_eq!(plate.point_mm(12), Vec3::new(120.0, 60.0, 0.0)); // row 2, col 2
        assert_eq!(plate.point_mm(19), Vec3::new(270.0, 90.0, 0.0)); // row 3, col 4
        assert!((plate.neighbour_mm() - 30.0 * 2f64.sqrt()).abs() < 1e-12);
        // Discs as wide as the diagonal neighbours' distance would touch.
        assert!(Plate::new(4, 5, 30.0, 42.5, true, Polarity::Dark).is_err());
        assert!(Plate::new(4, 5, 30.0, 42.0, true, Polarity::Dark).is_ok());
        for i in 0..plate.len() {
            let l = plate.lattice(i);
            let basis = Matrix2::new(1.0, 1.0, 1.0, -1.0) * 30.0;
            let xy = basis * Vector2::new(l[0] as f64, l[1] as f64);
            assert!((xy - plate.point_mm(i).xy()).norm() < 1e-12);
        }
    }

    #[test]
    fn an_asymmetric_plate_is_found_and_labelled_under_any_turn() {
        let plate = Plate::new(7, 5, 20.0, 10.0, true, Polarity::Dark).expect("valid");
        assert!(
            !plate.is_symmetric(),
            "an odd number of rows breaks the half turn"
        );
        for turn_deg in [0.0f64, 70.0, 160.0, 250.0] {
            let t = turn_deg.to_radians();
            let turn = Mat3::new(t.cos(), -t.sin(), 0.0, t.sin(), t.cos(), 0.0, 0.0, 0.0, 1.0);
            let h = tilted() * turn;
            let view = plate.find(&seen(&plate, &h)).expect("found");
            assert!(!view.symmetric);
            check_labels(&plate, &h, &view);
        }
    }

    #[test]
    fn a_symmetric_plate_is_labelled_with_x_to_the_right() {
        let plate = Plate::new(6, 8, 20.0, 10.0, false, Polarity::Dark).expect("valid");
        assert!(plate.is_symmetric());
        // Turned by half a turn, the labelling that keeps +x to the right is the other one.
        let half = Mat3::new(-1.0, 0.0, 140.0, 0.0, -1.0, 100.0, 0.0, 0.0, 1.0);
        let h = tilted() * half;
        let view = plate.find(&seen(&plate, &h)).expect("found");
        assert!(view.symmetric);
        check_labels(&plate, &tilted(), &view);
    }

    #[test]
    fn a_larger_origin_disc_fixes_the_labels_of_a_symmetric_plate_under_any_turn() {
        let plate = Plate::new(6, 6, 20.0, 10.0, false, Polarity::Dark)
            .and_then(|p| p.with_origin_diameter(20.0))
            .expect("valid");
        assert!(!plate.is_symmetric(), "the origin disc breaks the turns");
        assert_eq!(plate.disc_diameter_mm(0), 20.0);
        assert_eq!(plate.disc_diameter_mm(1), 10.0);
        for turn_deg in [0.0f64, 90.0, 180.0, 270.0, 35.0] {
            let t = turn_deg.to_radians();
            let turn = Mat3::new(t.cos(), -t.sin(), 0.0, t.sin(), t.cos(), 0.0, 0.0, 0.0, 1.0);
            let h = tilted() * turn;
            let mut blobs = seen(&plate, &h);
            // The origin disc images four times as large (its area); a speck and a large
            // blot off the grid stay out.
            let q = h * Vector3::new(0.0, 0.0, 1.0);
            let origin = Vector2::new(q.x / q.z, q.y / q.z);
            for b in &mut blobs {
                if (Vector2::new(b.centre_px[0], b.centre_px[1]) - origin).norm() < 1e-9 {
                    b.area_px = 320.0;
                }
            }
            let mut blot = blob_at(1500.0, 40.0);
            blot.area_px = 2000.0;
            blobs.push(blot);
            let view = plate.find(&blobs).expect("found");
            assert!(!view.symmetric);
            check_labels(&plate, &h, &view);
        }
        // Without the larger disc, the plate cannot be labelled.
        let even = seen(&plate, &tilted());
        let err = plate.find(&even).expect_err("no origin disc");
        assert!(err.to_string().contains("origin_diameter_mm"), "{err}");
        // An origin disc no larger than the others, or touching its neighbours, is refused.
        let base = Plate::new(6, 6, 20.0, 10.0, false, Polarity::Dark).expect("valid");
        assert!(base.with_origin_diameter(10.0).is_err());
        assert!(base.with_origin_diameter(30.0).is_err());
    }

    #[test]
    fn a_partly_visible_plate_is_refused_not_labelled() {
        let plate = Plate::new(7, 9, 20.0, 10.0, false, Polarity::Dark).expect("valid");
        let mut blobs = seen(&plate, &tilted());
        blobs.truncate(60);
        blobs.push(blob_at(2000.0, 2000.0));
        blobs.push(blob_at(2100.0, 2000.0));
        blobs.push(blob_at(2000.0, 2100.0));
        let err = plate.find(&blobs).expect_err("three missing");
        assert!(
            err.to_string().contains("60 of the plate's 63 discs"),
            "{err}"
        );
        let err = plate.find(&blobs[..50]).expect_err("too few");
        assert!(err.to_string().contains("50 disc(s) detected"), "{err}");
    }

    #[test]
    fn clutter_off_the_grid_is_ignored_and_a_wrong_size_is_named() {
        let plate = Plate::new(5, 6, 20.0, 10.0, true, Polarity::Dark).expect("valid");
        let mut blobs = seen(&plate, &tilted());
        blobs.push(blob_at(1500.0, 40.0));
        blobs.push(blob_at(20.0, 900.0));
        let view = plate.find(&blobs).expect("found");
        check_labels(&plate, &tilted(), &view);
        let wrong = Plate::new(6, 5, 20.0, 10.0, true, Polarity::Dark).expect("valid");
        let err = wrong.find(&blobs).expect_err("wrong shape");
        assert!(err.to_string().contains("not the plate's 6 x 5"), "{err}");
    }

    #[test]
    fn invalid_plates_are_refused_with_the_reason() {
        for (plate, needle) in [
            (
                Plate::new(2, 9, 20.0, 10.0, false, Polarity::Dark),
                "at least 3 rows",
            ),
            (
                Plate::new(7, 9, 20.0, 20.0, false, Polarity::Dark),
                "would touch",
            ),
            (
                Plate::new(7, 9, f64::NAN, 10.0, false, Polarity::Dark),
                "spacing_mm",
            ),
        ] {
            let err = plate.expect_err("invalid");
            assert!(err.to_string().contains(needle), "{err}");
        }
    }
}
