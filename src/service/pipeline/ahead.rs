//! Filtering ahead: the next group of ingest requests is filtered while the commit before it
//! is written by a task of its own ([`InFlight`]). A request that may repeat stored samples is
//! filtered after a read of what is stored before it: the committed samples through the
//! store's read side, with those of the commit in flight and of its group's earlier requests
//! from memory. See the module docs of [`crate::service`].

use super::*;
use futures::FutureExt;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;

impl Pipeline {
    /// The samples stored before a request that may repeat them, while a commit is being
    /// written: the committed ones over the request's spans, read through the store's read
    /// side, with the samples of the commit in flight and of the group's earlier jobs
    /// (`group`) from memory. A commit that lands during the read is then seen twice, with
    /// the same values. Only this pipeline writes samples, and nothing else of it is
    /// unconcluded, so that is all there is.
    pub(super) async fn stored_during_commit(
        &self,
        items: &[IngestItem],
        group: &[(Job, JobRows)],
    ) -> Result<HashMap<(LinkId, i64), SampleValues>, StoreError> {
        let spans = spans_of(items);
        let mut stored = stored_over_spans(&mut SampleSource::Reader(&self.read), &spans).await?;
        let in_flight = self.in_flight.iter().flat_map(|f| f.rows.iter());
        for rows in in_flight.chain(group.iter().map(|(_, rows)| rows)) {
            for s in &rows.samples {
                let within = spans
                    .get(&s.link)
                    .is_some_and(|&(from, to)| from <= s.time_ns && s.time_ns <= to);
                if within {
                    stored.insert((s.link, s.time_ns), s.values);
                }
            }
        }
        self.metrics.ingest_read_first.fetch_add(1, Relaxed);
        self.metrics.ingest_read_during_commit.fetch_add(1, Relaxed);
        Ok(stored)
    }

    /// Filters one ingest request after reading the stored samples of its links over its
    /// span, as the first of a group filtered ahead: while a commit is in flight, through
    /// [`Self::stored_during_commit`]; otherwise (or when that read fails) on the write
    /// connection once that commit has landed, so that what is read is all there is. When
    /// that read fails too, the request goes through a transaction of its own, which meets
    /// the same failure and answers it.
    pub(super) async fn filter_after_reading(
        &mut self,
        job: Job,
        rx: &mut mpsc::Receiver<Job>,
        publish: &impl Fn(Snapshot),
    ) {
        let Job::Ingest(call) = &job else {
            unreachable!("only ingest requests are read for first")
        };
        if self.in_flight.is_some() {
            match self.stored_during_commit(&call.request, &[]).await {
                Ok(stored) => return self.filter_ahead(vec![job], &stored, rx, publish).await,
                Err(e) => {
                    tracing::warn!(error = %e, "reading the stored samples while a commit is written");
                }
            }
        }
        // A failure of the commit in flight was concluded there: the bank and targets are
        // back at the last committed state, on which this request now runs.
        let _ = self.settle(publish).await;
        let Some(write) = self.write.as_mut() else {
            unreachable!("the write connection is back once the commit before has settled")
        };
        match stored_over_spans(
            &mut SampleSource::Committed(write),
            &spans_of(&call.request),
        )
        .await
        {
            Ok(stored) => {
                self.metrics.ingest_read_first.fetch_add(1, Relaxed);
                self.filter_ahead(vec![job], &stored, rx, publish).await;
            }
            Err(e) => {
                tracing::warn!(error = %e, "reading the stored samples before filtering");
                let targets_before = self.targets.clone();
                self.commit_in_turn(Vec::new(), None, vec![job], targets_before, publish)
                    .await;
            }
        }
    }

    /// Filters a group of ingest requests while the commit before it is written, taking into
    /// it the ingest requests that arrive until that commit lands (one that may repeat stored
    /// samples after [`Self::stored_during_commit`]), then sends this group's rows to be
    /// written in turn. `stored`: what is stored over the first job's spans, when it may
    /// repeat it (the others' are all new). When that commit fails,
    /// the bank and the targets return to its state before it and this group is refused too
    /// (nothing of it was written). A job whose samples complete groups older than memory
    /// from other links' stored samples needs the store: the group then goes on in the
    /// pipeline's own transaction once the commit before it has landed. One that holds every
    /// sample of those groups itself completes them here ([`completes_within_job`]).
    pub(super) async fn filter_ahead(
        &mut self,
        jobs: Vec<Job>,
        stored: &HashMap<(LinkId, i64), SampleValues>,
        rx: &mut mpsc::Receiver<Job>,
        publish: &impl Fn(Snapshot),
    ) {
        let started = std::time::Instant::now();
        if self.in_flight.is_some() {
            self.metrics
                .groups_filtered_ahead
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        let now = self.clock.now_ns();
        let targets_before = self.targets.clone();
        let mut filtered: Vec<(Job, JobRows)> = Vec::with_capacity(jobs.len());
        let mut stop = Ahead::Next;
        let mut rest = jobs.into_iter();
        for job in rest.by_ref() {
            stop = self.filter_job_ahead(job, now, stored, &mut filtered);
            if !matches!(stop, Ahead::Next) {
                break;
            }
        }
        let rest: Vec<Job> = rest.collect();
        // While the commit before is written, later ingest requests join this group (one
        // commit, one `fsync`, for as many requests as waited), until it lands.
        let mut landed: Option<Result<(), String>> = None;
        while matches!(stop, Ahead::Next) && filtered.len() < MAX_JOBS_PER_COMMIT {
            let Some(flight) = self.in_flight.as_mut() else {
                break;
            };
            // Jobs held (taken from the queue before) join first, in their order; either
            // way, once a look has found the commit not landed.
            let next = match self.held.pop_front() {
                Some(job) => match (&mut flight.handle).now_or_never() {
                    Some(joined) => {
                        self.held.push_front(job);
                        Err(joined)
                    }
                    None => Ok(Some(job)),
                },
                None => tokio::select! {
                    biased;
                    joined = &mut flight.handle => Err(joined),
                    job = rx.recv() => Ok(job),
                },
            };
            let job = match next {
                Ok(Some(job)) => job,
                Ok(None) => break,
                Err(joined) => {
                    landed = Some(self.land(joined, publish));
                    break;
                }
            };
            let stored = if self.all_new_samples(std::slice::from_ref(&job)) {
                HashMap::new()
            } else {
                // A request that may repeat stored samples joins too, once what is stored
                // before it is known: committed, in flight, or earlier in this group.
                let Job::Ingest(call) = &job else {
                    self.held.push_front(job);
                    break;
                };
                match self.stored_during_commit(&call.request, &filtered).await {
                    Ok(stored) => stored,
                    Err(e) => {
                        tracing::warn!(error = %e, "reading the stored samples while a commit is written");
                        self.held.push_front(job);
                        break;
                    }
                }
            };
            self.count_samples(std::slice::from_ref(&job));
            stop = self.filter_job_ahead(job, now, &stored, &mut filtered);
        }
        let settled = match landed {
            Some(result) => result,
            None => self.settle(publish).await,
        };
        if let Err(message) = settled {
            let needs_store = match stop {
                Ahead::NeedsStore(pending) => Some(pending.0),
                _ => None,
            };
            // The failure returned the bank and the targets to before that commit, which
            // undid these jobs too.
            let jobs = filtered.into_iter().map(|(j, _)| j);
            for job in jobs.chain(needs_store).chain(rest) {
                job.fail(&message);
            }
            return;
        }
        match stop {
            Ahead::Next => {}
            Ahead::Defect(e) => {
                let jobs = filtered.into_iter().map(|(j, _)| j).chain(rest).collect();
                self.refuse_group(jobs, targets_before, e, publish);
                return;
            }
            // Alone in its group, with nothing in flight: the stored samples it needs are
            // all committed, and are read before its rows go to be written like any other.
            Ahead::NeedsStore(pending) if filtered.is_empty() && rest.is_empty() => {
                let (mut job, mut f) = *pending;
                let Some(write) = self.write.as_mut() else {
                    unreachable!("the write connection is back once the commit before has settled")
                };
                let read = complete_stored_groups(
                    &mut SampleSource::Committed(write),
                    &self.bank,
                    &self.targets,
                    &mut f,
                )
                .await;
                if let Err(e) = read {
                    self.refuse_group(vec![job], targets_before, e, publish);
                    return;
                }
                let (report, rows) = f.into_rows(&self.bank, &mut self.targets);
                if let Job::Ingest(call) = &mut job {
                    call.answer = Ok(report);
                }
                filtered.push((job, rows));
            }
            Ahead::NeedsStore(pending) => {
                self.commit_in_turn(filtered, Some(*pending), rest, targets_before, publish)
                    .await;
                return;
            }
        }
        let record = self.bank.record();
        let state_json = match serde_json::to_string(&record) {
            Ok(json) => json,
            Err(e) => {
                let jobs = filtered.into_iter().map(|(j, _)| j).collect();
                let e = StoreError::Defect(format!("cannot encode the filter state: {e}"));
                self.refuse_group(jobs, targets_before, e, publish);
                return;
            }
        };
        let snapshot = self.snapshot();
        let (jobs, rows): (Vec<Job>, Vec<JobRows>) = filtered.into_iter().unzip();
        let rows: Arc<[JobRows]> = rows.into();
        let Some(write) = self.write.take() else {
            unreachable!("the write connection is back once the commit before has settled")
        };
        let handle = tokio::spawn(write_in_flight(
            write,
            Arc::clone(&rows),
            self.digest.clone(),
            state_json,
            now,
        ));
        self.in_flight = Some(InFlight {
            handle,
            rows,
            done: Done {
                jobs,
                effects: Effects::default(),
                record,
                snapshot,
                targets_before,
                started,
            },
        });
        // A task spawned from this one waits in this worker's next slot until this one
        // yields, and the filtering of the next group does not: let the commit start now.
        tokio::task::yield_now().await;
    }

    /// Waits for the commit in flight, if any, and concludes it (answers, or rolls back). An
    /// error says it failed, with the message its requests were refused with.
    pub(super) async fn settle(&mut self, publish: &impl Fn(Snapshot)) -> Result<(), String> {
        let Some(flight) = self.in_flight.as_mut() else {
            return Ok(());
        };
        let joined = (&mut flight.handle).await;
        self.land(joined, publish)
    }

    /// Concludes the commit in flight with what its task returned. A panic in the task goes on
    /// here, as it would have in the pipeline's own task.
    pub(super) fn land(
        &mut self,
        joined: Result<InFlightOutcome, tokio::task::JoinError>,
        publish: &impl Fn(Snapshot),
    ) -> Result<(), String> {
        let Some(flight) = self.in_flight.take() else {
            return Ok(());
        };
        let (write, outcome) = match joined {
            Ok(landed) => landed,
            Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
            Err(e) => panic!("the commit in flight was cancelled: {e}"),
        };
        self.write = Some(write);
        let failure = outcome.as_ref().err().map(ToString::to_string);
        self.conclude(flight.done, outcome, publish);
        match failure {
            None => Ok(()),
            Some(e) => Err(format!(
                "the database did not accept an earlier write, so this request was not applied: {e}"
            )),
        }
    }

    /// Refuses a group filtered ahead that failed before its transaction began (`error`, a
    /// defect), once the commit before it has settled: what the group did to the bank and
    /// the targets is undone and its requests are refused.
    fn refuse_group(
        &mut self,
        jobs: Vec<Job>,
        targets_before: Vec<TargetView>,
        error: StoreError,
        publish: &impl Fn(Snapshot),
    ) {
        let done = Done {
            jobs,
            effects: Effects::default(),
            record: self.committed_state.clone(),
            snapshot: self.snapshot(),
            targets_before,
            started: std::time::Instant::now(),
        };
        self.conclude(done, Err(error), publish);
    }

    /// Filters one ingest job ahead into `filtered`, and says whether the group can go on.
    fn filter_job_ahead(
        &mut self,
        mut job: Job,
        now: i64,
        stored: &HashMap<(LinkId, i64), SampleValues>,
        filtered: &mut Vec<(Job, JobRows)>,
    ) -> Ahead {
        let Job::Ingest(call) = &mut job else {
            unreachable!("only ingest jobs are filtered ahead")
        };
        let items = std::mem::take(&mut call.request);
        let result = match measurements_of(&self.bank, &items) {
            Err(refusal) => Ok(Err(refusal)),
            Ok(z) => filter_items(
                &mut self.bank,
                &mut self.targets,
                items,
                z,
                stored,
                now,
                None,
            ),
        };
        match result {
            Err(e) => {
                filtered.push((job, JobRows::default()));
                Ahead::Defect(e)
            }
            Ok(Err(refusal)) => {
                call.answer = Err(refusal);
                filtered.push((job, JobRows::default()));
                Ahead::Next
            }
            // No group older than memory, or a late batch of whole groups that completes
            // them from its own samples: no read.
            Ok(Ok(mut f)) if completes_within_job(&self.bank, &f) => {
                let completed = complete_stored_groups(
                    &mut SampleSource::JobAlone,
                    &self.bank,
                    &self.targets,
                    &mut f,
                )
                .now_or_never()
                .unwrap_or_else(|| {
                    Err(StoreError::Defect(
                        "completing a late batch's groups from itself waited".into(),
                    ))
                });
                match completed {
                    Ok(()) => {
                        let (report, rows) = f.into_rows(&self.bank, &mut self.targets);
                        call.answer = Ok(report);
                        filtered.push((job, rows));
                        Ahead::Next
                    }
                    Err(e) => {
                        filtered.push((job, JobRows::default()));
                        Ahead::Defect(e)
                    }
                }
            }
            Ok(Ok(f)) => {
                self.metrics
                    .ingest_old_groups_from_store
                    .fetch_add(1, Relaxed);
                Ahead::NeedsStore(Box::new((job, f)))
            }
        }
    }
}

/// A group's jobs and what concluding its commit needs.
pub(super) struct Done {
    pub(super) jobs: Vec<Job>,
    pub(super) effects: Effects,
    /// The bank's state the commit saves.
    pub(super) record: BankRecord,
    /// What readers see once it has committed.
    pub(super) snapshot: Snapshot,
    /// The targets before the group, restored when it fails.
    pub(super) targets_before: Vec<TargetView>,
    pub(super) started: std::time::Instant,
}

/// What the task writing a commit gives back: the connection, and the alarm transitions it
/// stored or why it failed.
type InFlightOutcome = (WriteConn, Result<Vec<StoredAlarm>, StoreError>);

/// A commit being written by a task of its own while the pipeline filters the next group.
pub(super) struct InFlight {
    pub(super) handle: tokio::task::JoinHandle<InFlightOutcome>,
    /// Its rows, for requests filtered before it lands that may repeat its samples.
    pub(super) rows: Arc<[JobRows]>,
    pub(super) done: Done,
}

/// Writes a group's rows and the filters' state in one transaction and commits, on the
/// connection it hands back.
async fn write_in_flight(
    mut write: WriteConn,
    rows: Arc<[JobRows]>,
    digest: String,
    state_json: String,
    now: i64,
) -> InFlightOutcome {
    let outcome = async {
        let mut tx = write.begin(now).await?;
        let alarms = write_rows(&mut tx, &rows, now).await?;
        tx.save_filter_state(&digest, &state_json, now).await?;
        tx.commit().await?;
        Ok(alarms)
    }
    .await;
    (write, outcome)
}
