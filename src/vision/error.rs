//! Errors of the measurement pipeline: pose estimation and station calibration.

/// Why a pose or a calibration could not be computed. Each variant says what to change.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VisionError {
    /// Fewer points than the solver needs.
    #[error("{given} point(s) given, at least {needed} are needed")]
    NotEnoughPoints {
        /// Points given.
        given: usize,
        /// Points needed.
        needed: usize,
    },
    /// The marker and image point lists do not pair up.
    #[error("{marker_points} marker point(s) but {image_points} image point(s)")]
    MismatchedPoints {
        /// Marker points.
        marker_points: usize,
        /// Image points.
        image_points: usize,
    },
    /// A NaN or infinite number.
    #[error("{what} is not a finite number")]
    NonFinite {
        /// Which quantity.
        what: String,
    },
    /// The geometry does not determine a pose (collinear points, a marker seen edge-on).
    #[error("degenerate geometry: {reason}")]
    Degenerate {
        /// What was found.
        reason: String,
    },
    /// The best pose puts points behind the camera.
    #[error("the best fit puts {count} marker point(s) behind the camera")]
    BehindCamera {
        /// How many.
        count: usize,
    },
    /// The fit is worse than the configured limit: a wrong marker, mislabelled points or bad
    /// intrinsics.
    #[error("reprojection RMS {rms_px:.3} px exceeds the limit of {limit_px} px")]
    ReprojectionTooLarge {
        /// The RMS found (px).
        rms_px: f64,
        /// The limit (px).
        limit_px: f64,
    },
    /// A pixel has no undistorted preimage (it lies past the fold of the distortion model).
    #[error(
        "pixel ({u_px}, {v_px}) cannot be undistorted: the distortion model does not converge there"
    )]
    UndistortDiverged {
        /// Pixel column.
        u_px: f64,
        /// Pixel row.
        v_px: f64,
    },
    /// Robust estimation found no pose supported by enough points.
    #[error(
        "no pose is supported by {needed} or more of the {given} points within {threshold_px} px"
    )]
    NoConsensus {
        /// Points given.
        given: usize,
        /// Points needed in agreement.
        needed: usize,
        /// Inlier threshold (px).
        threshold_px: f64,
    },
    /// Hand-eye: a motion is too small for its rotation axis to be defined.
    #[error(
        "motion {index}: rotation of {angle_deg:.4} deg is too small (at least {min_deg} deg) for its axis to be defined"
    )]
    MotionTooSmall {
        /// The pair's index.
        index: usize,
        /// Its rotation (degrees).
        angle_deg: f64,
        /// The least accepted (degrees).
        min_deg: f64,
    },
    /// Hand-eye: the two motions of a pair do not rotate by the same angle, so they cannot be
    /// the same rigid motion seen from two sensors.
    #[error(
        "motion {index}: A rotates by {a_deg:.4} deg but B by {b_deg:.4} deg (more than {tolerance_deg} deg apart); the pair is not one motion"
    )]
    InconsistentMotion {
        /// The pair's index.
        index: usize,
        /// Rotation of A (degrees).
        a_deg: f64,
        /// Rotation of B (degrees).
        b_deg: f64,
        /// Allowed difference (degrees).
        tolerance_deg: f64,
    },
    /// Hand-eye: a pair's translation does not fit the solution of all of them (a motion
    /// measured wrong, or pairs of different motions).
    #[error(
        "motion {index} does not fit the others: its translation residual is {residual_mm:.3} mm (more than {tolerance_mm} mm); measure it again or leave it out"
    )]
    TranslationDoesNotFit {
        /// The pair's index.
        index: usize,
        /// Its translation residual (mm).
        residual_mm: f64,
        /// Allowed (mm).
        tolerance_mm: f64,
    },
    /// Hand-eye: a pair does not fit the solution of all of them (a motion measured wrong,
    /// or pairs of different motions).
    #[error(
        "motion {index} does not fit the others: its rotation residual is {residual_deg:.3} deg (more than {tolerance_deg} deg); measure it again or leave it out"
    )]
    PairDoesNotFit {
        /// The pair's index.
        index: usize,
        /// Its rotation residual (degrees).
        residual_deg: f64,
        /// Allowed (degrees).
        tolerance_deg: f64,
    },
    /// Hand-eye: all rotation axes are nearly parallel, so the rotation about them is not
    /// observable.
    #[error(
        "the rotation axes of the motions are nearly parallel (largest angle between two axes {largest_deg:.3} deg, at least {min_deg} deg needed): rotate the station about a second, different axis"
    )]
    ParallelAxes {
        /// Largest angle between two motion axes (degrees).
        largest_deg: f64,
        /// The least accepted (degrees).
        min_deg: f64,
    },
    /// A plate description that cannot be a plate.
    #[error("invalid plate: {reason}")]
    PlateInvalid {
        /// What is wrong.
        reason: String,
    },
    /// The plate is not (wholly) in the frame.
    #[error("plate not found: {reason}")]
    PlateNotFound {
        /// What was found instead.
        reason: String,
    },
    /// The views cannot calibrate the camera.
    #[error("calibration refused: {reason}")]
    CalibrationRefused {
        /// Why, and what to change.
        reason: String,
    },
}
