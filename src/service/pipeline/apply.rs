//! The jobs other than ingest done inside a transaction of the pipeline's own (a reference,
//! a prune, a calibration, a restart of a link's filter, an acknowledgement), and what a
//! commit group's jobs change besides their answers.

use super::*;

/// What a commit group's jobs changed besides their answers, acted on after the commit (or
/// undone when it fails).
#[derive(Default)]
pub(super) struct Effects {
    /// Alarm transitions stored, for the notifier and live events.
    pub(super) transitions: Vec<StoredAlarm>,
    /// What goes to the visualisation.
    pub(super) viz_records: Vec<crate::viz::Record>,
    /// Calibrations added to the bank, removed again if the commit fails.
    pub(super) added_calibrations: Vec<(LinkId, i64)>,
}

/// What a job may touch inside the transaction.
pub(super) struct Step<'a, 'c> {
    pub(super) tx: &'a mut WriteTx<'c>,
    pub(super) bank: &'a mut FilterBank,
    pub(super) targets: &'a mut [TargetView],
    /// The visualisation, when it records.
    pub(super) viz: Option<&'a mut crate::viz::VizSender>,
    pub(super) now: i64,
    /// `[server] clock_tolerance_s`.
    pub(super) clock_tolerance_s: f64,
    pub(super) effects: &'a mut Effects,
}

/// Does one job in the transaction, setting its answer. An `Err` fails the whole transaction.
pub(super) async fn apply(job: &mut Job, step: &mut Step<'_, '_>) -> Result<(), StoreError> {
    match job {
        Job::Ingest(call) => {
            call.answer = apply_ingest(step, std::mem::take(&mut call.request)).await?;
        }
        Job::SetReference(call) => call.answer = apply_reference(step, &call.request).await?,
        Job::Prune(call) => call.answer = Ok(apply_prune(step, &call.request).await?),
        Job::RecordAck(call) => {
            let r = &call.request;
            step.tx.record_ack(r.tier, r.seq, step.now).await?;
            call.answer = Ok(());
        }
        Job::AddCalibration(call) => call.answer = apply_calibration(step, &call.request).await?,
        Job::ResetLink(call) => call.answer = apply_reset(step, &call.request).await?,
        Job::RecordAcceptance(call) => {
            let id = step
                .tx
                .insert_acceptance(&call.request.row(), step.now)
                .await?;
            call.answer = Ok((id, step.now));
        }
        Job::CheckLiveness(call) => {
            let raised = judge_liveness(step.bank, step.targets, step.now, step.clock_tolerance_s);
            let t = store_alarms(step.tx, &raised, step.now).await?;
            call.answer = Ok(t.len());
            step.effects.transitions.extend(t);
        }
        Job::AcknowledgeAlarm(call) => call.answer = apply_acknowledge(step, &call.request).await?,
    }
    Ok(())
}

async fn apply_ingest(
    step: &mut Step<'_, '_>,
    items: Vec<IngestItem>,
) -> Result<ServiceResult<IngestReport>, StoreError> {
    let mut t = Vec::new();
    let collect = step.viz.as_deref_mut().map(|sender| VizCollect {
        sender,
        records: &mut step.effects.viz_records,
    });
    let answer = ingest(
        step.tx,
        step.bank,
        step.targets,
        items,
        step.now,
        &mut t,
        collect,
    )
    .await?;
    step.effects.transitions.extend(t);
    Ok(answer)
}

async fn apply_reference(
    step: &mut Step<'_, '_>,
    r: &job::SetReference,
) -> Result<ServiceResult<ReferenceVersion>, StoreError> {
    let answer = set_reference(step.tx, step.targets, r.target, r.request, step.now).await?;
    if step.viz.is_some()
        && let Ok(current) = &answer
    {
        step.effects
            .viz_records
            .push(crate::viz::Record::Reference {
                target: r.target,
                time_ns: step.targets[r.target.0]
                    .latest
                    .as_ref()
                    .map_or(step.now, |l| l.time_ns),
                g0_from_b: current.reference.g0_from_b.whole.pose,
            });
    }
    Ok(answer)
}

/// One pass of retention: the ages, then the disk budget; a site keeps what the centre has
/// not acknowledged (unless the budget forces otherwise).
async fn apply_prune(step: &mut Step<'_, '_>, r: &job::Prune) -> Result<Pruned, StoreError> {
    let keep = match r.upstream_raw {
        None => KeepUnsent::default(),
        Some(raw) => KeepUnsent::from_acks(&step.tx.upstream_acks().await?, raw),
    };
    let newest = step
        .targets
        .iter()
        .filter_map(|t| t.latest.as_ref().map(|l| l.time_ns))
        .max();
    let (samples, results) = match r.retention.cutoffs_ns(newest, step.now) {
        Some((samples_before, results_before)) => {
            step.tx.prune(samples_before, results_before, keep).await?
        }
        None => (0, 0),
    };
    let budget = match r.retention.disk_budget_bytes {
        Some(b) => Some(step.tx.shrink_to_budget(b, keep).await?),
        None => None,
    };
    Ok(Pruned {
        samples,
        results,
        budget,
    })
}

async fn apply_calibration(
    step: &mut Step<'_, '_>,
    r: &job::AddCalibration,
) -> Result<ServiceResult<i64>, StoreError> {
    let version = step
        .tx
        .insert_calibration(r.link, r.valid_from_ns, &r.parent_from_child, step.now)
        .await?;
    Ok(
        if step
            .bank
            .add_calibration(r.link, r.valid_from_ns, r.parent_from_child)
        {
            step.effects
                .added_calibrations
                .push((r.link, r.valid_from_ns));
            Ok(version)
        } else {
            Err(ServiceError::Invalid {
                message: "only calibrated links take calibrations".into(),
                problems: Vec::new(),
            })
        },
    )
}

async fn apply_reset(
    step: &mut Step<'_, '_>,
    r: &job::ResetLink,
) -> Result<ServiceResult<i64>, StoreError> {
    if !step.bank.reset_link(r.link) {
        return Ok(Err(ServiceError::Invalid {
            message: "only measured links have a filter to reset".into(),
            problems: Vec::new(),
        }));
    }
    step.tx
        .insert_link_reset(r.link, r.by.as_deref(), r.note.as_deref(), step.now)
        .await?;
    Ok(Ok(step.now))
}

async fn apply_acknowledge(
    step: &mut Step<'_, '_>,
    r: &job::AcknowledgeAlarm,
) -> Result<ServiceResult<()>, StoreError> {
    use crate::alarms::{AckRefusal, Acknowledging, Level, acknowledging};
    let id = r.id;
    let Some((to, prev_by, prev_note)) = step.tx.alarm_ack_state(id).await? else {
        return Ok(Err(ServiceError::NotFound(format!("no alarm {id}"))));
    };
    let Some(to) = Level::parse(&to) else {
        // A damaged row refuses this request alone, not the group's transaction.
        return Ok(Err(ServiceError::Storage(StoreError::Malformed(format!(
            "alarm {id} has the unknown level `{to}`"
        )))));
    };
    let previous = prev_by.as_deref().map(|b| (b, prev_note.as_deref()));
    Ok(
        match acknowledging(to, previous, &r.by, r.note.as_deref()) {
            Ok(Acknowledging::AlreadyRecorded) => Ok(()),
            Ok(Acknowledging::Record) => {
                step.tx
                    .acknowledge_alarm(id, &r.by, r.note.as_deref(), step.now)
                    .await?;
                Ok(())
            }
            Err(AckRefusal::ReturnToNone) => Err(ServiceError::Invalid {
                message: format!(
                    "alarm {id} is a return to `none`: there is nothing to acknowledge"
                ),
                problems: vec![ItemProblem {
                    index: None,
                    field: Some("id".into()),
                    message: "a transition back to `none`".into(),
                }],
            }),
            Err(AckRefusal::AlreadyAcknowledged { by }) => Err(ServiceError::Conflict {
                message: format!("alarm {id} was already acknowledged by `{by}`"),
                problems: Vec::new(),
            }),
        },
    )
}

async fn set_reference(
    tx: &mut WriteTx<'_>,
    targets: &mut [TargetView],
    target: TargetId,
    request: ReferenceRequest,
    now: i64,
) -> Result<ServiceResult<ReferenceVersion>, StoreError> {
    let reference = match request {
        ReferenceRequest::Explicit(pose) => Reference::explicit(pose),
        ReferenceRequest::Window { from_ns, to_ns } => {
            let rows = tx.filtered_poses(target, from_ns, to_ns).await?;
            let poses: Vec<_> = rows.iter().map(|r| r.estimate).collect();
            match Reference::from_window(&poses, from_ns, to_ns) {
                Ok(r) => r,
                Err(_) => {
                    return Ok(Err(ServiceError::Invalid {
                        message: "there are no filtered results in the window".into(),
                        problems: vec![ItemProblem {
                            index: None,
                            field: Some("from".into()),
                            message: "no filtered result lies between `from` and `to`".into(),
                        }],
                    }));
                }
            }
        }
    };
    let version = tx.insert_reference(target, &reference, now).await?;
    let current = ReferenceVersion {
        version,
        reference,
        created_ns: now,
    };
    targets[target.0].reference = Some(current);
    Ok(Ok(current))
}
