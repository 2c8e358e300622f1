//! The measurement pipeline's geometry: the camera model, pose estimation (PnP) and station
//! calibration (hand-eye, `AX = XB`); `docs/interface.md`, "HTTP API" describes both endpoints.
//!
//! * [`CameraModel`]: pinhole with Brown-Conrady distortion (OpenCV's `k1 k2 p1 p2 k3`);
//!   projection with its Jacobian, undistortion by Newton's method with a convergence check.
//! * [`solve_pnp`]: `camera_from_marker` from marker points and pixels: IPPE (planar markers,
//!   both solutions) or SQPnP (markers with depth) to start, Levenberg-Marquardt on the
//!   reprojection error to finish (each point weighted by its own sigma when a detector gives
//!   one, [`solve_pnp_weighted`]), with the covariance `(J^T W J)^-1` in the left
//!   perturbation of [`crate::geometry`], the RMS, and a planar-ambiguity ratio. Refuses too few
//!   or collinear points, points behind the camera and a fit over the RMS limit; optionally
//!   robust (RANSAC) against a mislabelled point.
//! * [`detect`]: disc targets in a grey frame ([`GreyImage`]), each centre to a hundredth of a
//!   pixel with its covariance.
//! * [`disc_image_offset`]: the perspective eccentricity of a disc target, to turn a detected
//!   centroid into the image of the disc's centre.
//! * [`Plate`]: a calibration plate of discs in a grid, found in a frame without a pose.
//! * [`calibrate_camera`]: intrinsics and distortion from views of a plate, with their
//!   covariance and warnings, the plate flat or fitted with a sag along each axis
//!   ([`PlateShape`]); [`calibrate_camera_checked`] cross-validates that covariance
//!   against calibrations that leave one view out each and inflates it where it is too small.
//! * [`solve_hand_eye`]: a rigid station's calibrated link from motions `A_i X = X B_i`.
//!
//! Pure and synchronous, like the rest of the core; one error type, [`VisionError`].

mod calibrate;
mod camera;
mod crossval;
mod detect;
mod eccentricity;
mod error;
mod handeye;
mod image;
mod ippe;
mod plate;
mod pnp;
mod sqpnp;

pub use calibrate::{
    CalibrationOptions, CalibrationView, CalibrationWarning, CameraCalibration, Correlation,
    ImageCorner, Intrinsic, MAX_VIEWS, MIN_BIN_POINTS, MIN_VIEW_POINTS, MIN_VIEWS, PlateShape,
    PlateWarp, PointResidual, RECOMMENDED_TILT_DEG, RECOMMENDED_VIEWS, ResidualBin,
    ResidualStructure, SAG_SIGNIFICANCE_CHI2, STRUCTURE_BINS_X, STRUCTURE_PROBABILITY, SagBasis,
    ViewFit, WarningKind, calibrate_camera, describe_plate_shape, describe_residual_structure,
    intrinsics_of, residual_structure, structure_grid,
};
pub use camera::{CameraModel, DISTORTION_TERMS, INTRINSICS, LensModel};
pub use crossval::{
    CrossValidation, CrossValidationVerdict, MIN_CROSS_VALIDATION_VIEWS, calibrate_camera_checked,
    cross_validate, describe_cross_validation,
};
pub use detect::{Blob, DetectSettings, Polarity, SearchArea, TILE_PX, detect, detect_in};
pub use eccentricity::{disc_image_offset, solve_pnp_discs};
pub use error::VisionError;
pub use handeye::{
    HandEyeOptions, HandEyeSolution, MIN_MOTIONS, MotionSpread, PairResidual, solve_hand_eye,
};
pub use image::{BitDepth, GreyImage, StoredPixels};
pub use plate::{Plate, PlateView};
pub use pnp::{
    MIN_POINTS, PnpOptions, PnpSolution, Refinement, initial_poses, intrinsics_sensitivity, refine,
    solve_pnp, solve_pnp_weighted,
};
