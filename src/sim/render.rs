//! Synthetic frames of disc targets, rendered under the full camera model, for tests,
//! benchmarks and the simulator.
//!
//! Each pixel's disc coverage is integrated over a regular grid of sub-pixel samples: every
//! sample's pixel position is undistorted (the camera's Newton inversion), cast as a ray from
//! the camera centre, intersected with the disc's plane and tested against its radius. So the
//! picture is exact for any pose, tilt and distortion up to the sampling, whose error on a disc
//! centre is well under a thousandth of a pixel at the default 64 x 64 samples (taken where
//! the edge runs; pixels wholly inside or outside need none). Then a Gaussian
//! optics blur, vignetting and a gradient of the light across the scene, shot noise (Poisson, approximated as Gaussian above a few electrons)
//! and read noise, and rounding to digital numbers (DN) clamped to the bit depth.
//!
//! The real world's other parts: [`Clutter`] (stray discs of any size and [`Shape`]s that are
//! not discs: bars, rings, triangles) drawn with the discs by [`render_scene`], a colour
//! camera's Bayer mosaic and its demosaicing fringes ([`bayer_rgb`]), and JPEG compression
//! (`crate::imagefile::encode_jpeg`, `encode_rgb`).
//!
//! Pixel convention: integer coordinates are pixel centres (see [`crate::vision::GreyImage`]).

use crate::geometry::{Pose, Vec3};
use crate::model::ObservedLink;
use crate::vision::{BitDepth, CameraModel, GreyImage};
use nalgebra::Vector2;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};

/// A flat disc in the camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Disc {
    /// Its centre (mm, camera frame).
    pub centre_mm: Vec3,
    /// The normal of its plane (camera frame; any length but zero).
    pub normal: Vec3,
    /// Its diameter (mm).
    pub diameter_mm: f64,
}

/// How a frame is rendered.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderSettings {
    /// The background level (DN).
    pub background_dn: f64,
    /// The disc's level above the background (DN); negative for dark discs on a bright field.
    pub contrast_dn: f64,
    /// Standard deviation of the optics' Gaussian blur (px); 0 for none.
    pub blur_sigma_px: f64,
    /// Read noise (DN, standard deviation).
    pub read_noise_dn: f64,
    /// Electrons per DN for shot noise; `None` for no shot noise.
    pub gain_e_per_dn: Option<f64>,
    /// Relative fall-off of brightness at the image corners (`1 - vignetting` there, a quadratic
    /// in the distance from the principal point).
    pub vignetting: f64,
    /// Light that changes across the scene: the illumination is `1 + g . (u - cx, v - cy)`
    /// times the nominal one (at least 0.05), `g` this gradient (per px). A lamp to one side
    /// gives a few tenths over a frame.
    pub light_gradient_per_px: [f64; 2],
    /// Sub-pixel samples per pixel side.
    pub samples_per_side: usize,
    /// Bits per pixel of the frame.
    pub depth: BitDepth,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for RenderSettings {
    /// 200 DN discs on a 40 DN background, 0.6 px blur, 2 DN read noise, shot noise at 40 e-/DN
    /// (a 10 000 electron full well over 8 bits), 8 bits.
    fn default() -> Self {
        Self {
            background_dn: 40.0,
            contrast_dn: 200.0,
            blur_sigma_px: 0.6,
            read_noise_dn: 2.0,
            gain_e_per_dn: Some(40.0),
            vignetting: 0.0,
            light_gradient_per_px: [0.0; 2],
            samples_per_side: 64,
            depth: BitDepth::Eight,
            seed: 1,
        }
    }
}

/// Clutter drawn in the image at the discs' level: shapes that are not discs (a label, a
/// bracket, a washer, a cable's sheen).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// A filled rectangle turned by `angle_rad`.
    Bar {
        /// Its centre (px).
        centre_px: [f64; 2],
        /// Half its length and half its width (px).
        half_size_px: [f64; 2],
        /// Its turn from +u towards +v (rad).
        angle_rad: f64,
    },
    /// A ring.
    Ring {
        /// Its centre (px).
        centre_px: [f64; 2],
        /// Inner and outer radius (px).
        radii_px: [f64; 2],
    },
    /// A filled triangle.
    Triangle {
        /// Its corners (px).
        corners_px: [[f64; 2]; 3],
    },
}

impl Shape {
    fn contains(&self, u: f64, v: f64) -> bool {
        match *self {
            Shape::Bar {
                centre_px,
                half_size_px,
                angle_rad,
            } => {
                let (du, dv) = (u - centre_px[0], v - centre_px[1]);
                let (c, s) = (angle_rad.cos(), angle_rad.sin());
                (du * c + dv * s).abs() <= half_size_px[0]
                    && (-du * s + dv * c).abs() <= half_size_px[1]
            }
            Shape::Ring {
                centre_px,
                radii_px,
            } => {
                let r = (u - centre_px[0]).hypot(v - centre_px[1]);
                r >= radii_px[0] && r <= radii_px[1]
            }
            Shape::Triangle {
                corners_px: [a, b, c],
            } => {
                let side = |p: [f64; 2], q: [f64; 2]| {
                    (q[0] - p[0]) * (v - p[1]) - (q[1] - p[1]) * (u - p[0])
                };
                let (x, y, z) = (side(a, b), side(b, c), side(c, a));
                (x >= 0.0 && y >= 0.0 && z >= 0.0) || (x <= 0.0 && y <= 0.0 && z <= 0.0)
            }
        }
    }

    fn bounds(&self) -> ([f64; 2], [f64; 2]) {
        match *self {
            Shape::Bar {
                centre_px,
                half_size_px,
                ..
            } => {
                let r = half_size_px[0].hypot(half_size_px[1]);
                (
                    [centre_px[0] - r, centre_px[1] - r],
                    [centre_px[0] + r, centre_px[1] + r],
                )
            }
            Shape::Ring {
                centre_px,
                radii_px,
            } => (
                [centre_px[0] - radii_px[1], centre_px[1] - radii_px[1]],
                [centre_px[0] + radii_px[1], centre_px[1] + radii_px[1]],
            ),
            Shape::Triangle { corners_px } => {
                let lo = corners_px
                    .iter()
                    .fold([f64::INFINITY; 2], |m, c| [m[0].min(c[0]), m[1].min(c[1])]);
                let hi = corners_px.iter().fold([f64::NEG_INFINITY; 2], |m, c| {
                    [m[0].max(c[0]), m[1].max(c[1])]
                });
                (lo, hi)
            }
        }
    }
}

/// Things in a camera's view that belong to no marker.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Clutter {
    /// Discs of any size (a sticker, a bolt head, a lamp's reflection).
    pub discs: Vec<Disc>,
    /// Shapes that are not discs.
    pub shapes: Vec<Shape>,
}

impl Clutter {
    /// `count` pieces of clutter scattered over `camera`'s view from `seed`: half of them stray
    /// discs facing the camera at `depth_mm` (diameters from 5 to 40 mm, some the size of a
    /// marker's), half bars, rings and triangles of 5 to 80 px.
    pub fn scattered(camera: &CameraModel, count: usize, depth_mm: f64, seed: u64) -> Self {
        use rand::Rng;
        let mut rng = StdRng::seed_from_u64(seed);
        let (w, h) = (f64::from(camera.width_px), f64::from(camera.height_px));
        let mut clutter = Clutter::default();
        for k in 0..count {
            let (u, v) = (rng.random_range(0.0..w), rng.random_range(0.0..h));
            if k % 2 == 0 {
                let Ok(xy) = camera.undistort(Vector2::new(u, v)) else {
                    continue;
                };
                let tilt = Vec3::new(
                    rng.random_range(-0.5..0.5),
                    rng.random_range(-0.5..0.5),
                    -1.0,
                );
                clutter.discs.push(Disc {
                    centre_mm: Vec3::new(xy.x, xy.y, 1.0) * depth_mm,
                    normal: tilt,
                    diameter_mm: rng.random_range(5.0..40.0),
                });
                continue;
            }
            let size = rng.random_range(5.0..80.0);
            clutter.shapes.push(match k % 3 {
                0 => Shape::Bar {
                    centre_px: [u, v],
                    half_size_px: [size, rng.random_range(2.0..size.max(2.5))],
                    angle_rad: rng.random_range(0.0..std::f64::consts::PI),
                },
                1 => Shape::Ring {
                    centre_px: [u, v],
                    radii_px: [0.5 * size, size],
                },
                _ => Shape::Triangle {
                    corners_px: [
                        [u, v],
                        [u + size, v + rng.random_range(-size..size)],
                        [u + rng.random_range(-size..size), v + size],
                    ],
                },
            });
        }
        clutter
    }

    /// The clutter that stays `margin_px` clear of every point of `points_px` (the images of a
    /// marker's disc centres): a disc by its imaged radius, a shape by its bounding box. A piece
    /// over a marker's disc hides that point, which a scene about clutter does not mean to do.
    pub fn clear_of(
        &self,
        camera: &CameraModel,
        points_px: &[Vector2<f64>],
        margin_px: f64,
    ) -> Self {
        let box_clear = |lo: [f64; 2], hi: [f64; 2]| {
            points_px.iter().all(|p| {
                p.x < lo[0] - margin_px
                    || p.x > hi[0] + margin_px
                    || p.y < lo[1] - margin_px
                    || p.y > hi[1] + margin_px
            })
        };
        let discs = self
            .discs
            .iter()
            .filter(|d| {
                camera.project(&d.centre_mm).is_some_and(|c| {
                    let r = 0.5 * d.diameter_mm * camera.fx_px.max(camera.fy_px) / d.centre_mm.z;
                    box_clear([c.x - r, c.y - r], [c.x + r, c.y + r])
                })
            })
            .copied()
            .collect();
        let shapes = self
            .shapes
            .iter()
            .filter(|s| {
                let (lo, hi) = s.bounds();
                box_clear(lo, hi)
            })
            .copied()
            .collect();
        Clutter { discs, shapes }
    }
}

/// Renders `discs` as seen by `camera`.
pub fn render_discs(camera: &CameraModel, discs: &[Disc], settings: &RenderSettings) -> GreyImage {
    render_scene(camera, discs, &[], settings)
}

/// Renders `discs` and `shapes` as seen by `camera`, the shapes at the discs' level.
pub fn render_scene(
    camera: &CameraModel,
    discs: &[Disc],
    shapes: &[Shape],
    settings: &RenderSettings,
) -> GreyImage {
    scene_light(camera, discs, shapes, settings).expose(settings.seed)
}

/// The light a scene sends to each pixel before the sensor's noise: what a frame of a still
/// scene has in common with every other frame of it. Exposing it again with another seed
/// is rendering the scene again, at a fraction of the cost.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneLight {
    width_px: u32,
    height_px: u32,
    /// The mean level of each pixel (DN), row-major.
    mean_dn: Vec<f64>,
    read_noise_dn: f64,
    gain_e_per_dn: Option<f64>,
    depth: BitDepth,
}

impl SceneLight {
    /// Multiplies the light of each pixel by `factor(u, v)` (its centre's coordinates, px): a
    /// surface of another reflectance, a shadow.
    pub fn shade(&mut self, factor: impl Fn(usize, usize) -> f64) {
        let w = self.width_px as usize;
        for (i, mean) in self.mean_dn.iter_mut().enumerate() {
            *mean *= factor(i % w, i / w);
        }
    }

    /// A frame of the scene: shot and read noise drawn with `seed`, rounded to digital numbers
    /// and clamped to the bit depth.
    pub fn expose(&self, seed: u64) -> GreyImage {
        let mut rng = StdRng::seed_from_u64(seed);
        let max = f64::from(self.depth.max_value());
        let pixels = self
            .mean_dn
            .iter()
            .map(|&mean| {
                let mut var = self.read_noise_dn.powi(2);
                if let Some(gain) = self.gain_e_per_dn {
                    var += mean.max(0.0) / gain;
                }
                let z: f64 = StandardNormal.sample(&mut rng);
                (mean + var.sqrt() * z).round().clamp(0.0, max) as u16
            })
            .collect();
        // The size and the values fit by construction.
        #[allow(clippy::expect_used)]
        GreyImage::new(self.width_px, self.height_px, self.depth, pixels)
            .expect("a rendered frame is valid")
    }
}

/// The light of `discs` and `shapes` as seen by `camera` (see [`SceneLight`]).
pub fn scene_light(
    camera: &CameraModel,
    discs: &[Disc],
    shapes: &[Shape],
    settings: &RenderSettings,
) -> SceneLight {
    let (w, h) = (camera.width_px as usize, camera.height_px as usize);
    let mut coverage = vec![0.0f64; w * h];
    for disc in discs {
        add_coverage(
            camera,
            disc,
            settings.samples_per_side.max(1),
            &mut coverage,
            w,
            h,
        );
    }
    for shape in shapes {
        add_shape(shape, &mut coverage, w, h);
    }
    let coverage = blur_where_covered(&coverage, w, h, settings.blur_sigma_px);
    let corner2 = (camera.cx_px.max(w as f64 - camera.cx_px)).powi(2)
        + (camera.cy_px.max(h as f64 - camera.cy_px)).powi(2);
    let mean_dn = coverage
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            let r2 = ((u - camera.cx_px).powi(2) + (v - camera.cy_px).powi(2)) / corner2;
            let [gu, gv] = settings.light_gradient_per_px;
            let light = (1.0 + gu * (u - camera.cx_px) + gv * (v - camera.cy_px)).max(0.05);
            (settings.background_dn + settings.contrast_dn * c)
                * (1.0 - settings.vignetting * r2)
                * light
        })
        .collect();
    SceneLight {
        width_px: camera.width_px,
        height_px: camera.height_px,
        mean_dn,
        read_noise_dn: settings.read_noise_dn,
        gain_e_per_dn: settings.gain_e_per_dn,
        depth: settings.depth,
    }
}

/// What one camera sees: its discs, ready to render.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameScene {
    /// The camera's frame.
    pub camera: String,
    /// The camera.
    pub model: CameraModel,
    /// The discs in its view (camera frame).
    pub discs: Vec<Disc>,
    /// The seed of this frame's noise (replaces the settings' seed).
    pub seed: u64,
}

impl FrameScene {
    /// Renders the scene with `settings`, its own seed in place of theirs.
    pub fn render(&self, settings: &RenderSettings) -> GreyImage {
        render_discs(
            &self.model,
            &self.discs,
            &RenderSettings {
                seed: self.seed,
                ..*settings
            },
        )
    }
}

/// The discs of a link's marker at `camera_from_marker`, in the camera frame (none when the
/// marker declares no disc target).
pub fn marker_discs(link: &ObservedLink, camera_from_marker: &Pose) -> Vec<Disc> {
    let Some(target) = link.target else {
        return Vec::new();
    };
    link.points_mm
        .iter()
        .zip(&link.normals)
        .map(|(p, n)| Disc {
            centre_mm: (camera_from_marker * nalgebra::Point3::from(*p)).coords,
            normal: camera_from_marker.rotation * n,
            diameter_mm: target.diameter_mm,
        })
        .collect()
}

/// The image of a disc's centre: where an undistorted, noise-free detector of *centres* (not of
/// image centroids) would put it.
pub fn centre_px(camera: &CameraModel, disc: &Disc) -> Option<Vector2<f64>> {
    camera.project(&disc.centre_mm)
}

/// Adds one disc's coverage (0 to 1 per pixel) over the pixels its image can touch.
fn add_coverage(
    camera: &CameraModel,
    disc: &Disc,
    n: usize,
    coverage: &mut [f64],
    w: usize,
    h: usize,
) {
    let normal = disc.normal.normalize();
    let radius = disc.diameter_mm / 2.0;
    // The bounding box: the projections of points around the rim, plus a pixel.
    let (a, b) = {
        let helper = if normal.x.abs() < 0.9 {
            Vec3::x()
        } else {
            Vec3::y()
        };
        let a = normal.cross(&helper).normalize();
        (a, normal.cross(&a))
    };
    let (mut lo, mut hi) = (
        Vector2::repeat(f64::INFINITY),
        Vector2::repeat(f64::NEG_INFINITY),
    );
    for k in 0..64 {
        let t = k as f64 / 64.0 * std::f64::consts::TAU;
        let rim = disc.centre_mm + (a * t.cos() + b * t.sin()) * radius;
        let Some(p) = camera.project(&rim) else {
            return;
        };
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    let u0 = (lo.x.floor() - 1.0).max(0.0) as usize;
    let v0 = (lo.y.floor() - 1.0).max(0.0) as usize;
    let u1 = ((hi.x.ceil() + 1.0).max(0.0) as usize).min(w.saturating_sub(1));
    let v1 = ((hi.y.ceil() + 1.0).max(0.0) as usize).min(h.saturating_sub(1));
    if u0 > u1 || v0 > v1 {
        return; // wholly outside the frame
    }
    let inside = |u: f64, v: f64| -> bool {
        on_plane(camera, u, v, &normal, &disc.centre_mm)
            .is_some_and(|p| (p - disc.centre_mm).norm() <= radius)
    };
    // A coarse 5 x 5 look at every pixel finds where the edge runs; those pixels and their
    // neighbours (where an arc could bulge in between the coarse samples) are integrated on the
    // fine grid, the others are wholly inside or outside.
    let (bw, bh) = (u1 + 1 - u0, v1 + 1 - v0);
    let coarse = |u: usize, v: usize, k: usize| -> usize {
        let mut hits = 0;
        for j in 0..k {
            let sv = v as f64 - 0.5 + (j as f64 + 0.5) / k as f64;
            for i in 0..k {
                let su = u as f64 - 0.5 + (i as f64 + 0.5) / k as f64;
                hits += usize::from(inside(su, sv));
            }
        }
        hits
    };
    let mut state = vec![0u8; bw * bh]; // 0 outside, 1 inside, 2 edge
    for v in v0..=v1 {
        for u in u0..=u1 {
            let hits = coarse(u, v, 5);
            state[(v - v0) * bw + (u - u0)] = match hits {
                0 => 0,
                25 => 1,
                _ => 2,
            };
        }
    }
    let near_edge = |bu: usize, bv: usize| -> bool {
        (bv.saturating_sub(1)..=(bv + 1).min(bh - 1))
            .any(|y| (bu.saturating_sub(1)..=(bu + 1).min(bw - 1)).any(|x| state[y * bw + x] == 2))
    };
    for v in v0..=v1 {
        for u in u0..=u1 {
            let (bu, bv) = (u - u0, v - v0);
            let value = if near_edge(bu, bv) {
                coarse(u, v, n) as f64 / (n * n) as f64
            } else {
                f64::from(state[bv * bw + bu])
            };
            coverage[v * w + u] += value;
        }
    }
}

/// Where the ray through image point `(u, v)` (px) meets the plane through `point` with
/// `normal` (camera frame, mm); `None` behind the camera, along the plane, or where the
/// distortion cannot be undone.
pub(super) fn on_plane(
    camera: &CameraModel,
    u: f64,
    v: f64,
    normal: &Vec3,
    point: &Vec3,
) -> Option<Vec3> {
    let xy = camera.undistort(Vector2::new(u, v)).ok()?;
    let ray = Vec3::new(xy.x, xy.y, 1.0);
    let denom = normal.dot(&ray);
    if denom.abs() < 1e-12 {
        return None;
    }
    let t = normal.dot(point) / denom;
    (t > 0.0).then(|| ray * t)
}

/// One shape's coverage on a 4 x 4 grid per pixel, the total held at 1.
fn add_shape(shape: &Shape, coverage: &mut [f64], w: usize, h: usize) {
    let (lo, hi) = shape.bounds();
    let u0 = lo[0].floor().max(0.0) as usize;
    let v0 = lo[1].floor().max(0.0) as usize;
    let u1 = (hi[0].ceil().max(0.0) as usize).min(w.saturating_sub(1));
    let v1 = (hi[1].ceil().max(0.0) as usize).min(h.saturating_sub(1));
    for v in v0..=v1 {
        for u in u0..=u1 {
            let mut hits = 0;
            for j in 0..4 {
                for i in 0..4 {
                    let su = u as f64 - 0.375 + 0.25 * i as f64;
                    let sv = v as f64 - 0.375 + 0.25 * j as f64;
                    hits += usize::from(shape.contains(su, sv));
                }
            }
            let c = &mut coverage[v * w + u];
            *c = (*c + hits as f64 / 16.0).min(1.0);
        }
    }
}

/// A grey frame as a colour camera with a Bayer mosaic (RGGB) would give it: each photosite
/// keeps its own channel of the scene times that channel's `gains_rgb` (the light's colour
/// and the filters), and the colours are interpolated back bilinearly, with the fringes at
/// edges that demosaicing leaves. 8-bit RGB, row by row.
pub fn bayer_rgb(image: &GreyImage, gains_rgb: [f64; 3]) -> Vec<u8> {
    let (w, h) = (image.width_px() as usize, image.height_px() as usize);
    let px = image.pixels();
    let channel = |u: usize, v: usize| -> usize {
        match (v % 2, u % 2) {
            (0, 0) => 0,
            (1, 1) => 2,
            _ => 1,
        }
    };
    let raw: Vec<f64> = (0..w * h)
        .map(|i| f64::from(px[i]) * gains_rgb[channel(i % w, i / w)])
        .collect();
    let mut out = Vec::with_capacity(w * h * 3);
    for v in 0..h {
        for u in 0..w {
            for c in 0..3 {
                if channel(u, v) == c {
                    out.push(raw[v * w + u].round().clamp(0.0, 255.0) as u8);
                    continue;
                }
                let (mut sum, mut n) = (0.0, 0.0);
                for dv in -1i64..=1 {
                    for du in -1i64..=1 {
                        let (x, y) = (u as i64 + du, v as i64 + dv);
                        if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
                            continue;
                        }
                        let (x, y) = (x as usize, y as usize);
                        if channel(x, y) == c {
                            sum += raw[y * w + x];
                            n += 1.0;
                        }
                    }
                }
                out.push((sum / n).round().clamp(0.0, 255.0) as u8);
            }
        }
    }
    out
}

/// [`blur`] over the box that holds every covered pixel and the kernel's reach around them:
/// outside it the coverage is zero before and after, and inside it the result is the whole
/// frame's (the box's own edges, where they are not the frame's, hold zeros, which clamping
/// repeats as the frame's zeros beyond them would be).
fn blur_where_covered(image: &[f64], w: usize, h: usize, sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return image.to_vec();
    }
    let (mut u0, mut u1, mut v0, mut v1) = (usize::MAX, 0, usize::MAX, 0);
    for (i, &c) in image.iter().enumerate() {
        if c != 0.0 {
            let (u, v) = (i % w, i / w);
            u0 = u0.min(u);
            u1 = u1.max(u);
            v0 = v0.min(v);
            v1 = v1.max(v);
        }
    }
    if u0 > u1 {
        return image.to_vec();
    }
    let reach = (4.0 * sigma).ceil() as usize + 1;
    let (u0, v0) = (u0.saturating_sub(reach), v0.saturating_sub(reach));
    let (u1, v1) = ((u1 + reach).min(w - 1), (v1 + reach).min(h - 1));
    let (bw, bh) = (u1 + 1 - u0, v1 + 1 - v0);
    let mut part = Vec::with_capacity(bw * bh);
    for v in v0..=v1 {
        part.extend_from_slice(&image[v * w + u0..=v * w + u1]);
    }
    let blurred = blur(&part, bw, bh, sigma);
    let mut out = image.to_vec();
    for (k, v) in (v0..=v1).enumerate() {
        out[v * w + u0..=v * w + u1].copy_from_slice(&blurred[k * bw..(k + 1) * bw]);
    }
    out
}

/// A separable Gaussian blur (kernel to 4 sigma, normalised; edges clamped).
fn blur(image: &[f64], w: usize, h: usize, sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return image.to_vec();
    }
    let radius = (4.0 * sigma).ceil() as isize;
    let mut kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k as f64).powi(2) / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f64 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= total);
    let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
        let mut out = vec![0.0; w * h];
        for v in 0..h {
            for u in 0..w {
                let mut acc = 0.0;
                for (k, weight) in kernel.iter().enumerate() {
                    let d = k as isize - radius;
                    let (su, sv) = if horizontal {
                        ((u as isize + d).clamp(0, w as isize - 1) as usize, v)
                    } else {
                        (u, (v as isize + d).clamp(0, h as isize - 1) as usize)
                    };
                    acc += weight * src[sv * w + su];
                }
                out[v * w + u] = acc;
            }
        }
        out
    };
    pass(&pass(image, true), false)
}
