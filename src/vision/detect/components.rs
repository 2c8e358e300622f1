//! The detector's connected components of foreground (step 2 of [`super`]) and the test that a
//! component's outline is an ellipse (step 3's shape gate).

use super::threshold::THRESHOLD_TILE_PX;
use super::*;

/// How many pixels per unit of perimeter may disagree with the moments' ellipse.
pub(super) const MAX_MISMATCH_PER_PERIMETER: f64 = 0.35;

/// A connected set of foreground pixels, summarised.
#[derive(Debug, Clone, Copy)]
pub(super) struct Component {
    pub(super) area: usize,
    pub(super) sum_u: f64,
    pub(super) sum_v: f64,
    pub(super) sum_uu: f64,
    pub(super) sum_vv: f64,
    pub(super) sum_uv: f64,
    pub(super) u_min: usize,
    pub(super) u_max: usize,
    pub(super) v_min: usize,
    pub(super) v_max: usize,
}

impl Component {
    pub(super) fn add_run(&mut self, v: usize, u0: usize, u1: usize) {
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

    pub(super) fn merge(&mut self, o: &Component) {
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

    pub(super) fn empty() -> Self {
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
    pub(super) fn moments(&self) -> ([f64; 2], [f64; 3]) {
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
pub(super) fn components<P: Pixel>(
    w: usize,
    h: usize,
    area: &SearchArea,
    thresholds: &ThresholdMap,
    pixels: &[P],
) -> Vec<Component> {
    pub(super) fn find(parent: &mut [usize], mut i: usize) -> usize {
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
        // Only the searched tiles that can hold foreground are looked at: a blank tile has
        // none, so no run crosses it.
        if v % THRESHOLD_TILE_PX == 0 {
            spans = thresholds.live_spans(v / THRESHOLD_TILE_PX, area, w);
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
                            *m = u8::from(2 * u32::from(p.into()) > t);
                        }
                    }
                    Some(t) => {
                        for (m, &p) in out.iter_mut().zip(pixels) {
                            *m = u8::from(2 * u32::from(p.into()) < t);
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
pub(super) fn is_elliptic(
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
    let moments = c.moments();
    let (_, [cuu, cvv, cuv]) = moments;
    // Far from an ellipse's fill (a large shape of clutter, a streak): refused before any
    // pixel is looked at. A hole (below) lowers the fill by at most a quarter.
    let (major2, minor2) = eigen2(cuu, cvv, cuv);
    let fill = c.area as f64 / (std::f64::consts::PI * 4.0 * (major2 * minor2).max(0.0).sqrt());
    if !(0.5..=1.5).contains(&fill) {
        return None;
    }
    // A hole inflates the moments: fill it, then compare the outline.
    let reach = reach_of(c)?;
    let mut filled = *c;
    for v in rows.clone() {
        for u in columns_within(moments, v, 1.44, cols.clone()) {
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

/// The columns of `cols` in row `v` where `d^T C^-1 d <= r2` can hold for the moments' mean
/// and covariance `C`, widened by a pixel (each is still tested): between the roots of the
/// quadratic in `du` it is along the row. Empty where the row misses the ellipse.
fn columns_within(
    (mean, [cuu, cvv, cuv]): ([f64; 2], [f64; 3]),
    v: usize,
    r2: f64,
    cols: std::ops::RangeInclusive<usize>,
) -> std::ops::Range<usize> {
    let det = cuu * cvv - cuv * cuv;
    let dv = v as f64 - mean[1];
    // cvv du^2 - 2 cuv dv du + (cuu dv^2 - r2 det) <= 0
    let disc = (cuv * dv).powi(2) - cvv * (cuu * dv * dv - r2 * det);
    if cvv <= 0.0 || disc < 0.0 {
        return 0..0;
    }
    let (mid, half) = (cuv * dv / cvv, disc.sqrt() / cvv);
    let first = (mean[0] + mid - half - 1.0)
        .floor()
        .max(*cols.start() as f64) as usize;
    let last = (mean[0] + mid + half + 1.0).ceil().min(*cols.end() as f64);
    if last < first as f64 {
        return 0..0;
    }
    first..last as usize + 1
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The components the plain way: every searched pixel's foreground looked at one by one,
    /// grown by a flood fill over the eight neighbours.
    fn by_pixel(
        w: usize,
        h: usize,
        area: &SearchArea,
        thresholds: &ThresholdMap,
        pixels: &[u16],
    ) -> Vec<Component> {
        let searched = |u: usize, v: usize| area.is_active(u / TILE_PX, v / TILE_PX);
        let fore: Vec<bool> = (0..w * h)
            .map(|i| {
                let (u, v) = (i % w, i / w);
                searched(u, v) && thresholds.foreground(pixels[i], u, v)
            })
            .collect();
        let mut seen = vec![false; w * h];
        let mut out = Vec::new();
        for start in 0..w * h {
            if !fore[start] || seen[start] {
                continue;
            }
            let mut part = Component::empty();
            let mut stack = vec![start];
            seen[start] = true;
            while let Some(i) = stack.pop() {
                let (u, v) = (i % w, i / w);
                part.add_run(v, u, u);
                for nv in v.saturating_sub(1)..=(v + 1).min(h - 1) {
                    for nu in u.saturating_sub(1)..=(u + 1).min(w - 1) {
                        let k = nv * w + nu;
                        if fore[k] && !seen[k] {
                            seen[k] = true;
                            stack.push(k);
                        }
                    }
                }
            }
            out.push(part);
        }
        out.sort_by_key(|c| (c.v_min, c.u_min));
        out
    }

    proptest! {
        /// The shape test's row ranges hold every pixel of the box within the ellipse: the
        /// same pixels are tested as over the whole box.
        #[test]
        fn row_ranges_hold_every_pixel_within_the_ellipse(
            mean in (5.0f64..60.0, 5.0f64..60.0),
            axes in (0.3f64..20.0, 0.3f64..20.0),
            angle in 0.0f64..std::f64::consts::PI,
            r2 in 0.5f64..5.0,
        ) {
            let (cos, sin) = (angle.cos(), angle.sin());
            let (a2, b2) = (axes.0 * axes.0, axes.1 * axes.1);
            let cuu = a2 * cos * cos + b2 * sin * sin;
            let cvv = a2 * sin * sin + b2 * cos * cos;
            let cuv = (a2 - b2) * cos * sin;
            let det = cuu * cvv - cuv * cuv;
            prop_assume!(det > 1e-9);
            let cols = 0usize..=70;
            for v in 0..=70usize {
                let range = columns_within(([mean.0, mean.1], [cuu, cvv, cuv]), v, r2, cols.clone());
                for u in cols.clone() {
                    let (du, dv) = (u as f64 - mean.0, v as f64 - mean.1);
                    let reach = (cvv * du * du - 2.0 * cuv * du * dv + cuu * dv * dv) / det;
                    if reach <= r2 {
                        prop_assert!(range.contains(&u), "({u}, {v}) at {reach} outside {range:?}");
                    }
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// The components' scan skips unsearched and blank tiles and joins row runs: it finds
        /// exactly the components a pixel-by-pixel flood fill of the searched foreground does.
        #[test]
        fn components_equal_a_flood_fill_of_the_searched_foreground(
            w in 20usize..200,
            h in 20usize..200,
            seed in any::<u64>(),
            active_bits in any::<u64>(),
            discs in proptest::collection::vec((0.0f64..1.0, 0.0f64..1.0, 1.0f64..14.0), 0..12),
        ) {
            let mut next = xorshift(seed);
            let mut noise = move || (next() % 7) as f64;
            let pixels: Vec<u16> = (0..w * h)
                .map(|i| {
                    let (u, v) = ((i % w) as f64, (i / w) as f64);
                    let lit = discs.iter().any(|&(cu, cv, r)| {
                        (u - cu * w as f64).hypot(v - cv * h as f64) <= r
                    });
                    (if lit { 200.0 } else { 30.0 } + noise()) as u16
                })
                .collect();
            let mut area = SearchArea::empty(w as u32, h as u32);
            let tiles = area.active.len();
            for (i, a) in area.active.iter_mut().enumerate() {
                *a = active_bits >> (i % 64) & 1 == 1 || tiles == 1;
            }
            let settings = DetectSettings::default();
            let noise = noise_dn(&pixels, w, h);
            let thresholds = ThresholdMap::new(&pixels, w, h, &settings, 1.0, noise, &area);
            let fast = components(w, h, &area, &thresholds, &pixels);
            let plain = by_pixel(w, h, &area, &thresholds, &pixels);
            prop_assert_eq!(fast.len(), plain.len());
            for (f, p) in fast.iter().zip(&plain) {
                prop_assert_eq!(
                    (f.area, f.u_min, f.u_max, f.v_min, f.v_max),
                    (p.area, p.u_min, p.u_max, p.v_min, p.v_max)
                );
                for (a, b) in [(f.sum_u, p.sum_u), (f.sum_v, p.sum_v), (f.sum_uv, p.sum_uv)] {
                    prop_assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0), "{a} against {b}");
                }
            }
        }
    }
}
