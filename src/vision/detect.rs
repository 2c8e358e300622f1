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

use super::image::GreyImage;

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
    let scale = f64::from(image.depth().max_value()) / 255.0;
    let noise = noise_dn(pixels, w, h);
    let thresholds = ThresholdMap::new(pixels, w, h, settings, scale, noise, area);
    let foreground = |u: usize, v: usize| thresholds.foreground(pixels[v * w + u], u, v);
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
                image,
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

/// Side of the tiles the threshold is set on (px).
const THRESHOLD_TILE_PX: usize = 16;

/// The local threshold: per tile of [`THRESHOLD_TILE_PX`], the midpoint between the darkest
/// and the brightest pixel of the tile and its eight neighbours, where they differ by more
/// than the contrast a disc needs (the noise's spread and the minimum contrast); a tile without
/// that contrast (plain background, or the inside of a disc larger than three tiles) takes the
/// mean of its neighbours' thresholds, spread outwards from the tiles that have one. So the
/// threshold follows the light wherever discs are, whatever their size, and splits each
/// disc's edge at half its contrast.
struct ThresholdMap {
    tiles_x: usize,
    /// Per tile, twice the threshold (DN): the sum of the darkest and brightest values; `None`
    /// where no tile in the frame had contrast (nothing is foreground).
    twice: Vec<Option<u32>>,
    bright: bool,
}

impl ThresholdMap {
    fn new(
        pixels: &[u16],
        w: usize,
        h: usize,
        s: &DetectSettings,
        scale: f64,
        noise: f64,
        area: &SearchArea,
    ) -> Self {
        let t = THRESHOLD_TILE_PX;
        let (tiles_x, tiles_y) = (w.div_ceil(t), h.div_ceil(t));
        // Only the tiles of the searched area and two around them are measured: a disc's
        // threshold comes from its own surroundings, as in the whole frame.
        let per = TILE_PX / t;
        let wanted: Vec<bool> = (0..tiles_x * tiles_y)
            .map(|i| {
                let (tx, ty) = (i % tiles_x, i / tiles_x);
                let near =
                    |x: usize, n: usize| (x.saturating_sub(2) / per)..=((x + 2) / per).min(n - 1);
                near(ty, area.tiles_y)
                    .any(|sy| near(tx, area.tiles_x).any(|sx| area.is_active(sx, sy)))
            })
            .collect();
        let mut lo = vec![u16::MAX; tiles_x * tiles_y];
        let mut hi = vec![0u16; tiles_x * tiles_y];
        // Per tile, the sum and count of neighbouring pixels' absolute differences along every
        // fourth row: the tile's own noise where it is flat.
        let mut steps = vec![(0u32, 0u32); tiles_x * tiles_y];
        for v in 0..h {
            let row = &pixels[v * w..(v + 1) * w];
            let base = (v / t) * tiles_x;
            let sampled = v % 4 == 0;
            for (tx, chunk) in row.chunks(t).enumerate() {
                if !wanted[base + tx] {
                    continue;
                }
                let (a, b) = chunk
                    .iter()
                    .fold((u16::MAX, 0u16), |(a, b), &p| (a.min(p), b.max(p)));
                lo[base + tx] = lo[base + tx].min(a);
                hi[base + tx] = hi[base + tx].max(b);
                if sampled {
                    let sum: u32 = chunk
                        .windows(2)
                        .map(|p| u32::from(p[0].abs_diff(p[1])))
                        .sum();
                    let e = &mut steps[base + tx];
                    e.0 += sum;
                    e.1 += chunk.len().saturating_sub(1) as u32;
                }
            }
        }
        // A tile's noise: the mean absolute difference of neighbours is 2 / sqrt(pi) = 1.128
        // sigmas of noise, plus what an edge in the tile adds.
        let tile_noise: Vec<f64> = steps
            .iter()
            .map(|&(sum, n)| {
                if n == 0 {
                    f64::INFINITY
                } else {
                    f64::from(sum) / f64::from(n) / 1.128
                }
            })
            .collect();
        let base_gate = s.min_contrast_dn * scale;
        let mut twice: Vec<Option<u32>> = vec![None; tiles_x * tiles_y];
        for ty in 0..tiles_y {
            for tx in 0..tiles_x {
                if !wanted[ty * tiles_x + tx] {
                    continue;
                }
                let (mut a, mut b) = (u16::MAX, 0u16);
                let mut local = f64::INFINITY;
                let mut step = 0u16;
                for ny in ty.saturating_sub(1)..=(ty + 1).min(tiles_y - 1) {
                    for nx in tx.saturating_sub(1)..=(tx + 1).min(tiles_x - 1) {
                        let k = ny * tiles_x + nx;
                        a = a.min(lo[k]);
                        b = b.max(hi[k]);
                        local = local.min(tile_noise[k]);
                        step = step.max(hi[k].saturating_sub(lo[k]));
                    }
                }
                // The noise here: the frame's, or where the signal is brighter and its shot
                // noise larger, the flattest neighbouring tile's. A disc's edge inflates its
                // own tile's figure, never a flat neighbour's.
                let sigma = if local.is_finite() {
                    noise.max(local)
                } else {
                    noise
                };
                let gate = base_gate.max(2.0 * s.threshold_sigmas * sigma);
                // The contrast must show within one tile: across three, light that changes
                // smoothly (a lamp to one side, vignetting) adds to the noise's spread.
                if f64::from(step) >= gate {
                    twice[ty * tiles_x + tx] = Some(u32::from(a) + u32::from(b));
                }
            }
        }
        // Spread the thresholds into the tiles without contrast, a ring of tiles at a time:
        // each ring's tiles take the mean of their neighbours that had one before the ring.
        // Only the tiles beside the last ring are looked at again, so every tile is visited a
        // few times however far the nearest contrast is.
        let neighbours = |i: usize| {
            let (tx, ty) = (i % tiles_x, i / tiles_x);
            (ty.saturating_sub(1)..=(ty + 1).min(tiles_y - 1)).flat_map(move |ny| {
                (tx.saturating_sub(1)..=(tx + 1).min(tiles_x - 1)).map(move |nx| ny * tiles_x + nx)
            })
        };
        let open = |i: usize, twice: &[Option<u32>]| twice[i].is_none() && wanted[i];
        let mut ring: Vec<usize> = (0..tiles_x * tiles_y)
            .filter(|&i| open(i, &twice) && neighbours(i).any(|k| twice[k].is_some()))
            .collect();
        let mut filled: Vec<(usize, u32)> = Vec::new();
        while !ring.is_empty() {
            filled.clear();
            for &i in &ring {
                let (mut sum, mut n) = (0u64, 0u64);
                for k in neighbours(i) {
                    if let Some(x) = twice[k] {
                        sum += u64::from(x);
                        n += 1;
                    }
                }
                if let Some(mean) = (sum + n / 2).checked_div(n) {
                    filled.push((i, mean as u32));
                }
            }
            for &(i, x) in &filled {
                twice[i] = Some(x);
            }
            ring.clear();
            for &(i, _) in &filled {
                ring.extend(neighbours(i).filter(|&k| open(k, &twice)));
            }
            ring.sort_unstable();
            ring.dedup();
        }
        Self {
            tiles_x,
            twice,
            bright: s.polarity == Polarity::Bright,
        }
    }

    /// Twice the threshold of the tile holding pixel `(u, v)`.
    fn twice_at(&self, u: usize, v: usize) -> Option<u32> {
        self.twice[(v / THRESHOLD_TILE_PX) * self.tiles_x + u / THRESHOLD_TILE_PX]
    }

    fn foreground(&self, p: u16, u: usize, v: usize) -> bool {
        match self.twice_at(u, v) {
            Some(t) if self.bright => 2 * u32::from(p) > t,
            Some(t) => 2 * u32::from(p) < t,
            None => false,
        }
    }
}

/// The frame's pixel noise (DN, one sigma): the median absolute difference of horizontal
/// neighbours over every sixteenth row, which edges hardly move (`|a - b|` of two independent
/// values of sigma `s` has a median of `0.954 s`).
fn noise_dn(pixels: &[u16], w: usize, h: usize) -> f64 {
    const BINS: usize = 4096;
    let mut histogram = vec![0u32; BINS];
    let mut count = 0u64;
    for v in (0..h).step_by(16) {
        let row = &pixels[v * w..(v + 1) * w];
        for pair in row.windows(2) {
            let d = (i32::from(pair[0]) - i32::from(pair[1])).unsigned_abs() as usize;
            histogram[d.min(BINS - 1)] += 1;
            count += 1;
        }
    }
    if count == 0 {
        return 0.0;
    }
    let mut seen = 0u64;
    for (d, &n) in histogram.iter().enumerate() {
        seen += u64::from(n);
        if 2 * seen >= count {
            // The median of integer differences: half a DN of quantisation at least.
            return (d as f64).max(0.5) / 0.954;
        }
    }
    BINS as f64
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
        // Sums over u0..=u1 in closed form: n values, their sum and their sum of squares.
        let n = (u1 - u0 + 1) as f64;
        let (a, b, y) = (u0 as f64, u1 as f64, v as f64);
        let sum = n * (a + b) / 2.0;
        let squares = |k: f64| k * (k + 1.0) * (2.0 * k + 1.0) / 6.0;
        let sum_sq = squares(b) - squares(a - 1.0);
        self.area += u1 - u0 + 1;
        self.sum_u += sum;
        self.sum_v += n * y;
        self.sum_uu += sum_sq;
        self.sum_vv += n * y * y;
        self.sum_uv += sum * y;
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
    thresholds: &ThresholdMap,
    pixels: &[u16],
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
    // One byte per pixel of the row (1: foreground), padded to whole words so that runs of
    // background are skipped a word (8 pixels) at a time.
    let mut mask = vec![0u8; w.next_multiple_of(8) + 8];
    for v in 0..h {
        if v % TILE_PX == 0 {
            spans = area.spans(v / TILE_PX, w);
        }
        current.clear();
        let mut next_previous = 0;
        let row = &pixels[v * w..(v + 1) * w];
        for &(start, end) in &spans {
            // The row's foreground, a threshold tile at a time.
            let mut u = start;
            while u < end {
                let stop = ((u / THRESHOLD_TILE_PX + 1) * THRESHOLD_TILE_PX).min(end);
                let (out, pixels) = (&mut mask[u..stop], &row[u..stop]);
                match thresholds.twice_at(u, v) {
                    Some(t) if thresholds.bright => {
                        for (m, &p) in out.iter_mut().zip(pixels) {
                            *m = u8::from(2 * u32::from(p) > t);
                        }
                    }
                    Some(t) => {
                        for (m, &p) in out.iter_mut().zip(pixels) {
                            *m = u8::from(2 * u32::from(p) < t);
                        }
                    }
                    None => out.fill(0),
                }
                u = stop;
            }
            mask[end..end.next_multiple_of(8) + 8].fill(0);
            let mut u = start;
            while u < end {
                if mask[u] == 0 {
                    // Skip background a word at a time once aligned.
                    if u % 8 == 0 && mask[u..u + 8] == [0u8; 8] {
                        u += 8;
                        continue;
                    }
                    u += 1;
                    continue;
                }
                let u0 = u;
                while u < end && mask[u] != 0 {
                    u += 1;
                }
                let u1 = u - 1;
                let label = parent.len();
                parent.push(label);
                let mut part = Component::empty();
                part.add_run(v, u0, u1);
                parts.push(part);
                // 8-connected: runs touch when they overlap with one column of slack. Both
                // rows' runs are in column order, so one pass over the previous row serves.
                while next_previous < previous.len() && previous[next_previous].1 + 1 < u0 {
                    next_previous += 1;
                }
                for &(p0, _, pl) in &previous[next_previous..] {
                    if p0 > u1 + 1 {
                        break;
                    }
                    let (a, b) = (find(&mut parent, label), find(&mut parent, pl));
                    if a != b {
                        parent[a] = b;
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
/// an ellipse's). A hole well inside (a speck of dust, a reflection in the middle of a disc)
/// is allowed up to a quarter of the area: the disc's outline is still an ellipse.
fn is_elliptic(
    c: &Component,
    foreground: &impl Fn(usize, usize) -> bool,
    w: usize,
    h: usize,
) -> Option<Component> {
    if c.area < 4 {
        return None;
    }
    let rows = c.v_min.saturating_sub(1)..=(c.v_max + 1).min(h - 1);
    let cols = c.u_min.saturating_sub(1)..=(c.u_max + 1).min(w - 1);
    // d^T C^-1 d: at most 4 inside the moments' ellipse (a filled ellipse has
    // C = diag(a^2, b^2) / 4); under 1.44 in the inner part, where a miss is a hole.
    let reach_of = |c: &Component| {
        let (mean, [cuu, cvv, cuv]) = c.moments();
        let det = cuu * cvv - cuv * cuv;
        (det > 0.0).then_some(move |u: usize, v: usize| {
            let (du, dv) = (u as f64 - mean[0], v as f64 - mean[1]);
            (cvv * du * du - 2.0 * cuv * du * dv + cuu * dv * dv) / det
        })
    };
    // Far from an ellipse's fill (a large shape of clutter, a streak): refused before any
    // pixel is looked at. A hole (below) lowers the fill by at most a quarter.
    let (_, [cuu, cvv, cuv]) = c.moments();
    let (major2, minor2) = eigen2(cuu, cvv, cuv);
    let fill = c.area as f64 / (std::f64::consts::PI * 4.0 * (major2 * minor2).max(0.0).sqrt());
    if !(0.5..=1.5).contains(&fill) {
        return None;
    }
    // A hole inflates the moments: fill it, then compare the outline.
    let reach = reach_of(c)?;
    let mut filled = *c;
    for v in rows.clone() {
        for u in cols.clone() {
            if reach(u, v) <= 1.44 && !foreground(u, v) {
                filled.add_run(v, u, u);
            }
        }
    }
    let holes = filled.area - c.area;
    if holes * 4 > filled.area {
        return None;
    }
    let reach = reach_of(&filled)?;
    let mut mismatch = 0usize;
    for v in rows {
        for u in cols.clone() {
            let d = reach(u, v);
            if d > 1.44 && foreground(u, v) != (d <= 4.0) {
                mismatch += 1;
            }
        }
    }
    // The boundary's pixels may fall either way: rendered discs of 4 to 20 px, frontal or
    // tilted by 65 degrees, noisy or not, disagree on under 0.1 pixel per unit of perimeter,
    // photographed ones with reflections and compression on up to 0.3; three discs in a row
    // on 0.6, two touching on 1.0.
    let (_, [cuu, cvv, _]) = filled.moments();
    let perimeter = std::f64::consts::PI * 2.0 * (2.0 * (cuu + cvv)).sqrt();
    ((mismatch as f64) <= MAX_MISMATCH_PER_PERIMETER * perimeter).then_some(filled)
}

/// The centroid's weights are clipped this many noise sigmas below the disc's level, and this
/// many background sigmas above the background.
const CLIP_SIGMAS: f64 = 3.0;

/// How many pixels per unit of perimeter may disagree with the moments' ellipse.
const MAX_MISMATCH_PER_PERIMETER: f64 = 0.35;

/// A disc candidate's outline, so that its neighbours leave its pixels out of their windows.
#[derive(Debug, Clone, Copy)]
struct Shape {
    mean: [f64; 2],
    /// The inverse of the second moments, over four (so `d^T m d <= 1` on the outline).
    inverse: [f64; 3],
    /// How far its pixels reach beyond the outline, relative: the outline widened by
    /// [`SHAPE_MARGIN_PX`] on its minor axis.
    inflate2: f64,
    /// The outline's semi-major axis plus the margin (px).
    outer_px: f64,
}

/// Pixels this close outside a neighbour's outline belong to it (its blur, its threshold's
/// underestimate).
const SHAPE_MARGIN_PX: f64 = 2.0;

impl Shape {
    fn of(c: &Component) -> Self {
        let (mean, [cuu, cvv, cuv]) = c.moments();
        let det = (cuu * cvv - cuv * cuv).max(1e-9);
        let (major2, minor2) = eigen2(cuu, cvv, cuv);
        let (a, b) = (2.0 * major2.max(0.0).sqrt(), 2.0 * minor2.max(1e-9).sqrt());
        Shape {
            mean,
            inverse: [cvv / det / 4.0, cuu / det / 4.0, -cuv / det / 4.0],
            inflate2: ((b + SHAPE_MARGIN_PX) / b).powi(2),
            outer_px: a + SHAPE_MARGIN_PX,
        }
    }

    /// Whether pixel `(x, y)` belongs to this disc (its outline widened by the margin).
    fn holds(&self, x: f64, y: f64) -> bool {
        let (dx, dy) = (x - self.mean[0], y - self.mean[1]);
        let [a, b, c] = self.inverse;
        a * dx * dx + b * dy * dy + 2.0 * c * dx * dy <= self.inflate2
    }

    /// How far from its centre this disc's measurement reads pixels (px): window and ring.
    fn reach_px(&self) -> f64 {
        let radius = self.outer_px - SHAPE_MARGIN_PX;
        window_px(radius) + RING_PX
    }
}

/// The radius of the window a disc of `radius_px` is measured in: wide enough for the blur's
/// tails and the threshold's underestimate of the edge, which grow with a large (near, so often
/// less sharp) disc.
fn window_px(radius_px: f64) -> f64 {
    radius_px + 3.0 + 0.1 * (radius_px - 20.0).max(0.0)
}

/// The width of the ring around the window the background is read from (px).
const RING_PX: f64 = 3.0;

/// Buffers reused from disc to disc.
#[derive(Default)]
struct Scratch {
    /// Ring pixels: offset from the centre (px) and value (DN).
    ring: Vec<(f64, f64, f64)>,
    values: Vec<f64>,
    /// Window pixels: position, weight, whether its noise reaches the centre.
    window: Vec<(f64, f64, f64, bool)>,
    /// Whether each pixel of the square around a disc belongs to a neighbour or to foreign
    /// foreground.
    theirs: Vec<bool>,
    /// The foreign foreground widened along rows, on the way to `theirs`.
    spread: Vec<bool>,
}

/// The background under a disc: a level, and a slope when the light visibly changes across
/// the disc's surroundings (a plane fitted to the ring around the window).
#[derive(Debug, Clone, Copy)]
struct Background {
    level: f64,
    slope: [f64; 2],
    /// The ring's variance about it (DN^2).
    variance: f64,
}

impl Background {
    fn at(&self, du: f64, dv: f64) -> f64 {
        self.level + self.slope[0] * du + self.slope[1] * dv
    }

    /// From the ring's pixels (offsets from the centre and values): their median, or where a
    /// plane fits them significantly better (its slope beyond the noise at 99.7 %, chi-square
    /// with two degrees of freedom), a plane fitted twice, the second time without the pixels
    /// a neighbouring disc or a speck puts more than three sigmas off the first.
    fn fit(ring: &[(f64, f64, f64)], values: &mut Vec<f64>) -> Option<Self> {
        let n = ring.len();
        if n < 8 {
            return None;
        }
        values.clear();
        values.extend(ring.iter().map(|r| r.2));
        let median = *values.select_nth_unstable_by(n / 2, f64::total_cmp).1;
        let mean = ring.iter().map(|r| r.2).sum::<f64>() / n as f64;
        let variance = ring.iter().map(|r| (r.2 - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        let flat = Background {
            level: median,
            slope: [0.0; 2],
            variance,
        };
        let Some(plane) = fit_plane(ring, |_| true) else {
            return Some(flat);
        };
        let residual_variance = |p: &Background, keep: &dyn Fn(&(f64, f64, f64)) -> bool| {
            let (mut s, mut k) = (0.0, 0usize);
            for r in ring.iter().filter(|r| keep(r)) {
                s += (r.2 - p.at(r.0, r.1)).powi(2);
                k += 1;
            }
            (k > 3).then(|| s / (k - 3) as f64)
        };
        let first_variance = residual_variance(&plane, &|_| true)?;
        let sigma = first_variance.sqrt().max(0.5);
        let inlier = |r: &(f64, f64, f64)| (r.2 - plane.at(r.0, r.1)).abs() <= 3.0 * sigma;
        let refit = fit_plane(ring, inlier).unwrap_or(plane);
        let variance = residual_variance(&refit, &|r| inlier(r)).unwrap_or(first_variance);
        // The slope's significance: s^T (X^T X) s / variance, chi-square(2) under no slope.
        let (mut sxx, mut syy, mut sxy, mut sx, mut sy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for r in ring.iter().filter(|r| inlier(r)) {
            sxx += r.0 * r.0;
            syy += r.1 * r.1;
            sxy += r.0 * r.1;
            sx += r.0;
            sy += r.1;
        }
        let k = ring.iter().filter(|r| inlier(r)).count() as f64;
        let (cxx, cyy, cxy) = (sxx - sx * sx / k, syy - sy * sy / k, sxy - sx * sy / k);
        let [a, b] = refit.slope;
        let chi2 = (a * a * cxx + 2.0 * a * b * cxy + b * b * cyy) / variance.max(1e-12);
        Some(if chi2 > 11.6 {
            Background { variance, ..refit }
        } else {
            flat
        })
    }
}

/// The least-squares plane `level + slope . (du, dv)` through the kept ring pixels.
fn fit_plane(
    ring: &[(f64, f64, f64)],
    keep: impl Fn(&(f64, f64, f64)) -> bool,
) -> Option<Background> {
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    let mut r = nalgebra::Vector3::<f64>::zeros();
    for p in ring.iter().filter(|p| keep(p)) {
        let x = nalgebra::Vector3::new(1.0, p.0, p.1);
        m += x * x.transpose();
        r += x * p.2;
    }
    let s = m.cholesky()?.solve(&r);
    Some(Background {
        level: s[0],
        slope: [s[1], s[2]],
        variance: 0.0,
    })
}

/// Gates a component and measures its centre; `None` when it is not a disc. `scale` is the
/// frame's full scale over an 8-bit one's, `noise_dn` its pixel noise.
fn refine(
    image: &GreyImage,
    c: &Component,
    s: &DetectSettings,
    (scale, noise_dn): (f64, f64),
    others: &[&Shape],
    foreground: &impl Fn(usize, usize) -> bool,
    scratch: &mut Scratch,
) -> Option<Blob> {
    let (w, h) = (image.width_px() as usize, image.height_px() as usize);
    let pixels = image.pixels();
    let area = c.area as f64;
    // A disc the frame's edge cuts has a wrong centre; one wholly inside is measured however
    // close it lies, its window clipped.
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
    let window = window_px(radius);
    let ring = RING_PX;
    // A neighbour's pixels are left out of the window and the ring: marked once over a square
    // that holds the window and ring wherever the iterations move them (at most a pixel).
    let reach_i = (window + RING_PX).ceil() as isize;
    let side = 2 * (reach_i + 2) + 1;
    let (mu, mv) = (
        mean[0].round() as isize - reach_i - 2,
        mean[1].round() as isize - reach_i - 2,
    );
    // Foreground beyond this disc's own outline is something else's: the dark surround of a
    // light plate, a shadow, a disc that was refused. It is left out of the window and the
    // ring with the pixels its blurred edge reaches, as a neighbour's pixels are, or it would
    // pull the centre towards it and tilt the background.
    let mine = Shape::of(c);
    let foreign = |u: isize, v: isize| {
        u >= 0
            && v >= 0
            && (u as usize) < w
            && (v as usize) < h
            && foreground(u as usize, v as usize)
            && !mine.holds(u as f64, v as f64)
    };
    // Marked once over a square that holds the window and ring wherever the iterations move
    // them (at most a pixel): a neighbour's outline, and foreign foreground widened by
    // [`SHAPE_MARGIN_PX`] (a separable maximum, rows then columns).
    let n = (side * side) as usize;
    let margin = SHAPE_MARGIN_PX as isize;
    scratch.theirs.clear();
    scratch
        .theirs
        .extend((0..n as isize).map(|i| foreign(mu + i % side, mv + i / side)));
    let any_foreign = scratch.theirs.iter().any(|&f| f);
    if any_foreign {
        scratch.spread.clear();
        scratch.spread.extend((0..n as isize).map(|i| {
            let (x, y) = (i % side, i / side);
            ((x - margin).max(0)..=(x + margin).min(side - 1))
                .any(|k| scratch.theirs[(y * side + k) as usize])
        }));
        for i in 0..n as isize {
            let (x, y) = (i % side, i / side);
            scratch.theirs[i as usize] = ((y - margin).max(0)..=(y + margin).min(side - 1))
                .any(|k| scratch.spread[(k * side + x) as usize]);
        }
    }
    if !others.is_empty() {
        for (i, mark) in scratch.theirs.iter_mut().enumerate() {
            let (px, py) = (
                (mu + i as isize % side) as f64,
                (mv + i as isize / side) as f64,
            );
            *mark = *mark || others.iter().any(|o| o.holds(px, py));
        }
    } else if !any_foreign {
        // Nothing is anyone else's: no marks to look up.
        scratch.theirs.clear();
    }
    let marks = std::mem::take(&mut scratch.theirs);
    let theirs = |x: f64, y: f64| {
        if marks.is_empty() {
            return false;
        }
        let (du, dv) = (x as isize - mu, y as isize - mv);
        if du < 0 || dv < 0 || du >= side || dv >= side {
            // Beyond the square (a centre that wandered): asked directly.
            return others.iter().any(|o| o.holds(x, y)) || foreign(x as isize, y as isize);
        }
        marks[(dv * side + du) as usize]
    };
    let reach = (window + ring).ceil() as isize;
    // The disc's inner part, where its level is read and a speck weighs as the disc.
    let inner = (0.5 * 2.0 * minor2.sqrt()).max(1.0);
    // The background and the disc's level, read once around the blob's own centre: the ring
    // lies beyond the disc's blur, so where exactly it is centred does not matter.
    let bounds = |c: [f64; 2], reach: isize| {
        let (cu, cv) = (c[0].round() as isize, c[1].round() as isize);
        let (u0, u1) = ((cu - reach).max(0), (cu + reach).min(w as isize - 1));
        let (v0, v1) = ((cv - reach).max(0), (cv + reach).min(h as isize - 1));
        ([u0, u1, v0, v1], [cu, cv])
    };
    let (inner2, outer2) = (window * window, (window + ring) * (window + ring));
    let ([u0, u1, v0, v1], _) = bounds(mean, reach);
    scratch.ring.clear();
    for v in v0..=v1 {
        let dv = v as f64 - mean[1];
        let row = &pixels[v as usize * w..];
        // The ring's columns in this row: outside the window's circle, inside the outer one.
        let span = |r2: f64| (r2 - dv * dv).max(0.0).sqrt();
        let (outer, hole) = (span(outer2), span(inner2));
        let first = ((mean[0] - outer).floor() as isize).max(u0);
        let last = ((mean[0] + outer).ceil() as isize).min(u1);
        for u in first..=last {
            let du = u as f64 - mean[0];
            if du.abs() < hole - 1.0 {
                continue;
            }
            let d2 = du * du + dv * dv;
            if d2 >= inner2 && d2 < outer2 && !theirs(u as f64, v as f64) {
                scratch.ring.push((du, dv, f64::from(row[u as usize])));
            }
        }
    }
    // A ring cut to under a third by the frame cannot tell the background.
    let full_ring = std::f64::consts::PI * (outer2 - inner2);
    if (scratch.ring.len() as f64) < full_ring / 3.0 {
        return None;
    }
    let fitted = Background::fit(&scratch.ring, &mut scratch.values)?;
    // The plane is kept about the blob's own centre; `at` takes offsets from there.
    let background = |x: f64, y: f64| fitted.at(x - mean[0], y - mean[1]);
    // A dark disc on a lit surface: the light that changes across the background changes the
    // disc's contrast in proportion, which would weigh the brighter side's edge more; each
    // pixel's contrast is taken relative to the light there (the background plane over its
    // value at the centre). Bright discs (retro-reflectors lit from the camera) are not lit by
    // the background's light: their contrast is taken as it is.
    let relative = s.polarity == Polarity::Dark && fitted.slope != [0.0; 2] && fitted.level > 0.0;
    let contrast = |value: f64, x: f64, y: f64| {
        let b = background(x, y);
        if relative {
            sign * (value - b) * (fitted.level / b.max(0.05 * fitted.level))
        } else {
            sign * (value - b)
        }
    };
    // A pixel's noise: the ring's, but never less than the frame's (a saturated or flattened
    // background has none, its disc's edge still has).
    let ring_var = fitted.variance.max(noise_dn * noise_dn);
    // The disc's level: the median of its inner pixels.
    scratch.values.clear();
    let r = inner.ceil() as isize;
    let (cu, cv) = (mean[0].round() as isize, mean[1].round() as isize);
    for v in (cv - r).max(0)..=(cv + r).min(h as isize - 1) {
        let row = &pixels[v as usize * w..];
        for u in (cu - r).max(0)..=(cu + r).min(w as isize - 1) {
            let (x, y) = (u as f64, v as f64);
            if (x - mean[0]).powi(2) + (y - mean[1]).powi(2) <= inner * inner {
                scratch
                    .values
                    .push(contrast(f64::from(row[u as usize]), x, y));
            }
        }
    }
    let half = scratch.values.len() / 2;
    let level = if scratch.values.is_empty() {
        0.0
    } else {
        *scratch
            .values
            .select_nth_unstable_by(half, f64::total_cmp)
            .1
    };
    // Weights are clipped a few noise sigmas below that level: the plateau's pixels then weigh
    // the same whatever their noise (only the edge, where the position is, counts), and the
    // clipped image of a centrally symmetric blob is still centrally symmetric, so the clip
    // adds no bias. When the level is not clear of its noise, nothing is clipped.
    let level_sigma = (ring_var + s.gain_e_per_dn.map_or(0.0, |g| level.max(0.0) / g)).sqrt();
    let clip = level - CLIP_SIGMAS * level_sigma;
    let clip = if clip >= 0.5 * level {
        clip
    } else {
        f64::INFINITY
    };
    // And a few background sigmas above the background: the window's pixels outside the disc
    // then weigh nothing whatever their noise, so only the edge adds scatter. The same
    // pointwise clip keeps a centrally symmetric image so: no bias.
    let floor = if clip.is_finite() {
        (CLIP_SIGMAS * ring_var.sqrt()).min(0.5 * clip)
    } else {
        0.0
    };
    let window_reach = window.ceil() as isize;
    let mut centre = mean;
    let mut result = None;
    for _ in 0..4 {
        let ([u0, u1, v0, v1], [cu, cv]) = bounds(centre, window_reach);
        let clipped = u0 > cu - window_reach
            || u1 < cu + window_reach
            || v0 > cv - window_reach
            || v1 < cv + window_reach;
        let (mut sw, mut su, mut sv, mut peak) = (0.0, 0.0, 0.0, 0.0f64);
        scratch.window.clear();
        for v in v0..=v1 {
            let y = v as f64;
            let dv = y - centre[1];
            let row = &pixels[v as usize * w..];
            for u in u0..=u1 {
                let x = u as f64;
                let du = x - centre[0];
                let d2 = du * du + dv * dv;
                if d2 >= window * window || theirs(x, y) {
                    continue;
                }
                let raw = contrast(f64::from(row[u as usize]), x, y);
                // A speck or reflection in the disc's inner part weighs as the disc does.
                let raw = if clip.is_finite() && d2 <= inner * inner {
                    raw.max(clip)
                } else {
                    raw
                };
                let weight = if floor > 0.0 {
                    raw.clamp(floor, clip) - floor
                } else {
                    raw.min(clip)
                };
                sw += weight;
                su += weight * x;
                sv += weight * y;
                peak = peak.max(raw);
                scratch
                    .window
                    .push((x, y, weight, raw < clip && (floor == 0.0 || raw > floor)));
            }
        }
        if sw <= 0.0 || peak < s.min_contrast_dn * scale {
            return None;
        }
        let next = [su / sw, sv / sw];
        // Covariance of the centroid: sum_i (x_i - c)(x_i - c)^T var_i / (sum w)^2.
        let (mut cxx, mut cyy, mut cxy) = (0.0, 0.0, 0.0);
        let (mut muu, mut mvv, mut muv) = (0.0, 0.0, 0.0);
        for &(x, y, weight, free) in &scratch.window {
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
        if clipped {
            // The window's part beyond the frame is missing from the centroid: at most as much
            // weight per pixel as the frame's outermost pixels in the window carry. That bound
            // on the shift, taken as uniform, widens the covariance.
            let (bu, bv) = clipped_shift_px(
                &scratch.window,
                next,
                window,
                [u0, u1, v0, v1],
                [cu, cv],
                window_reach,
                sw,
            );
            cxx += bu * bu / 3.0 * sw2;
            cyy += bv * bv / 3.0 * sw2;
        }
        let (a2, b2) = eigen2(muu / sw, mvv / sw, muv / sw);
        let angle = 0.5 * (2.0 * muv).atan2(muu - mvv);
        result = Some(Blob {
            centre_px: next,
            covariance_px2: [[cxx / sw2, cxy / sw2], [cxy / sw2, cyy / sw2]],
            area_px: area,
            ellipse: [2.0 * a2.max(0.0).sqrt(), 2.0 * b2.max(0.0).sqrt(), angle],
            contrast_dn: peak,
            background_dn: fitted.level,
        });
        let moved = (next[0] - centre[0]).hypot(next[1] - centre[1]);
        centre = next;
        if moved < 1e-4 {
            break;
        }
    }
    scratch.theirs = marks;
    // A centre far from the blob's own is pulled by something else in the window.
    let drift = (centre[0] - mean[0]).hypot(centre[1] - mean[1]);
    if drift > (0.25 * radius).max(1.0) {
        return None;
    }
    result
}

/// A bound on the centroid's shift (px, per axis) from the part of its window the frame cut
/// off: on each cut side, the largest weight among the window's pixels on the frame's last
/// row or column there, times the pixels missing on that side, times their lever arm.
fn clipped_shift_px(
    window_pixels: &[(f64, f64, f64, bool)],
    centre: [f64; 2],
    window: f64,
    [u0, u1, v0, v1]: [isize; 4],
    [cu, cv]: [isize; 2],
    reach: isize,
    sw: f64,
) -> (f64, f64) {
    let edge_weight = |on_edge: &dyn Fn(f64, f64) -> bool| {
        window_pixels
            .iter()
            .filter(|p| on_edge(p.0, p.1))
            .map(|p| p.2)
            .fold(0.0f64, f64::max)
    };
    // Pixels of the window's disc beyond a straight cut at distance `d` from the centre, and
    // their mean distance from the centre along the cut's normal.
    let beyond = |d: f64| {
        if d >= window {
            return (0.0, 0.0);
        }
        let theta = (d / window).clamp(-1.0, 1.0).acos();
        let segment = window * window * (theta - theta.sin() * theta.cos());
        let arm = if segment > 0.0 {
            2.0 * (window * theta.sin()).powi(3) / (3.0 * segment)
        } else {
            0.0
        };
        (segment, arm)
    };
    let mut shift = [0.0f64; 2];
    let sides: [(bool, f64, usize); 4] = [
        (u0 > cu - reach, centre[0] - (u0 as f64 - 0.5), 0),
        (u1 < cu + reach, (u1 as f64 + 0.5) - centre[0], 0),
        (v0 > cv - reach, centre[1] - (v0 as f64 - 0.5), 1),
        (v1 < cv + reach, (v1 as f64 + 0.5) - centre[1], 1),
    ];
    for (k, &(cut, d, axis)) in sides.iter().enumerate() {
        if !cut {
            continue;
        }
        let last = match k {
            0 => u0 as f64,
            1 => u1 as f64,
            2 => v0 as f64,
            _ => v1 as f64,
        };
        let peak = edge_weight(&|x, y| if axis == 0 { x == last } else { y == last });
        let (missing, arm) = beyond(d);
        shift[axis] += peak * missing * arm / sw;
    }
    (shift[0], shift[1])
}

/// Eigenvalues `(larger, smaller)` of the symmetric 2x2 matrix `[[a, c], [c, b]]`.
fn eigen2(a: f64, b: f64, c: f64) -> (f64, f64) {
    let mean = (a + b) / 2.0;
    let d = (((a - b) / 2.0).powi(2) + c * c).sqrt();
    (mean + d, mean - d)
}
