//! Disc targets found in a grey frame, each centre to a hundredth of a pixel with its own
//! uncertainty.
//!
//! 1. **Background and threshold**, per tile of [`TILE_PX`] pixels: the background is a low (for
//!    bright discs; high for dark) percentile of a sample of the tile, its noise the spread
//!    between two percentiles below (above) it, so discs covering up to most of a tile do not
//!    lift it. A pixel is foreground when it stands out by more than `threshold_sigmas` noise
//!    and half the minimum contrast.
//! 2. **Connected components** (8-connected) of the foreground, from runs of each row joined by
//!    union-find.
//! 3. **Gates**: the shape (the component's pixels are those of the ellipse of its second
//!    moments but for its boundary: a streak, two discs run together, a disc with a reflection
//!    are not), area, not touching the frame's edge (a cut disc has a wrong centre), roundness
//!    (minor over major axis) and fill (the area over that of the moments' ellipse), contrast.
//! 4. **Centre**: the background-corrected grey-weighted centroid over a circular window a few
//!    pixels wider than the blob, the background taken from a ring just outside the window,
//!    iterated with the window re-centred so that the window's placement leaves no bias. The
//!    weights are clipped three noise sigmas below the disc's level and three background sigmas
//!    above the background (shifted down by that floor), so that neither the plateau's shot
//!    noise nor the window's background noise adds scatter: only the edge, where the position
//!    is, does. The clip is one pointwise function of the grey value, so a centrally symmetric
//!    image stays so under it: no bias.
//!    Under perspective the image of a disc is an ellipse of uniform brightness, and its centroid
//!    is the ellipse's centre (not the image of the disc's centre: see the eccentricity
//!    correction of the PnP step).
//! 5. **Uncertainty**: the centroid's covariance propagated from each pixel's noise (the ring's
//!    background variance, plus the shot noise of the signal when the camera's gain is known).
//!
//! Why hand-written rather than a crate: the accuracy target (a hundredth of a pixel, no bias)
//! depends on exactly how the background is removed and the window placed, which blob
//! detectors built for speed or robustness (thresholding at several levels, clipping) do not
//! control.

use super::image::GreyImage;

/// Side of the tiles the background is estimated on (px).
pub const TILE_PX: usize = 64;

/// Bright discs on a dark field, or dark on bright.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Polarity {
    /// Light discs on a dark background (retro-reflective targets under on-axis light).
    Bright,
    /// Dark discs on a light background.
    Dark,
}

impl Polarity {
    fn sign(self) -> f64 {
        match self {
            Polarity::Bright => 1.0,
            Polarity::Dark => -1.0,
        }
    }
}

/// What counts as a disc.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectSettings {
    /// Bright or dark discs.
    pub polarity: Polarity,
    /// Smallest blob area (px).
    pub min_area_px: f64,
    /// Largest blob area (px).
    pub max_area_px: f64,
    /// Smallest ratio of the minor to the major axis (a disc tilted by 70 degrees images at
    /// about 0.34).
    pub min_axis_ratio: f64,
    /// Smallest area over the area of the ellipse of the blob's second moments (and its
    /// reciprocal the largest).
    pub min_fill: f64,
    /// Smallest peak contrast over the background (DN).
    pub min_contrast_dn: f64,
    /// A foreground pixel stands out by at least this many background sigmas.
    pub threshold_sigmas: f64,
    /// Electrons per DN of the camera, for the shot noise in the uncertainty; `None` counts
    /// the background noise only.
    pub gain_e_per_dn: Option<f64>,
}

impl Default for DetectSettings {
    fn default() -> Self {
        Self {
            polarity: Polarity::Bright,
            min_area_px: 12.0,
            max_area_px: 40_000.0,
            min_axis_ratio: 0.3,
            min_fill: 0.8,
            min_contrast_dn: 20.0,
            threshold_sigmas: 5.0,
            gain_e_per_dn: None,
        }
    }
}

/// A detected disc image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Blob {
    /// The centre (px, pixel-centre convention).
    pub centre_px: [f64; 2],
    /// The centre's covariance (px^2), `[[xx, xy], [xy, yy]]`.
    pub covariance_px2: [[f64; 2]; 2],
    /// The foreground area (px).
    pub area_px: f64,
    /// Semi-major and semi-minor axes of the weighted second moments' ellipse (px) and the
    /// major axis' angle from +u towards +v (rad).
    pub ellipse: [f64; 3],
    /// The peak's contrast over the background (DN, positive for either polarity).
    pub contrast_dn: f64,
    /// The background around the disc (DN).
    pub background_dn: f64,
}

impl Blob {
    /// One standard deviation of the centre per axis, combined: `sqrt((var_u + var_v) / 2)`.
    pub fn sigma_px(&self) -> f64 {
        ((self.covariance_px2[0][0] + self.covariance_px2[1][1]) / 2.0).sqrt()
    }
}

/// Which tiles of a frame to search: all of them, or those near where discs are expected.
///
/// A disc is reported only when it and the pixels around it lie in searched tiles (a disc cut
/// by the edge of the searched area is refused like one cut by the frame's edge), so a disc
/// found in part of a frame is found with the same centre as in the whole frame: the tiles are
/// the whole frame's, and so are their thresholds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SearchArea {
    tiles_x: usize,
    tiles_y: usize,
    active: Vec<bool>,
}

impl SearchArea {
    /// Every tile of a `width_px` x `height_px` frame.
    pub fn whole(width_px: u32, height_px: u32) -> Self {
        Self::filled(width_px, height_px, true)
    }

    /// No tile yet.
    pub fn empty(width_px: u32, height_px: u32) -> Self {
        Self::filled(width_px, height_px, false)
    }

    fn filled(width_px: u32, height_px: u32, active: bool) -> Self {
        let (tiles_x, tiles_y) = Self::tiles(width_px, height_px);
        Self {
            tiles_x,
            tiles_y,
            active: vec![active; tiles_x * tiles_y],
        }
    }

    fn tiles(width_px: u32, height_px: u32) -> (usize, usize) {
        (
            (width_px as usize).div_ceil(TILE_PX),
            (height_px as usize).div_ceil(TILE_PX),
        )
    }

    /// Adds the tiles that overlap the square of half side `half_side_px` around `centre_px`
    /// (clipped to the frame; a square wholly outside adds nothing).
    pub fn add_square(&mut self, centre_px: [f64; 2], half_side_px: f64) {
        let span = |c: f64, tiles: usize| -> Option<(usize, usize)> {
            let (lo, hi) = (c - half_side_px, c + half_side_px);
            let last = (tiles * TILE_PX) as f64 - 0.5;
            if !(hi >= -0.5 && lo <= last) {
                return None;
            }
            let tile = |x: f64| ((x.clamp(0.0, last) + 0.5) as usize / TILE_PX).min(tiles - 1);
            Some((tile(lo), tile(hi)))
        };
        let (Some((x0, x1)), Some((y0, y1))) = (
            span(centre_px[0], self.tiles_x),
            span(centre_px[1], self.tiles_y),
        ) else {
            return;
        };
        for ty in y0..=y1 {
            for tx in x0..=x1 {
                self.active[ty * self.tiles_x + tx] = true;
            }
        }
    }

    /// The share of the frame's tiles searched (0 to 1).
    pub fn fraction(&self) -> f64 {
        self.active.iter().filter(|a| **a).count() as f64 / self.active.len() as f64
    }

    fn is_active(&self, tx: usize, ty: usize) -> bool {
        self.active[ty * self.tiles_x + tx]
    }

    /// Whether every tile the pixel rectangle touches is searched.
    fn covers(&self, u0: usize, u1: usize, v0: usize, v1: usize) -> bool {
        let (tx1, ty1) = (
            (u1 / TILE_PX).min(self.tiles_x - 1),
            (v1 / TILE_PX).min(self.tiles_y - 1),
        );
        (v0 / TILE_PX..=ty1).all(|ty| (u0 / TILE_PX..=tx1).all(|tx| self.is_active(tx, ty)))
    }

    /// The column ranges `[u0, u1)` of searched tiles in tile row `ty`.
    fn spans(&self, ty: usize, w: usize) -> Vec<(usize, usize)> {
        let mut out: Vec<(usize, usize)> = Vec::new();
        for tx in (0..self.tiles_x).filter(|&tx| self.is_active(tx, ty)) {
            let (u0, u1) = (tx * TILE_PX, ((tx + 1) * TILE_PX).min(w));
            match out.last_mut() {
                Some(last) if last.1 == u0 => last.1 = u1,
                _ => out.push((u0, u1)),
            }
        }
        out
    }
}

/// Finds the discs of a frame, in the order of their first row (then column).
pub fn detect(image: &GreyImage, settings: &DetectSettings) -> Vec<Blob> {
    let area = SearchArea::whole(image.width_px(), image.height_px());
    detect_in(image, settings, &area)
}

/// Finds the discs in the searched tiles of a frame, in the order of their first row (then
/// column). `area` must be made for the frame's size.
pub fn detect_in(image: &GreyImage, settings: &DetectSettings, area: &SearchArea) -> Vec<Blob> {
    let (w, h) = (image.width_px() as usize, image.height_px() as usize);
    assert_eq!(
        (area.tiles_x, area.tiles_y),
        SearchArea::tiles(image.width_px(), image.height_px()),
        "a search area made for another frame size"
    );
    let pixels = image.pixels();
    let sign = settings.polarity.sign();
    let thresholds = tile_thresholds(pixels, w, h, settings, area);
    let tiles_x = area.tiles_x;
    let foreground = |u: usize, v: usize| -> bool {
        let t = thresholds[(v / TILE_PX) * tiles_x + u / TILE_PX];
        sign * f64::from(pixels[v * w + u]) > t
    };
    components(w, h, area, &foreground)
        .into_iter()
        .filter(|c| {
            area.covers(
                c.u_min.saturating_sub(1),
                c.u_max + 1,
                c.v_min.saturating_sub(1),
                c.v_max + 1,
            )
        })
        .filter(|c| is_elliptic(c, &foreground, w, h))
        .filter_map(|c| refine(image, &c, settings))
        .collect()
}

/// Per tile, the signed threshold: a pixel `p` is foreground when `sign * p > threshold`;
/// infinite (nothing is foreground) in the tiles not searched.
fn tile_thresholds(
    pixels: &[u16],
    w: usize,
    h: usize,
    settings: &DetectSettings,
    area: &SearchArea,
) -> Vec<f64> {
    let sign = settings.polarity.sign();
    let (tiles_x, tiles_y) = (area.tiles_x, area.tiles_y);
    let mut out = Vec::with_capacity(tiles_x * tiles_y);
    let mut sample = Vec::with_capacity(TILE_PX * TILE_PX / 4);
    for ty in 0..tiles_y {
        for tx in 0..tiles_x {
            if !area.is_active(tx, ty) {
                out.push(f64::INFINITY);
                continue;
            }
            sample.clear();
            for v in (ty * TILE_PX..((ty + 1) * TILE_PX).min(h)).step_by(2) {
                for u in (tx * TILE_PX..((tx + 1) * TILE_PX).min(w)).step_by(2) {
                    sample.push(sign * f64::from(pixels[v * w + u]));
                }
            }
            // The 30th percentile is background while discs cover under 70 % of the tile; the
            // 5th to 30th spread is 1.12 sigma of Gaussian noise. Two selections, not a sort:
            // the same values in linear time.
            let rank = |q: f64| ((sample.len() - 1) as f64 * q).round() as usize;
            let (i05, i30) = (rank(0.05), rank(0.30));
            let (below, at30, _) = sample.select_nth_unstable_by(i30, f64::total_cmp);
            let background = *at30;
            let low = if i05 < i30 {
                *below.select_nth_unstable_by(i05, f64::total_cmp).1
            } else {
                background
            };
            let sigma = ((background - low) / 1.121).max(0.5);
            out.push(
                background
                    + (settings.threshold_sigmas * sigma).max(settings.min_contrast_dn / 2.0),
            );
        }
    }
    out
}

/// A connected set of foreground pixels, summarised.
#[derive(Debug, Clone, Copy)]
struct Component {
    area: usize,
    sum_u: f64,
    sum_v: f64,
    sum_uu: f64,
    sum_vv: f64,
    sum_uv: f64,
    u_min: usize,
    u_max: usize,
    v_min: usize,
    v_max: usize,
}

impl Component {
    fn add_run(&mut self, v: usize, u0: usize, u1: usize) {
        for u in u0..=u1 {
            let (x, y) = (u as f64, v as f64);
            self.area += 1;
            self.sum_u += x;
            self.sum_v += y;
            self.sum_uu += x * x;
            self.sum_vv += y * y;
            self.sum_uv += x * y;
        }
        self.u_min = self.u_min.min(u0);
        self.u_max = self.u_max.max(u1);
        self.v_min = self.v_min.min(v);
        self.v_max = self.v_max.max(v);
    }

    fn merge(&mut self, o: &Component) {
        self.area += o.area;
        self.sum_u += o.sum_u;
        self.sum_v += o.sum_v;
        self.sum_uu += o.sum_uu;
        self.sum_vv += o.sum_vv;
        self.sum_uv += o.sum_uv;
        self.u_min = self.u_min.min(o.u_min);
        self.u_max = self.u_max.max(o.u_max);
        self.v_min = self.v_min.min(o.v_min);
        self.v_max = self.v_max.max(o.v_max);
    }

    fn empty() -> Self {
        Component {
            area: 0,
            sum_u: 0.0,
            sum_v: 0.0,
            sum_uu: 0.0,
            sum_vv: 0.0,
            sum_uv: 0.0,
            u_min: usize::MAX,
            u_max: 0,
            v_min: usize::MAX,
            v_max: 0,
        }
    }

    /// Mean and the central second moments `(cuu, cvv, cuv)`.
    fn moments(&self) -> ([f64; 2], [f64; 3]) {
        let n = self.area as f64;
        let (mu, mv) = (self.sum_u / n, self.sum_v / n);
        (
            [mu, mv],
            [
                self.sum_uu / n - mu * mu,
                self.sum_vv / n - mv * mv,
                self.sum_uv / n - mu * mv,
            ],
        )
    }
}

/// The 8-connected components of the foreground, from row runs joined by union-find.
fn components(
    w: usize,
    h: usize,
    area: &SearchArea,
    foreground: &impl Fn(usize, usize) -> bool,
) -> Vec<Component> {
    fn find(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let mut parent: Vec<usize> = Vec::new();
    let mut parts: Vec<Component> = Vec::new();
    // Runs of the previous row: (u0, u1, label).
    let mut previous: Vec<(usize, usize, usize)> = Vec::new();
    let mut current: Vec<(usize, usize, usize)> = Vec::new();
    let mut spans = Vec::new();
    for v in 0..h {
        if v % TILE_PX == 0 {
            spans = area.spans(v / TILE_PX, w);
        }
        current.clear();
        for &(start, end) in &spans {
            let mut u = start;
            while u < end {
                if !foreground(u, v) {
                    u += 1;
                    continue;
                }
                let u0 = u;
                while u < end && foreground(u, v) {
                    u += 1;
                }
                let u1 = u - 1;
                let label = parent.len();
                parent.push(label);
                let mut part = Component::empty();
                part.add_run(v, u0, u1);
                parts.push(part);
                for &(p0, p1, pl) in &previous {
                    // 8-connected: runs touch when they overlap with one column of slack.
                    if p0 <= u1 + 1 && u0 <= p1 + 1 {
                        let (a, b) = (find(&mut parent, label), find(&mut parent, pl));
                        if a != b {
                            parent[a] = b;
                        }
                    }
                }
                current.push((u0, u1, label));
            }
        }
        std::mem::swap(&mut previous, &mut current);
    }
    let mut roots: Vec<Option<Component>> = vec![None; parts.len()];
    for (i, part) in parts.iter().enumerate() {
        let r = find(&mut parent, i);
        match &mut roots[r] {
            Some(c) => c.merge(part),
            slot @ None => *slot = Some(*part),
        }
    }
    let mut out: Vec<Component> = roots.into_iter().flatten().collect();
    out.sort_by_key(|c| (c.v_min, c.u_min));
    out
}

/// Whether a component's pixels are those of the ellipse of its second moments, up to the
/// pixels its boundary passes near: a disc's image is an ellipse, a streak, two discs run
/// together or a disc with a reflection on its rim are not (their moments can still look like
/// an ellipse's).
fn is_elliptic(
    c: &Component,
    foreground: &impl Fn(usize, usize) -> bool,
    w: usize,
    h: usize,
) -> bool {
    if c.area < 4 {
        return false;
    }
    let (mean, [cuu, cvv, cuv]) = c.moments();
    let det = cuu * cvv - cuv * cuv;
    if det <= 0.0 {
        return false;
    }
    // Inside the moments' ellipse: d^T C^-1 d <= 4 (a filled ellipse has C = diag(a^2, b^2) / 4).
    let inside = |u: usize, v: usize| {
        let (du, dv) = (u as f64 - mean[0], v as f64 - mean[1]);
        (cvv * du * du - 2.0 * cuv * du * dv + cuu * dv * dv) / det <= 4.0
    };
    let mut mismatch = 0usize;
    for v in c.v_min.saturating_sub(1)..=(c.v_max + 1).min(h - 1) {
        for u in c.u_min.saturating_sub(1)..=(c.u_max + 1).min(w - 1) {
            if foreground(u, v) != inside(u, v) {
                mismatch += 1;
            }
        }
    }
    // The boundary's pixels may fall either way: discs of 4 to 20 px, frontal or tilted by 65
    // degrees, noisy or not, disagree on under 0.1 pixel per unit of perimeter; three discs in
    // a row on 0.6, two touching on 1.0.
    let perimeter = std::f64::consts::PI * 2.0 * (2.0 * (cuu + cvv)).sqrt();
    (mismatch as f64) <= MAX_MISMATCH_PER_PERIMETER * perimeter
}

/// The centroid's weights are clipped this many noise sigmas below the disc's level, and this
/// many background sigmas above the background.
const CLIP_SIGMAS: f64 = 3.0;

/// How many pixels per unit of perimeter may disagree with the moments' ellipse.
const MAX_MISMATCH_PER_PERIMETER: f64 = 0.25;

/// Gates a component and measures its centre; `None` when it is not a disc.
fn refine(image: &GreyImage, c: &Component, s: &DetectSettings) -> Option<Blob> {
    let (w, h) = (image.width_px() as usize, image.height_px() as usize);
    let area = c.area as f64;
    if area < s.min_area_px || area > s.max_area_px {
        return None;
    }
    if c.u_min == 0 || c.v_min == 0 || c.u_max + 1 >= w || c.v_max + 1 >= h {
        return None;
    }
    let (mean, [cuu, cvv, cuv]) = c.moments();
    let (major2, minor2) = eigen2(cuu, cvv, cuv);
    if minor2 <= 0.0 || (minor2 / major2).sqrt() < s.min_axis_ratio {
        return None;
    }
    // A filled ellipse of semi-axes a, b has second moments a^2/4, b^2/4 and area pi a b.
    let ellipse_area = std::f64::consts::PI * 4.0 * (major2 * minor2).sqrt();
    // Two discs touching fill more than their moments' ellipse; a streak or a cut blob less.
    let fill = area / ellipse_area;
    if fill < s.min_fill || fill > 1.0 / s.min_fill {
        return None;
    }
    let sign = s.polarity.sign();
    let radius = 2.0 * major2.sqrt();
    // Wide enough for the blur's tails and the threshold's underestimate of the edge.
    let window = radius + 3.0;
    let ring = 3.0;
    let reach = (window + ring).ceil() as isize;
    let mut centre = mean;
    let mut result = None;
    for _ in 0..3 {
        let (cu, cv) = (centre[0].round() as isize, centre[1].round() as isize);
        if cu - reach < 0 || cv - reach < 0 || cu + reach >= w as isize || cv + reach >= h as isize
        {
            return None;
        }
        let mut ring_values = Vec::new();
        let (inner2, outer2) = (window * window, (window + ring) * (window + ring));
        for v in cv - reach..=cv + reach {
            for u in cu - reach..=cu + reach {
                let d2 = (u as f64 - centre[0]).powi(2) + (v as f64 - centre[1]).powi(2);
                if d2 >= inner2 && d2 < outer2 {
                    ring_values.push(f64::from(image.at(u as u32, v as u32)));
                }
            }
        }
        if ring_values.len() < 8 {
            return None;
        }
        let half = ring_values.len() / 2;
        let background = *ring_values.select_nth_unstable_by(half, f64::total_cmp).1;
        let ring_mean = ring_values.iter().sum::<f64>() / ring_values.len() as f64;
        let ring_var = ring_values
            .iter()
            .map(|x| (x - ring_mean).powi(2))
            .sum::<f64>()
            / (ring_values.len() - 1) as f64;
        // The disc's level: the median of its inner pixels (within half the minor semi-axis).
        let inner = (0.5 * 2.0 * minor2.sqrt()).max(1.0);
        let mut levels = Vec::new();
        for v in cv - reach..=cv + reach {
            for u in cu - reach..=cu + reach {
                let (x, y) = (u as f64, v as f64);
                if (x - centre[0]).powi(2) + (y - centre[1]).powi(2) <= inner * inner {
                    levels.push(sign * (f64::from(image.at(u as u32, v as u32)) - background));
                }
            }
        }
        let half = levels.len() / 2;
        let level = if levels.is_empty() {
            0.0
        } else {
            *levels.select_nth_unstable_by(half, f64::total_cmp).1
        };
        // Weights are clipped a few noise sigmas below that level: the plateau's pixels then
        // weigh the same whatever their noise (only the edge, where the position is, counts),
        // and the clipped image of a centrally symmetric blob is still centrally symmetric, so
        // the clip adds no bias. When the level is not clear of its noise, nothing is clipped.
        let level_sigma = (ring_var + s.gain_e_per_dn.map_or(0.0, |g| level.max(0.0) / g)).sqrt();
        let clip = level - CLIP_SIGMAS * level_sigma;
        let clip = if clip >= 0.5 * level {
            clip
        } else {
            f64::INFINITY
        };
        // And a few background sigmas above the background: the window's pixels outside the
        // disc then weigh nothing whatever their noise, so only the edge adds scatter. The
        // same pointwise clip keeps a centrally symmetric image so: no bias.
        let floor = if clip.is_finite() {
            (CLIP_SIGMAS * ring_var.sqrt()).min(0.5 * clip)
        } else {
            0.0
        };
        let (mut sw, mut su, mut sv, mut peak) = (0.0, 0.0, 0.0, 0.0f64);
        let mut pixels_in = Vec::new();
        for v in cv - reach..=cv + reach {
            for u in cu - reach..=cu + reach {
                let (x, y) = (u as f64, v as f64);
                if (x - centre[0]).powi(2) + (y - centre[1]).powi(2) >= window * window {
                    continue;
                }
                let value = f64::from(image.at(u as u32, v as u32));
                let raw = sign * (value - background);
                let weight = if floor > 0.0 {
                    raw.clamp(floor, clip) - floor
                } else {
                    raw.min(clip)
                };
                sw += weight;
                su += weight * x;
                sv += weight * y;
                peak = peak.max(raw);
                pixels_in.push((x, y, weight, raw < clip && (floor == 0.0 || raw > floor)));
            }
        }
        if sw <= 0.0 || peak < s.min_contrast_dn {
            return None;
        }
        let next = [su / sw, sv / sw];
        // Covariance of the centroid: sum_i (x_i - c)(x_i - c)^T var_i / (sum w)^2.
        let (mut cxx, mut cyy, mut cxy) = (0.0, 0.0, 0.0);
        let (mut muu, mut mvv, mut muv) = (0.0, 0.0, 0.0);
        for &(x, y, weight, free) in &pixels_in {
            let (dx, dy) = (x - next[0], y - next[1]);
            // A clipped pixel's noise does not reach the centre.
            let mut var = if free { ring_var } else { 0.0 };
            if let Some(gain) = s.gain_e_per_dn
                && free
            {
                var += (weight + floor).max(0.0) / gain;
            }
            cxx += dx * dx * var;
            cyy += dy * dy * var;
            cxy += dx * dy * var;
            muu += weight * dx * dx;
            mvv += weight * dy * dy;
            muv += weight * dx * dy;
        }
        let sw2 = sw * sw;
        let (a2, b2) = eigen2(muu / sw, mvv / sw, muv / sw);
        let angle = 0.5 * (2.0 * muv).atan2(muu - mvv);
        result = Some(Blob {
            centre_px: next,
            covariance_px2: [[cxx / sw2, cxy / sw2], [cxy / sw2, cyy / sw2]],
            area_px: area,
            ellipse: [2.0 * a2.max(0.0).sqrt(), 2.0 * b2.max(0.0).sqrt(), angle],
            contrast_dn: peak,
            background_dn: background,
        });
        let moved = (next[0] - centre[0]).hypot(next[1] - centre[1]);
        centre = next;
        if moved < 1e-4 {
            break;
        }
    }
    result
}

/// Eigenvalues `(larger, smaller)` of the symmetric 2x2 matrix `[[a, c], [c, b]]`.
fn eigen2(a: f64, b: f64, c: f64) -> (f64, f64) {
    let mean = (a + b) / 2.0;
    let d = (((a - b) / 2.0).powi(2) + c * c).sqrt();
    (mean + d, mean - d)
}
