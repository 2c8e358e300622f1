//! The writer filters a group of new samples while the commit before it is still being
//! written, and reads what is stored before it filters a request that may repeat it. What it
//! stores and answers must not depend on that: the same requests, sent one at a time or one
//! after another without waiting, or each in a transaction of the writer's own (Rerun on),
//! give the same rows and answers.

use super::helpers::{START_NS, T0_NS, TestApp};
use brokenray::bank::{MeasurementUncertainty, ResultSource, Sample};
use brokenray::model::TargetId;
use brokenray::service::{IngestItem, IngestReport, Metrics, Service, ServiceError, ServiceResult};
use brokenray::sim::{Scenario, SimSettings, Simulator};
use brokenray::store::Quality;

/// Groups a batch.
const GROUPS_PER_BATCH: usize = 4;
/// Batches: 140 groups at 25 Hz, 5.6 s, inside what the test clock takes as current.
const BATCHES: usize = 35;

/// The requests both services get, in order: the simulated ship's link poses in batches of
/// whole groups, with a batch sent again after two later ones (a retry: every sample a
/// duplicate), a batch that holds a sample older than those stored, and the last sample of
/// batch 5 held back until the last batch: its group is then older than the filters keep in
/// memory, and is completed from the other links' stored samples.
fn requests(app: &TestApp) -> Vec<Vec<IngestItem>> {
    let mut batches = whole_batches(app);
    let mut withheld = batches[5].pop().expect("a sample");
    // A retry of batch 10 after batch 12, and batch 20's first sample again among batch 22's.
    let retry = batches[10].clone();
    batches.insert(13, retry);
    let mut late = batches[23].clone();
    let mut old = batches[21][0];
    old.index = late.len();
    late.push(old);
    batches[23] = late;
    let last = batches.last_mut().expect("batches");
    withheld.index = last.len();
    last.push(withheld);
    batches
}

/// The simulated ship's link poses in batches of whole groups, in time order.
fn whole_batches(app: &TestApp) -> Vec<Vec<IngestItem>> {
    let model = &app.service.installation().model;
    let settings = SimSettings {
        scenario: Scenario::Ship,
        rate_hz: 25.0,
        start_ns: T0_NS,
        duration_s: Some(60.0),
        pixel_sigma_px: Some(0.0),
        outlier_rate: 0.0,
        seed: 11,
    };
    let mut sim = Simulator::new(model, settings).expect("the built-in installation simulates");
    let mut batches: Vec<Vec<IngestItem>> = Vec::new();
    for _ in 0..BATCHES {
        let mut items = Vec::new();
        for _ in 0..GROUPS_PER_BATCH {
            let g = sim.next_group();
            for (name, pose) in &g.link_truth {
                items.push(IngestItem {
                    index: items.len(),
                    sample: Sample {
                        link: model.topology.link_id(name).expect("a link of the model"),
                        time_ns: g.time_ns,
                        parent_from_child: *pose,
                        uncertainty: MeasurementUncertainty::Default,
                    },
                    quality: Quality::default(),
                });
            }
        }
        batches.push(items);
    }
    batches
}

/// Every stored sample and result, as text (their values bit for bit).
async fn stored(app: &TestApp) -> (Vec<String>, Vec<String>) {
    let store = app.service.store();
    let model = &app.service.installation().model;
    let mut samples = Vec::new();
    for l in 0..model.links.len() {
        for s in store
            .samples(brokenray::chain::LinkId(l), 0, i64::MAX, i64::MAX)
            .await
            .expect("samples read")
        {
            samples.push(format!("{s:?}"));
        }
    }
    let mut results = Vec::new();
    for source in [ResultSource::Raw, ResultSource::Filtered] {
        for r in store
            .results(TargetId(0), source, 0, i64::MAX, i64::MAX)
            .await
            .expect("results read")
        {
            results.push(format!("{r:?}"));
        }
    }
    (samples, results)
}

/// The 1 s rollups of both sources, read through the history (a 100 s window in 100 points).
/// A rollup bucket: start (ns), results, of which with a deformation; per component the
/// minimum, sum and maximum.
type Rollup = (i64, i64, i64, Vec<f64>, Vec<f64>, Vec<f64>);

async fn rollups(app: &TestApp) -> Vec<Rollup> {
    let mut out = Vec::new();
    for source in [ResultSource::Raw, ResultSource::Filtered] {
        let h = app
            .service
            .store()
            .history(
                TargetId(0),
                source,
                T0_NS - 50_000_000_000,
                T0_NS + 50_000_000_000,
                100,
            )
            .await
            .expect("the history");
        assert_eq!(h.resolution_s, Some(1), "read from the rollups");
        out.extend(h.buckets.iter().map(|b| {
            (
                b.start_ns,
                b.n,
                b.n_def,
                b.min.to_vec(),
                b.sum.to_vec(),
                b.max.to_vec(),
            )
        }));
    }
    out
}

/// Rollups agree when their counts, minima and maxima are equal and their sums differ by no
/// more than rounding: a commit's requests are added up before the stored sum, one request at
/// a time each is.
fn assert_rollups_agree(got: &[Rollup], want: &[Rollup]) {
    assert_eq!(got.len(), want.len());
    assert!(!want.is_empty());
    for (g, w) in got.iter().zip(want) {
        assert_eq!(
            (g.0, g.1, g.2, &g.3, &g.5),
            (w.0, w.1, w.2, &w.3, &w.5),
            "counts, minima, maxima"
        );
        for (a, b) in g.4.iter().zip(&w.4) {
            assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{a} against {b}");
        }
    }
}

/// Sends `batches` to `app` one at a time, each accepted.
async fn one_at_a_time_ok(app: &TestApp, batches: &[Vec<IngestItem>]) {
    for b in batches {
        app.service
            .ingest(b.clone())
            .await
            .expect("a batch is stored");
    }
}

fn answers(list: &[ServiceResult<IngestReport>]) -> Vec<String> {
    list.iter().map(|a| format!("{a:?}")).collect()
}

/// Holds SQLite's write lock on `app`'s database in a transaction of the test's own, so that
/// the service's next commit waits at its start (for up to its busy timeout) until that
/// transaction commits. Readers are not held.
fn hold_write_lock(app: &TestApp) -> rusqlite::Connection {
    let conn = rusqlite::Connection::open(&app.database).expect("the database opens");
    conn.execute_batch("begin immediate")
        .expect("the write lock");
    conn
}

/// Sends `batches` to `app` and gives their answers in order: the first `held` while the
/// service's write lock is held elsewhere, so that the first one's commit waits in flight and
/// the others arrive while it does (they are filtered ahead, into one group); then
/// `in_the_lock` runs in the lock's transaction, which commits, and the rest go up to three on
/// their way at once. This runtime runs its tasks in the order they were spawned, and a
/// request is spawned only once the one before has reached the writer or been answered, so
/// the requests reach the writer in the order given.
async fn send_overlapping(
    app: &TestApp,
    batches: &[Vec<IngestItem>],
    held: usize,
    in_the_lock: impl FnOnce(&rusqlite::Connection),
) -> Vec<ServiceResult<IngestReport>> {
    let spawn = |items: Vec<IngestItem>| {
        let service: Service = app.service.clone();
        tokio::spawn(async move { service.ingest(items).await })
    };
    let lock = hold_write_lock(app);
    let mut on_their_way = std::collections::VecDeque::new();
    // The runtime idles only once the writer has taken a batch and filtered it (the first
    // one's commit then waits for the lock).
    for b in &batches[..held] {
        on_their_way.push_back(spawn(b.clone()));
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    in_the_lock(&lock);
    lock.execute_batch("commit").expect("the lock released");
    let mut answers = Vec::new();
    for b in &batches[held..] {
        on_their_way.push_back(spawn(b.clone()));
        if on_their_way.len() == 3
            && let Some(first) = on_their_way.pop_front()
        {
            answers.push(first.await.expect("the request's task"));
        }
    }
    for h in on_their_way {
        answers.push(h.await.expect("the request's task"));
    }
    answers
}

#[tokio::test]
async fn requests_sent_without_waiting_store_and_answer_what_they_do_one_at_a_time() {
    let one_at_a_time = TestApp::start(None).await;
    let batches = requests(&one_at_a_time);
    let mut serial_answers = Vec::new();
    for b in &batches {
        serial_answers.push(one_at_a_time.service.ingest(b.clone()).await);
    }
    let without_waiting = TestApp::start(None).await;
    let paced_answers = send_overlapping(&without_waiting, &batches, 2, |_| {}).await;
    // With Rerun on (a viewer that is not there), every request goes through a transaction
    // of the writer's own, which reads what is stored inside it.
    let in_transactions = TestApp::start(Some(&super::recordings::with_rerun(
        "mode = \"connect\"\nurl = \"rerun+http://127.0.0.1:1/proxy\"",
    )))
    .await;
    let mut in_transaction_answers = Vec::new();
    for b in &batches {
        in_transaction_answers.push(in_transactions.service.ingest(b.clone()).await);
    }

    assert!(
        serial_answers.iter().all(Result::is_ok),
        "{serial_answers:?}"
    );
    assert_eq!(answers(&paced_answers), answers(&serial_answers));
    assert_eq!(answers(&in_transaction_answers), answers(&serial_answers));
    let retry = serial_answers[13].as_ref().expect("the retry is accepted");
    assert_eq!(
        (retry.duplicates, retry.stored),
        (batches[13].len(), 0),
        "{retry:?}"
    );
    let late = serial_answers[23]
        .as_ref()
        .expect("the late sample's batch");
    assert_eq!(late.duplicates, 1, "{late:?}");
    let completes_old = serial_answers
        .last()
        .expect("answers")
        .as_ref()
        .expect("stored");
    // Its own groups' raw results, and the old group's from the stored samples.
    assert_eq!(
        (completes_old.raw_results, completes_old.out_of_order),
        (GROUPS_PER_BATCH + 1, 1),
        "{completes_old:?}"
    );
    let (serial_samples, serial_results) = stored(&one_at_a_time).await;
    let (paced_samples, paced_results) = stored(&without_waiting).await;
    assert_eq!(
        serial_samples.len(),
        BATCHES * GROUPS_PER_BATCH * 3,
        "every sample stored once"
    );
    assert!(
        serial_results.len() > BATCHES * GROUPS_PER_BATCH,
        "raw and filtered results"
    );
    assert_eq!(paced_samples, serial_samples);
    assert_eq!(paced_results, serial_results);
    assert_eq!(
        stored(&in_transactions).await,
        (serial_samples, serial_results)
    );
    let serial_rollups = rollups(&one_at_a_time).await;
    assert_rollups_agree(&rollups(&without_waiting).await, &serial_rollups);
    assert_rollups_agree(&rollups(&in_transactions).await, &serial_rollups);
    assert_eq!(
        Metrics::get(&in_transactions.service.metrics().groups_filtered_ahead),
        0
    );
    let metrics = without_waiting.service.metrics();
    assert!(
        Metrics::get(&metrics.groups_filtered_ahead) >= 1,
        "the second batch was filtered while the first one's commit waited"
    );
    assert_eq!(Metrics::get(&metrics.commits_failed), 0);
}

/// Late batches of whole groups, one within the filters' memory (batch 5 after batch 6) and
/// one older than it (batch 2 last), lie in gaps of what is stored: they are read for nothing,
/// join the group filtered ahead, and the old one completes its groups from its own samples
/// (no wait for the commit before it). Answers and stored rows equal those of the same
/// requests one at a time.
#[tokio::test]
async fn late_batches_of_whole_groups_are_filtered_ahead_without_reading_the_store() {
    let one_at_a_time = TestApp::start(None).await;
    let in_order = whole_batches(&one_at_a_time);
    let order: Vec<usize> = [0, 1, 3, 4, 6, 5]
        .into_iter()
        .chain(7..BATCHES)
        .chain([2])
        .collect();
    let batches: Vec<Vec<IngestItem>> = order.iter().map(|&b| in_order[b].clone()).collect();
    let mut serial_answers = Vec::new();
    for b in &batches {
        serial_answers.push(one_at_a_time.service.ingest(b.clone()).await);
    }
    let without_waiting = TestApp::start(None).await;
    let overlapping = send_overlapping(&without_waiting, &batches, 2, |_| {}).await;

    assert!(
        serial_answers.iter().all(Result::is_ok),
        "{serial_answers:?}"
    );
    assert_eq!(answers(&overlapping), answers(&serial_answers));
    let oldest = serial_answers
        .last()
        .expect("answers")
        .as_ref()
        .expect("stored");
    // Behind every link's filter, and each group completed from the batch's own samples.
    assert_eq!(
        (oldest.out_of_order, oldest.raw_results, oldest.duplicates),
        (GROUPS_PER_BATCH * 3, GROUPS_PER_BATCH, 0),
        "{oldest:?}"
    );
    assert_eq!(stored(&without_waiting).await, stored(&one_at_a_time).await);
    for app in [&one_at_a_time, &without_waiting] {
        let metrics = app.service.metrics();
        assert_eq!(Metrics::get(&metrics.ingest_read_first), 0);
        assert_eq!(Metrics::get(&metrics.ingest_old_groups_from_store), 0);
        assert_eq!(Metrics::get(&metrics.commits_failed), 0);
    }
    assert!(Metrics::get(&without_waiting.service.metrics().groups_filtered_ahead) >= 1);
}

/// Retries of samples not yet committed: a batch again while its own commit waits in flight,
/// a batch again in the group filtered behind that commit, right after the batch itself, and a
/// sample of the first batch again once the group behind it is in flight. What is stored before
/// each comes from a reader (the committed samples) and from memory (the commit in flight, the
/// group's earlier requests): each must be answered as a duplicate and stored once, as when
/// the same requests come one at a time.
#[tokio::test]
async fn retries_of_samples_in_flight_or_earlier_in_the_group_are_duplicates_of_them() {
    let one_at_a_time = TestApp::start(None).await;
    let plain = requests(&one_at_a_time);
    let mut late = plain[2].clone();
    let mut again = plain[0][1];
    again.index = late.len();
    late.push(again);
    let batches = vec![
        plain[0].clone(),
        plain[0].clone(),
        plain[1].clone(),
        plain[1].clone(),
        late,
        plain[3].clone(),
    ];
    let mut serial_answers = Vec::new();
    for b in &batches {
        serial_answers.push(one_at_a_time.service.ingest(b.clone()).await);
    }
    let without_waiting = TestApp::start(None).await;
    let overlapping = send_overlapping(&without_waiting, &batches, 4, |_| {}).await;

    for retry in [1, 3] {
        let report = serial_answers[retry].as_ref().expect("a retry is accepted");
        assert_eq!(
            (report.duplicates, report.stored),
            (batches[retry].len(), 0),
            "{report:?}"
        );
    }
    let late = serial_answers[4].as_ref().expect("the late sample's batch");
    assert_eq!(late.duplicates, 1, "{late:?}");
    assert_eq!(answers(&overlapping), answers(&serial_answers));
    let (serial_samples, serial_results) = stored(&one_at_a_time).await;
    assert_eq!(
        serial_samples.len(),
        4 * GROUPS_PER_BATCH * 3,
        "each sample once"
    );
    assert_eq!(
        stored(&without_waiting).await,
        (serial_samples, serial_results)
    );
    let metrics = without_waiting.service.metrics();
    // The two retries sent while the lock was held were read while a commit was in flight.
    assert!(
        Metrics::get(&metrics.ingest_read_during_commit) >= 2,
        "{}",
        Metrics::get(&metrics.ingest_read_during_commit)
    );
    assert_eq!(
        Metrics::get(&metrics.ingest_read_first),
        3,
        "each retry read once"
    );
    assert!(Metrics::get(&metrics.groups_filtered_ahead) >= 1);
    assert_eq!(Metrics::get(&metrics.commits_failed), 0);
    // One at a time, every commit has landed before the next request: the retries are read
    // on the write connection.
    let serial = one_at_a_time.service.metrics();
    assert_eq!(
        (
            Metrics::get(&serial.ingest_read_first),
            Metrics::get(&serial.ingest_read_during_commit)
        ),
        (3, 0)
    );
}

#[tokio::test]
async fn when_a_commit_fails_the_batch_filtered_behind_it_is_refused_and_retries_store_all() {
    let one_at_a_time = TestApp::start(None).await;
    let batches = requests(&one_at_a_time);
    let batches = &batches[..6];
    // The retries below are received a nanosecond later than the first attempts.
    one_at_a_time.clock.set_ns(START_NS + 1);
    one_at_a_time_ok(&one_at_a_time, batches).await;

    let failing = TestApp::start(None).await;
    // The database refuses the first batch's last sample as first received, so its commit
    // fails after the second batch was filtered on top of it.
    let refused_ns = batches[0].last().expect("a sample").sample.time_ns;
    let answers = send_overlapping(&failing, &batches[..2], 2, |lock| {
        lock.execute_batch(&format!(
            "create trigger planted before insert on samples \
             when new.time_ns = {refused_ns} and new.received_ns = {START_NS} \
             begin select raise(abort, 'a planted refusal'); end"
        ))
        .expect("the trigger");
    })
    .await;
    match &answers[0] {
        Err(ServiceError::CommitFailed(m)) => assert!(m.contains("planted"), "{m}"),
        other => panic!("the first batch must be refused by its commit: {other:?}"),
    }
    match &answers[1] {
        Err(ServiceError::CommitFailed(m)) => {
            assert!(m.contains("earlier write") && m.contains("planted"), "{m}")
        }
        other => panic!("the batch filtered behind it must be refused too: {other:?}"),
    }
    let metrics = failing.service.metrics();
    assert_eq!(Metrics::get(&metrics.commits_failed), 1);
    assert_eq!(Metrics::get(&metrics.groups_filtered_ahead), 1);
    let (nothing, no_results) = stored(&failing).await;
    assert!(nothing.is_empty() && no_results.is_empty(), "{nothing:?}");

    // The filters went back to before the failed commit: the retries give what one at a
    // time gave.
    failing.clock.set_ns(START_NS + 1);
    one_at_a_time_ok(&failing, batches).await;
    assert_eq!(stored(&failing).await, stored(&one_at_a_time).await);
}

/// Requests taken from the queue together are filtered in the order they came, even when two
/// of them must be read first and a request behind them repeats one they overtook. The
/// writer is held in a transaction of its own (a prune waiting for the write lock) while the
/// queue fills with two retries, a new sample, more new samples up to a full group, and that
/// new sample again; each commit after the lock is made slow, so that the second retry is
/// read and filtered while the first one's commit is written, and the repeat, still on the
/// queue, arrives then. The repeat must be answered as the duplicate, as one at a time.
#[tokio::test]
async fn requests_taken_together_are_filtered_in_their_order_behind_retries_read_first() {
    let one_at_a_time = TestApp::start(None).await;
    let batches = whole_batches(&one_at_a_time);
    let singles: Vec<Vec<IngestItem>> = batches[2..]
        .iter()
        .flatten()
        .map(|item| vec![IngestItem { index: 0, ..*item }])
        .collect();
    // The writer takes at most 256 requests into a group: the retries, the new sample and
    // 253 more fill it, and the repeat stays on the queue.
    let mut queued = vec![batches[0].clone(), batches[1].clone()];
    queued.extend(singles[..254].iter().cloned());
    queued.push(singles[0].clone());
    let repeat = queued.len() - 1;

    one_at_a_time_ok(&one_at_a_time, &batches[..2]).await;
    one_at_a_time.service.prune().await.expect("a prune");
    let mut serial_answers = Vec::new();
    for b in &queued {
        serial_answers.push(one_at_a_time.service.ingest(b.clone()).await);
    }

    let taken_together = TestApp::start(None).await;
    one_at_a_time_ok(&taken_together, &batches[..2]).await;
    let lock = hold_write_lock(&taken_together);
    // About half a second of work for every commit from here on.
    lock.execute_batch(
        "create trigger slow after update on filter_state begin \
         select count(*) from (with recursive c(x) as (select 1 union all \
         select x + 1 from c where x < 1000000) select x from c); end",
    )
    .expect("the trigger");
    let service = taken_together.service.clone();
    let prune = tokio::spawn(async move { service.prune().await });
    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    let mut on_their_way = Vec::new();
    for b in &queued {
        let service = taken_together.service.clone();
        let items = b.clone();
        on_their_way.push(tokio::spawn(async move { service.ingest(items).await }));
    }
    tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    lock.execute_batch("commit").expect("the lock released");
    prune
        .await
        .expect("the prune's task")
        .expect("the prune waited for the lock");
    let mut together_answers = Vec::new();
    for h in on_their_way {
        together_answers.push(h.await.expect("the request's task"));
    }

    let again = serial_answers[repeat].as_ref().expect("the repeat");
    assert_eq!((again.duplicates, again.stored), (1, 0), "{again:?}");
    // The new sample and its repeat, each as one at a time answered them.
    for i in [2, repeat] {
        assert_eq!(
            answers(&together_answers[i..=i]),
            answers(&serial_answers[i..=i]),
            "request {i}"
        );
    }
    assert_eq!(answers(&together_answers), answers(&serial_answers));
    assert_eq!(stored(&taken_together).await, stored(&one_at_a_time).await);
    let metrics = taken_together.service.metrics();
    assert!(
        Metrics::get(&metrics.ingest_read_during_commit) >= 1,
        "the second retry was read while the first one's commit was written"
    );
    assert_eq!(Metrics::get(&metrics.commits_failed), 0);
}
