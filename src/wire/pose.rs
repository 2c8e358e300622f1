//! Poses and sigmas as every document writes them: a pose sent in any of three rotation
//! forms and answered in two, sigmas per axis or one for all, a covariance as 36 numbers, and
//! the problem of a field that does not hold what it must (`docs/interface.md`, "Conventions").

use crate::geometry::{
    ARCSEC_PER_RAD, MAX_ROTATION_SIGMA_ARCSEC, MAX_TRANSLATION_SIGMA_MM, Mat6, Pose, PoseCov,
    ReportedSigmas, check_covariance, euler_from_rotation, pose_from_parts, quaternion_wxyz,
    rotation_from_euler, rotation_from_matrix, rotation_from_quaternion_wxyz,
};
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// A pose as sent: `t_mm` with exactly one of `q_wxyz`, `euler_deg`, `r`.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PoseIn {
    /// Translation (mm).
    pub t_mm: [f64; 3],
    /// Unit quaternion `[w, x, y, z]`.
    pub q_wxyz: Option<[f64; 4]>,
    /// Euler angles `[Ax, Ay, Az]` (degrees), `R = Rz Ry Rx`.
    pub euler_deg: Option<[f64; 3]>,
    /// Rotation matrix, row-major.
    pub r: Option<[[f64; 3]; 3]>,
}

/// Sigmas as sent: each a number (all axes) or three numbers.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct SigmaIn {
    /// Rotation sigma (arc-seconds).
    #[schema(schema_with = sigma_schema)]
    pub rotation_arcsec: Value,
    /// Translation sigma (mm).
    #[schema(schema_with = sigma_schema)]
    pub translation_mm: Value,
}

/// The OpenAPI schema of a time as sent: RFC 3339 text, or integer nanoseconds since the Unix
/// epoch (UTC).
pub fn time_schema() -> utoipa::openapi::schema::Schema {
    use utoipa::openapi::schema::{KnownFormat, ObjectBuilder, OneOfBuilder, SchemaFormat, Type};
    OneOfBuilder::new()
        .item(
            ObjectBuilder::new()
                .schema_type(Type::String)
                .format(Some(SchemaFormat::KnownFormat(KnownFormat::DateTime))),
        )
        .item(
            ObjectBuilder::new()
                .schema_type(Type::Integer)
                .format(Some(SchemaFormat::KnownFormat(KnownFormat::Int64))),
        )
        .description(Some(
            "RFC 3339 text, or integer nanoseconds since the Unix epoch (UTC)",
        ))
        .build()
        .into()
}

/// The OpenAPI schema of a sigma as sent: one positive number for all three axes, or three.
pub fn sigma_schema() -> utoipa::openapi::schema::Schema {
    use utoipa::openapi::schema::{ArrayBuilder, ObjectBuilder, OneOfBuilder, Type};
    let number = || {
        ObjectBuilder::new()
            .schema_type(Type::Number)
            .exclusive_minimum(Some(0.0))
    };
    OneOfBuilder::new()
        .item(number())
        .item(
            ArrayBuilder::new()
                .items(number())
                .min_items(Some(3))
                .max_items(Some(3)),
        )
        .description(Some("One positive number for every axis, or one per axis"))
        .build()
        .into()
}

/// At most the first 80 characters of an offending value, for an error message (a message
/// never echoes a whole junk value back).
pub fn clip(text: &str) -> String {
    match text.char_indices().nth(80) {
        Some((i, _)) => format!("{}...", &text[..i]),
        None => text.to_owned(),
    }
}

/// A field that does not hold what it must: its path (`pose.q_wxyz`), the item of a list it is
/// in when it is in one, and what is wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldProblem {
    /// The item's index in its list (`samples[3]`), when the document is a list.
    pub index: Option<usize>,
    /// The field's path inside the item.
    pub field: String,
    /// What is wrong.
    pub message: String,
}

impl FieldProblem {
    /// A problem of `field`, in no list.
    pub fn new(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self {
            index: None,
            field: field.into(),
            message: message.into(),
        }
    }

    /// The same problem, in item `index` of a list.
    #[must_use]
    pub fn at(self, index: usize) -> Self {
        Self {
            index: Some(index),
            ..self
        }
    }
}

fn finite(field: &str, values: &[f64]) -> Result<(), FieldProblem> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(FieldProblem::new(
            format!("{field}[{i}]"),
            "is not a finite number",
        )),
        None => Ok(()),
    }
}

impl PoseIn {
    /// The pose, validated; `prefix` names the field in problems (`pose`). Several rotation
    /// forms may be given (a pose as this API answers it has `q_wxyz` and `euler_deg`) when
    /// they agree within 1e-6 rad; `q_wxyz`, then `r`, then `euler_deg` is used.
    pub fn to_pose(&self, prefix: &str) -> Result<Pose, FieldProblem> {
        finite(&format!("{prefix}.t_mm"), &self.t_mm)?;
        let mut forms: Vec<(String, crate::geometry::Rotation)> = Vec::new();
        if let Some(q) = self.q_wxyz {
            let field = format!("{prefix}.q_wxyz");
            finite(&field, &q)?;
            let r = rotation_from_quaternion_wxyz(q)
                .map_err(|e| FieldProblem::new(field.clone(), e.to_string()))?;
            forms.push((field, r));
        }
        if let Some(m) = self.r {
            let field = format!("{prefix}.r");
            for (i, row) in m.iter().enumerate() {
                finite(&format!("{field}[{i}]"), row)?;
            }
            let r = rotation_from_matrix(m)
                .map_err(|e| FieldProblem::new(field.clone(), e.to_string()))?;
            forms.push((field, r));
        }
        if let Some(e) = self.euler_deg {
            let field = format!("{prefix}.euler_deg");
            finite(&field, &e)?;
            let r = rotation_from_euler(e.map(f64::to_radians))
                .map_err(|e| FieldProblem::new(field.clone(), e.to_string()))?;
            forms.push((field, r));
        }
        let Some((first_field, rotation)) = forms.first().cloned() else {
            return Err(FieldProblem::new(
                prefix.to_owned(),
                "needs a rotation: `q_wxyz`, `euler_deg` or `r`".to_owned(),
            ));
        };
        for (field, other) in &forms[1..] {
            let angle = rotation.angle_to(other);
            if angle > 1e-6 {
                return Err(FieldProblem::new(
                    field.clone(),
                    format!(
                        "disagrees with `{first_field}` by {:.6} degrees; give one rotation, or agreeing ones",
                        angle.to_degrees()
                    ),
                ));
            }
        }
        pose_from_parts(self.t_mm, rotation)
            .map_err(|e| FieldProblem::new(format!("{prefix}.t_mm"), e.to_string()))
    }
}

/// A sigma as sent: a positive number or three, each at most `max`.
fn scalar_or_3(field: &str, v: &Value, max: f64) -> Result<[f64; 3], FieldProblem> {
    let values = match v {
        Value::Number(n) => {
            let x = n
                .as_f64()
                .ok_or_else(|| FieldProblem::new(field.to_owned(), "is not a number".to_owned()))?;
            [x; 3]
        }
        Value::Array(a) if a.len() == 3 => {
            let mut out = [0.0; 3];
            for (i, item) in a.iter().enumerate() {
                out[i] = item.as_f64().ok_or_else(|| {
                    FieldProblem::new(
                        format!("{field}[{i}]"),
                        format!("must be a number, not {}", clip(&item.to_string())),
                    )
                })?;
            }
            out
        }
        other => {
            return Err(FieldProblem::new(
                field.to_owned(),
                format!(
                    "must be a number or three numbers, not {}",
                    clip(&other.to_string())
                ),
            ));
        }
    };
    for (i, x) in values.iter().enumerate() {
        if !(x.is_finite() && *x > 0.0) {
            return Err(FieldProblem::new(
                format!("{field}[{i}]"),
                format!("must be a positive number, not {x}"),
            ));
        }
        if *x > max {
            return Err(FieldProblem::new(
                format!("{field}[{i}]"),
                format!("{x:e} is beyond the plausible limit of {max:e}"),
            ));
        }
    }
    Ok(values)
}

impl SigmaIn {
    /// The sigmas, validated (positive, finite).
    pub fn to_sigmas(&self, prefix: &str) -> Result<ReportedSigmas, FieldProblem> {
        Ok(ReportedSigmas {
            rotation_arcsec: scalar_or_3(
                &format!("{prefix}.rotation_arcsec"),
                &self.rotation_arcsec,
                MAX_ROTATION_SIGMA_ARCSEC,
            )?,
            translation_mm: scalar_or_3(
                &format!("{prefix}.translation_mm"),
                &self.translation_mm,
                MAX_TRANSLATION_SIGMA_MM,
            )?,
        })
    }
}

/// A covariance given as 36 numbers, row-major, checked symmetric positive definite.
pub fn covariance_from(field: &str, values: &[f64]) -> Result<Mat6, FieldProblem> {
    if values.len() != 36 {
        return Err(FieldProblem::new(
            field.to_owned(),
            format!("must have 36 numbers, has {}", values.len()),
        ));
    }
    finite(field, values)?;
    let m = Mat6::from_row_slice(values);
    check_covariance(&m).map_err(|e| FieldProblem::new(field.to_owned(), e.to_string()))?;
    // Plausibility of the variances (the off-diagonal entries follow from them).
    let max_rotation_rad = MAX_ROTATION_SIGMA_ARCSEC / ARCSEC_PER_RAD;
    for i in 0..6 {
        let (max_sigma, unit) = if i < 3 {
            (MAX_TRANSLATION_SIGMA_MM, "mm")
        } else {
            (max_rotation_rad, "rad")
        };
        if m[(i, i)] > max_sigma * max_sigma {
            return Err(FieldProblem::new(
                format!("{field}[{}]", i * 7),
                format!(
                    "a variance of {:e} is beyond the plausible limit of ({max_sigma:e} {unit})^2",
                    m[(i, i)]
                ),
            ));
        }
    }
    if m.cholesky().is_none() {
        return Err(FieldProblem::new(
            field.to_owned(),
            "is singular (a measurement is never exact)",
        ));
    }
    Ok(m)
}

/// A pose as answered.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct PoseOut {
    /// Translation (mm).
    pub t_mm: [f64; 3],
    /// Quaternion `[w, x, y, z]`, `w >= 0`.
    pub q_wxyz: [f64; 4],
    /// Euler angles `[Ax, Ay, Az]` (degrees).
    pub euler_deg: [f64; 3],
}

impl From<&Pose> for PoseOut {
    fn from(p: &Pose) -> Self {
        Self {
            t_mm: p.translation.vector.into(),
            q_wxyz: quaternion_wxyz(&p.rotation),
            euler_deg: euler_from_rotation(&p.rotation).to_degrees(),
        }
    }
}

/// Sigmas as answered.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct SigmaOut {
    /// Per axis (arc-seconds).
    pub rotation_arcsec: [f64; 3],
    /// Per translation component (mm).
    pub translation_mm: [f64; 3],
}

impl From<ReportedSigmas> for SigmaOut {
    fn from(s: ReportedSigmas) -> Self {
        Self {
            rotation_arcsec: s.rotation_arcsec,
            translation_mm: s.translation_mm,
        }
    }
}

impl From<&PoseCov> for SigmaOut {
    fn from(p: &PoseCov) -> Self {
        p.reported_sigmas().into()
    }
}

/// The rotation vector of a pose in arc-seconds.
pub fn rotation_vector_arcsec(p: &Pose) -> [f64; 3] {
    let v = crate::geometry::so3_log(&p.rotation) * ARCSEC_PER_RAD;
    [v.x, v.y, v.z]
}
