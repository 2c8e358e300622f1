//! A camera calibration's report: one HTML page with what a photogrammetrist signs a
//! calibration by.
//!
//! * the intrinsics with their sigmas (as reported: cross-validated), the lens model, the
//!   plate's shape, the fit's RMS and variance factor, and every judgement in words (the
//!   cross-validation, the plate's sag, the residuals' structure, the warnings);
//! * the residual vectors of every view over the image, coloured by view and magnified;
//! * the coverage of the image by plate points, per cell of the residuals' grid;
//! * the binned mean residual, each bin's arrow with its one-sigma circle, red where the bin's
//!   `z^2` is over the chi-square quantile of two degrees of freedom at 99.9 % (13.8);
//! * the uncertainty of projection over the image: for the ray through each cell's centre, the
//!   largest standard deviation (px) of its pixel under the intrinsics' covariance,
//!   `sqrt(lambda_max(J C J^T))`, `J = d(u, v) / d(intrinsics)` (the ray fixed in the camera's
//!   frame; the camera's pose is not re-aligned to the views, so where the principal point
//!   trades with the views' rotations it says more than a re-aligned projection would);
//! * the cross-validation's table, the plate's fitted (or tested) sag drawn over the plate, and
//!   each view's fit.

use super::{Svg, escape, page, ramp, series};
use crate::geometry::Vec3;
use crate::vision::{
    CameraCalibration, CrossValidationVerdict, INTRINSICS, Intrinsic, Plate, PlateShape, SagBasis,
    describe_cross_validation, describe_plate_shape, describe_residual_structure,
};
use nalgebra::{SMatrix, Vector2};
use std::fmt::Write as _;

/// The chi-square quantile of two degrees of freedom at 99.9 %: a bin whose mean's `z^2` is over
/// it is drawn red.
const BIN_Z2_LIMIT: f64 = 13.82;
/// Columns of the projection-uncertainty map.
const UNCERTAINTY_COLUMNS: usize = 16;
/// Width of each picture (px).
const PICTURE_PX: f64 = 720.0;

/// What the report is made of.
pub struct CalibrationReport<'a> {
    /// What the page is about (a camera's name, or the frames' folder).
    pub title: &'a str,
    /// The calibration.
    pub calibration: &'a CameraCalibration,
    /// The plate it was calibrated with.
    pub plate: &'a Plate,
    /// Each view's name (its frame file), in the calibration's order.
    pub view_names: &'a [String],
    /// What else the user should know (frames left out, lossy files), one line each.
    pub notes: &'a [String],
    /// When it was made (text).
    pub made: &'a str,
}

/// The report's page.
pub fn calibration_report(r: &CalibrationReport<'_>) -> String {
    let c = r.calibration;
    let mut body = String::new();
    let _ = writeln!(
        body,
        "<h1>Camera calibration: {}</h1>\n<p>Made {} from {} views of a {} x {} plate ({} mm \
         apart), {} x {} px. Lens model <b>{}</b>; plate fitted <b>{}</b>.</p>",
        escape(r.title),
        escape(r.made),
        c.views.len(),
        r.plate.rows(),
        r.plate.cols(),
        r.plate.spacing_mm(),
        c.camera.width_px,
        c.camera.height_px,
        c.model,
        c.plate_shape
    );
    summary(&mut body, c);
    verdicts(&mut body, r);
    let _ = writeln!(body, "<h2>Residuals over the image</h2>");
    body.push_str(&figure(
        &residual_vectors(r),
        "Every point's residual (detected minus predicted), magnified, coloured by view.",
    ));
    body.push_str(&figure(
        &coverage(c),
        "The image covered by plate points: every detection, and the points per cell of the \
         residuals' grid (darker: more). Distortion where no point fell is extrapolated.",
    ));
    if let Some(picture) = binned_means(c) {
        body.push_str(&figure(
            &picture,
            "The mean residual of each cell with five points or more, magnified, with its \
             one-sigma circle; red where its z² is over 13.8 (chi-square, two degrees of \
             freedom, 99.9 %).",
        ));
    }
    let _ = writeln!(body, "<h2>Uncertainty of projection</h2>");
    body.push_str(&figure(
        &projection_uncertainty(c),
        "The largest standard deviation (px) of the pixel of a ray fixed in the camera frame, \
         under the reported covariance of the intrinsics, per cell.",
    ));
    cross_validation_table(&mut body, c);
    plate_shape(&mut body, r);
    views_table(&mut body, r);
    page(&format!("Camera calibration: {}", r.title), &body)
}

fn figure(svg: &str, caption: &str) -> String {
    format!(
        "<figure>{svg}<figcaption>{}</figcaption></figure>\n",
        escape(caption)
    )
}

fn summary(body: &mut String, c: &CameraCalibration) {
    let _ = writeln!(
        body,
        "<h2>Intrinsics</h2>\n<table><tr><th class=\"l\">parameter</th><th>value</th>\
         <th>sigma</th></tr>"
    );
    let values = crate::vision::intrinsics_of(&c.camera);
    for p in Intrinsic::of_model(c.model) {
        let i = p.index();
        let sigma = if c.fixed.contains(p) {
            "fixed".to_owned()
        } else {
            format!("{:.6}", c.sigma[i])
        };
        let _ = writeln!(
            body,
            "<tr><td class=\"l\">{}</td><td>{:.6}</td><td>{sigma}</td></tr>",
            p.name(),
            values[i]
        );
    }
    let _ = writeln!(
        body,
        "</table>\n<table><tr><th class=\"l\">RMS (px)</th><td>{:.4}</td></tr>\
         <tr><th class=\"l\">variance factor</th><td>{:.3}</td></tr>\
         <tr><th class=\"l\">pixel_sigma (px)</th><td>{:.4}</td></tr>\
         <tr><th class=\"l\">iterations</th><td>{}</td></tr></table>",
        c.rms_px,
        c.variance_factor,
        c.pixel_sigma(),
        c.iterations
    );
    if !c.correlations.is_empty() {
        let pairs: Vec<String> = c
            .correlations
            .iter()
            .map(|k| format!("{}-{} {:+.3}", k.a, k.b, k.r))
            .collect();
        let _ = writeln!(
            body,
            "<p>Correlated over 0.9: {}.</p>",
            escape(&pairs.join(", "))
        );
    }
}

fn verdicts(body: &mut String, r: &CalibrationReport<'_>) {
    let c = r.calibration;
    let _ = writeln!(body, "<h2>Judgements</h2>");
    let mut line = |good: bool, text: &str| {
        let _ = writeln!(
            body,
            "<p class=\"verdict {}\">{}</p>",
            if good { "good" } else { "bad" },
            escape(text)
        );
    };
    match &c.cross_validation {
        Some(check) => line(
            check.verdict == CrossValidationVerdict::Honest && !check.model_misfit,
            &describe_cross_validation(check),
        ),
        None => line(
            false,
            "not cross-validated: the covariance is the fit's own",
        ),
    }
    line(
        true,
        &describe_plate_shape(c.plate_shape, c.plate_warp.as_ref()),
    );
    if let Some(s) = &c.residual_structure {
        line(!s.significant, &describe_residual_structure(s, c.model));
    }
    for w in &c.warnings {
        line(false, &w.to_string());
    }
    for note in r.notes {
        line(false, note);
    }
}

/// The image's outline, its size in px.
fn image_canvas(c: &CameraCalibration) -> Svg {
    let (w, h) = (f64::from(c.camera.width_px), f64::from(c.camera.height_px));
    let mut svg = Svg::new(w, h, PICTURE_PX);
    svg.rect(0.0, 0.0, w, h, "#fafafa", Some("#999"));
    svg
}

fn residual_vectors(r: &CalibrationReport<'_>) -> String {
    let c = r.calibration;
    let mut svg = image_canvas(c);
    let mut lengths: Vec<f64> = c
        .residuals
        .iter()
        .flatten()
        .map(|p| p.residual_px.norm())
        .collect();
    lengths.sort_by(f64::total_cmp);
    let p95 = lengths
        .get(lengths.len() * 95 / 100)
        .copied()
        .unwrap_or(0.0)
        .max(1e-6);
    // The 95th percentile drawn as 3 % of the image's width.
    let scale = (0.03 * f64::from(c.camera.width_px) / p95).round().max(1.0);
    let n = c.residuals.len();
    for (v, points) in c.residuals.iter().enumerate() {
        let colour = series(v, n);
        for p in points {
            let d = p.residual_px * scale;
            svg.arrow(p.at_px.x, p.at_px.y, d.x, d.y, &colour);
        }
    }
    let unit = svg.unit();
    svg.text(
        8.0 * unit,
        16.0 * unit,
        12.0,
        &format!("arrows x{scale:.0}; 95 % of residuals under {p95:.3} px"),
    );
    svg.finish("residual vectors of every view over the image")
}

/// The residuals' grid: columns and rows as [`crate::vision::STRUCTURE_BINS_X`] makes them.
fn grid(c: &CameraCalibration) -> (usize, usize, f64, f64) {
    crate::vision::structure_grid(c.camera.width_px, c.camera.height_px)
}

fn coverage(c: &CameraCalibration) -> String {
    let mut svg = image_canvas(c);
    let (cols, rows, cw, ch) = grid(c);
    let mut counts = vec![0usize; cols * rows];
    for p in c.residuals.iter().flatten() {
        let col = ((p.at_px.x / cw).floor().max(0.0) as usize).min(cols - 1);
        let row = ((p.at_px.y / ch).floor().max(0.0) as usize).min(rows - 1);
        counts[row * cols + col] += 1;
    }
    let most = counts.iter().copied().max().unwrap_or(1).max(1) as f64;
    for (i, &n) in counts.iter().enumerate() {
        let (col, row) = (i % cols, i / cols);
        let shade = 250.0 - 120.0 * n as f64 / most;
        svg.rect(
            col as f64 * cw,
            row as f64 * ch,
            cw,
            ch,
            &format!("rgb({shade:.0},{shade:.0},{:.0})", shade + 5.0),
            Some("#ddd"),
        );
        let unit = svg.unit();
        svg.text(
            col as f64 * cw + 4.0 * unit,
            row as f64 * ch + 14.0 * unit,
            11.0,
            &n.to_string(),
        );
    }
    let n = c.residuals.len();
    for (v, points) in c.residuals.iter().enumerate() {
        let colour = series(v, n);
        for p in points {
            svg.dot(p.at_px.x, p.at_px.y, 1.5, &colour);
        }
    }
    svg.finish("coverage of the image by plate points")
}

fn binned_means(c: &CameraCalibration) -> Option<String> {
    let s = c.residual_structure.as_ref()?;
    let mut svg = image_canvas(c);
    let (_, _, cw, ch) = grid(c);
    let largest = s
        .bins
        .iter()
        .map(|b| b.mean_px.norm() + b.sigma_px)
        .fold(0.0, f64::max)
        .max(1e-6);
    // The largest mean and its sigma drawn as 45 % of a cell.
    let scale = 0.45 * cw.min(ch) / largest;
    for b in &s.bins {
        let colour = if b.z2 > BIN_Z2_LIMIT {
            "#c0392b"
        } else {
            "#2c3e50"
        };
        svg.rect(
            b.centre_px.x - cw / 2.0,
            b.centre_px.y - ch / 2.0,
            cw,
            ch,
            "none",
            Some("#eee"),
        );
        svg.ring(b.centre_px.x, b.centre_px.y, b.sigma_px * scale, "#999");
        let d = b.mean_px * scale;
        svg.arrow(b.centre_px.x, b.centre_px.y, d.x, d.y, colour);
    }
    let unit = svg.unit();
    svg.text(
        8.0 * unit,
        16.0 * unit,
        12.0,
        &format!(
            "arrows x{scale:.0}; chi-square {:.1} over {} bins, at most {:.1} when the model fits",
            s.chi2,
            s.bins.len(),
            s.threshold
        ),
    );
    Some(svg.finish("binned mean residual over the image"))
}

/// The largest standard deviation (px) of the pixel of the ray through `uv_px`; `None` where
/// the pixel does not undistort.
pub fn projection_sigma_px(c: &CameraCalibration, uv_px: Vector2<f64>) -> Option<f64> {
    let xy = c.camera.undistort(uv_px).ok()?;
    let j = c.camera.intrinsics_jacobian(&Vec3::new(xy.x, xy.y, 1.0));
    let cov = SMatrix::<f64, INTRINSICS, INTRINSICS>::from_fn(|a, b| c.covariance[a][b]);
    let pixel = j * cov * j.transpose();
    let largest = pixel.symmetric_eigenvalues().max();
    Some(largest.max(0.0).sqrt())
}

fn projection_uncertainty(c: &CameraCalibration) -> String {
    let mut svg = image_canvas(c);
    let (w, h) = (f64::from(c.camera.width_px), f64::from(c.camera.height_px));
    let cols = UNCERTAINTY_COLUMNS;
    let rows = ((cols as f64 * h / w).round() as usize).max(1);
    let (cw, ch) = (w / cols as f64, h / rows as f64);
    let cells: Vec<Option<f64>> = (0..rows * cols)
        .map(|i| {
            let (col, row) = (i % cols, i / cols);
            projection_sigma_px(
                c,
                Vector2::new((col as f64 + 0.5) * cw, (row as f64 + 0.5) * ch),
            )
        })
        .collect();
    let largest = cells
        .iter()
        .flatten()
        .copied()
        .fold(0.0, f64::max)
        .max(1e-9);
    let unit = svg.unit();
    for (i, cell) in cells.iter().enumerate() {
        let (col, row) = (i % cols, i / cols);
        let (x, y) = (col as f64 * cw, row as f64 * ch);
        match cell {
            Some(s) => {
                svg.rect(x, y, cw, ch, &ramp(s / largest), None);
                svg.text(
                    x + 3.0 * unit,
                    y + ch / 2.0 + 4.0 * unit,
                    10.0,
                    &format!("{s:.2}"),
                );
            }
            None => svg.rect(x, y, cw, ch, "#ccc", None),
        }
    }
    svg.finish("uncertainty of projection over the image (px)")
}

fn cross_validation_table(body: &mut String, c: &CameraCalibration) {
    let _ = writeln!(body, "<h2>Cross-validation</h2>");
    let Some(check) = &c.cross_validation else {
        let _ = writeln!(body, "<p>Not checked.</p>");
        return;
    };
    let cell = |v: f64| {
        if v.is_finite() {
            format!("{v:.2}")
        } else {
            "-".to_owned()
        }
    };
    let _ = writeln!(
        body,
        "<table><tr><th class=\"l\">verdict</th><th>calibrations</th><th>fx</th><th>fy</th>\
         <th>cx</th><th>cy</th><th>ratio</th><th>noise bound</th><th>inflation</th>\
         <th class=\"l\">model misfit</th></tr><tr><td class=\"l\">{}</td><td>{}</td>\
         <td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td>\
         <td class=\"l\">{}</td></tr></table>\n<p>Each ratio is the leave-one-view-out \
         variance of the parameter over its formal variance; an honest covariance gives 1 \
         within the noise bound.</p>",
        check.verdict,
        check.calibrations,
        cell(check.ratios[0]),
        cell(check.ratios[1]),
        cell(check.ratios[2]),
        cell(check.ratios[3]),
        cell(check.ratio),
        cell(check.noise_bound),
        check.inflation,
        if check.model_misfit { "yes" } else { "no" }
    );
}

fn plate_shape(body: &mut String, r: &CalibrationReport<'_>) {
    let c = r.calibration;
    let _ = writeln!(body, "<h2>The plate's shape</h2>");
    let Some(warp) = &c.plate_warp else {
        let _ = writeln!(
            body,
            "<p>No sag was fitted: the plate was taken as flat.</p>"
        );
        return;
    };
    let _ = writeln!(
        body,
        "<table><tr><th></th><th>sag (mm)</th><th>sigma (mm)</th></tr>\
         <tr><th class=\"l\">along x</th><td>{:+.3}</td><td>{:.3}</td></tr>\
         <tr><th class=\"l\">along y</th><td>{:+.3}</td><td>{:.3}</td></tr></table>\
         <p>Correlation {:+.2}; chi-square {:.1} of two degrees of freedom, {} (over 9.21 is \
         significant). {}</p>",
        warp.sag_mm[0],
        warp.sigma_mm[0],
        warp.sag_mm[1],
        warp.sigma_mm[1],
        warp.correlation,
        warp.chi2,
        if warp.significant {
            "significant"
        } else {
            "not significant"
        },
        if c.plate_shape == PlateShape::Warped {
            "The calibration fitted the plate with this sag."
        } else {
            "The calibration took the plate as flat; this is the sag that was tested."
        }
    );
    let points = r.plate.points_mm();
    let Some(basis) = SagBasis::of(&points) else {
        return;
    };
    let ([x0, y0], [x1, y1]) = basis.bounds();
    let margin = r.plate.spacing_mm();
    let (w, h) = (x1 - x0 + 2.0 * margin, y1 - y0 + 2.0 * margin);
    let mut svg = Svg::new(w, h, 480.0);
    let dz = |x: f64, y: f64| {
        let [bx, by] = basis.at(&Vec3::new(x, y, 0.0));
        warp.sag_mm[0] * bx + warp.sag_mm[1] * by
    };
    let largest = (warp.sag_mm[0].abs() + warp.sag_mm[1].abs()).max(1e-9);
    let cells = 24;
    let (cw, ch) = ((x1 - x0) / cells as f64, (y1 - y0) / cells as f64);
    for i in 0..cells {
        for j in 0..cells {
            let (x, y) = (x0 + (i as f64 + 0.5) * cw, y0 + (j as f64 + 0.5) * ch);
            let t = 0.5 + 0.5 * dz(x, y) / largest;
            svg.rect(
                x - x0 + margin - cw / 2.0,
                y - y0 + margin - ch / 2.0,
                cw,
                ch,
                &ramp(t),
                None,
            );
        }
    }
    for p in &points {
        svg.dot(p.x - x0 + margin, p.y - y0 + margin, 2.0, "#222");
    }
    let unit = svg.unit();
    svg.text(
        4.0 * unit,
        14.0 * unit,
        11.0,
        &format!("height along the plate's z: blue -{largest:.2} mm, red +{largest:.2} mm"),
    );
    body.push_str(&figure(
        &svg.finish("the plate's sag"),
        "The sag over the plate (its points in black): the height of each place above the \
         plate's edges, along its z.",
    ));
}

fn views_table(body: &mut String, r: &CalibrationReport<'_>) {
    let c = r.calibration;
    let _ = writeln!(
        body,
        "<h2>Views</h2>\n<table><tr><th class=\"l\">view</th><th>points</th><th>RMS (px)</th>\
         <th>tilt (deg)</th><th>distance (mm)</th></tr>"
    );
    for (k, v) in c.views.iter().enumerate() {
        let name = r
            .view_names
            .get(k)
            .cloned()
            .unwrap_or_else(|| format!("view {k}"));
        let _ = writeln!(
            body,
            "<tr><td class=\"l\">{}</td><td>{}</td><td>{:.4}</td><td>{:.1}</td><td>{:.0}</td></tr>",
            escape(&name),
            v.points,
            v.rms_px,
            v.tilt_deg,
            v.camera_from_plate.translation.vector.norm()
        );
    }
    let _ = writeln!(body, "</table>");
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::{CameraModel, LensModel};

    fn calibration(covariance: [[f64; INTRINSICS]; INTRINSICS]) -> CameraCalibration {
        CameraCalibration {
            camera: CameraModel::pinhole(800.0, 800.0, 320.0, 240.0, 640, 480)
                .with_distortion(&[-0.2, 0.05]),
            model: LensModel::Brown,
            sigma: std::array::from_fn(|i| covariance[i][i].sqrt()),
            covariance,
            rms_px: 0.1,
            variance_factor: 1.0,
            views: Vec::new(),
            correlations: Vec::new(),
            warnings: Vec::new(),
            fixed: Vec::new(),
            iterations: 0,
            cross_validation: None,
            plate_shape: PlateShape::Flat,
            plate_warp: None,
            residual_structure: None,
            residuals: Vec::new(),
        }
    }

    #[test]
    fn the_projection_sigma_is_the_principal_points_where_only_it_is_uncertain() {
        // du/dcx = 1 everywhere: a cx of sigma 0.3 px moves every pixel by 0.3 px.
        let mut cov = [[0.0; INTRINSICS]; INTRINSICS];
        cov[2][2] = 0.09;
        let c = calibration(cov);
        for uv in [(0.0, 0.0), (320.0, 240.0), (600.0, 100.0)] {
            let s = projection_sigma_px(&c, Vector2::new(uv.0, uv.1)).expect("undistorts");
            assert!((s - 0.3).abs() < 1e-12, "{uv:?}: {s}");
        }
    }

    #[test]
    fn the_projection_sigma_of_the_focal_length_grows_with_the_distance_from_the_centre() {
        // du/dfx = xd = (u - cx) / fx: a focal length of sigma 2 px moves a pixel 160 px from
        // the centre by 2 * 160 / 800 = 0.4 px, and the centre not at all.
        let mut cov = [[0.0; INTRINSICS]; INTRINSICS];
        cov[0][0] = 4.0;
        let c = calibration(cov);
        let centre = projection_sigma_px(&c, Vector2::new(320.0, 240.0)).expect("undistorts");
        assert!(centre.abs() < 1e-9, "{centre}");
        let off = projection_sigma_px(&c, Vector2::new(480.0, 240.0)).expect("undistorts");
        assert!((off - 0.4).abs() < 1e-9, "{off}");
    }

    #[test]
    fn the_page_stands_alone_and_escapes_what_it_is_given() {
        let c = calibration([[0.0; INTRINSICS]; INTRINSICS]);
        let plate = Plate::new(4, 5, 10.0, 5.0, false, crate::vision::Polarity::Dark)
            .expect("a valid plate");
        let page = calibration_report(&CalibrationReport {
            title: "<C1>",
            calibration: &c,
            plate: &plate,
            view_names: &[],
            notes: &["a & b".to_owned()],
            made: "2026-11-27T10:00:00Z",
        });
        assert!(page.starts_with("<!DOCTYPE html>"));
        assert!(page.contains("Camera calibration: &lt;C1&gt;"));
        assert!(page.contains("a &amp; b"));
        // Nothing outside the page: no script, no linked file.
        assert!(!page.contains("<script"));
        assert!(!page.contains("src=") && !page.contains("href="));
        assert!(page.contains("<svg"));
    }
}
