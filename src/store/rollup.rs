//! Rollups: per bucket, the count and min, sum and max of every result component, so a history
//! at any scale reads a bounded number of rows and a spike survives downsampling.

use super::{NewResult, Reader, Store, StoreResult, codec, sql};
use crate::bank::ResultSource;
use crate::geometry::{PoseCov, ReportedSigmas, euler_from_rotation};
use crate::model::TargetId;
use std::collections::HashMap;

/// Bucket widths of the rollup levels (s).
pub(crate) const ROLLUP_WIDTHS_S: [i64; 5] = [1, 10, 60, 600, 3600];

/// How many components a result has.
pub(crate) const N_COMPONENTS: usize = 18;

/// The components, in column order: Euler angles (deg), translation (mm), deformation rotation
/// (arcsec) and translation (mm), sigmas of rotation (arcsec) and translation (mm).
pub(crate) const COMPONENTS: [&str; N_COMPONENTS] = [
    "euler_x_deg",
    "euler_y_deg",
    "euler_z_deg",
    "t_x_mm",
    "t_y_mm",
    "t_z_mm",
    "def_rx_arcsec",
    "def_ry_arcsec",
    "def_rz_arcsec",
    "def_tx_mm",
    "def_ty_mm",
    "def_tz_mm",
    "sigma_rx_arcsec",
    "sigma_ry_arcsec",
    "sigma_rz_arcsec",
    "sigma_tx_mm",
    "sigma_ty_mm",
    "sigma_tz_mm",
];

/// Indices of the deformation components (absent while a target has no reference).
const DEF: std::ops::Range<usize> = 6..12;

/// A bucket of results: count and per component min, sum, max.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bucket {
    /// Bucket start (ns).
    pub start_ns: i64,
    /// Results in the bucket.
    pub n: i64,
    /// Of which with a deformation.
    pub n_def: i64,
    /// Minimum per component.
    pub min: [f64; N_COMPONENTS],
    /// Sum per component.
    pub sum: [f64; N_COMPONENTS],
    /// Maximum per component.
    pub max: [f64; N_COMPONENTS],
}

impl Bucket {
    /// An empty bucket starting at `start_ns`.
    pub fn empty(start_ns: i64) -> Self {
        Self {
            start_ns,
            n: 0,
            n_def: 0,
            min: [f64::INFINITY; N_COMPONENTS],
            sum: [0.0; N_COMPONENTS],
            max: [f64::NEG_INFINITY; N_COMPONENTS],
        }
    }

    /// Adds one result's components.
    pub fn add(&mut self, values: &[f64; N_COMPONENTS], has_deformation: bool) {
        self.n += 1;
        if has_deformation {
            self.n_def += 1;
        }
        for (i, v) in values.iter().enumerate() {
            if DEF.contains(&i) && !has_deformation {
                continue;
            }
            self.min[i] = self.min[i].min(*v);
            self.max[i] = self.max[i].max(*v);
            self.sum[i] += v;
        }
    }

    /// Merges another bucket into this one.
    pub fn merge(&mut self, other: &Bucket) {
        self.n += other.n;
        self.n_def += other.n_def;
        for i in 0..N_COMPONENTS {
            self.min[i] = self.min[i].min(other.min[i]);
            self.max[i] = self.max[i].max(other.max[i]);
            self.sum[i] += other.sum[i];
        }
    }

    /// The mean of component `i`, `None` when no result carried it.
    pub fn mean(&self, i: usize) -> Option<f64> {
        let n = if DEF.contains(&i) { self.n_def } else { self.n };
        (n > 0).then(|| self.sum[i] / n as f64)
    }

    /// True when component `i` has values in this bucket.
    pub fn has(&self, i: usize) -> bool {
        if DEF.contains(&i) {
            self.n_def > 0
        } else {
            self.n > 0
        }
    }
}

/// The components of a result, given its reported sigmas.
pub(crate) fn components(
    estimate: &PoseCov,
    s: &ReportedSigmas,
    deformation: Option<([f64; 3], [f64; 3])>,
) -> ([f64; N_COMPONENTS], bool) {
    let e = euler_from_rotation(&estimate.pose.rotation).to_degrees();
    let t = estimate.pose.translation.vector;
    let (dr, dt) = deformation.unwrap_or(([0.0; 3], [0.0; 3]));
    let mut out = [0.0; N_COMPONENTS];
    let values = [e[0], e[1], e[2], t.x, t.y, t.z]
        .into_iter()
        .chain(dr)
        .chain(dt)
        .chain(s.axes());
    for (slot, v) in out.iter_mut().zip(values) {
        *slot = v;
    }
    (out, deformation.is_some())
}

/// The buckets that new results add to, per (target, source, width, bucket start).
pub(super) fn aggregate(
    results: &[&NewResult],
    sigmas: &[ReportedSigmas],
) -> HashMap<(TargetId, ResultSource, i64, i64), Bucket> {
    let mut out: HashMap<(TargetId, ResultSource, i64, i64), Bucket> = HashMap::new();
    for (r, s) in results.iter().zip(sigmas) {
        let (values, has_def) = components(
            &r.estimate.whole,
            s,
            r.deformation
                .map(|(_, d)| (d.rotation_arcsec, d.translation_mm)),
        );
        for width_s in ROLLUP_WIDTHS_S {
            let width_ns = width_s * 1_000_000_000;
            // Saturating, never wrapping: a bucket of the far past cannot land in the future.
            let start = floor_to(r.time_ns, width_ns);
            out.entry((r.target, r.source, width_s, start))
                .or_insert_with(|| Bucket::empty(start))
                .add(&values, has_def);
        }
    }
    out
}

/// Encodes a bucket's min, sum and max per component (432 bytes).
pub(super) fn encode_stats(b: &Bucket) -> Vec<u8> {
    let mut out = Vec::with_capacity(N_COMPONENTS * 3 * 8);
    for i in 0..N_COMPONENTS {
        for v in [b.min[i], b.sum[i], b.max[i]] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Decodes a stored bucket.
pub(super) fn decode_bucket(
    start_ns: i64,
    n: i64,
    n_def: i64,
    stats: &[u8],
) -> StoreResult<Bucket> {
    let values = super::codec::decode_f64s(stats, N_COMPONENTS * 3)?;
    let mut b = Bucket::empty(start_ns);
    b.n = n;
    b.n_def = n_def;
    for i in 0..N_COMPONENTS {
        b.min[i] = values[3 * i];
        b.sum[i] = values[3 * i + 1];
        b.max[i] = values[3 * i + 2];
    }
    Ok(b)
}

/// A target's history over a window, downsampled to at most a number of buckets.
#[derive(Debug, Clone, PartialEq)]
pub struct History {
    /// The window actually covered: the asked-for ends, or the history's own where open; `None`
    /// when the target has no history.
    pub window_ns: Option<(i64, i64)>,
    /// The width of each bucket (ns).
    pub bucket_ns: i64,
    /// What the buckets were built from: a rollup width (s), or `None` for the results.
    pub resolution_s: Option<i64>,
    /// The buckets that hold results, oldest first.
    pub buckets: Vec<Bucket>,
}

/// How a window of `[from_ns, to_ns]` is read in at most `max_points` buckets: from the widest
/// rollup no wider than the bucket the window needs (`Some(width_s)`), or from the results
/// (`None`, when even the finest rollup is too coarse); the bucket width (ns) and the time the
/// buckets are aligned on. A rollup-read bucket is a whole number of rollup buckets, aligned
/// on the rollup grid, and the count stays within `max_points` after the alignment.
pub(crate) fn history_plan(from_ns: i64, to_ns: i64, max_points: usize) -> (Option<i64>, i64, i64) {
    let max_points = max_points.max(1) as f64;
    let span = (to_ns as i128 - from_ns as i128 + 1) as f64;
    let wanted_ns = (span / max_points).ceil().max(1.0) as i64;
    let level = ROLLUP_WIDTHS_S
        .iter()
        .rev()
        .copied()
        .find(|w| w * 1_000_000_000 <= wanted_ns);
    match level {
        Some(w) => {
            let level_ns = w * 1_000_000_000;
            let start = floor_to(from_ns, level_ns);
            // The aligned span may be one level bucket longer: widen to stay within max_points.
            let aligned = (to_ns as i128 - start as i128 + 1) as f64;
            let width_ns =
                ((aligned / max_points / level_ns as f64).ceil() as i64).max(1) * level_ns;
            (Some(w), width_ns, start)
        }
        None => (None, wanted_ns, from_ns),
    }
}

impl Store {
    /// A target's history in `[from_ns, to_ns]` (either end open: `i64::MIN`, `i64::MAX`) in at
    /// most `max_points` buckets: read from the rollups when the buckets are at least as wide
    /// as the finest rollup, otherwise from the results (streamed, memory that of the buckets).
    pub async fn history(
        &self,
        target: TargetId,
        source: ResultSource,
        from_ns: i64,
        to_ns: i64,
        max_points: usize,
    ) -> StoreResult<History> {
        let bounds = self.result_bounds(target, source).await?;
        let Some((lo, hi)) = bounds else {
            return Ok(History {
                window_ns: None,
                bucket_ns: 1,
                resolution_s: None,
                buckets: Vec::new(),
            });
        };
        let from = if from_ns == i64::MIN { lo } else { from_ns };
        let to = if to_ns == i64::MAX { hi } else { to_ns };
        if from > to {
            return Ok(History {
                window_ns: Some((from, to)),
                bucket_ns: 1,
                resolution_s: None,
                buckets: Vec::new(),
            });
        }
        let (level, width_ns, start) = history_plan(from, to, max_points);
        let rows = match level {
            Some(w) => self.rollup_buckets(target, source, w, from, to).await?,
            None => {
                self.result_buckets(target, source, from, to, start, width_ns)
                    .await?
            }
        };
        let mut buckets: std::collections::BTreeMap<i64, Bucket> =
            std::collections::BTreeMap::new();
        for row in rows {
            let bucket_start = align(row.start_ns, start, width_ns);
            buckets
                .entry(bucket_start)
                .or_insert_with(|| Bucket::empty(bucket_start))
                .merge(&row);
        }
        Ok(History {
            window_ns: Some((from, to)),
            bucket_ns: width_ns,
            resolution_s: level,
            buckets: buckets.into_values().collect(),
        })
    }

    /// The span of a target's history: from the finest rollup, which is kept when old results
    /// are pruned (its last bucket counts to its end), else from the results. Each end is its
    /// own indexed lookup.
    pub async fn result_bounds(
        &self,
        target: TargetId,
        source: ResultSource,
    ) -> StoreResult<Option<(i64, i64)>> {
        let (id, column, width_s) = (
            self.target_ids[target.0],
            codec::source_column(source),
            ROLLUP_WIDTHS_S[0],
        );
        let mut ends = [None, None];
        for (i, statement) in [sql::ROLLUP_FIRST, sql::ROLLUP_LAST]
            .into_iter()
            .enumerate()
        {
            let end: Option<(i64,)> = query_on!(
                &self.reader, Reader, r => &r.pool,
                statement, [id, column, width_s],
                fetch_optional
            )?;
            ends[i] = end.map(|(b,)| b);
        }
        if let [Some(lo), Some(hi)] = ends {
            return Ok(Some((lo, hi + width_s * 1_000_000_000 - 1)));
        }
        let first = self
            .results_around(target, source, i64::MIN)
            .await?
            .1
            .map(|r| r.time_ns);
        let last = self.latest_result(target, source).await?.map(|r| r.time_ns);
        Ok(first.zip(last))
    }

    /// The rollup buckets of width `width_s` overlapping `[from_ns, to_ns]`, oldest first.
    pub async fn rollup_buckets(
        &self,
        target: TargetId,
        source: ResultSource,
        width_s: i64,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<Bucket>> {
        let width_ns = width_s * 1_000_000_000;
        let (id, source, from) = (
            self.target_ids[target.0],
            codec::source_column(source),
            floor_to(from_ns, width_ns),
        );
        let rows: Vec<(i64, i64, i64, Vec<u8>)> = query_on!(
            &self.reader, Reader, r => &r.pool,
            sql::ROLLUP_ROWS, [id, source, width_s, from, to_ns],
            fetch_all
        )?;
        rows.iter()
            .map(|(start, n, n_def, stats)| decode_bucket(*start, *n, *n_def, stats))
            .collect()
    }

    /// The results in `[from_ns, to_ns]` merged into buckets of `width_ns` aligned on
    /// `start_ns`, oldest first (for history finer than the finest rollup). The rows are
    /// streamed: memory is that of the buckets, however many results the window holds.
    pub async fn result_buckets(
        &self,
        target: TargetId,
        source: ResultSource,
        from_ns: i64,
        to_ns: i64,
        start_ns: i64,
        width_ns: i64,
    ) -> StoreResult<Vec<Bucket>> {
        let mut buckets: std::collections::BTreeMap<i64, Bucket> =
            std::collections::BTreeMap::new();
        let mut add = |row: super::rows::ResultRow| -> StoreResult<()> {
            let r = row.into_result()?;
            let (values, has_def) = components(
                &r.estimate.whole,
                &r.estimate.whole.reported_sigmas(),
                r.deformation.map(|(_, rot, t)| (rot, t)),
            );
            let bucket_start = align(r.time_ns, start_ns, width_ns);
            buckets
                .entry(bucket_start)
                .or_insert_with(|| Bucket::empty(bucket_start))
                .add(&values, has_def);
            Ok(())
        };
        let (id, source) = (self.target_ids[target.0], codec::source_column(source));
        on_backend!(&self.reader, Reader, r => {
            use futures::TryStreamExt as _;
            let mut rows = sqlx::query_as::<_, super::rows::ResultRow>(&sql::RESULTS_IN)
                .bind(id)
                .bind(source)
                .bind(from_ns)
                .bind(to_ns)
                .bind(i64::MAX)
                .fetch(&r.pool);
            while let Some(row) = rows.try_next().await? {
                add(row)?;
            }
            StoreResult::Ok(())
        })?;
        Ok(buckets.into_values().collect())
    }
}

/// The start of the bucket of width `width_ns` (aligned on `start_ns`) that holds `time_ns`;
/// computed wide so that no time, however far from `start_ns`, overflows.
pub(crate) fn align(time_ns: i64, start_ns: i64, width_ns: i64) -> i64 {
    let (t, s, w) = (
        i128::from(time_ns),
        i128::from(start_ns),
        i128::from(width_ns.max(1)),
    );
    let aligned = s + (t - s).div_euclid(w) * w;
    aligned.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64
}

/// `time_ns` rounded down to a multiple of `width_ns`, saturating at the ends of time.
pub(crate) fn floor_to(time_ns: i64, width_ns: i64) -> i64 {
    let w = i128::from(width_ns.max(1));
    let floored = i128::from(time_ns).div_euclid(w) * w;
    floored.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// However the window and the count fall, a plan never gives more than `max_points`
    /// buckets, reads a rollup exactly when buckets of at least its width are wanted, and
    /// covers the window's first time.
    #[test]
    fn history_plans_stay_within_max_points_and_pick_the_widest_fitting_rollup() {
        let s = 1_000_000_000i64;
        for &(from, to, max_points) in &[
            (0i64, 10 * s, 1000usize),
            (123_456_789, 3600 * s + 7, 1000),
            (5 * s + 1, 86_400 * 30 * s, 500),
            (-7 * s, 7 * s, 3),
            (0, 599 * s, 1),
            (17, 17, 10),
        ] {
            let (level, width_ns, start) = history_plan(from, to, max_points);
            assert!(width_ns >= 1);
            assert!(start <= from && from - start < width_ns.max(1));
            let buckets = (align(to, start, width_ns) - start) / width_ns + 1;
            assert!(
                buckets as usize <= max_points,
                "{buckets} buckets for {max_points} over [{from}, {to}]"
            );
            let wanted = ((to - from + 1) as f64 / max_points as f64).ceil() as i64;
            let expected = ROLLUP_WIDTHS_S
                .iter()
                .rev()
                .copied()
                .find(|w| w * s <= wanted);
            assert_eq!(level, expected);
            if let Some(w) = level {
                assert_eq!(width_ns % (w * s), 0, "a whole number of rollup buckets");
                assert_eq!(start % (w * s), 0, "aligned on the rollup grid");
            }
        }
    }
}

#[cfg(test)]
mod far_time_tests {
    use super::{align, floor_to};

    /// The bucket of the earliest representable time stays at the start of time instead of
    /// wrapping into the far future (where it would make a partition no upkeep can keep).
    #[test]
    fn buckets_of_the_ends_of_time_saturate_instead_of_wrapping() {
        let hour = 3_600_000_000_000;
        assert_eq!(floor_to(i64::MIN, hour), i64::MIN);
        assert!(floor_to(i64::MIN + 1, hour) <= i64::MIN + 1);
        assert_eq!(
            floor_to(i64::MAX, hour),
            i64::MAX - i64::MAX.rem_euclid(hour)
        );
        assert_eq!(floor_to(-1, hour), -hour);
        assert_eq!(align(i64::MIN, 7, hour), i64::MIN);
    }
}
