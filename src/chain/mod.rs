//! Relay chains: the graph of frames and links, path resolution, composition and fusion.
//!
//! Frames (B, C1, C2, M, C3, G, ...) are the nodes; links `parent_from_child` are the edges.
//! A target is resolved from its base by walking links forwards (`parent_from_child` takes us
//! from the child frame to the parent) or inverted. Composing the steps of a path gives
//! `target_from_base` with its covariance (`docs/interface.md`, "Conventions" and "Filtering"). Where several
//! link-disjoint paths reach a target, their estimates are independent and are fused by
//! information weighting, with a chi-square statistic of their disagreement.

mod compose;
mod error;
mod fuse;
mod sources;
mod topology;

pub use compose::compose_path;
pub use error::ChainError;
pub use fuse::{Consistency, DEFAULT_CONSISTENCY_PROBABILITY, Fused, chi_square_quantile, fuse};
pub use sources::{
    Budget, BudgetLine, Contributor, ContributorKind, ErrorTerms, FACTOR_COLUMNS, Factor,
    IntrinsicsCovariance, SourcedPose, Term, UncertaintyPart, axis_variances, budget_sigmas,
    compose_path_terms, factor_of_covariance, fuse_terms, intrinsics_root,
};
pub use topology::{Direction, FrameId, LinkEnds, LinkId, Path, Resolution, Step, Topology};
