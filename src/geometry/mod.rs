//! Geometry core: rigid transforms on SE(3), their Lie-group maps, uncertainty and averaging.
//!
//! Conventions (the project's contract, stated for users in `docs/interface.md`, "Conventions"):
//!
//! * A [`Pose`] named `a_from_b` maps coordinates in frame b to frame a: `p_a = R p_b + t`.
//!   Composition reads right to left, `a_from_c = a_from_b * b_from_c`.
//! * Translations are millimetres; angles inside the core are radians. Degrees and arc-seconds
//!   appear only in the explicitly named conversion helpers (`*_deg`, `*_arcsec`).
//! * Tangent vectors ([`Twist`]) are ordered `[rho; phi]`: translation part (mm) first, rotation
//!   part (rad) second.
//! * Uncertainty is a 6x6 covariance of a *left* perturbation: `T = Exp(xi) * T_mean`.
//! * Euler angles `[Ax, Ay, Az]` mean `R = Rz(Az) * Ry(Ay) * Rx(Ax)` (fixed axes: roll about x,
//!   then pitch about y, then yaw about z), with Ax, Az in (-180, 180] and Ay in [-90, 90] degrees.
//! * Quaternions are unit Hamilton quaternions written `[w, x, y, z]`, output with `w >= 0`.
//!
//! Everything here is pure and synchronous, and fails only on invalid input, with
//! [`GeometryError`].

mod convert;
mod error;
mod lie;
mod mean;
mod uncertain;

pub use convert::{
    ARCSEC_PER_RAD, EulerAngles, MAX_EULER_DEG, MAX_ROTATION_SIGMA_ARCSEC, MAX_TRANSLATION_MM,
    MAX_TRANSLATION_SIGMA_MM, check_magnitude, euler_from_rotation, pose_from_parts,
    quaternion_wxyz, rotation_from_euler, rotation_from_matrix, rotation_from_quaternion_wxyz,
    validate_finite,
};
pub use error::GeometryError;
pub use lie::{
    adjoint, se3_exp, se3_left_jacobian, se3_left_jacobian_inv, se3_log, skew, so3_exp,
    so3_left_jacobian, so3_left_jacobian_inv, so3_log,
};
pub use mean::{MeanPose, chordal_mean_rotation, mean_pose};
pub use uncertain::{
    Covariance6, PoseCov, ReportedSigmas, check_covariance, symmetrize, transform_covariance,
};

/// A rigid transform `a_from_b` (rotation and translation in millimetres).
pub type Pose = nalgebra::Isometry3<f64>;
/// A rotation on SO(3).
pub type Rotation = nalgebra::UnitQuaternion<f64>;
/// A 3-vector (millimetres or radians, as the name of the binding says).
pub type Vec3 = nalgebra::Vector3<f64>;
/// A 3x3 matrix.
pub type Mat3 = nalgebra::Matrix3<f64>;
/// A tangent vector of SE(3), `[rho (mm); phi (rad)]`.
pub type Twist = nalgebra::Vector6<f64>;
/// A 6x6 matrix on the tangent space of SE(3).
pub type Mat6 = nalgebra::Matrix6<f64>;
