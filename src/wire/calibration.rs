//! A camera calibration's request and result, and the plate they describe, as
//! `POST /calibration/camera` and `brokenray calibrate-camera` read and write them; the plate
//! description ([`PlateIn`]) is also the plate file the command reads (TOML).
//! `docs/interface.md` describes them (`POST /api/v1/calibration/camera` under "HTTP API", and
//! "Calibration plates").

use super::{FieldProblem, PoseOut, Rejection};
use crate::vision::{
    CalibrationOptions, CalibrationView, CameraCalibration, CameraModel, Intrinsic, LensModel,
    Plate, Polarity, calibrate_camera_checked, intrinsics_of,
};
use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

/// Dark discs on a light plate, or bright ones.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum PlatePolarity {
    /// Dark discs on a light plate (printed plates).
    #[default]
    Dark,
    /// Light discs on a dark plate (retro-reflective targets).
    Bright,
}

/// A calibration plate: `rows` x `cols` discs; point `i` at row `i / cols`, column `i % cols`,
/// `(col * spacing_mm, row * spacing_mm, 0)`, or when `asymmetric` (OpenCV's asymmetric circle
/// grid) at `((2 col + row mod 2) * spacing_mm, row * spacing_mm, 0)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PlateIn {
    /// Rows of points (3 or more).
    pub rows: usize,
    /// Points per row (3 or more).
    pub cols: usize,
    /// Distance between rows, and between neighbouring points of a row on a symmetric plate
    /// (on an asymmetric one they are twice as far apart) (mm).
    pub spacing_mm: f64,
    /// Disc diameter (mm), less than the distance between neighbouring discs.
    pub diameter_mm: f64,
    /// OpenCV's asymmetric circle grid (`x = (2 col + row mod 2) s`, `y = row s`): a plate
    /// that looks different after any turn when `rows` is odd.
    #[serde(default)]
    pub asymmetric: bool,
    /// `dark` (default) or `bright` discs.
    #[serde(default)]
    pub polarity: PlatePolarity,
    /// The diameter of the disc at point 0 when it is larger than the others (mm): the
    /// "modified circle grid", whose labelling the larger disc fixes whatever the layout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin_diameter_mm: Option<f64>,
}

impl PlateIn {
    /// The plate, or what is wrong with it (field `plate`).
    pub fn to_plate(&self) -> Result<Plate, FieldProblem> {
        let polarity = match self.polarity {
            PlatePolarity::Dark => Polarity::Dark,
            PlatePolarity::Bright => Polarity::Bright,
        };
        Plate::new(
            self.rows,
            self.cols,
            self.spacing_mm,
            self.diameter_mm,
            self.asymmetric,
            polarity,
        )
        .and_then(|plate| match self.origin_diameter_mm {
            Some(d) => plate.with_origin_diameter(d),
            None => Ok(plate),
        })
        .map_err(|e| FieldProblem::new("plate", e.to_string()))
    }
}

/// One view: the plate points found in one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PlateViewIn {
    /// Detected centres `[u, v]` (px, pixel centres at integers).
    pub points_px: Vec<[f64; 2]>,
    /// The plate point of each.
    pub ids: Vec<usize>,
    /// Each point's standard deviation (px) when the detector measured it; equal weights
    /// without.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_px: Option<Vec<f64>>,
}

/// Intrinsics in JSON: a camera's, their sigmas, or the known values of fixed ones.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    /// Focal length along x (px).
    pub fx: f64,
    /// Focal length along y (px).
    pub fy: f64,
    /// Principal point x (px).
    pub cx: f64,
    /// Principal point y (px).
    pub cy: f64,
    /// OpenCV's coefficients `[k1, k2, p1, p2, k3]`, with `k4, k5, k6` for the rational
    /// model and `s1, s2, s3, s4` for the thin prism (zeros when left out).
    #[serde(default)]
    pub distortion: Vec<f64>,
}

impl Intrinsics {
    /// The first `4 + model's terms` of `p` (in [`Intrinsic::ALL`]'s order).
    fn of_model(p: &[f64; crate::vision::INTRINSICS], model: LensModel) -> Self {
        Self {
            fx: p[0],
            fy: p[1],
            cx: p[2],
            cy: p[3],
            distortion: p[4..model.intrinsics()].to_vec(),
        }
    }
}

/// A calibration request.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraCalibrationIn {
    /// The plate.
    pub plate: PlateIn,
    /// `[width, height]` of the frames (px).
    pub image_size: [u32; 2],
    /// Three views or more (ten or more recommended).
    pub views: Vec<PlateViewIn>,
    /// Parameters kept fixed: distortion terms at zero, `cx`/`cy` at the image centre, unless
    /// `initial` gives their values (which `fx` and `fy` need).
    #[serde(default)]
    pub fix: Vec<String>,
    /// Known values of fixed parameters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub initial: Option<Intrinsics>,
    /// The plate's shape: `auto` (the default) fits a sag along each axis and keeps it when it
    /// is significant, `warped` keeps it always, `flat` takes the plate as flat.
    #[serde(default = "auto_shape")]
    #[schema(value_type = String)]
    pub plate_shape: crate::vision::PlateShape,
    /// The lens model: `brown` (the default: `k1 k2 p1 p2 k3`), `rational` (with `k4 k5 k6`)
    /// or `rational_prism` (with `s1 s2 s3 s4` too).
    #[serde(default)]
    #[schema(value_type = String)]
    pub model: LensModel,
}

fn auto_shape() -> crate::vision::PlateShape {
    crate::vision::PlateShape::Auto
}

/// One view's fit.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ViewFitOut {
    /// Reprojection RMS of its points (px).
    pub rms_px: f64,
    /// `camera_from_plate`.
    pub pose: PoseOut,
    /// Angle between the plate's normal and the optical axis (degrees).
    pub tilt_deg: f64,
    /// Points used.
    pub points: usize,
}

/// Two intrinsics whose estimates are correlated by more than 0.9.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CorrelationOut {
    /// One parameter.
    pub a: Intrinsic,
    /// The other.
    pub b: Intrinsic,
    /// Their correlation coefficient.
    pub r: f64,
}

/// Something about the views that could be better.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CalibrationWarningOut {
    /// What is wrong; `lossy_frames` (views that came as JPEG) only from `calibrate-camera`.
    pub kind: crate::vision::WarningKind,
    /// What to do, in words.
    pub message: String,
}

/// A calibrated camera.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CameraCalibrationOut {
    /// The intrinsics.
    pub camera: Intrinsics,
    /// Their standard deviations (0 for fixed ones).
    pub sigma: Intrinsics,
    /// The lens model fitted.
    #[schema(value_type = String)]
    pub model: LensModel,
    /// Their covariance, `n x n` numbers row-major in the order of `parameters`.
    pub covariance: Vec<f64>,
    /// `fx fy cx cy` and the model's distortion terms: `k1 k2 p1 p2 k3`, then `k4 k5 k6`,
    /// then `s1 s2 s3 s4`.
    pub parameters: Vec<Intrinsic>,
    /// Those kept fixed.
    pub fixed: Vec<Intrinsic>,
    /// Reprojection RMS over every point (px; the length of the residual, both axes).
    pub rms_px: f64,
    /// The factor the covariance was scaled by: `chi2 / (2 n - p)` (near 1 when the detector's
    /// sigmas are right).
    pub variance_factor: f64,
    /// Each view, in request order.
    pub views: Vec<ViewFitOut>,
    /// Pairs of parameters correlated by more than 0.9.
    pub correlations: Vec<CorrelationOut>,
    /// What could be better, with what to do.
    pub warnings: Vec<CalibrationWarningOut>,
    /// `[width, height]` (px).
    pub image_size: [u32; 2],
    /// A point's error when predicted with this calibration, per axis (px): the
    /// installation's `pixel_sigma`.
    pub pixel_sigma: f64,
    /// Levenberg-Marquardt iterations.
    pub iterations: usize,
    /// The covariance checked against calibrations that leave one view out each.
    pub cross_validation: Option<CrossValidationOut>,
    /// The shape the plate was fitted with: `flat` or `warped`.
    #[schema(value_type = String)]
    pub plate_shape: crate::vision::PlateShape,
    /// The plate's sag (fitted when warped; when `auto` chose flat, the sag tested and found
    /// not significant; null when it was not fitted).
    pub plate_warp: Option<PlateWarpOut>,
    /// The plate's shape in a sentence.
    pub plate_message: String,
    /// The residuals binned over the image and judged for structure the lens model does not
    /// explain (null when no bin had enough points).
    pub residual_structure: Option<ResidualStructureOut>,
    /// That judgement in a sentence.
    pub residual_message: Option<String>,
}

/// The residuals binned over the image.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ResidualStructureOut {
    /// Columns of the grid.
    pub bins_x: usize,
    /// Rows of the grid.
    pub bins_y: usize,
    /// The sum of the judged bins' `z2`.
    pub chi2: f64,
    /// Its degrees of freedom (two per bin judged).
    pub dof: usize,
    /// The chi-square quantile at 99.9 % for `dof`.
    pub threshold: f64,
    /// `chi2` over `threshold`: structure the lens model does not explain.
    pub significant: bool,
    /// The bins with enough points to judge, row by row.
    pub bins: Vec<ResidualBinOut>,
}

/// One bin of the residuals' grid.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ResidualBinOut {
    /// Its column.
    pub column: usize,
    /// Its row.
    pub row: usize,
    /// Its centre `[u, v]` (px).
    pub centre_px: [f64; 2],
    /// Points in it.
    pub points: usize,
    /// The mean residual `[du, dv]`, detected minus predicted (px).
    pub mean_px: [f64; 2],
    /// The standard deviation of that mean, per axis (px).
    pub sigma_px: f64,
    /// `|mean|² / sigma²` (chi-square, two degrees of freedom, when the model fits).
    pub z2: f64,
}

impl From<&crate::vision::ResidualStructure> for ResidualStructureOut {
    fn from(s: &crate::vision::ResidualStructure) -> Self {
        Self {
            bins_x: s.bins_x,
            bins_y: s.bins_y,
            chi2: s.chi2,
            dof: s.dof,
            threshold: s.threshold,
            significant: s.significant,
            bins: s
                .bins
                .iter()
                .map(|b| ResidualBinOut {
                    column: b.cell.0,
                    row: b.cell.1,
                    centre_px: [b.centre_px.x, b.centre_px.y],
                    points: b.points,
                    mean_px: [b.mean_px.x, b.mean_px.y],
                    sigma_px: b.sigma_px,
                    z2: b.z2,
                })
                .collect(),
        }
    }
}

/// A plate's fitted sag along each of its axes.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct PlateWarpOut {
    /// The height of the plate's middle above its two edges along x, along the plate's z (mm).
    pub sag_x_mm: f64,
    /// The same along y (mm).
    pub sag_y_mm: f64,
    /// The standard deviation of `sag_x_mm` (mm; cross-validated with the intrinsics).
    pub sigma_x_mm: f64,
    /// The standard deviation of `sag_y_mm` (mm).
    pub sigma_y_mm: f64,
    /// The correlation of the two.
    pub correlation: f64,
    /// The Wald statistic of the two sags against zero (chi-square of 2 degrees of freedom).
    pub chi2: f64,
    /// Whether it is over the 99 % quantile, 9.21.
    pub significant: bool,
}

impl From<&crate::vision::PlateWarp> for PlateWarpOut {
    fn from(w: &crate::vision::PlateWarp) -> Self {
        Self {
            sag_x_mm: w.sag_mm[0],
            sag_y_mm: w.sag_mm[1],
            sigma_x_mm: w.sigma_mm[0],
            sigma_y_mm: w.sigma_mm[1],
            correlation: w.correlation,
            chi2: w.chi2,
            significant: w.significant,
        }
    }
}

/// The cross-validation of a calibration's covariance.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct CrossValidationOut {
    /// `honest` (the formal covariance is reported), `inflated` (it is reported scaled by
    /// `inflation`), or `too_few_views` (unchecked: fewer than four views).
    #[schema(value_type = String)]
    pub verdict: crate::vision::CrossValidationVerdict,
    /// Calibrations made, one view left out of each.
    pub calibrations: usize,
    /// For fx, fy, cx, cy: the leave-one-view-out (jackknife) variance over the formal one
    /// (null when unchecked).
    pub ratios: [Option<f64>; 4],
    /// Their mean (null when unchecked).
    pub ratio: Option<f64>,
    /// The largest mean ratio that is the check's own noise about 1.
    pub noise_bound: Option<f64>,
    /// What the formal covariance was multiplied by.
    pub inflation: f64,
    /// The spread is over twice the formal sigmas: the model (plate shape, lens) does not fit.
    pub model_misfit: bool,
    /// What it means, in a sentence.
    pub message: String,
}

impl From<&crate::vision::CrossValidation> for CrossValidationOut {
    fn from(c: &crate::vision::CrossValidation) -> Self {
        let finite = |v: f64| v.is_finite().then_some(v);
        Self {
            verdict: c.verdict,
            calibrations: c.calibrations,
            ratios: c.ratios.map(finite),
            ratio: finite(c.ratio),
            noise_bound: finite(c.noise_bound),
            inflation: c.inflation,
            model_misfit: c.model_misfit,
            message: crate::vision::describe_cross_validation(c),
        }
    }
}

impl From<&CameraCalibration> for CameraCalibrationOut {
    fn from(c: &CameraCalibration) -> Self {
        let n = c.model.intrinsics();
        Self {
            camera: Intrinsics::of_model(&intrinsics_of(&c.camera), c.model),
            sigma: Intrinsics::of_model(&c.sigma, c.model),
            model: c.model,
            covariance: c.covariance[..n]
                .iter()
                .flat_map(|row| row[..n].iter().copied())
                .collect(),
            parameters: Intrinsic::of_model(c.model).to_vec(),
            fixed: c.fixed.clone(),
            rms_px: c.rms_px,
            variance_factor: c.variance_factor,
            views: c
                .views
                .iter()
                .map(|v| ViewFitOut {
                    rms_px: v.rms_px,
                    pose: PoseOut::from(&v.camera_from_plate),
                    tilt_deg: v.tilt_deg,
                    points: v.points,
                })
                .collect(),
            correlations: c
                .correlations
                .iter()
                .map(|k| CorrelationOut {
                    a: k.a,
                    b: k.b,
                    r: k.r,
                })
                .collect(),
            warnings: c
                .warnings
                .iter()
                .map(|w| CalibrationWarningOut {
                    kind: w.kind(),
                    message: w.to_string(),
                })
                .collect(),
            image_size: [c.camera.width_px, c.camera.height_px],
            pixel_sigma: c.pixel_sigma(),
            iterations: c.iterations,
            cross_validation: c.cross_validation.as_ref().map(CrossValidationOut::from),
            plate_shape: c.plate_shape,
            plate_warp: c.plate_warp.as_ref().map(PlateWarpOut::from),
            plate_message: crate::vision::describe_plate_shape(
                c.plate_shape,
                c.plate_warp.as_ref(),
            ),
            residual_structure: c
                .residual_structure
                .as_ref()
                .map(ResidualStructureOut::from),
            residual_message: c
                .residual_structure
                .as_ref()
                .map(|r| crate::vision::describe_residual_structure(r, c.model)),
        }
    }
}

/// The fixed parameters named in `fix`, or the unknown names.
pub fn parse_fix(fix: &[String]) -> Result<Vec<Intrinsic>, FieldProblem> {
    let mut out = Vec::with_capacity(fix.len());
    for name in fix {
        match Intrinsic::parse(name.trim()) {
            Some(p) => out.push(p),
            None => {
                return Err(FieldProblem::new(
                    "fix",
                    format!("`{name}` is not one of {}", Intrinsic::WORDS.join(", ")),
                ));
            }
        }
    }
    Ok(out)
}

impl CameraCalibrationIn {
    /// Validates the request and calibrates; `cancel` set stops the work.
    pub fn solve(
        &self,
        cancel: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
    ) -> Result<(CameraCalibration, CameraCalibrationOut), Rejection> {
        let mut problems: Vec<FieldProblem> = Vec::new();
        let plate = self.plate.to_plate().map_err(|p| problems.push(p)).ok();
        let fixed = parse_fix(&self.fix).map_err(|p| problems.push(p)).ok();
        let [w, h] = self.image_size;
        if w == 0 || h == 0 {
            problems.push(FieldProblem::new("image_size", "must not be zero"));
        }
        let mut views = Vec::with_capacity(self.views.len());
        for (i, v) in self.views.iter().enumerate() {
            if v.points_px.len() != v.ids.len() {
                problems.push(
                    FieldProblem::new(
                        "ids",
                        format!("{} id(s) for {} point(s)", v.ids.len(), v.points_px.len()),
                    )
                    .at(i),
                );
            }
            if v.points_px.iter().flatten().any(|c| !c.is_finite()) {
                problems.push(FieldProblem::new("points_px", "not finite").at(i));
            }
            views.push(CalibrationView {
                points_px: v
                    .points_px
                    .iter()
                    .map(|p| Vector2::new(p[0], p[1]))
                    .collect(),
                ids: v.ids.clone(),
                sigmas_px: v.sigma_px.clone(),
            });
        }
        if let Some(c) = &self.initial
            && c.distortion.len() > self.model.distortion_terms()
        {
            problems.push(FieldProblem::new(
                "initial",
                format!(
                    "distortion has {} numbers; the {} model has {}",
                    c.distortion.len(),
                    self.model.name(),
                    self.model.distortion_terms()
                ),
            ));
        }
        let initial = self.initial.as_ref().map(|c| {
            CameraModel::pinhole(c.fx, c.fy, c.cx, c.cy, w, h).with_distortion(&c.distortion)
        });
        if let Some(c) = &initial
            && !intrinsics_of(c).iter().all(|v| v.is_finite())
        {
            problems.push(FieldProblem::new("initial", "not finite"));
        }
        let (Some(plate), Some(fixed), true) = (plate, fixed, problems.is_empty()) else {
            return Err(Rejection::Invalid {
                message: format!("{} invalid field(s)", problems.len()),
                problems,
            });
        };
        let options = CalibrationOptions {
            fixed,
            initial,
            cancel,
            plate_shape: self.plate_shape,
            model: self.model,
            ..CalibrationOptions::default()
        };
        let calibration = calibrate_camera_checked(&plate, w, h, &views, &options)?;
        let out = CameraCalibrationOut::from(&calibration);
        Ok((calibration, out))
    }
}
