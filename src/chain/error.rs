//! Errors of chain resolution and composition.

/// A topology or composition problem, naming the frame, link or path concerned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ChainError {
    /// A frame name that no link, camera or marker introduces.
    #[error("unknown frame `{0}`")]
    UnknownFrame(String),
    /// Two links with the same name.
    #[error("duplicate link `{0}`")]
    DuplicateLink(String),
    /// A link joining a frame to itself.
    #[error("link `{0}` joins a frame to itself")]
    SelfLink(String),
    /// No path of links joins the target to its base.
    #[error("target `{target}` is unreachable from base `{base}`: no chain of links joins them")]
    Unreachable {
        /// The target frame.
        target: String,
        /// The base frame.
        base: String,
    },
    /// A target that is its own base.
    #[error("target `{0}` is its own base")]
    TargetIsBase(String),
    /// Fusion needs invertible covariances.
    #[error("estimate {index} has a singular covariance; it cannot be information-weighted")]
    SingularCovariance {
        /// Index of the offending estimate.
        index: usize,
    },
    /// Fusion of nothing.
    #[error("nothing to fuse")]
    NothingToFuse,
}
