//! Reports people file and read: self-contained HTML pages whose pictures are SVG drawn here,
//! so a page needs no script, no network and no other file to be read or printed.
//!
//! [`calibration`] is a camera calibration's report, [`period`] a period's report of the
//! installation's targets. The helpers below are what every report
//! shares: text escaped for HTML, a page's frame and style, and an SVG canvas in the units of
//! what it draws.

pub mod acceptance;
pub mod calibration;
pub mod period;

use std::fmt::Write as _;

/// `text` escaped for HTML text and attribute values.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A whole page: `title` and `body` (HTML) with the reports' print-friendly style.
pub(crate) fn page(title: &str, body: &str) -> String {
    format!(
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>{}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n{body}</body>\n</html>\n",
        escape(title)
    )
}

/// The Content-Security-Policy source that admits the reports' style sheet (`'sha256-...'`):
/// a page that shows a report it fetched (the dashboard, which opens it from a blob) lists it
/// so that the report keeps its style under the page's own policy.
pub fn style_hash_source() -> String {
    use base64::Engine as _;
    use sha2::Digest as _;
    let digest = sha2::Sha256::digest(STYLE.as_bytes());
    format!(
        "'sha256-{}'",
        base64::engine::general_purpose::STANDARD.encode(digest)
    )
}

/// The policy a report is served with: its own style, its SVG, nothing else (no script, no
/// connection, no form, no framing).
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; style-src 'unsafe-inline'; \
     img-src data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

const STYLE: &str = "\
body{font-family:system-ui,sans-serif;margin:2em auto;max-width:60em;color:#222;line-height:1.4}\
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ccc}\
table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:0.2em 0.6em;\
text-align:right}th{background:#f3f3f3}td.l,th.l{text-align:left}\
figure{margin:1em 0;break-inside:avoid}figcaption,p.caption{font-size:0.9em;color:#444}\
svg{max-width:100%;height:auto;border:1px solid #ddd;background:#fff}\
p.verdict{padding:0.4em 0.6em;background:#f6f6f6;border-left:4px solid #888}\
p.bad{border-left-color:#c0392b}p.good{border-left-color:#27ae60}\
@media print{body{margin:0;max-width:none}h2{break-after:avoid}}";

/// An SVG picture of a `width` x `height` region (in the units of what is drawn, pixels of an
/// image or millimetres of a plate), scaled to `view_px` across.
pub(crate) struct Svg {
    body: String,
    width: f64,
    height: f64,
    view_px: f64,
}

impl Svg {
    /// An empty picture.
    pub(crate) fn new(width: f64, height: f64, view_px: f64) -> Self {
        Self {
            body: String::new(),
            width,
            height,
            view_px,
        }
    }

    /// How many units of the region one pixel of the picture is (for strokes and text).
    pub(crate) fn unit(&self) -> f64 {
        self.width / self.view_px
    }

    /// A rectangle filled with `fill`, outlined by `stroke` when given.
    pub(crate) fn rect(
        &mut self,
        x: f64,
        y: f64,
        w: f64,
        h: f64,
        fill: &str,
        stroke: Option<&str>,
    ) {
        let u = self.unit();
        let _ = write!(
            self.body,
            "<rect x=\"{x:.3}\" y=\"{y:.3}\" width=\"{w:.3}\" height=\"{h:.3}\" fill=\"{fill}\""
        );
        if let Some(s) = stroke {
            let _ = write!(self.body, " stroke=\"{s}\" stroke-width=\"{:.3}\"", u);
        }
        self.body.push_str("/>");
    }

    /// A dot of `radius_px` picture pixels.
    pub(crate) fn dot(&mut self, x: f64, y: f64, radius_px: f64, fill: &str) {
        let _ = write!(
            self.body,
            "<circle cx=\"{x:.3}\" cy=\"{y:.3}\" r=\"{:.3}\" fill=\"{fill}\"/>",
            radius_px * self.unit()
        );
    }

    /// A circle of `radius` units, outlined.
    pub(crate) fn ring(&mut self, x: f64, y: f64, radius: f64, stroke: &str) {
        let _ = write!(
            self.body,
            "<circle cx=\"{x:.3}\" cy=\"{y:.3}\" r=\"{radius:.3}\" fill=\"none\" stroke=\"{stroke}\" stroke-width=\"{:.3}\"/>",
            self.unit()
        );
    }

    /// An arrow from `(x, y)` by `(dx, dy)` units, with a head when it is long enough to carry
    /// one.
    pub(crate) fn arrow(&mut self, x: f64, y: f64, dx: f64, dy: f64, stroke: &str) {
        let u = self.unit();
        let (x2, y2) = (x + dx, y + dy);
        let _ = write!(
            self.body,
            "<line x1=\"{x:.3}\" y1=\"{y:.3}\" x2=\"{x2:.3}\" y2=\"{y2:.3}\" stroke=\"{stroke}\" stroke-width=\"{:.3}\"/>",
            1.2 * u
        );
        let length = (dx * dx + dy * dy).sqrt();
        if length > 6.0 * u {
            let (ux, uy) = (dx / length, dy / length);
            let head = 4.0 * u;
            let (lx, ly) = (x2 - head * (ux + 0.5 * uy), y2 - head * (uy - 0.5 * ux));
            let (rx, ry) = (x2 - head * (ux - 0.5 * uy), y2 - head * (uy + 0.5 * ux));
            let _ = write!(
                self.body,
                "<path d=\"M{lx:.3},{ly:.3}L{x2:.3},{y2:.3}L{rx:.3},{ry:.3}\" fill=\"none\" stroke=\"{stroke}\" stroke-width=\"{:.3}\"/>",
                1.2 * u
            );
        }
    }

    /// A path (`d` in the region's units) filled with `fill`, stroked by `stroke` one picture
    /// pixel wide when given.
    pub(crate) fn path(&mut self, d: &str, fill: &str, stroke: Option<&str>) {
        let _ = write!(self.body, "<path d=\"{d}\" fill=\"{fill}\"");
        if let Some(s) = stroke {
            let _ = write!(
                self.body,
                " stroke=\"{s}\" stroke-width=\"{:.3}\"",
                self.unit()
            );
        }
        self.body.push_str("/>");
    }

    /// Text of `size_px` picture pixels at `(x, y)`.
    pub(crate) fn text(&mut self, x: f64, y: f64, size_px: f64, text: &str) {
        let _ = write!(
            self.body,
            "<text x=\"{x:.3}\" y=\"{y:.3}\" font-size=\"{:.3}\" font-family=\"sans-serif\">{}</text>",
            size_px * self.unit(),
            escape(text)
        );
    }

    /// The picture as an SVG element, `label` its accessible name.
    pub(crate) fn finish(self, label: &str) -> String {
        let height_px = self.view_px * self.height / self.width;
        format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" role=\"img\" aria-label=\"{}\" \
             viewBox=\"0 0 {} {}\" width=\"{:.0}\" height=\"{:.0}\">{}</svg>",
            escape(label),
            self.width,
            self.height,
            self.view_px,
            height_px,
            self.body
        )
    }
}

/// A colour from blue (0) through green to red (1), for values on a scale.
pub(crate) fn ramp(t: f64) -> String {
    let t = t.clamp(0.0, 1.0);
    format!("hsl({:.0},75%,50%)", 240.0 * (1.0 - t))
}

/// A distinct colour for the `i`-th of `n` series.
pub(crate) fn series(i: usize, n: usize) -> String {
    format!("hsl({:.0},70%,42%)", 360.0 * i as f64 / n.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_escaped_for_html() {
        assert_eq!(
            escape("a<b & \"c\" 'd'>"),
            "a&lt;b &amp; &quot;c&quot; &#39;d&#39;&gt;"
        );
    }

    #[test]
    fn a_picture_keeps_its_region_and_aspect() {
        let mut svg = Svg::new(1280.0, 1024.0, 640.0);
        assert_eq!(svg.unit(), 2.0);
        svg.arrow(10.0, 10.0, 100.0, 0.0, "red");
        let out = svg.finish("x <y>");
        assert!(out.contains("viewBox=\"0 0 1280 1024\""), "{out}");
        assert!(out.contains("width=\"640\" height=\"512\""), "{out}");
        assert!(out.contains("aria-label=\"x &lt;y&gt;\""), "{out}");
        // A long arrow has a head.
        assert!(out.contains("<path d=\"M"), "{out}");
    }
}
