//! The acceptance section of a period's report: the acceptance in force at the period's end,
//! where it stands now, and each step's figures against its limits (see
//! [`crate::acceptance`]).

use super::escape;
use crate::acceptance::{MoveFigures, Standing, StillFigures};
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
    /// Its steps.
    pub steps: Vec<AcceptanceStep>,
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
    let now = match a.standing {
        Standing::Valid => "it holds".to_owned(),
        Standing::Due => format!("it is due for reverification since {}", format_ns(a.due_ns)),
        Standing::NoLongerHolds => format!("it no longer holds: {}", a.changed.join("; ")),
        Standing::Failed => "it did not pass".to_owned(),
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
                "{} results; deviation {} &plusmn; {} (u); |deviation| + 2u within {}",
                m.count,
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
