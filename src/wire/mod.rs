//! The JSON documents more than one door reads or writes: poses and sigmas (in every answer
//! and every sample), observations (written by the detector, posted by the simulator's feed,
//! read by `POST /observations`), and the hand-eye and camera calibrations' requests and results
//! (the HTTP API's bodies and the calibration commands' files). Each converts itself to the
//! core's types, naming every field that does not hold what it must; how a refusal is told
//! (an HTTP 422, a command's message) is the reader's. A shape only one endpoint has lives with
//! that endpoint in `api`.

mod calibration;
mod hand_eye;
pub mod json;
mod observation;
mod pose;

pub use calibration::{
    CalibrationWarningOut, CameraCalibrationIn, CameraCalibrationOut, PlateIn, PlatePolarity,
    parse_fix,
};
pub use hand_eye::{HandEyeIn, HandEyeOut};
pub use json::parse;
pub use observation::ObservationIn;
pub use pose::{
    FieldProblem, PoseIn, PoseOut, SigmaIn, SigmaOut, clip, covariance_from,
    rotation_vector_arcsec, sigma_schema, time_schema,
};

/// Why a document was not turned into what it asks for.
#[derive(Debug, thiserror::Error)]
pub enum Rejection {
    /// The text is not UTF-8 or not JSON (the message says where).
    #[error("{0}")]
    Malformed(String),
    /// Fields that do not hold what they must, each named; nothing was computed.
    #[error("{message}")]
    Invalid {
        /// A summary (`2 invalid field(s)`).
        message: String,
        /// Every problem found.
        problems: Vec<FieldProblem>,
    },
    /// Valid input the computation cannot use (too few views, motions about parallel axes).
    #[error(transparent)]
    Refused(#[from] crate::vision::VisionError),
}

impl Rejection {
    /// One field's problem.
    pub fn field(field: impl Into<String>, message: impl Into<String>) -> Self {
        let problem = FieldProblem::new(field, message);
        Self::Invalid {
            message: format!("`{}`: {}", problem.field, problem.message),
            problems: vec![problem],
        }
    }

    /// The rejection as text: the summary, then each problem on a line of its own
    /// (`[3] pose.q_wxyz: ...`).
    pub fn describe(&self) -> String {
        let mut text = self.to_string();
        if let Self::Invalid { problems, .. } = self {
            for p in problems {
                text.push_str("\n  ");
                if let Some(i) = p.index {
                    text.push_str(&format!("[{i}] "));
                }
                text.push_str(&format!("{}: {}", p.field, p.message));
            }
        }
        text
    }
}
