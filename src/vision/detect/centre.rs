//! A disc candidate's gates and centre (steps 3 to 5 of [`super`]): the background around it,
//! the clipped, background-corrected centroid over its window with what is not its own left
//! out, and the centre's covariance.

use super::components::Component;
use super::*;

/// The centroid's weights are clipped this many noise sigmas below the disc's level, and this
/// many background sigmas above the background.
pub(super) const CLIP_SIGMAS: f64 = 3.0;

/// A disc candidate's outline, so that its neighbours leave its pixels out of their windows.
#[derive(Debug, Clone, Copy)]
pub(super) struct Shape {
    pub(super) mean: [f64; 2],
    /// The inverse of the second moments, over four (so `d^T m d <= 1` on the outline).
    pub(super) inverse: [f64; 3],
    /// How far its pixels reach beyond the outline, relative: the outline widened by
    /// [`SHAPE_MARGIN_PX`] on its minor axis.
    pub(super) inflate2: f64,
    /// The outline's semi-major axis plus the margin (px).
    pub(super) outer_px: f64,
}

/// Pixels this close outside a neighbour's outline belong to it (its blur, its threshold's
/// underestimate).
pub(super) const SHAPE_MARGIN_PX: f64 = 2.0;

impl Shape {
    pub(super) fn of(c: &Component) -> Self {
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
    pub(super) fn holds(&self, x: f64, y: f64) -> bool {
        let (dx, dy) = (x - self.mean[0], y - self.mean[1]);
        let [a, b, c] = self.inverse;
        a * dx * dx + b * dy * dy + 2.0 * c * dx * dy <= self.inflate2
    }

    /// How far from its centre this disc's measurement reads pixels (px): window and ring.
    pub(super) fn reach_px(&self) -> f64 {
        let radius = self.outer_px - SHAPE_MARGIN_PX;
        window_px(radius) + RING_PX
    }
}

/// The radius of the window a disc of `radius_px` is measured in: wide enough for the blur's
/// tails and the threshold's underestimate of the edge, which grow with a large (near, so often
/// less sharp) disc.
pub(super) fn window_px(radius_px: f64) -> f64 {
    radius_px + 3.0 + 0.1 * (radius_px - 20.0).max(0.0)
}

/// The width of the ring around the window the background is read from (px).
pub(super) const RING_PX: f64 = 3.0;

/// Buffers reused from disc to disc.
#[derive(Default)]
pub(super) struct Scratch {
    /// Ring pixels: offset from the centre (px) and value (DN).
    pub(super) ring: Vec<(f64, f64, f64)>,
    pub(super) values: Vec<f64>,
    /// Window pixels: position, weight, whether its noise reaches the centre.
    pub(super) window: Vec<(f64, f64, f64, bool)>,
    /// Whether each pixel of the square around a disc belongs to a neighbour or to foreign
    /// foreground.
    pub(super) theirs: Vec<bool>,
    /// The foreign foreground widened along rows, on the way to `theirs`.
    pub(super) spread: Vec<bool>,
}

/// The background under a disc: a level, and a slope when the light visibly changes across
/// the disc's surroundings (a plane fitted to the ring around the window).
#[derive(Debug, Clone, Copy)]
pub(super) struct Background {
    pub(super) level: f64,
    pub(super) slope: [f64; 2],
    /// The ring's variance about it (DN^2).
    pub(super) variance: f64,
}

impl Background {
    pub(super) fn at(&self, du: f64, dv: f64) -> f64 {
        self.level + self.slope[0] * du + self.slope[1] * dv
    }

    /// From the ring's pixels (offsets from the centre and values): their median, or where a
    /// plane fits them significantly better (its slope beyond the noise at 99.7 %, chi-square
    /// with two degrees of freedom), a plane fitted twice, the second time without the pixels
    /// a neighbouring disc or a speck puts more than three sigmas off the first.
    pub(super) fn fit(ring: &[(f64, f64, f64)], values: &mut Vec<f64>) -> Option<Self> {
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
pub(super) fn fit_plane(
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
pub(super) fn refine<P: Pixel>(
    (pixels, w, h): (&[P], usize, usize),
    c: &Component,
    s: &DetectSettings,
    (scale, noise_dn): (f64, f64),
    others: &[&Shape],
    foreground: &impl Fn(usize, usize) -> bool,
    scratch: &mut Scratch,
) -> Option<Blob> {
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
                scratch
                    .ring
                    .push((du, dv, f64::from(row[u as usize].into())));
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
                    .push(contrast(f64::from(row[u as usize].into()), x, y));
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
    const ITERATIONS: usize = 4;
    for iteration in 0..ITERATIONS {
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
                let raw = contrast(f64::from(row[u as usize].into()), x, y);
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
        let moved = (next[0] - centre[0]).hypot(next[1] - centre[1]);
        if moved >= 1e-4 && iteration + 1 < ITERATIONS {
            // Not the last window: its covariance and shape would be replaced.
            centre = next;
            continue;
        }
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
        centre = next;
        break;
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
pub(super) fn clipped_shift_px(
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
