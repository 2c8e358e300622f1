//! The acceptance section of a period's report (the acceptance in force at the period's end,
//! where it stands now, and each step's figures against its limits), and an acceptance's
//! certificate: the page a metrologist signs (see [`crate::acceptance`]).

use super::{escape, page};
use crate::acceptance::{COVERAGE_FACTOR, Limits, MoveFigures, Standing, StillFigures};
use crate::clock::format_ns;
use std::fmt::Write as _;

/// What a report says of the rig's acceptance.
#[derive(Debug, Clone)]
pub enum AcceptanceSection {
    /// The installation states no procedure (`[acceptance]`).
    NotStated,
    /// None was recorded by the period's end.
    NoneRecorded,
    /// The newest recorded by the period's end.
    Latest(Box<AcceptanceLine>),
}

/// An acceptance as a report shows it.
#[derive(Debug, Clone)]
pub struct AcceptanceLine {
    /// Its id.
    pub id: i64,
    /// When it was recorded (ns, the service's clock).
    pub at_ns: i64,
    /// Who ran it.
    pub by: String,
    /// Their note.
    pub note: Option<String>,
    /// Whether it passed.
    pub passed: bool,
    /// Where it stands when the report is made.
    pub standing: Standing,
    /// When reverification is due (ns).
    pub due_ns: i64,
    /// What changed since that it no longer holds.
    pub changed: Vec<String>,
    /// The names of its failed steps.
    pub failed: Vec<String>,
    /// Its steps.
    pub steps: Vec<AcceptanceStep>,
    /// The installation it was run on.
    pub installation: String,
    /// The limits it was judged by.
    pub limits: Limits,
    /// How long it holds (days).
    pub reverify_every_days: f64,
    /// What each target was measured with.
    pub targets: Vec<AcceptedTargetLine>,
}

/// A target as an acceptance accepted it.
#[derive(Debug, Clone)]
pub struct AcceptedTargetLine {
    /// The target.
    pub target: String,
    /// The calibrations its results were measured with.
    pub calibration_stamp: Option<i64>,
    /// The links on its paths.
    pub links: Vec<String>,
}

/// A step of an acceptance.
#[derive(Debug, Clone)]
pub struct AcceptanceStep {
    /// Its name.
    pub name: String,
    /// Whether it passed.
    pub passed: bool,
    /// Why it has no figures.
    pub problem: Option<String>,
    /// The still window's figures per target.
    pub still: Vec<(String, StillFigures)>,
    /// A move's figures.
    pub moved: Option<MoveFigures>,
}

/// Six axes as `rx, ry, rz arcsec; tx, ty, tz mm`.
fn axes(a: &[f64; 6]) -> String {
    format!(
        "{:.1}, {:.1}, {:.1} arcsec; {:.3}, {:.3}, {:.3} mm",
        a[0], a[1], a[2], a[3], a[4], a[5]
    )
}

/// Writes the section.
pub(super) fn section(b: &mut String, acceptance: &AcceptanceSection) {
    b.push_str("<h2>Acceptance</h2>\n");
    let a = match acceptance {
        AcceptanceSection::NotStated => {
            b.push_str("<p>The installation states no acceptance procedure.</p>\n");
            return;
        }
        AcceptanceSection::NoneRecorded => {
            b.push_str("<p>No acceptance of the rig was recorded by the period's end.</p>\n");
            return;
        }
        AcceptanceSection::Latest(a) => a,
    };
    verdict(b, a);
    steps_table(b, a);
}

/// Where an acceptance stands, in one paragraph.
fn verdict(b: &mut String, a: &AcceptanceLine) {
    let now = match a.standing {
        Standing::Valid => "it holds".to_owned(),
        Standing::Due => format!("it is due for reverification since {}", format_ns(a.due_ns)),
        Standing::NoLongerHolds => format!("it no longer holds: {}", a.changed.join("; ")),
        Standing::Failed => format!("it did not pass: {}", a.failed.join(", ")),
    };
    let _ = writeln!(
        b,
        "<p id=\"acceptance\" data-standing=\"{}\">Acceptance {} by {}, recorded {}{}: <b>{}</b>; \
         {}{}.</p>",
        a.standing.name(),
        a.id,
        escape(&a.by),
        escape(&format_ns(a.at_ns)),
        a.note
            .as_ref()
            .map(|n| format!(" ({})", escape(n)))
            .unwrap_or_default(),
        if a.passed { "passed" } else { "failed" },
        escape(&now),
        if a.passed && a.standing == Standing::Valid {
            format!("; reverification due {}", escape(&format_ns(a.due_ns)))
        } else {
            String::new()
        },
    );
}

/// Each step's result and figures.
fn steps_table(b: &mut String, a: &AcceptanceLine) {
    b.push_str(
        "<table><tr><th class=\"l\">step</th><th class=\"l\">result</th>\
         <th class=\"l\">figures (rotation x, y, z; translation x, y, z)</th></tr>\n",
    );
    for s in &a.steps {
        let mut figures = Vec::new();
        if let Some(p) = &s.problem {
            figures.push(escape(p));
        }
        for (target, f) in &s.still {
            figures.push(format!(
                "{}: {} results, rms {} (expected {}; limit {}); scatter chi-square {:.0} of at most {:.0}",
                escape(target),
                f.count,
                axes(&f.rms),
                axes(&f.expected_rms),
                axes(&f.limit),
                f.chi2,
                f.threshold
            ));
        }
        if let Some(m) = &s.moved {
            figures.push(format!(
                "{} results; stated {}; deviation {} &plusmn; {} (u); |deviation| + 2u within {}",
                m.count,
                axes(&m.stated),
                axes(&m.deviation),
                axes(&m.uncertainty),
                axes(&m.limit)
            ));
        }
        let _ = writeln!(
            b,
            "<tr><td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l\">{}</td></tr>",
            escape(&s.name),
            if s.passed { "pass" } else { "FAIL" },
            figures.join("<br>")
        );
    }
    b.push_str("</table>\n");
}

/// An acceptance's certificate: the rig, what was accepted, the limits and the rule they were
/// applied by, every step's figures, and lines to sign. Printable; no script.
pub fn certificate(a: &AcceptanceLine, generated_ns: i64) -> String {
    let title = format!("Acceptance certificate {}", a.id);
    let mut b = String::new();
    let _ = writeln!(
        b,
        "<h1>{}</h1>\n<p>Installation <code>{}</code>; printed {}.</p>",
        escape(&title),
        escape(&a.installation),
        escape(&format_ns(generated_ns))
    );
    verdict(&mut b, a);
    b.push_str(
        "<h2>What was accepted</h2>\n<table><tr><th class=\"l\">target</th>\
        <th class=\"l\">calibrations measured with (stamp)</th><th class=\"l\">links</th></tr>\n",
    );
    for t in &a.targets {
        let _ = writeln!(
            b,
            "<tr><td class=\"l\">{}</td><td class=\"l\">{}</td><td class=\"l\">{}</td></tr>",
            escape(&t.target),
            t.calibration_stamp.map_or_else(
                || "changed during the run".to_owned(),
                |s| format!("{s:016x}")
            ),
            escape(&t.links.join(", "))
        );
    }
    b.push_str("</table>\n");
    let l = &a.limits;
    let _ = writeln!(
        b,
        "<h2>Limits and decision rule</h2>\n<p>Still: the rms of each axis of the raw results \
         about their mean at most {} arc-seconds (rotation) and {} mm (translation), and their \
         scatter within what their sigmas allow (chi-square under its 0.999 quantile). Known \
         moves: on each axis, |measured &minus; stated| + {COVERAGE_FACTOR} u at most {} \
         arc-seconds and {} mm, u the deviation's standard uncertainty (conformance proven with \
         the expanded uncertainty, ISO 14253-1). The acceptance holds {} days, and no longer \
         once a link of a target is calibrated again or reset.</p>",
        l.still_rms_arcsec, l.still_rms_mm, l.move_arcsec, l.move_mm, a.reverify_every_days
    );
    b.push_str("<h2>Steps</h2>\n");
    steps_table(&mut b, a);
    b.push_str(
        "<h2>Signatures</h2>\n<table class=\"signatures\"><tr><th class=\"l\">role</th>\
         <th class=\"l\">name</th><th class=\"l\">date</th><th class=\"l\">signature</th></tr>\n",
    );
    for role in ["Performed by", "Checked by", "Accepted for the owner by"] {
        let _ = writeln!(
            b,
            "<tr><td class=\"l\">{role}</td><td class=\"l\">&nbsp;</td><td class=\"l\">&nbsp;</td>\
             <td class=\"l\">&nbsp;</td></tr>"
        );
    }
    b.push_str("</table>\n");
    page(&title, &b)
}
