//! The acceptance procedure against the running service: one run at a time, its steps judged
//! on the stored raw results, its record kept in the store (`docs/interface.md`,
//! "Acceptance").
//!
//! The run lives in memory: the operator (a person with `brokenray acceptance`, a stage's
//! script, the simulator) starts it, places each step and says so; each read of the run moves
//! it on as far as the stored results allow ([`crate::acceptance::Procedure`] decides). When
//! the last step is done the record is written by the writer and the run stays, finished,
//! until the next starts. A restart forgets a run that had not finished (nothing of it was
//! stored). A step whose targets' results stop coming is judged on what came once its deadline
//! on the server's clock passes, so a camera that stops fails the step instead of holding the
//! run.
//!
//! Where a recorded acceptance stands ([`crate::acceptance::Standing`]): failed; no longer
//! holding when a calibrated link of a target it accepted was calibrated since, a measured
//! link's filter reset since, or the target's newest results carry other calibrations than
//! those accepted; due once its reverification interval is over; valid otherwise.

use super::{Service, ServiceError, ServiceResult, job};
use crate::acceptance::{
    Displacement, Limits, MoveFigures, Offered, Phase, Procedure, Standing, StepFigures, StepKind,
    StillFigures, standing,
};
use crate::bank::ResultSource;
use crate::clock::format_ns;
use crate::deformation::CalibrationStamp;
use crate::model::TargetId;
use crate::store::{StoreResult, StoredAcceptance};

/// The most raw results a window is read with (an hour at 25 Hz is 90 000).
const MAX_WINDOW_RESULTS: i64 = 400_000;

/// How long past a step's expected end (on the server's clock) its results are waited for.
const STEP_GRACE_NS: i64 = 60_000_000_000;

/// How long `/healthz` waits for the acceptances' standing.
const HEALTH_READ_LIMIT: std::time::Duration = std::time::Duration::from_secs(2);

/// What the store says now of what an acceptance accepted: each link's newest manual reset,
/// each link's newest calibration (ns, server clock), each target's newest raw result (its
/// time and calibration stamp).
struct CurrentState {
    resets: Vec<(crate::chain::LinkId, i64, Option<String>, Option<String>)>,
    calibrated_ns: Vec<Option<i64>>,
    latest: Vec<Option<(i64, Option<i64>)>>,
}

/// A run in memory.
pub(super) struct Run {
    procedure: Procedure,
    by: String,
    note: Option<String>,
    started_ns: i64,
    /// When the current step's results stop being waited for (server clock).
    deadline_ns: Option<i64>,
    /// The calibrations of every result each target's windows held.
    stamps: Vec<Vec<Option<CalibrationStamp>>>,
    /// Once recorded: its id and whether it passed.
    recorded: Option<(i64, bool)>,
}

/// A planned step as the run shows it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct PlannedStepOut {
    /// Its name.
    pub name: String,
    /// Still window or known move.
    pub kind: StepKind,
    /// The target a move moves (none for the still window, which measures every target).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target: Option<String>,
    /// The stated displacement: rotation vector (arc-seconds) and translation (mm).
    #[schema(value_type = Object)]
    pub stated: Displacement,
    /// Whether it passed, once done.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub passed: Option<bool>,
}

/// A time window.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct WindowOut {
    /// Its start (RFC 3339, measurement time).
    pub from: String,
    /// Its end.
    pub to: String,
}

/// A run of the procedure, as its operator follows it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct RunOut {
    /// Who runs it.
    pub by: String,
    /// Their note.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// When it started (server clock).
    pub started: String,
    /// Where it is.
    pub phase: Phase,
    /// The current step's index in `steps` (none once finished).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step: Option<usize>,
    /// What the operator is to do now.
    pub instruction: String,
    /// The window being measured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub window: Option<WindowOut>,
    /// How many times the current window slid on because its results had not settled.
    pub slides: u32,
    /// Every step, in order.
    pub steps: Vec<PlannedStepOut>,
    /// Once finished: the recorded acceptance's id.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub acceptance_id: Option<i64>,
    /// Once finished: whether it passed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub passed: Option<bool>,
}

/// A target as an acceptance accepted it.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct AcceptedTarget {
    /// The target.
    pub target: String,
    /// The calibrations its results were measured with (none when they changed during the
    /// run, which fails it).
    pub calibration_stamp: Option<i64>,
    /// The links on its paths.
    pub links: Vec<String>,
}

/// A still target's figures in a record.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct StillOut {
    /// The target.
    pub target: String,
    /// Its figures (axes: rotation x, y, z in arc-seconds, translation x, y, z in mm).
    #[serde(flatten)]
    #[schema(value_type = Object)]
    pub figures: StillFigures,
}

/// A step done, in a record.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct StepOut {
    /// Its name.
    pub name: String,
    /// Still window or known move.
    pub kind: StepKind,
    /// The target a move moved.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target: Option<String>,
    /// Its window (measurement time).
    pub window: WindowOut,
    /// Whether it passed.
    pub passed: bool,
    /// Why it has no figures (it did not settle, too few results).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub problem: Option<String>,
    /// The still window's figures per target.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub still: Vec<StillOut>,
    /// A move's figures (axes: rotation x, y, z in arc-seconds, translation x, y, z in mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Object>)]
    pub moved: Option<MoveFigures>,
}

/// The record of an acceptance, as stored.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct AcceptanceRecord {
    /// The installation it was run on.
    pub installation: String,
    /// When the run started (server clock).
    pub started: String,
    /// The limits it was judged by.
    #[schema(value_type = Object)]
    pub limits: Limits,
    /// How long it holds (days).
    pub reverify_every_days: f64,
    /// The targets and what they were measured with.
    pub targets: Vec<AcceptedTarget>,
    /// The steps.
    pub steps: Vec<StepOut>,
    /// The names of the steps that failed, and of the targets whose calibrations changed
    /// during the run.
    pub failed: Vec<String>,
}

/// A recorded acceptance and where it stands.
#[derive(Debug, Clone, serde::Serialize, utoipa::ToSchema)]
pub struct AcceptanceSummary {
    /// Its id.
    pub id: i64,
    /// When it was recorded (server clock).
    pub at: String,
    /// Who ran it.
    pub by: String,
    /// Their note.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
    /// Whether it passed.
    pub passed: bool,
    /// Where it stands now.
    pub standing: Standing,
    /// When reverification is due.
    pub due: String,
    /// What changed since that it no longer holds.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub changed: Vec<String>,
    /// The names of its failed steps.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub failed: Vec<String>,
}

/// A recorded acceptance whole.
#[derive(Debug, Clone, serde::Serialize, utoipa::ToSchema)]
pub struct AcceptanceOut {
    /// Where it stands.
    #[serde(flatten)]
    pub summary: AcceptanceSummary,
    /// Its record.
    pub record: AcceptanceRecord,
}

fn conflict(message: impl Into<String>) -> ServiceError {
    ServiceError::Conflict {
        message: message.into(),
        problems: Vec::new(),
    }
}

fn no_procedure() -> ServiceError {
    ServiceError::Invalid {
        message: "the installation states no [acceptance]: no procedure to run".into(),
        problems: Vec::new(),
    }
}

impl Service {
    fn acceptance_settings(&self) -> ServiceResult<&crate::config::AcceptanceSettings> {
        self.installation()
            .acceptance
            .as_ref()
            .ok_or_else(no_procedure)
    }

    fn target_name(&self, t: usize) -> String {
        self.installation().model.targets[t].name.clone()
    }

    /// Starts a run (admin): `Conflict` while another is measuring.
    pub async fn start_acceptance(
        &self,
        by: String,
        note: Option<String>,
    ) -> ServiceResult<RunOut> {
        let settings = self.acceptance_settings()?;
        let mut slot = self.inner.acceptance.lock().await;
        if let Some(run) = slot.as_ref()
            && run.procedure.phase() != Phase::Finished
        {
            return Err(conflict(format!(
                "an acceptance by {} started at {} is running: finish it or abandon it first",
                run.by,
                format_ns(run.started_ns)
            )));
        }
        let plan = settings.plan.clone();
        let run = Run {
            stamps: vec![Vec::new(); plan.targets],
            procedure: Procedure::new(plan),
            by,
            note,
            started_ns: self.now_ns(),
            deadline_ns: None,
            recorded: None,
        };
        let out = self.run_out(&run);
        *slot = Some(run);
        Ok(out)
    }

    /// The run, moved on as far as the stored results allow; `None` when none was started.
    pub async fn acceptance_run(&self) -> ServiceResult<Option<RunOut>> {
        let mut slot = self.inner.acceptance.lock().await;
        let Some(run) = slot.as_mut() else {
            return Ok(None);
        };
        self.advance(run).await?;
        Ok(Some(self.run_out(run)))
    }

    /// The operator placed the current step: its results settle from the newest raw result of
    /// its targets (measurement time, so a rig whose clock runs apart from the server's is
    /// judged on its own times). `Conflict` while the step is measured or when a target has
    /// no raw result at all.
    pub async fn acceptance_ready(&self) -> ServiceResult<RunOut> {
        let mut slot = self.inner.acceptance.lock().await;
        let Some(run) = slot.as_mut() else {
            return Err(ServiceError::NotFound("no acceptance is running".into()));
        };
        self.advance(run).await?;
        let Some(k) = run.procedure.current() else {
            return Err(conflict("the acceptance has finished: start a new one"));
        };
        if run.procedure.phase() != Phase::AwaitingOperator {
            return Err(conflict(format!(
                "step `{}` is being measured: wait until it asks for the next",
                run.procedure.plan().step_name(k)
            )));
        }
        let mut newest = i64::MIN;
        for t in run.procedure.plan().step_targets(k) {
            let latest = self
                .store()
                .latest_result(TargetId(t), ResultSource::Raw)
                .await?;
            let Some(latest) = latest else {
                return Err(conflict(format!(
                    "target {} has no raw result yet: the rig must be measuring before a step is placed",
                    self.target_name(t)
                )));
            };
            newest = newest.max(latest.time_ns);
        }
        let now = self.now_ns();
        run.procedure.ready(newest);
        let plan = run.procedure.plan();
        let length = if k == 0 { plan.still_ns } else { plan.step_ns };
        let span =
            (plan.settle_ns + length) * (i64::from(crate::acceptance::procedure::MAX_SLIDES) + 1);
        run.deadline_ns = Some(now.saturating_add(span).saturating_add(STEP_GRACE_NS));
        Ok(self.run_out(run))
    }

    /// Abandons the run (nothing of it is stored).
    pub async fn abandon_acceptance(&self) -> ServiceResult<()> {
        let mut slot = self.inner.acceptance.lock().await;
        match slot.take() {
            Some(_) => Ok(()),
            None => Err(ServiceError::NotFound("no acceptance is running".into())),
        }
    }

    /// Judges the current window as often as the stored results allow, and records the run
    /// once its last step is done.
    async fn advance(&self, run: &mut Run) -> ServiceResult<()> {
        while let (Some(k), Some((from, to))) = (run.procedure.current(), run.procedure.window_ns())
        {
            let targets = run.procedure.plan().step_targets(k);
            let mut complete = true;
            for &t in &targets {
                let latest = self
                    .store()
                    .latest_result(TargetId(t), ResultSource::Raw)
                    .await?;
                complete &= latest.is_some_and(|r| r.time_ns > to);
            }
            let overdue = run.deadline_ns.is_some_and(|d| self.now_ns() >= d);
            if !complete && !overdue {
                break;
            }
            let mut windows = Vec::with_capacity(targets.len());
            for &t in &targets {
                let results = self
                    .store()
                    .results(TargetId(t), ResultSource::Raw, from, to, MAX_WINDOW_RESULTS)
                    .await?;
                run.stamps[t].extend(results.iter().map(|r| r.estimate.calibration));
                windows.push(results.iter().map(|r| r.estimate).collect::<Vec<_>>());
            }
            if run.procedure.offer(&windows) == Offered::StepDone {
                run.deadline_ns = None;
            }
        }
        if run.procedure.phase() == Phase::Finished && run.recorded.is_none() {
            let record = self.record_of(run);
            let passed = record.failed.is_empty();
            let record_json = serde_json::to_string(&record).map_err(|e| {
                ServiceError::CommitFailed(format!(
                    "the acceptance's record cannot be written: {e}"
                ))
            })?;
            let (id, _) = self
                .submit(
                    job::RecordAcceptance {
                        by: run.by.clone(),
                        note: run.note.clone(),
                        passed,
                        record_json,
                    },
                    job::Job::RecordAcceptance,
                )
                .await?;
            run.recorded = Some((id, passed));
            tracing::info!(id, passed, by = %run.by, "acceptance recorded");
        }
        Ok(())
    }

    fn planned_steps(&self, run: &Run) -> Vec<PlannedStepOut> {
        let plan = run.procedure.plan();
        (0..plan.steps())
            .map(|k| PlannedStepOut {
                name: plan.step_name(k).to_owned(),
                kind: plan.step_kind(k),
                target: (k > 0).then(|| self.target_name(plan.moves[k - 1].target)),
                stated: if k == 0 {
                    Displacement::ZERO
                } else {
                    plan.moves[k - 1].displacement
                },
                passed: run.procedure.done().get(k).map(|d| d.figures.passed()),
            })
            .collect()
    }

    fn run_out(&self, run: &Run) -> RunOut {
        let p = &run.procedure;
        let plan = p.plan();
        let instruction = match (p.phase(), p.current()) {
            (Phase::AwaitingOperator, Some(0)) => {
                "keep every target still, then say ready: the still window is measured".to_owned()
            }
            (Phase::AwaitingOperator, Some(k)) => {
                let m = &plan.moves[k - 1];
                let d = m.displacement;
                format!(
                    "move target {} from where it stood still by rotation [{}, {}, {}] arc-seconds and translation [{}, {}, {}] mm (step `{}`), then say ready",
                    self.target_name(m.target),
                    d.rotation_arcsec[0],
                    d.rotation_arcsec[1],
                    d.rotation_arcsec[2],
                    d.translation_mm[0],
                    d.translation_mm[1],
                    d.translation_mm[2],
                    m.name
                )
            }
            (Phase::Measuring, Some(k)) => format!(
                "hold still: step `{}` settles, then its window is measured",
                plan.step_name(k)
            ),
            _ => match run.recorded {
                Some((id, true)) => format!("finished: acceptance {id} passed"),
                Some((id, false)) => format!("finished: acceptance {id} failed"),
                None => "finished: the record is being written".to_owned(),
            },
        };
        RunOut {
            by: run.by.clone(),
            note: run.note.clone(),
            started: format_ns(run.started_ns),
            phase: p.phase(),
            step: p.current(),
            instruction,
            window: p.window_ns().map(|(from, to)| WindowOut {
                from: format_ns(from),
                to: format_ns(to),
            }),
            slides: p.slides(),
            steps: self.planned_steps(run),
            acceptance_id: run.recorded.map(|(id, _)| id),
            passed: run.recorded.map(|(_, passed)| passed),
        }
    }

    fn record_of(&self, run: &Run) -> AcceptanceRecord {
        let inst = self.installation();
        let plan = run.procedure.plan();
        let settings = inst.acceptance.as_ref();
        let mut failed = Vec::new();
        let steps: Vec<StepOut> = run
            .procedure
            .done()
            .iter()
            .enumerate()
            .map(|(k, done)| {
                let passed = done.figures.passed();
                if !passed {
                    failed.push(plan.step_name(k).to_owned());
                }
                let (problem, still, moved) = match &done.figures {
                    StepFigures::Still(targets) => (
                        None,
                        targets
                            .iter()
                            .enumerate()
                            .map(|(t, (_, f))| StillOut {
                                target: self.target_name(t),
                                figures: f.clone(),
                            })
                            .collect(),
                        None,
                    ),
                    StepFigures::Move(m) => (None, Vec::new(), Some((**m).clone())),
                    StepFigures::NotSettled(s) => (
                        Some(format!(
                            "the results did not settle: the halves of the last window differ by chi-square {:.1} against {:.1}",
                            s.chi2, s.threshold
                        )),
                        Vec::new(),
                        None,
                    ),
                    StepFigures::Unmeasured(e) => (Some(e.to_string()), Vec::new(), None),
                };
                StepOut {
                    name: plan.step_name(k).to_owned(),
                    kind: plan.step_kind(k),
                    target: (k > 0).then(|| self.target_name(plan.moves[k - 1].target)),
                    window: WindowOut {
                        from: format_ns(done.window_ns.0),
                        to: format_ns(done.window_ns.1),
                    },
                    passed,
                    problem,
                    still,
                    moved,
                }
            })
            .collect();
        let targets = (0..plan.targets)
            .map(|t| {
                let stamp = crate::acceptance::common_calibration(run.stamps[t].iter().copied());
                if stamp.is_none() && !run.stamps[t].is_empty() {
                    failed.push(format!(
                        "{}: its calibrations changed during the run",
                        self.target_name(t)
                    ));
                }
                AcceptedTarget {
                    target: self.target_name(t),
                    calibration_stamp: stamp.map(|s| s.0),
                    links: inst.model.targets[t]
                        .resolution
                        .paths
                        .iter()
                        .flat_map(|p| p.links())
                        .map(|l| inst.model.links[l.0].name.clone())
                        .collect(),
                }
            })
            .collect();
        AcceptanceRecord {
            installation: inst.source.clone(),
            started: format_ns(run.started_ns),
            limits: plan.limits,
            reverify_every_days: settings.map_or(0.0, |s| s.reverify_every_ns as f64 / 86_400e9),
            targets,
            steps,
            failed,
        }
    }

    /// What the store says now of what acceptances accept: read once for any number of
    /// acceptances judged against it.
    async fn current_state(&self) -> StoreResult<CurrentState> {
        let inst = self.installation();
        let mut calibrated_ns = Vec::with_capacity(inst.model.links.len());
        for l in 0..inst.model.links.len() {
            let versions = self.store().calibrations(crate::chain::LinkId(l)).await?;
            calibrated_ns.push(versions.iter().map(|c| c.created_ns).max());
        }
        let mut latest = Vec::with_capacity(inst.model.targets.len());
        for t in 0..inst.model.targets.len() {
            let r = self
                .store()
                .latest_result(TargetId(t), ResultSource::Raw)
                .await?;
            latest.push(r.map(|r| (r.time_ns, r.estimate.calibration.map(|s| s.0))));
        }
        Ok(CurrentState {
            resets: self.store().last_link_resets().await?,
            calibrated_ns,
            latest,
        })
    }

    /// What changed since an acceptance recorded at `at_ns` that it no longer holds.
    fn changed_since(
        &self,
        now: &CurrentState,
        at_ns: i64,
        record: &AcceptanceRecord,
    ) -> Vec<String> {
        let inst = self.installation();
        let mut changed = Vec::new();
        for accepted in &record.targets {
            for name in &accepted.links {
                let Some(l) = inst.model.links.iter().position(|l| &l.name == name) else {
                    changed.push(format!("link `{name}` is no longer in the installation"));
                    continue;
                };
                if let Some(t) = now.calibrated_ns[l].filter(|t| *t > at_ns) {
                    changed.push(format!("link `{name}` was calibrated at {}", format_ns(t)));
                }
                let link = crate::chain::LinkId(l);
                if let Some((_, t, by, _)) = now
                    .resets
                    .iter()
                    .find(|(r, t, ..)| *r == link && *t > at_ns)
                {
                    changed.push(format!(
                        "link `{name}`'s filter was reset at {}{}",
                        format_ns(*t),
                        by.as_ref().map(|b| format!(" by {b}")).unwrap_or_default()
                    ));
                }
            }
            let Some(t) = inst
                .model
                .targets
                .iter()
                .position(|t| t.name == accepted.target)
            else {
                changed.push(format!(
                    "target `{}` is no longer in the installation",
                    accepted.target
                ));
                continue;
            };
            if let Some((time_ns, stamp)) = now.latest[t]
                && time_ns > at_ns
                && stamp != accepted.calibration_stamp
            {
                changed.push(format!(
                    "target `{}` is measured with other calibrations than those accepted (a camera's intrinsics or a station's calibration changed)",
                    accepted.target
                ));
            }
        }
        changed
    }

    fn summary_of(
        &self,
        now: &CurrentState,
        stored: StoredAcceptance,
    ) -> StoreResult<AcceptanceOut> {
        let record: AcceptanceRecord = serde_json::from_str(&stored.record_json).map_err(|e| {
            crate::store::StoreError::Malformed(format!("acceptance {}'s record: {e}", stored.id))
        })?;
        let interval_ns = (record.reverify_every_days * 86_400e9).round() as i64;
        let changed = if stored.passed {
            self.changed_since(now, stored.created_ns, &record)
        } else {
            Vec::new()
        };
        let now = self.now_ns();
        Ok(AcceptanceOut {
            summary: AcceptanceSummary {
                id: stored.id,
                at: format_ns(stored.created_ns),
                by: stored.by,
                note: stored.note,
                passed: stored.passed,
                standing: standing(
                    stored.passed,
                    stored.created_ns,
                    now,
                    interval_ns,
                    !changed.is_empty(),
                ),
                due: format_ns(stored.created_ns.saturating_add(interval_ns)),
                changed,
                failed: record.failed.clone(),
            },
            record,
        })
    }

    /// The newest acceptances, newest first, each with where it stands.
    pub async fn acceptances(&self, limit: i64) -> ServiceResult<Vec<AcceptanceSummary>> {
        let mut out = Vec::new();
        let stored = self.store().acceptances(limit).await?;
        if stored.is_empty() {
            return Ok(out);
        }
        let now = self.current_state().await?;
        for stored in stored {
            out.push(self.summary_of(&now, stored)?.summary);
        }
        Ok(out)
    }

    /// One acceptance whole.
    pub async fn acceptance(&self, id: i64) -> ServiceResult<AcceptanceOut> {
        match self.store().acceptance(id).await? {
            Some(stored) => Ok(self.summary_of(&self.current_state().await?, stored)?),
            None => Err(ServiceError::NotFound(format!("no acceptance {id}"))),
        }
    }

    /// What a period's report says of the rig's acceptance: the newest recorded at or before
    /// `at_ns` (the period's end), with where it stands now.
    pub(super) async fn acceptance_section(
        &self,
        at_ns: i64,
    ) -> StoreResult<crate::report::acceptance::AcceptanceSection> {
        use crate::report::acceptance::AcceptanceSection;
        if self.installation().acceptance.is_none() {
            return Ok(AcceptanceSection::NotStated);
        }
        Ok(match self.store().acceptance_at(at_ns).await? {
            Some(stored) => AcceptanceSection::Latest(Box::new(self.line_of(stored).await?)),
            None => AcceptanceSection::NoneRecorded,
        })
    }

    /// Acceptance `id`'s certificate: the page to print and sign.
    pub async fn acceptance_certificate(&self, id: i64) -> ServiceResult<String> {
        match self.store().acceptance(id).await? {
            Some(stored) => Ok(crate::report::acceptance::certificate(
                &self.line_of(stored).await?,
                self.now_ns(),
            )),
            None => Err(ServiceError::NotFound(format!("no acceptance {id}"))),
        }
    }

    /// A recorded acceptance as the reports show it.
    async fn line_of(
        &self,
        stored: StoredAcceptance,
    ) -> StoreResult<crate::report::acceptance::AcceptanceLine> {
        use crate::report::acceptance::{AcceptanceLine, AcceptanceStep, AcceptedTargetLine};
        let at_ns = stored.created_ns;
        let a = self.summary_of(&self.current_state().await?, stored)?;
        let interval_ns = (a.record.reverify_every_days * 86_400e9).round() as i64;
        Ok(AcceptanceLine {
            id: a.summary.id,
            at_ns,
            by: a.summary.by,
            note: a.summary.note,
            passed: a.summary.passed,
            standing: a.summary.standing,
            due_ns: at_ns.saturating_add(interval_ns),
            changed: a.summary.changed,
            failed: a.summary.failed,
            steps: a
                .record
                .steps
                .into_iter()
                .map(|s| AcceptanceStep {
                    name: s.name,
                    passed: s.passed,
                    problem: s.problem,
                    still: s.still.into_iter().map(|t| (t.target, t.figures)).collect(),
                    moved: s.moved,
                })
                .collect(),
            installation: a.record.installation,
            limits: a.record.limits,
            reverify_every_days: a.record.reverify_every_days,
            targets: a
                .record
                .targets
                .into_iter()
                .map(|t| AcceptedTargetLine {
                    target: t.target,
                    calibration_stamp: t.calibration_stamp,
                    links: t.links,
                })
                .collect(),
        })
    }

    /// For `/healthz`: what is wrong with the rig's acceptance when the installation states a
    /// procedure (none recorded, the latest failed, due, or no longer holding).
    ///
    /// Read within two seconds: a store that does not answer is `/healthz`'s own
    /// problem to tell, and must not hold its answer.
    pub async fn acceptance_problem(&self) -> Option<String> {
        self.installation().acceptance.as_ref()?;
        let latest = match tokio::time::timeout(HEALTH_READ_LIMIT, self.acceptances(1)).await {
            Ok(Ok(l)) => l.into_iter().next(),
            Ok(Err(e)) => return Some(format!("the acceptances cannot be read: {e}")),
            Err(_) => {
                return Some(format!(
                    "the acceptances could not be read within {} s",
                    HEALTH_READ_LIMIT.as_secs_f64()
                ));
            }
        };
        let Some(a) = latest else {
            return Some("the rig has no acceptance: run `brokenray acceptance`".into());
        };
        match a.standing {
            Standing::Valid => None,
            Standing::Due => Some(format!(
                "acceptance {} of {} is due for reverification since {}",
                a.id, a.at, a.due
            )),
            Standing::NoLongerHolds => Some(format!(
                "acceptance {} of {} no longer holds: {}",
                a.id,
                a.at,
                a.changed.join("; ")
            )),
            Standing::Failed => Some(format!(
                "the latest acceptance ({} of {}) failed: {}",
                a.id,
                a.at,
                a.failed.join(", ")
            )),
        }
    }
}
