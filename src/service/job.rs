//! The writer's jobs: each a request and the channel its typed answer goes to.
//!
//! A [`Call`] carries its request, its reply channel and the answer it will give, which is
//! "not applied" until the job is done in a transaction that commits. Whatever fails (a
//! statement, the commit, a cancelled task), every requester is answered: with its answer
//! after the commit, or with the commit's failure.

use super::{IngestItem, IngestReport, Pruned, ReferenceRequest, ServiceError, ServiceResult};
use crate::chain::LinkId;
use crate::geometry::PoseCov;
use crate::model::TargetId;
use tokio::sync::oneshot;

/// A request to the writer, its reply channel, and the answer it will give.
pub(crate) struct Call<R, A> {
    /// What is asked.
    pub(crate) request: R,
    /// The answer so far: "not applied" until the job is done.
    pub(crate) answer: ServiceResult<A>,
    reply: oneshot::Sender<ServiceResult<A>>,
}

impl<R, A> Call<R, A> {
    /// A call whose answer is "not applied" until the job is done.
    pub(crate) fn new(request: R, reply: oneshot::Sender<ServiceResult<A>>) -> Self {
        Self {
            request,
            answer: Err(ServiceError::CommitFailed(
                "the transaction failed before this request was applied".into(),
            )),
            reply,
        }
    }

    /// Sends the answer. A requester that gave up (a closed connection) no longer listens:
    /// nothing to do then.
    fn send(self) {
        let _ = self.reply.send(self.answer);
    }

    /// Answers with the commit's failure, whatever the job's own answer was.
    fn fail(self, message: &str) {
        let _ = self
            .reply
            .send(Err(ServiceError::CommitFailed(message.to_owned())));
    }
}

/// A new reference for a target.
pub(crate) struct SetReference {
    pub(crate) target: TargetId,
    pub(crate) request: ReferenceRequest,
}

/// One pass of retention.
pub(crate) struct Prune {
    pub(crate) retention: crate::config::RetentionSettings,
    /// On a fleet's site: whether raw samples are uploaded (what is not yet acknowledged is
    /// then kept); `None` when nothing is uploaded.
    pub(crate) upstream_raw: Option<bool>,
}

/// The centre's acknowledgement of a tier's commits up to `seq`.
pub(crate) struct RecordAck {
    pub(crate) tier: crate::store::outbox::Tier,
    pub(crate) seq: i64,
}

/// A new calibration of a calibrated link.
pub(crate) struct AddCalibration {
    pub(crate) link: LinkId,
    pub(crate) valid_from_ns: i64,
    pub(crate) parent_from_child: PoseCov,
}

/// A manual restart of a measured link's filter.
pub(crate) struct ResetLink {
    pub(crate) link: LinkId,
    pub(crate) by: Option<String>,
    pub(crate) note: Option<String>,
}

/// Someone's acknowledgement of an alarm transition.
pub(crate) struct AcknowledgeAlarm {
    pub(crate) id: i64,
    pub(crate) by: String,
    pub(crate) note: Option<String>,
}

/// An acceptance of the rig to record.
pub(crate) struct RecordAcceptance {
    pub(crate) by: String,
    pub(crate) note: Option<String>,
    pub(crate) passed: bool,
    pub(crate) record_json: String,
}

impl RecordAcceptance {
    /// The row it is stored as.
    pub(crate) fn row(&self) -> crate::store::NewAcceptance<'_> {
        crate::store::NewAcceptance {
            by: &self.by,
            note: self.note.as_deref(),
            passed: self.passed,
            record_json: &self.record_json,
        }
    }
}

/// One job of the writer.
#[allow(
    clippy::large_enum_variant,
    reason = "one per request on the queue; boxing buys nothing"
)]
pub(crate) enum Job {
    Ingest(Call<Vec<IngestItem>, IngestReport>),
    SetReference(Call<SetReference, crate::deformation::ReferenceVersion>),
    Prune(Call<Prune, Pruned>),
    RecordAck(Call<RecordAck, ()>),
    AddCalibration(Call<AddCalibration, i64>),
    ResetLink(Call<ResetLink, i64>),
    CheckLiveness(Call<(), usize>),
    AcknowledgeAlarm(Call<AcknowledgeAlarm, ()>),
    RecordAcceptance(Call<RecordAcceptance, (i64, i64)>),
}

/// Runs `$body` with `$call` bound to the job's call, whatever its kind.
macro_rules! on_call {
    ($job:expr, $call:ident => $body:expr) => {
        match $job {
            Job::Ingest($call) => $body,
            Job::SetReference($call) => $body,
            Job::Prune($call) => $body,
            Job::RecordAck($call) => $body,
            Job::AddCalibration($call) => $body,
            Job::ResetLink($call) => $body,
            Job::CheckLiveness($call) => $body,
            Job::AcknowledgeAlarm($call) => $body,
            Job::RecordAcceptance($call) => $body,
        }
    };
}

impl Job {
    /// Sends the job's answer (after its transaction committed).
    pub(crate) fn answer(self) {
        on_call!(self, call => call.send());
    }

    /// Answers with the commit's failure.
    pub(crate) fn fail(self, message: &str) {
        on_call!(self, call => call.fail(message));
    }
}
