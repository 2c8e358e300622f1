//! Disc targets found in a grey frame, each centre to a hundredth of a pixel with its own
//! uncertainty.
//!
//! 1. **Threshold**: per tile of 16 px, the midpoint between the darkest and the brightest pixel
//!    of the tile and its neighbours, where they differ by more than a disc's contrast (the
//!    minimum contrast, and ten times the frame's pixel noise, measured from neighbouring
//!    pixels' differences); tiles without (plain background, the inside of a large disc) take
//!    their neighbours' thresholds. So the threshold follows the light across the frame and
//!    splits every disc's edge at half its contrast, for discs from 4 to 300 px across in one
//!    frame and light that changes several times over across a plate. The contrast must show
//!    within one tile, against the noise of the flattest tile around (the frame's noise, or
//!    more where the signal is brighter and its shot noise larger): a bright plate's own
//!    noise, or light that changes smoothly across three tiles, is not taken for a disc's edge.
//! 2. **Connected components** (8-connected) of the foreground, from runs of each row joined by
//!    union-find.
//! 3. **Gates**: the shape (the component's pixels are those of the ellipse of its second
//!    moments but for its boundary and a hole well inside, a speck or a reflection: a streak, two
//!    discs run together, a disc with a reflection on its rim are not), area, not cut by the
//!    frame's edge (a component that reaches it; a disc wholly inside is measured however close),
//!    roundness (minor over major axis) and fill (the area over that of the moments' ellipse),
//!    contrast.
//! 4. **Centre**: the background-corrected grey-weighted centroid over a circular window a few
//!    pixels wider than the blob, the background taken from a ring just outside the window (its
//!    median, or a plane where the light changes significantly across it; the pixels of
//!    neighbouring discs left out of both, and foreground that is not this disc's (the dark
//!    surround of a light plate, a shadow) with the pixels its blurred edge reaches), iterated with the window re-centred so that the
//!    window's placement leaves no bias. Pixels of the disc's inner part weigh fully whatever
//!    their value (a reflection there moves nothing). The
//!    weights are clipped three noise sigmas below the disc's level and three background sigmas
//!    above the background (shifted down by that floor), so that neither the plateau's shot
//!    noise nor the window's background noise adds scatter: only the edge, where the position
//!    is, does. The clip is one pointwise function of the grey value, so a centrally symmetric
//!    image stays so under it: no bias.
//!    Under perspective the image of a disc is an ellipse of uniform brightness, and its centroid
//!    is the ellipse's centre (not the image of the disc's centre: see the eccentricity
//!    correction of the PnP step).
//! 5. **Uncertainty**: the centroid's covariance propagated from each pixel's noise (the ring's
//!    background variance, never under the frame's noise, plus the shot noise of the signal
//!    when the camera's gain is known); a window the frame's edge clips adds a bound on what
//!    the missing pixels could have moved.
//!
//! Why hand-written rather than a crate: the accuracy target (a hundredth of a pixel, no bias)
//! depends on exactly how the background is removed and the window placed, which blob
//! detectors built for speed or robustness (thresholding at several levels, clipping) do not
//! control.

mod centre;
mod components;
mod threshold;

use super::image::{GreyImage, Pixel, StoredPixels};
use centre::{Scratch, Shape, refine};
use components::{Component, components, is_elliptic};
use threshold::{ThresholdMap, noise_dn};

/// Side of the tiles a search area is made of (px).
pub const TILE_PX: usize = 64;

crate::words! {
    /// Bright discs on a dark field, or dark on bright.
    pub enum Polarity("polarity") {
        /// Light discs on a dark background (retro-reflective targets under on-axis light).
        Bright = "bright",
        /// Dark discs on a light background.
        Dark = "dark",
    }
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
    /// Largest blob area (px): the default takes discs to 500 px across, a plate close to a
    /// short lens.
    pub max_area_px: f64,
    /// Smallest ratio of the minor to the major axis (a disc tilted by 70 degrees images at
    /// about 0.34).
    pub min_axis_ratio: f64,
    /// Smallest area over the area of the ellipse of the blob's second moments (and its
    /// reciprocal the largest).
    pub min_fill: f64,
    /// Smallest peak contrast over the background (DN of an 8-bit frame; a 16-bit frame's is
    /// 257 times this, the same share of full scale).
    pub min_contrast_dn: f64,
    /// A tile has a disc's contrast when its darkest and brightest pixels differ by at least
    /// twice this many sigmas of the frame's noise.
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
            max_area_px: 200_000.0,
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
}

/// The column ranges `[u0, u1)` of the runs of marked tiles in one row of tiles `tile_px`
/// wide, in a frame `w` pixels wide.
fn column_spans(marked: &[bool], tile_px: usize, w: usize) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    for tx in (0..marked.len()).filter(|&tx| marked[tx]) {
        let (u0, u1) = (tx * tile_px, ((tx + 1) * tile_px).min(w));
        match out.last_mut() {
            Some(last) if last.1 == u0 => last.1 = u1,
            _ => out.push((u0, u1)),
        }
    }
    out
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
    let scale = f64::from(image.depth().max_value()) / 255.0;
    // Read at the frame's own depth: an 8-bit frame is half the bytes to pass over.
    match image.stored() {
        StoredPixels::Eight(pixels) => detect_pixels(pixels, (w, h), scale, settings, area),
        StoredPixels::Sixteen(pixels) => detect_pixels(pixels, (w, h), scale, settings, area),
    }
}

/// [`detect_in`] over a frame's pixels as they are stored; `scale` is the frame's full scale
/// over an 8-bit one's.
fn detect_pixels<P: Pixel>(
    pixels: &[P],
    (w, h): (usize, usize),
    scale: f64,
    settings: &DetectSettings,
    area: &SearchArea,
) -> Vec<Blob> {
    let noise = noise_dn(pixels, w, h);
    let thresholds = ThresholdMap::new(pixels, w, h, settings, scale, noise, area);
    let foreground = |u: usize, v: usize| thresholds.foreground(pixels[v * w + u].into(), u, v);
    let mut scratch = Scratch::default();
    let candidates: Vec<Component> = components(w, h, area, &thresholds, pixels)
        .into_iter()
        .filter(|c| {
            area.covers(
                c.u_min.saturating_sub(1),
                c.u_max + 1,
                c.v_min.saturating_sub(1),
                c.v_max + 1,
            )
        })
        .filter(|c| {
            let a = c.area as f64;
            a >= settings.min_area_px && a <= settings.max_area_px
        })
        .filter_map(|c| is_elliptic(&c, &foreground, w, h))
        .collect();
    let shapes: Vec<Shape> = candidates.iter().map(Shape::of).collect();
    candidates
        .iter()
        .enumerate()
        .filter_map(|(k, c)| {
            // The other discs near enough to reach into this one's window or ring.
            let me = &shapes[k];
            let reach = me.reach_px();
            let others: Vec<&Shape> = shapes
                .iter()
                .enumerate()
                .filter(|&(j, o)| {
                    j != k
                        && (o.mean[0] - me.mean[0]).hypot(o.mean[1] - me.mean[1])
                            < reach + o.outer_px
                })
                .map(|(_, o)| o)
                .collect();
            refine(
                (pixels, w, h),
                c,
                settings,
                (scale, noise),
                &others,
                &foreground,
                &mut scratch,
            )
        })
        .collect()
}

/// Eigenvalues `(larger, smaller)` of the symmetric 2x2 matrix `[[a, c], [c, b]]`.
fn eigen2(a: f64, b: f64, c: f64) -> (f64, f64) {
    let mean = (a + b) / 2.0;
    let d = (((a - b) / 2.0).powi(2) + c * c).sqrt();
    (mean + d, mean - d)
}

/// A xorshift generator for the detector's property tests: reproducible noise from a seed.
#[cfg(test)]
fn xorshift(seed: u64) -> impl FnMut() -> u64 {
    let mut x = seed | 1;
    move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// An 8-bit frame is read a byte a pixel: it gives exactly the blobs the same values
        /// give read as 16-bit words at an 8-bit frame's scale.
        #[test]
        fn an_eight_bit_frame_read_as_bytes_finds_what_it_does_read_as_words(
            seed in any::<u64>(),
            bright in any::<bool>(),
            discs in proptest::collection::vec((-8.0f64..8.0, -8.0f64..8.0, 4.0f64..12.0), 1..=6),
        ) {
            let (w, h) = (160usize, 120usize);
            let mut next = xorshift(seed);
            let (lit, dark) = if bright { (220.0, 25.0) } else { (25.0, 220.0) };
            let bytes: Vec<u8> = (0..w * h)
                .map(|i| {
                    let (u, v) = ((i % w) as f64, (i / w) as f64);
                    // A soft edge, so that the centroids read grey levels.
                    // Each disc in its own cell of a 3 x 2 grid, apart from the others.
                    let inside = discs
                        .iter()
                        .enumerate()
                        .map(|(k, &(du, dv, r))| {
                            let cu = (k % 3) as f64 * 53.0 + 27.0 + du;
                            let cv = (k / 3) as f64 * 60.0 + 30.0 + dv;
                            (r + 0.5 - (u - cu).hypot(v - cv)).clamp(0.0, 1.0)
                        })
                        .fold(0.0, f64::max);
                    (dark + (lit - dark) * inside + (next() % 9) as f64) as u8
                })
                .collect();
            let settings = DetectSettings {
                polarity: if bright { Polarity::Bright } else { Polarity::Dark },
                ..DetectSettings::default()
            };
            let image = GreyImage::from_u8(w as u32, h as u32, &bytes).expect("frame");
            let area = SearchArea::whole(w as u32, h as u32);
            let as_bytes = detect_in(&image, &settings, &area);
            let words: Vec<u16> = bytes.iter().map(|&b| u16::from(b)).collect();
            let as_words = detect_pixels(&words, (w, h), 1.0, &settings, &area);
            prop_assert!(!as_bytes.is_empty(), "no disc found");
            prop_assert_eq!(as_bytes, as_words);
        }
    }
}
