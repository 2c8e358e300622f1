//! The vocabularies of the HTTP API: each a [`crate::words!`] enum, documented in the OpenAPI
//! document as a string with its words listed (from the enum's `ALL`, so the document cannot
//! drift from what is sent), and the few vocabularies only responses use.

use crate::words::Word;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{ObjectBuilder, Schema, Type};

/// The schema of a vocabulary: a string whose values are its words.
fn word_schema<W: Word>() -> RefOr<Schema> {
    ObjectBuilder::new()
        .schema_type(Type::String)
        .description(Some(format!("A {}.", W::WHAT)))
        .enum_values(Some(W::words()))
        .build()
        .into()
}

/// Gives each vocabulary its OpenAPI schema (named after the type).
macro_rules! word_schemas {
    ($($t:ty),+ $(,)?) => {
        $(
            impl utoipa::PartialSchema for $t {
                fn schema() -> RefOr<Schema> {
                    word_schema::<$t>()
                }
            }
            impl utoipa::ToSchema for $t {}
        )+
    };
}

word_schemas!(
    crate::acceptance::Phase,
    crate::acceptance::Standing,
    crate::acceptance::StepKind,
    crate::acquire::SourceStatus,
    crate::alarms::AlarmKind,
    crate::alarms::Level,
    crate::alarms::ValueUnit,
    crate::archive::ArchiveReason,
    crate::bank::ResultSource,
    crate::bank::TargetStatus,
    crate::config::NotifyLevel,
    crate::config::TimestampMode,
    crate::config::TriggerMode,
    crate::filter::DispositionKind,
    crate::filter::MotionModel,
    crate::outputs::OutputKind,
    crate::fleet::protocol::Outcome,
    crate::service::LinkState,
    crate::store::outbox::Tier,
    crate::vision::Intrinsic,
    crate::vision::WarningKind,
    super::error::ErrorCode,
    super::frames::NotFoundCode,
    crate::service::CompensationSource,
    ContributorKind,
    HealthStatus,
    LinkKindName,
    RawRequestState,
    ReferenceOriginKind,
    UncertaintyPart,
);

crate::words! {
    /// The service's health (`GET /healthz`).
    pub enum HealthStatus("health status") {
        /// Every check passes.
        Ok = "ok",
        /// A check fails: the problems say which.
        Unavailable = "unavailable",
    }
}

crate::words! {
    /// What kind of link (`GET /api/v1/links`).
    pub enum LinkKindName("link kind") {
        /// A camera that sees a marker measures it.
        Measured = "measured",
        /// A rigid station's calibrated transform.
        Calibrated = "calibrated",
    }
}

crate::words! {
    /// Where an office's request for a site's raw rows stands.
    pub enum RawRequestState("raw request state") {
        /// The site has not delivered all of it yet.
        Pending = "pending",
        /// Delivered.
        Done = "done",
        /// Withdrawn by the office first.
        Cancelled = "cancelled",
    }
}

crate::words! {
    /// How a reference was set.
    pub enum ReferenceOriginKind("reference origin") {
        /// Given explicitly: exact.
        Explicit = "explicit",
        /// The mean of filtered results over a window.
        Window = "window",
    }
}

pub use super::frames::NotFoundCode;
pub use crate::chain::{ContributorKind, UncertaintyPart};
pub use crate::service::CompensationSource;
