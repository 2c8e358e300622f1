//! Errors of the geometry core.

/// Invalid geometric input. Each variant names what is wrong with the number it was given.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    /// A number is NaN or infinite.
    #[error("{what} is not a finite number ({value})")]
    NonFinite {
        /// Which quantity (for example `q_wxyz[2]`).
        what: String,
        /// The offending value.
        value: f64,
    },
    /// A finite number too large to be a measurement (a unit mistake or garbage).
    #[error("{what} is {value:e} {unit}, beyond the plausible limit of {limit:e} {unit}")]
    Implausible {
        /// Which quantity (for example `t_mm[2]`).
        what: String,
        /// The offending value.
        value: f64,
        /// The largest magnitude accepted.
        limit: f64,
        /// The unit of both.
        unit: &'static str,
    },
    /// A quaternion whose norm is too far from 1 to be a rotation written with rounding error.
    #[error("quaternion norm is {norm:.6}, more than {tolerance} away from 1")]
    QuaternionNotUnit {
        /// The norm found.
        norm: f64,
        /// The allowed deviation from 1.
        tolerance: f64,
    },
    /// A 3x3 matrix that is not a proper rotation.
    #[error("matrix is not a rotation: {reason}")]
    NotARotation {
        /// What the check found (orthogonality error or determinant).
        reason: String,
    },
    /// A covariance matrix that is not symmetric positive semi-definite.
    #[error("covariance is not symmetric positive semi-definite: {reason}")]
    BadCovariance {
        /// What the check found.
        reason: String,
    },
    /// An average over nothing.
    #[error("cannot average an empty set of poses")]
    EmptyMean,
}
