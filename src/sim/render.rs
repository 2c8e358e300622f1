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

/// Renders `discs` as seen by `camera`.
pub fn render_discs(camera: &CameraModel, discs: &[Disc], settings: &RenderSettings) -> GreyImage {
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
    let coverage = blur_where_covered(&coverage, w, h, settings.blur_sigma_px);
    let mut rng = StdRng::seed_from_u64(settings.seed);
    let max = f64::from(settings.depth.max_value());
    let corner2 = (camera.cx_px.max(w as f64 - camera.cx_px)).powi(2)
        + (camera.cy_px.max(h as f64 - camera.cy_px)).powi(2);
    let pixels = coverage
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            let r2 = ((u - camera.cx_px).powi(2) + (v - camera.cy_px).powi(2)) / corner2;
            let [gu, gv] = settings.light_gradient_per_px;
            let light = (1.0 + gu * (u - camera.cx_px) + gv * (v - camera.cy_px)).max(0.05);
            let mean = (settings.background_dn + settings.contrast_dn * c)
                * (1.0 - settings.vignetting * r2)
                * light;
            let mut var = settings.read_noise_dn.powi(2);
            if let Some(gain) = settings.gain_e_per_dn {
                var += mean.max(0.0) / gain;
            }
            let z: f64 = StandardNormal.sample(&mut rng);
            (mean + var.sqrt() * z).round().clamp(0.0, max) as u16
        })
        .collect();
    // The size and the values fit by construction.
    #[allow(clippy::expect_used)]
    GreyImage::new(camera.width_px, camera.height_px, settings.depth, pixels)
        .expect("a rendered frame is valid")
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
    let n_c = normal.dot(&disc.centre_mm);
    let inside = |u: f64, v: f64| -> bool {
        let Ok(xy) = camera.undistort(Vector2::new(u, v)) else {
            return false;
        };
        let ray = Vec3::new(xy.x, xy.y, 1.0);
        let denom = normal.dot(&ray);
        if denom.abs() < 1e-12 {
            return false;
        }
        let t = n_c / denom;
        t > 0.0 && (ray * t - disc.centre_mm).norm() <= radius
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
