//! A period's report, the page an owner files: the installation and its calibrations, the
//! acceptance in force at the period's end, then per
//! target its deformation drawn over the period (the filtered result with its sigma band over
//! the raw results' spread), the paper's statistics (Table 4/5) of the raw and the filtered
//! results with the rms the model expects, the trend over the period, the alarms and their
//! acknowledgements, the silences in the data with what the store says of their causes, and
//! where the newest result's uncertainty comes from.
//!
//! [`PeriodReport`] holds what the page shows, gathered by the service from its store and its
//! filters; [`render`] only draws it. Every figure is printed from the same value the API
//! answers for the same period (the statistics of `GET .../stats`, the buckets of
//! `GET .../history`, the lines of `GET .../budget`), and each statistic's cell carries an id
//! (`TARGET-SOURCE-QUANTITY-STATISTIC-AXIS`) so that a reader or a test can find it.

use super::{Svg, escape, page};
use crate::alarms::Level;
use crate::chain::{Budget, UncertaintyPart, budget_sigmas};
use crate::clock::format_ns;
use crate::stats::PoseStats;
use crate::store::StoredAlarm;
use crate::store::rollup::{Bucket, History};
use crate::vision::CameraModel;
use std::fmt::Write as _;

/// What a period's report shows.
#[derive(Debug, Clone)]
pub struct PeriodReport {
    /// The installation (its file, or the built-in one's name).
    pub installation: String,
    /// When the report was made (ns, the service's clock).
    pub generated_ns: i64,
    /// The period (ns, inclusive).
    pub from_ns: i64,
    /// The period's end.
    pub to_ns: i64,
    /// A silence between results longer than this is listed as a gap (ns).
    pub min_gap_ns: i64,
    /// The cameras and their calibrations.
    pub cameras: Vec<CameraLine>,
    /// The calibration versions of the calibrated links.
    pub calibrations: Vec<CalibrationLine>,
    /// One section per target.
    pub targets: Vec<TargetReport>,
    /// The rig's acceptance in force at the period's end.
    pub acceptance: super::acceptance::AcceptanceSection,
}

/// A camera's calibration as the installation states it.
#[derive(Debug, Clone)]
pub struct CameraLine {
    /// Its frame.
    pub frame: String,
    /// Its intrinsics.
    pub intrinsics: CameraModel,
    /// The sigma of a measured image point (px).
    pub pixel_sigma_px: f64,
    /// The calibration's sigmas of `fx fy cx cy` (px), when it states a covariance.
    pub intrinsics_sigma_px: Option<[f64; 4]>,
    /// Whether the installation names its calibration report.
    pub has_report: bool,
}

/// A calibrated link's calibration version.
#[derive(Debug, Clone)]
pub struct CalibrationLine {
    /// The link.
    pub link: String,
    /// The version stored; `None` for the installation's own calibration (never replaced).
    pub version: Option<i64>,
    /// In force from (ns); `None` for the installation's own.
    pub valid_from_ns: Option<i64>,
    /// Its sigmas: rotation about x, y, z (arc-seconds) and translation (mm).
    pub sigma: [f64; 6],
}

/// The results of one source over the period.
#[derive(Debug, Clone)]
pub struct SourceWindow {
    /// The paper's statistics; `None` when the period holds no result.
    pub stats: Option<PoseStats>,
    /// Min, mean and max per bucket.
    pub history: History,
}

/// A silence in a target's results.
#[derive(Debug, Clone)]
pub struct Gap {
    /// The last result before it, or the period's start.
    pub from_ns: i64,
    /// The first result after it, or the period's end.
    pub to_ns: i64,
    /// What each measured link of the target's chain stored during it.
    pub links: Vec<LinkInGap>,
}

/// What a measured link stored during a gap.
#[derive(Debug, Clone)]
pub struct LinkInGap {
    /// The link.
    pub link: String,
    /// Samples stored in the gap.
    pub samples: u64,
    /// Of them, rejected as outliers.
    pub outliers: u64,
}

/// The gaps of a target's raw results over the period.
#[derive(Debug, Clone, Default)]
pub struct Gaps {
    /// The longest gaps, the longest first.
    pub listed: Vec<Gap>,
    /// How many gaps there are in all.
    pub count: usize,
    /// Their summed length (ns).
    pub total_ns: i64,
    /// True when there were more gaps than were read (the count and total are then at least).
    pub truncated: bool,
}

/// The uncertainty budget of a target's newest filtered result.
#[derive(Debug, Clone)]
pub struct BudgetSnapshot {
    /// That result's time.
    pub time_ns: i64,
    /// The budget.
    pub budget: Budget,
    /// Each contributor's name.
    pub names: std::collections::BTreeMap<crate::chain::Contributor, String>,
}

/// A target's section.
#[derive(Debug, Clone)]
pub struct TargetReport {
    /// The target.
    pub name: String,
    /// Its raw results (one per measurement group).
    pub raw: SourceWindow,
    /// Its filtered results (the compensation's).
    pub filtered: SourceWindow,
    /// The reference its deformation is measured against at the period's end: version, time
    /// set (ns).
    pub reference: Option<(i64, i64)>,
    /// The alarm transitions of the period, oldest first.
    pub alarms: Vec<StoredAlarm>,
    /// The silences of its raw results.
    pub gaps: Gaps,
    /// Where the newest result's uncertainty comes from.
    pub budget: Option<BudgetSnapshot>,
}

/// Three quantities drawn per panel row: a component's index in the rollups' components, the index of
/// its sigma, what one sigma unit is in the component's unit, and the axis' label.
struct Panel {
    value: usize,
    sigma: usize,
    sigma_scale: f64,
    label: &'static str,
}

/// The panels of a target: its deformation when the period has one, its pose otherwise.
fn panels(deformation: bool) -> [Panel; 6] {
    let labels_def = [
        "rotation x (arcsec)",
        "rotation y (arcsec)",
        "rotation z (arcsec)",
        "translation x (mm)",
        "translation y (mm)",
        "translation z (mm)",
    ];
    let labels_pose = [
        "Euler x (deg)",
        "Euler y (deg)",
        "Euler z (deg)",
        "t x (mm)",
        "t y (mm)",
        "t z (mm)",
    ];
    std::array::from_fn(|k| Panel {
        value: if deformation { 6 + k } else { k },
        sigma: 12 + k,
        sigma_scale: if !deformation && k < 3 {
            1.0 / 3600.0
        } else {
            1.0
        },
        label: if deformation {
            labels_def[k]
        } else {
            labels_pose[k]
        },
    })
}

/// A figure as the report prints it: degrees to 6 decimals (under a hundredth of an
/// arc-second), millimetres and arc-seconds to 4.
pub fn figure(value: f64, quantity: Quantity) -> String {
    match quantity {
        Quantity::EulerDeg => format!("{value:.6}"),
        Quantity::TranslationMm | Quantity::RotationArcsec => format!("{value:.4}"),
    }
}

/// The units a figure is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    /// Euler angles (degrees).
    EulerDeg,
    /// Translation (mm).
    TranslationMm,
    /// Rotation (arc-seconds).
    RotationArcsec,
}

/// The id of a statistic's cell: `TARGET-SOURCE-QUANTITY-STATISTIC-AXIS`, as
/// `G-raw-t_mm-rms-x`.
pub fn cell_id(target: &str, source: &str, quantity: &str, statistic: &str, axis: usize) -> String {
    format!(
        "{target}-{source}-{quantity}-{statistic}-{}",
        ["x", "y", "z"][axis]
    )
}

/// The page.
pub fn render(report: &PeriodReport) -> String {
    let mut b = String::new();
    let title = format!(
        "Deformation report {} to {}",
        format_ns(report.from_ns),
        format_ns(report.to_ns)
    );
    let _ = write!(
        b,
        "<h1>{}</h1>\n<p>Installation <code>{}</code>; made {}. A silence of over {} s \
         between raw results is counted as a gap.</p>\n",
        escape(&title),
        escape(&report.installation),
        escape(&format_ns(report.generated_ns)),
        report.min_gap_ns as f64 / 1e9
    );
    cameras_section(&mut b, report);
    super::acceptance::section(&mut b, &report.acceptance);
    for target in &report.targets {
        target_section(&mut b, report, target);
    }
    page(&title, &b)
}

fn cameras_section(b: &mut String, report: &PeriodReport) {
    b.push_str("<h2>Cameras and calibrations</h2>\n");
    if report.cameras.is_empty() {
        b.push_str("<p>The installation has no camera: its links are measured elsewhere.</p>\n");
    } else {
        b.push_str(
            "<table><tr><th class=\"l\">camera</th><th>size (px)</th><th>fx (px)</th>\
             <th>fy (px)</th><th>cx (px)</th><th>cy (px)</th><th>pixel sigma (px)</th>\
             <th class=\"l\">calibration</th></tr>\n",
        );
        for c in &report.cameras {
            let i = &c.intrinsics;
            let with = |v: f64, s: Option<f64>| match s {
                Some(s) => format!("{v:.2} &plusmn; {s:.2}"),
                None => format!("{v:.2}"),
            };
            let s = c.intrinsics_sigma_px;
            let _ = writeln!(
                b,
                "<tr><td class=\"l\">{}</td><td>{} x {}</td><td>{}</td><td>{}</td><td>{}</td>\
                 <td>{}</td><td>{:.3}</td><td class=\"l\">{}</td></tr>",
                escape(&c.frame),
                i.width_px,
                i.height_px,
                with(i.fx_px, s.map(|s| s[0])),
                with(i.fy_px, s.map(|s| s[1])),
                with(i.cx_px, s.map(|s| s[2])),
                with(i.cy_px, s.map(|s| s[3])),
                c.pixel_sigma_px,
                match (s.is_some(), c.has_report) {
                    (true, true) => "with its covariance and report",
                    (true, false) => "with its covariance",
                    (false, true) => "no covariance stated; a report",
                    (false, false) => "no covariance stated",
                }
            );
        }
        b.push_str("</table>\n");
    }
    if !report.calibrations.is_empty() {
        b.push_str(
            "<table><tr><th class=\"l\">calibrated link</th><th>version</th>\
             <th class=\"l\">in force from</th><th>sigma rx, ry, rz (arcsec)</th>\
             <th>sigma tx, ty, tz (mm)</th></tr>\n",
        );
        for c in &report.calibrations {
            let s = c.sigma;
            let _ = writeln!(
                b,
                "<tr><td class=\"l\">{}</td><td>{}</td><td class=\"l\">{}</td>\
                 <td>{:.2}, {:.2}, {:.2}</td><td>{:.4}, {:.4}, {:.4}</td></tr>",
                escape(&c.link),
                c.version
                    .map_or_else(|| "installation".to_owned(), |v| v.to_string()),
                c.valid_from_ns
                    .map_or_else(|| "the start".to_owned(), |t| escape(&format_ns(t))),
                s[0],
                s[1],
                s[2],
                s[3],
                s[4],
                s[5]
            );
        }
        b.push_str("</table>\n");
    }
}

fn target_section(b: &mut String, report: &PeriodReport, t: &TargetReport) {
    let _ = writeln!(b, "<h2>Target {}</h2>", escape(&t.name));
    let count = |w: &SourceWindow| w.stats.map_or(0, |s| s.count);
    let _ = writeln!(
        b,
        "<p>The period holds {} raw results (one per measurement group) and {} filtered results. {}</p>",
        count(&t.raw),
        count(&t.filtered),
        match t.reference {
            Some((version, at)) => format!(
                "Deformation is measured against reference version {version}, set {}.",
                escape(&format_ns(at))
            ),
            None => "No reference is set: the pictures show the pose itself.".to_owned(),
        }
    );
    plots(b, report, t);
    stats_table(b, t);
    trend_table(b, t);
    alarms_table(b, t);
    gaps_table(b, t);
    budget_table(b, t);
}

/// Whether any bucket of a history holds a deformation.
fn has_deformation(h: &History) -> bool {
    h.buckets.iter().any(|b| b.n_def > 0)
}

impl TargetReport {
    /// Whether the pictures and the trend show the deformation (some result of the period has
    /// one) or the pose.
    fn shows_deformation(&self) -> bool {
        has_deformation(&self.filtered.history) || has_deformation(&self.raw.history)
    }
}

fn plots(b: &mut String, report: &PeriodReport, t: &TargetReport) {
    let deformation = t.shows_deformation();
    if t.filtered.history.buckets.is_empty() && t.raw.history.buckets.is_empty() {
        b.push_str("<p>No result in the period: nothing to draw.</p>\n");
        return;
    }
    let _ = writeln!(
        b,
        "<p class=\"caption\">{} over the period: the filtered result (line) with its \
         1-sigma band (blue), over the spread of the raw results (grey, min to max per \
         bucket of {}).</p>",
        if deformation { "Deformation" } else { "Pose" },
        duration_text(t.filtered.history.bucket_ns.max(t.raw.history.bucket_ns))
    );
    // A figure a panel: each stays whole on a printed page.
    for p in panels(deformation) {
        let picture = panel(report, t, &p);
        if !picture.is_empty() {
            let _ = writeln!(b, "<figure>{picture}</figure>");
        }
    }
}

/// A duration as people read it: `40 ms`, `12.5 s`, `4.3 min`, `2.0 h`, `3.5 d`.
pub fn duration_text(ns: i64) -> String {
    let s = ns as f64 / 1e9;
    if s < 1.0 {
        format!("{:.0} ms", s * 1e3)
    } else if s < 120.0 {
        format!("{s:.1} s")
    } else if s < 7200.0 {
        format!("{:.1} min", s / 60.0)
    } else if s < 172_800.0 {
        format!("{:.1} h", s / 3600.0)
    } else {
        format!("{:.1} d", s / 86_400.0)
    }
}

/// Runs of consecutive buckets (a bucket more than one width after the previous starts a new
/// run), with the points `f` gives for each bucket.
fn runs(
    history: &History,
    f: impl Fn(&Bucket) -> Option<(f64, f64, f64)>,
) -> Vec<Vec<(i64, [f64; 3])>> {
    let mut out: Vec<Vec<(i64, [f64; 3])>> = Vec::new();
    let mut last: Option<i64> = None;
    for bucket in &history.buckets {
        let Some((lo, mid, hi)) = f(bucket) else {
            last = None;
            continue;
        };
        let joined = last.is_some_and(|l| bucket.start_ns - l <= history.bucket_ns);
        if !joined {
            out.push(Vec::new());
        }
        if let Some(run) = out.last_mut() {
            run.push((bucket.start_ns + history.bucket_ns / 2, [lo, mid, hi]));
        }
        last = Some(bucket.start_ns);
    }
    out
}

fn panel(report: &PeriodReport, t: &TargetReport, p: &Panel) -> String {
    let (w, h) = (720.0, 150.0);
    let (left, right, top, bottom) = (70.0, 10.0, 18.0, 22.0);
    let raw = runs(&t.raw.history, |b| {
        b.has(p.value).then(|| {
            (
                b.min[p.value],
                b.mean(p.value).unwrap_or(0.0),
                b.max[p.value],
            )
        })
    });
    let filtered = runs(&t.filtered.history, |b| {
        let mean = b.mean(p.value)?;
        let sigma = b.mean(p.sigma).unwrap_or(0.0) * p.sigma_scale;
        Some((mean - sigma, mean, mean + sigma))
    });
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for run in raw.iter().chain(&filtered) {
        for (_, [a, _, c]) in run {
            lo = lo.min(*a);
            hi = hi.max(*c);
        }
    }
    if !lo.is_finite() || !hi.is_finite() {
        return String::new();
    }
    if hi - lo < 1e-9 {
        (lo, hi) = (lo - 0.5, hi + 0.5);
    }
    let pad = 0.05 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let span_ns = (report.to_ns - report.from_ns).max(1) as f64;
    let x = |t_ns: i64| left + (w - left - right) * ((t_ns - report.from_ns) as f64 / span_ns);
    let y = |v: f64| top + (h - top - bottom) * (hi - v) / (hi - lo);
    let mut svg = Svg::new(w, h, w);
    svg.rect(
        left,
        top,
        w - left - right,
        h - top - bottom,
        "none",
        Some("#bbb"),
    );
    // The path through one of a run's three values (0 low, 1 middle, 2 high), forwards or
    // backwards, its first point a move when `start`.
    let trace =
        |d: &mut String, run: &[(i64, [f64; 3])], which: usize, forwards: bool, start: bool| {
            let points: Box<dyn Iterator<Item = &(i64, [f64; 3])>> = if forwards {
                Box::new(run.iter())
            } else {
                Box::new(run.iter().rev())
            };
            for (i, (t, v)) in points.enumerate() {
                let step = if i == 0 && start { 'M' } else { 'L' };
                let _ = write!(d, "{step}{:.1},{:.1}", x(*t), y(v[which]));
            }
        };
    // A band from the high values forwards and back along the low ones.
    let band = |run: &[(i64, [f64; 3])]| -> String {
        let mut d = String::new();
        trace(&mut d, run, 2, true, true);
        trace(&mut d, run, 0, false, false);
        d.push('Z');
        d
    };
    for run in &raw {
        svg.path(&band(run), "#d5d5d5", None);
    }
    for run in &filtered {
        svg.path(&band(run), "rgba(52,120,200,0.35)", None);
        let mut line = String::new();
        trace(&mut line, run, 1, true, true);
        svg.path(&line, "none", Some("#1f4e8c"));
    }
    svg.text(4.0, 12.0, 11.0, p.label);
    svg.text(4.0, top + 10.0, 10.0, &format!("{hi:.4}"));
    svg.text(4.0, h - bottom, 10.0, &format!("{lo:.4}"));
    svg.text(left, h - 6.0, 10.0, &format_ns(report.from_ns));
    svg.text(w - right - 190.0, h - 6.0, 10.0, &format_ns(report.to_ns));
    svg.finish(&format!("{}: {}", t.name, p.label))
}

fn stats_table(b: &mut String, t: &TargetReport) {
    b.push_str(
        "<h3>Statistics of the period</h3>\n<table><tr><th class=\"l\">results</th>\
         <th class=\"l\">quantity</th><th class=\"l\">statistic</th><th>x</th><th>y</th>\
         <th>z</th></tr>\n",
    );
    for (source, window) in [("raw", &t.raw), ("filtered", &t.filtered)] {
        let Some(stats) = window.stats else {
            let _ = writeln!(
                b,
                "<tr><td class=\"l\">{source}</td><td class=\"l\" colspan=\"5\">no result</td></tr>"
            );
            continue;
        };
        let expected = stats
            .repeatability
            .map(|r| (r.expected_euler_rms_deg, r.expected_t_rms_mm));
        for (quantity, name, c, exp) in [
            (
                Quantity::EulerDeg,
                "euler_deg",
                &stats.euler_deg,
                expected.map(|e| e.0),
            ),
            (
                Quantity::TranslationMm,
                "t_mm",
                &stats.t_mm,
                expected.map(|e| e.1),
            ),
        ] {
            let rows: [(&str, Option<[f64; 3]>); 5] = [
                ("min", Some(c.min)),
                ("max", Some(c.max)),
                ("mean", Some(c.mean)),
                ("rms", Some(c.rms)),
                ("expected_rms", exp),
            ];
            for (statistic, values) in rows {
                let Some(values) = values else { continue };
                let _ = write!(
                    b,
                    "<tr><td class=\"l\">{source}</td><td class=\"l\">{name}</td><td class=\"l\">{statistic}</td>"
                );
                for (axis, v) in values.iter().enumerate() {
                    let _ = write!(
                        b,
                        "<td id=\"{}\">{}</td>",
                        escape(&cell_id(&t.name, source, name, statistic, axis)),
                        figure(*v, quantity)
                    );
                }
                b.push_str("</tr>\n");
            }
        }
    }
    b.push_str("</table>\n");
    if let Some(r) = t.raw.stats.and_then(|s| s.repeatability) {
        let _ = writeln!(
            b,
            "<p class=\"verdict {}\">Repeatability of the raw results: chi-square {:.1} on {} \
             degrees of freedom against {:.1} (99.9 %): {}.</p>",
            if r.exceeded() { "bad" } else { "good" },
            r.chi2,
            r.dof,
            r.threshold,
            if r.exceeded() {
                "the scatter exceeds what the model's noise explains (a pixel sigma or a link's \
                 sigma set too small, or something that moves)"
            } else {
                "the scatter is what the model's noise explains"
            }
        );
    }
}

/// The least-squares slope (per day) of a component's bucket means, each weighted by its
/// count, and the change it makes over the period; `None` with fewer than two buckets.
pub fn trend_per_day(history: &History, component: usize) -> Option<f64> {
    let points: Vec<(f64, f64, f64)> = history
        .buckets
        .iter()
        .filter_map(|b| {
            let n = if (6..12).contains(&component) {
                b.n_def
            } else {
                b.n
            };
            b.mean(component)
                .map(|m| (b.start_ns as f64 / 86_400e9, m, n as f64))
        })
        .collect();
    if points.len() < 2 {
        return None;
    }
    let w: f64 = points.iter().map(|p| p.2).sum();
    let tm = points.iter().map(|p| p.2 * p.0).sum::<f64>() / w;
    let vm = points.iter().map(|p| p.2 * p.1).sum::<f64>() / w;
    let sxx: f64 = points.iter().map(|p| p.2 * (p.0 - tm).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| p.2 * (p.0 - tm) * (p.1 - vm)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

fn trend_table(b: &mut String, t: &TargetReport) {
    let deformation = t.shows_deformation();
    let rates: Vec<Option<f64>> = panels(deformation)
        .iter()
        .map(|p| trend_per_day(&t.filtered.history, p.value))
        .collect();
    if rates.iter().all(Option::is_none) {
        return;
    }
    let _ = writeln!(
        b,
        "<h3>Trend</h3>\n<p>The {} filtered rate of change per day: the slope of a least-squares line \
         through the buckets' means, each weighted by its results. It describes the period; \
         the filtered results are correlated in time, so it carries no sigma of its own.</p>\n\
         <table><tr>{}</tr><tr>{}</tr></table>",
        if deformation {
            "deformation's"
        } else {
            "pose's"
        },
        panels(deformation)
            .iter()
            .map(|p| format!("<th>{}</th>", escape(p.label)))
            .collect::<String>(),
        rates
            .iter()
            .map(|r| match r {
                Some(r) => format!("<td>{r:.4}</td>"),
                None => "<td></td>".to_owned(),
            })
            .collect::<String>()
    );
}

fn alarms_table(b: &mut String, t: &TargetReport) {
    b.push_str("<h3>Alarms</h3>\n");
    if t.alarms.is_empty() {
        b.push_str("<p>No alarm changed level in the period.</p>\n");
        return;
    }
    b.push_str(
        "<table><tr><th class=\"l\">time</th><th class=\"l\">kind</th><th class=\"l\">level</th>\
         <th class=\"l\">what</th><th class=\"l\">acknowledged</th></tr>\n",
    );
    for a in &t.alarms {
        let tr = &a.transition;
        let ack = match &a.ack {
            Some(ack) => format!(
                "by {} at {}{}",
                escape(&ack.by),
                escape(&format_ns(ack.at_ns)),
                ack.note
                    .as_deref()
                    .map(|n| format!(": {}", escape(n)))
                    .unwrap_or_default()
            ),
            None if tr.to == Level::None => "(a return to normal)".to_owned(),
            None => "<strong>not acknowledged</strong>".to_owned(),
        };
        let _ = writeln!(
            b,
            "<tr><td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l\">{} &rarr; {}</td>\
             <td class=\"l\">{}</td><td class=\"l\">{}</td></tr>",
            escape(&format_ns(tr.time_ns)),
            tr.kind.name(),
            tr.from.name(),
            tr.to.name(),
            escape(&tr.message),
            ack
        );
    }
    b.push_str("</table>\n");
}

fn gaps_table(b: &mut String, t: &TargetReport) {
    b.push_str("<h3>Gaps in the data</h3>\n");
    let g = &t.gaps;
    if g.count == 0 {
        b.push_str("<p>No gap: the raw results follow one another through the period.</p>\n");
        return;
    }
    let _ = writeln!(
        b,
        "<p>{}{} gap{}, {:.0} s in all{}.</p>",
        if g.truncated { "At least " } else { "" },
        g.count,
        if g.count == 1 { "" } else { "s" },
        g.total_ns as f64 / 1e9,
        if g.listed.len() < g.count {
            format!("; the {} longest are listed", g.listed.len())
        } else {
            String::new()
        }
    );
    b.push_str(
        "<table><tr><th class=\"l\">from</th><th class=\"l\">to</th><th>length (s)</th>\
         <th class=\"l\">what the links stored in it</th></tr>\n",
    );
    for gap in &g.listed {
        let _ = writeln!(
            b,
            "<tr><td class=\"l\">{}</td><td class=\"l\">{}</td><td>{:.1}</td><td class=\"l\">{}</td></tr>",
            escape(&format_ns(gap.from_ns)),
            escape(&format_ns(gap.to_ns)),
            (gap.to_ns - gap.from_ns) as f64 / 1e9,
            escape(&gap_cause(gap))
        );
    }
    b.push_str("</table>\n");
}

/// What the links' samples say of a gap.
pub fn gap_cause(gap: &Gap) -> String {
    if gap.links.iter().all(|l| l.samples == 0) {
        return "no link of its chain stored a sample: nothing was measured (a camera \
                stopped, the marker out of view, or the service not running)"
            .to_owned();
    }
    gap.links
        .iter()
        .map(|l| match (l.samples, l.outliers) {
            (0, _) => format!("{}: no sample", l.link),
            (n, o) if o == n => format!("{}: all {n} samples rejected as outliers", l.link),
            (n, 0) => format!("{}: {n} samples", l.link),
            (n, o) => format!("{}: {n} samples, {o} rejected as outliers", l.link),
        })
        .collect::<Vec<_>>()
        .join("; ")
}

fn budget_table(b: &mut String, t: &TargetReport) {
    b.push_str("<h3>Uncertainty budget</h3>\n");
    let Some(snap) = &t.budget else {
        b.push_str("<p>The target has no filtered result yet: no budget.</p>\n");
        return;
    };
    let budget = &snap.budget;
    let sig = budget_sigmas(budget.total);
    let rnd = budget_sigmas(budget.part_variance(UncertaintyPart::Random));
    let sys = budget_sigmas(budget.part_variance(UncertaintyPart::Systematic));
    let _ = writeln!(
        b,
        "<p>Of the newest filtered result ({}); rotation in arc-seconds, translation in mm.</p>\n\
         <table><tr><th class=\"l\">contributor</th><th class=\"l\">part</th><th>rx</th>\
         <th>ry</th><th>rz</th><th>tx</th><th>ty</th><th>tz</th><th>largest share</th></tr>",
        escape(&format_ns(snap.time_ns))
    );
    let row = |b: &mut String, name: &str, part: &str, s: [f64; 6], share: Option<f64>| {
        let _ = write!(
            b,
            "<tr><td class=\"l\">{}</td><td class=\"l\">{part}</td>",
            escape(name)
        );
        for (a, v) in s.iter().enumerate() {
            let _ = write!(
                b,
                "<td>{}</td>",
                figure(
                    *v,
                    if a < 3 {
                        Quantity::RotationArcsec
                    } else {
                        Quantity::TranslationMm
                    }
                )
            );
        }
        let _ = writeln!(
            b,
            "<td>{}</td></tr>",
            share
                .map(|s| format!("{:.0} %", 100.0 * s))
                .unwrap_or_default()
        );
    };
    for (line, share) in budget.lines_by_share() {
        let name = snap.names.get(&line.contributor).map_or("", String::as_str);
        row(
            b,
            &format!("{} {}", line.contributor.kind().name(), name),
            line.contributor.part().name(),
            budget_sigmas(line.variance),
            Some(share.iter().copied().fold(0.0, f64::max)),
        );
    }
    row(b, "random part", "", rnd, None);
    row(b, "systematic part", "", sys, None);
    row(b, "whole sigma", "", sig, None);
    b.push_str("</table>\n");
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bucket(start_s: i64, n: i64, value: f64, component: usize) -> Bucket {
        let mut b = Bucket::empty(start_s * 1_000_000_000);
        b.n = n;
        b.n_def = n;
        b.min[component] = value;
        b.max[component] = value;
        b.sum[component] = value * n as f64;
        b
    }

    fn history(buckets: Vec<Bucket>, bucket_s: i64) -> History {
        History {
            window_ns: None,
            bucket_ns: bucket_s * 1_000_000_000,
            resolution_s: None,
            buckets,
        }
    }

    #[test]
    fn the_trend_is_the_slope_of_a_line_through_the_means() {
        // 2 arc-seconds a day, sampled hourly with unequal counts: exactly that slope.
        let c = 6;
        let buckets: Vec<Bucket> = (0..48)
            .map(|h| bucket(h * 3600, 1 + h % 5, 5.0 + 2.0 * h as f64 / 24.0, c))
            .collect();
        let slope = trend_per_day(&history(buckets, 3600), c).expect("a trend");
        assert!((slope - 2.0).abs() < 1e-9, "{slope}");
        // One bucket makes no line.
        assert_eq!(
            trend_per_day(&history(vec![bucket(0, 3, 1.0, c)], 3600), c),
            None
        );
    }

    #[test]
    fn a_run_breaks_where_buckets_are_missing() {
        let c = 0;
        let starts = [0, 10, 20, 50, 60];
        let buckets = starts.iter().map(|&s| bucket(s, 1, 1.0, c)).collect();
        let h = history(buckets, 10);
        let runs = runs(&h, |b| b.mean(c).map(|m| (m, m, m)));
        let lengths: Vec<usize> = runs.iter().map(Vec::len).collect();
        assert_eq!(lengths, [3, 2]);
    }

    #[test]
    fn a_gap_says_what_each_link_stored() {
        let link = |samples, outliers| LinkInGap {
            link: "C1_from_B".to_owned(),
            samples,
            outliers,
        };
        let gap = |links| Gap {
            from_ns: 0,
            to_ns: 1,
            links,
        };
        assert!(gap_cause(&gap(vec![link(0, 0)])).starts_with("no link of its chain"));
        assert_eq!(
            gap_cause(&gap(vec![link(4, 4)])),
            "C1_from_B: all 4 samples rejected as outliers"
        );
        assert_eq!(
            gap_cause(&gap(vec![link(0, 0), link(9, 2)])),
            "C1_from_B: no sample; C1_from_B: 9 samples, 2 rejected as outliers"
        );
    }

    #[test]
    fn durations_read_in_the_unit_that_fits() {
        assert_eq!(duration_text(40_000_000), "40 ms");
        assert_eq!(duration_text(12_500_000_000), "12.5 s");
        assert_eq!(duration_text(258_000_000_000), "4.3 min");
        assert_eq!(duration_text(432_000_000_000_000), "5.0 d");
    }
}
