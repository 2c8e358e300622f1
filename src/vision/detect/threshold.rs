//! The local threshold of the detector (step 1 of [`super`]): per tile, the midpoint of the
//! darkest and brightest pixels around it where a tile shows a disc's contrast, spread into
//! the tiles without; and the frame's pixel noise.

use super::*;

/// Side of the tiles the threshold is set on (px).
pub(super) const THRESHOLD_TILE_PX: usize = 16;

/// The local threshold: per tile of [`THRESHOLD_TILE_PX`], the midpoint between the darkest
/// and the brightest pixel of the tile and its eight neighbours, where they differ by more
/// than the contrast a disc needs (the noise's spread and the minimum contrast); a tile without
/// that contrast (plain background, or the inside of a disc larger than three tiles) takes the
/// mean of its neighbours' thresholds, spread outwards from the tiles that have one. So the
/// threshold follows the light wherever discs are, whatever their size, and splits each
/// disc's edge at half its contrast.
pub(super) struct ThresholdMap {
    pub(super) tiles_x: usize,
    /// Per tile, twice the threshold (DN): the sum of the darkest and brightest values; `None`
    /// where no tile in the frame had contrast (nothing is foreground).
    pub(super) twice: Vec<Option<u32>>,
    /// Per tile, true when no pixel of it is foreground (its brightest pixel is under its
    /// threshold, or its darkest above for dark discs, or it has no threshold).
    blank: Vec<bool>,
    pub(super) bright: bool,
}

impl ThresholdMap {
    pub(super) fn new<P: Pixel>(
        pixels: &[P],
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
        let TileExtremes { lo, hi, steps } = TileExtremes::measure(pixels, w, h, &wanted);
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
        let bright = s.polarity == Polarity::Bright;
        // A tile none of whose pixels passes its threshold: the components skip it whole.
        let blank = twice
            .iter()
            .zip(lo.iter().zip(&hi))
            .map(|(t, (&lo, &hi))| match t {
                None => true,
                Some(t) if bright => 2 * u32::from(hi) <= *t,
                Some(t) => 2 * u32::from(lo) >= *t,
            })
            .collect();
        Self {
            tiles_x,
            twice,
            blank,
            bright,
        }
    }

    /// Twice the threshold of the tile holding pixel `(u, v)`.
    pub(super) fn twice_at(&self, u: usize, v: usize) -> Option<u32> {
        self.twice[(v / THRESHOLD_TILE_PX) * self.tiles_x + u / THRESHOLD_TILE_PX]
    }

    /// The column ranges `[u0, u1)` of threshold-tile row `ty` that the components must look
    /// at: the searched tiles that are not blank (a tile with no threshold is blank).
    pub(super) fn live_spans(&self, ty: usize, area: &SearchArea, w: usize) -> Vec<(usize, usize)> {
        let per = TILE_PX / THRESHOLD_TILE_PX;
        let row = &self.blank[ty * self.tiles_x..(ty + 1) * self.tiles_x];
        let live: Vec<bool> = row
            .iter()
            .enumerate()
            .map(|(tx, &blank)| !blank && area.is_active(tx / per, ty / per))
            .collect();
        column_spans(&live, THRESHOLD_TILE_PX, w)
    }

    pub(super) fn foreground(&self, p: u16, u: usize, v: usize) -> bool {
        match self.twice_at(u, v) {
            Some(t) if self.bright => 2 * u32::from(p) > t,
            Some(t) => 2 * u32::from(p) < t,
            None => false,
        }
    }
}

/// Per threshold tile: the darkest and brightest pixel, and the sum and count of neighbouring
/// pixels' absolute differences along every fourth row (the tile's own noise where it is flat).
/// Tiles not wanted keep `u16::MAX`, 0 and no differences.
pub(super) struct TileExtremes {
    pub(super) lo: Vec<u16>,
    pub(super) hi: Vec<u16>,
    pub(super) steps: Vec<(u32, u32)>,
}

impl TileExtremes {
    /// One pass over the wanted tiles. The extremes are taken down the columns of a tile row
    /// first (an elementwise minimum and maximum of whole rows, which the compiler vectorises),
    /// then across each tile's 16 columns once: a reduction across a tile per row would cost
    /// sixteen times as many.
    pub(super) fn measure<P: Pixel>(pixels: &[P], w: usize, h: usize, wanted: &[bool]) -> Self {
        let t = THRESHOLD_TILE_PX;
        let (tiles_x, tiles_y) = (w.div_ceil(t), h.div_ceil(t));
        let mut lo = vec![u16::MAX; tiles_x * tiles_y];
        let mut hi = vec![0u16; tiles_x * tiles_y];
        let mut steps = vec![(0u32, 0u32); tiles_x * tiles_y];
        let mut column_lo = vec![P::MAX; w];
        let mut column_hi = vec![P::MIN; w];
        for ty in 0..tiles_y {
            let base = ty * tiles_x;
            let row_tiles = &wanted[base..base + tiles_x];
            // The runs of wanted tiles of this tile row, as column ranges.
            let spans = column_spans(row_tiles, t, w);
            if spans.is_empty() {
                continue;
            }
            for &(u0, u1) in &spans {
                column_lo[u0..u1].fill(P::MAX);
                column_hi[u0..u1].fill(P::MIN);
            }
            for v in ty * t..((ty + 1) * t).min(h) {
                let row = &pixels[v * w..(v + 1) * w];
                for &(u0, u1) in &spans {
                    let (row, lo, hi) =
                        (&row[u0..u1], &mut column_lo[u0..u1], &mut column_hi[u0..u1]);
                    for ((l, h), &p) in lo.iter_mut().zip(hi.iter_mut()).zip(row) {
                        *l = (*l).min(p);
                        *h = (*h).max(p);
                    }
                }
                if v % 4 == 0 {
                    for (tx, chunk) in row.chunks(t).enumerate() {
                        if !row_tiles[tx] {
                            continue;
                        }
                        let sum: u32 = chunk
                            .windows(2)
                            .map(|p| u32::from(p[0].into().abs_diff(p[1].into())))
                            .sum();
                        let e = &mut steps[base + tx];
                        e.0 += sum;
                        e.1 += chunk.len().saturating_sub(1) as u32;
                    }
                }
            }
            for &(u0, u1) in &spans {
                for (k, (l, h)) in column_lo[u0..u1]
                    .chunks(t)
                    .zip(column_hi[u0..u1].chunks(t))
                    .enumerate()
                {
                    let i = base + u0 / t + k;
                    lo[i] = l.iter().copied().fold(P::MAX, P::min).into();
                    hi[i] = h.iter().copied().fold(P::MIN, P::max).into();
                }
            }
        }
        Self { lo, hi, steps }
    }
}

/// The frame's pixel noise (DN, one sigma): the median absolute difference of horizontal
/// neighbours over every sixteenth row, which edges hardly move (`|a - b|` of two independent
/// values of sigma `s` has a median of `0.954 s`).
pub(super) fn noise_dn<P: Pixel>(pixels: &[P], w: usize, h: usize) -> f64 {
    const BINS: usize = 4096;
    let mut histogram = vec![0u32; BINS];
    let mut count = 0u64;
    for v in (0..h).step_by(16) {
        let row = &pixels[v * w..(v + 1) * w];
        for pair in row.windows(2) {
            let d = usize::from(pair[0].into().abs_diff(pair[1].into()));
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

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Each tile's extremes and noise sums the plain way: every pixel of the tile, one by one.
    fn by_pixel(pixels: &[u16], w: usize, h: usize, wanted: &[bool]) -> TileExtremes {
        let t = THRESHOLD_TILE_PX;
        let tiles_x = w.div_ceil(t);
        let n = tiles_x * h.div_ceil(t);
        let mut e = TileExtremes {
            lo: vec![u16::MAX; n],
            hi: vec![0; n],
            steps: vec![(0, 0); n],
        };
        for v in 0..h {
            for u in 0..w {
                let i = (v / t) * tiles_x + u / t;
                if !wanted[i] {
                    continue;
                }
                let p = pixels[v * w + u];
                e.lo[i] = e.lo[i].min(p);
                e.hi[i] = e.hi[i].max(p);
                // The difference to the right-hand neighbour within the same tile.
                if v % 4 == 0 && (u + 1) % t != 0 && u + 1 < w {
                    e.steps[i].0 += u32::from(p.abs_diff(pixels[v * w + u + 1]));
                    e.steps[i].1 += 1;
                }
            }
        }
        e
    }

    proptest! {
        #[test]
        fn tile_extremes_equal_those_taken_pixel_by_pixel(
            w in 1usize..70,
            h in 1usize..70,
            seed in any::<u64>(),
            wanted_bits in any::<u64>(),
        ) {
            let mut next = xorshift(seed);
            let pixels: Vec<u16> = (0..w * h).map(|_| (next() % 4096) as u16).collect();
            let tiles = w.div_ceil(THRESHOLD_TILE_PX) * h.div_ceil(THRESHOLD_TILE_PX);
            let wanted: Vec<bool> = (0..tiles).map(|i| wanted_bits >> (i % 64) & 1 == 1).collect();
            let fast = TileExtremes::measure(&pixels, w, h, &wanted);
            let plain = by_pixel(&pixels, w, h, &wanted);
            prop_assert_eq!(fast.lo, plain.lo);
            prop_assert_eq!(fast.hi, plain.hi);
            prop_assert_eq!(fast.steps, plain.steps);
        }
    }
}
