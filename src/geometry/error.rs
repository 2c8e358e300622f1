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
