//! The store's behaviour, the same on both backends: each test runs once on an SQLite file and
//! once on a fresh database of the throwaway PostgreSQL cluster.

use crate::service::helpers::{Backend, ONE_LINK, T0_NS, installation_at};
use brokenray::alarms::{AlarmKind, Level, Transition, ValueUnit};
use brokenray::bank::{MeasurementUncertainty, ResultSource};
use brokenray::chain::LinkId;
use brokenray::config::Installation;
use brokenray::deformation::MeasuredPose;
use brokenray::geometry::{Mat6, Pose, PoseCov, ReportedSigmas, rotation_from_euler};
use brokenray::model::TargetId;
use brokenray::store::{self, NewResult, NewSample, Quality, SampleValues, Store, WriteConn};
use nalgebra::Translation3;

const S: i64 = 1_000_000_000;
const DAY: i64 = 86_400 * S;

async fn open(backend: Backend) -> (tempfile::TempDir, Installation, Store, WriteConn) {
    let dir = tempfile::tempdir().unwrap();
    let inst = installation_at(&backend.database(&dir), Some(ONE_LINK));
    let (store, write) = store::open(&inst, T0_NS).await.expect("the store opens");
    (dir, inst, store, write)
}

fn pose(k: i64) -> Pose {
    let t = k as f64 * 0.37;
    Pose::from_parts(
        Translation3::new(t.sin() * 3.0, -2952.0 + t.cos(), 532.0 + 1e-3 * k as f64),
        rotation_from_euler([-0.07 + 1e-5 * t.sin(), 0.026, 2.87]).unwrap(),
    )
}

fn sample(k: i64, time_ns: i64) -> NewSample {
    let uncertainty = match k % 3 {
        0 => MeasurementUncertainty::Default,
        1 => MeasurementUncertainty::Sigmas(ReportedSigmas {
            rotation_arcsec: [1.0, 2.0, 3.0 + k as f64],
            translation_mm: [0.1, 0.2, 0.3],
        }),
        _ => MeasurementUncertainty::Covariance(Mat6::identity() * (1e-8 * (k + 1) as f64)),
    };
    NewSample {
        link: LinkId(0),
        time_ns,
        values: SampleValues {
            pose: pose(k),
            uncertainty,
            quality: Quality {
                reprojection_rms_px: (k % 2 == 0).then_some(0.01 * k as f64),
                points: (k % 2 == 1).then_some(9),
            },
        },
        disposition: brokenray::filter::DispositionKind::Fused,
        outlier: k % 5 == 0,
        nis: (k % 4 != 0).then_some(1.5 + k as f64),
        received_ns: time_ns + 7,
    }
}

fn result(k: i64, time_ns: i64) -> NewResult {
    NewResult {
        target: TargetId(0),
        source: ResultSource::Filtered,
        time_ns,
        estimate: MeasuredPose {
            whole: PoseCov {
                pose: pose(k),
                cov: Mat6::identity() * 1e-7,
            },
            systematic_cov: Mat6::identity() * (k as f64 + 1.0) * 1e-9,
            calibration: Some(brokenray::deformation::CalibrationStamp(k * 31)),
        },
        status: brokenray::bank::TargetStatus::Ok,
        age_s: 0.25,
        chi2: (k % 2 == 0).then_some(3.5),
        deformation: None,
    }
}

async fn commit_samples(write: &mut WriteConn, samples: &[NewSample]) {
    let mut tx = write.begin(0).await.unwrap();
    tx.insert_samples(&[samples]).await.unwrap();
    tx.commit().await.unwrap();
}

async fn commit_results(write: &mut WriteConn, results: &[NewResult]) {
    let mut tx = write.begin(0).await.unwrap();
    tx.insert_results(&[results]).await.unwrap();
    tx.commit().await.unwrap();
}

on_both_backends!(
    samples_and_results_read_back_exactly,
    a_result_at_an_existing_key_is_replaced,
    a_transaction_dropped_without_commit_leaves_nothing,
    versions_alarms_resets_and_filter_state_round_trip,
    retention_removes_old_rows_and_keeps_rollups,
    rollups_agree_with_the_results_they_summarise,
    rows_before_the_partitions_are_moved_into_their_own_by_maintenance,
);

/// Every column of a sample and a result comes back bit for bit (all three uncertainty
/// forms, absent and present optional values), in time order, in batches larger than one
/// statement holds.
async fn samples_and_results_read_back_exactly(backend: Backend) {
    let (_dir, _inst, store, mut write) = open(backend).await;
    let samples: Vec<NewSample> = (0..25_000).map(|k| sample(k, T0_NS + k * S / 10)).collect();
    commit_samples(&mut write, &samples).await;
    let results: Vec<NewResult> = (0..12_000).map(|k| result(k, T0_NS + k * S / 10)).collect();
    commit_results(&mut write, &results).await;

    let stored = store
        .samples(LinkId(0), i64::MIN, i64::MAX, i64::MAX)
        .await
        .unwrap();
    assert_eq!(stored.len(), samples.len());
    for (s, new) in stored.iter().zip(&samples) {
        assert_eq!(s.time_ns, new.time_ns);
        assert_eq!(s.values, new.values);
        assert_eq!(
            (s.disposition, s.outlier, s.nis, s.received_ns),
            (new.disposition, new.outlier, new.nis, new.received_ns)
        );
    }
    let back = store
        .results(
            TargetId(0),
            ResultSource::Filtered,
            i64::MIN,
            i64::MAX,
            i64::MAX,
        )
        .await
        .unwrap();
    assert_eq!(back.len(), results.len());
    for (r, new) in back.iter().zip(&results) {
        assert_eq!(r.time_ns, new.time_ns);
        assert_eq!(r.estimate, new.estimate);
        assert_eq!(
            (r.status, r.age_s, r.chi2),
            (new.status, new.age_s, new.chi2)
        );
    }
    assert_eq!(
        store
            .count_samples(LinkId(0), T0_NS, T0_NS + 100 * S)
            .await
            .unwrap(),
        1001
    );
    assert_eq!(
        store
            .count_results(TargetId(0), ResultSource::Filtered, T0_NS, T0_NS + 100 * S)
            .await
            .unwrap(),
        1001
    );
    assert!(
        store
            .results(TargetId(0), ResultSource::Raw, i64::MIN, i64::MAX, 10)
            .await
            .unwrap()
            .is_empty()
    );
    let (before, after) = store
        .results_around(TargetId(0), ResultSource::Filtered, T0_NS + 55 * S + 1)
        .await
        .unwrap();
    assert_eq!(before.unwrap().time_ns, T0_NS + 55 * S);
    assert_eq!(after.unwrap().time_ns, T0_NS + 55 * S + S / 10);
    let (stats, span) = store
        .pose_stats(TargetId(0), ResultSource::Filtered, i64::MIN, i64::MAX)
        .await
        .unwrap();
    assert!(stats.is_some());
    assert_eq!(span, Some((T0_NS, T0_NS + 11_999 * S / 10)));
    write.close().await.unwrap();
    store.close().await;
}

/// A result written again at its key (a group completed again) replaces the stored one, also
/// when both are in one call.
async fn a_result_at_an_existing_key_is_replaced(backend: Backend) {
    let (_dir, _inst, store, mut write) = open(backend).await;
    commit_results(&mut write, &[result(1, T0_NS), result(2, T0_NS + S)]).await;
    let mut again = result(3, T0_NS);
    again.age_s = 9.0;
    let mut last = result(4, T0_NS + S);
    last.age_s = 11.0;
    commit_results(&mut write, &[again, result(5, T0_NS + S), last]).await;
    let back = store
        .results(
            TargetId(0),
            ResultSource::Filtered,
            i64::MIN,
            i64::MAX,
            i64::MAX,
        )
        .await
        .unwrap();
    assert_eq!(back.len(), 2);
    assert_eq!((back[0].estimate, back[0].age_s), (again.estimate, 9.0));
    assert_eq!((back[1].estimate, back[1].age_s), (last.estimate, 11.0));
    write.close().await.unwrap();
    store.close().await;
}

/// A transaction dropped before its commit (a failed request, a cancelled task) leaves no row,
/// and the writer's next transaction commits normally.
async fn a_transaction_dropped_without_commit_leaves_nothing(backend: Backend) {
    let (_dir, _inst, store, mut write) = open(backend).await;
    {
        let mut tx = write.begin(0).await.unwrap();
        tx.insert_samples(&[&[sample(1, T0_NS)]]).await.unwrap();
        tx.insert_results(&[&[result(1, T0_NS)]]).await.unwrap();
    }
    commit_samples(&mut write, &[sample(2, T0_NS + S)]).await;
    let stored = store
        .samples(LinkId(0), i64::MIN, i64::MAX, i64::MAX)
        .await
        .unwrap();
    assert_eq!(stored.len(), 1);
    assert_eq!(stored[0].time_ns, T0_NS + S);
    assert!(
        store
            .latest_result(TargetId(0), ResultSource::Filtered)
            .await
            .unwrap()
            .is_none()
    );
    let history = store
        .history(TargetId(0), ResultSource::Filtered, i64::MIN, i64::MAX, 100)
        .await
        .unwrap();
    assert!(
        history.buckets.is_empty(),
        "no rollup of the dropped results"
    );
    write.close().await.unwrap();
    store.close().await;
}

/// References and calibrations count their versions from 1; an alarm recomputed at its key
/// keeps its id and acknowledgement; link resets and the filter state come back.
async fn versions_alarms_resets_and_filter_state_round_trip(backend: Backend) {
    let (_dir, inst, store, mut write) = open(backend).await;
    let reference = brokenray::deformation::Reference {
        g0_from_b: MeasuredPose {
            whole: PoseCov {
                pose: pose(3),
                cov: Mat6::identity() * 1e-9,
            },
            systematic_cov: Mat6::identity() * 4e-10,
            calibration: Some(brokenray::deformation::CalibrationStamp(-77)),
        },
        origin: brokenray::deformation::ReferenceOrigin::Window {
            from_ns: T0_NS,
            to_ns: T0_NS + 60 * S,
            count: 600,
        },
    };
    let transition = Transition {
        kind: AlarmKind::Deformation,
        time_ns: T0_NS + 5 * S,
        from: Level::None,
        to: Level::Warn,
        value: 61.5,
        unit: ValueUnit::Arcsec,
        message: "rotation 61.5 arcsec".into(),
    };
    let mut tx = write.begin(0).await.unwrap();
    assert_eq!(
        tx.insert_reference(TargetId(0), &reference, T0_NS)
            .await
            .unwrap(),
        1
    );
    assert_eq!(
        tx.insert_reference(TargetId(0), &reference, T0_NS + 1)
            .await
            .unwrap(),
        2
    );
    assert_eq!(
        tx.insert_calibration(LinkId(0), T0_NS, &reference.g0_from_b.whole, T0_NS)
            .await
            .unwrap(),
        1
    );
    let id = tx
        .insert_alarm(TargetId(0), &transition, T0_NS)
        .await
        .unwrap();
    tx.acknowledge_alarm(id, "ops", Some("seen"), T0_NS + 9)
        .await
        .unwrap();
    let mut recomputed = transition.clone();
    recomputed.to = Level::Alarm;
    assert_eq!(
        tx.insert_alarm(TargetId(0), &recomputed, T0_NS + 10)
            .await
            .unwrap(),
        id
    );
    tx.insert_link_reset(LinkId(0), Some("ops"), Some("lens cleaned"), T0_NS + 20)
        .await
        .unwrap();
    tx.save_filter_state("digest-1", "{\"links\":[]}", T0_NS)
        .await
        .unwrap();
    tx.save_filter_state("digest-2", "{\"links\":[1]}", T0_NS + 1)
        .await
        .unwrap();
    tx.commit().await.unwrap();

    let references = store.references(TargetId(0)).await.unwrap();
    assert_eq!(references.len(), 2);
    assert_eq!(references[1].version, 2);
    assert_eq!(references[1].reference, reference);
    let calibrations = store.calibrations(LinkId(0)).await.unwrap();
    assert_eq!(calibrations.len(), 1);
    assert_eq!(calibrations[0].parent_from_child, reference.g0_from_b.whole);
    let alarm = store.alarm(id).await.unwrap().expect("stored");
    assert_eq!(alarm.transition, recomputed);
    let ack = alarm.ack.expect("kept");
    assert_eq!(
        (ack.by.as_str(), ack.note.as_deref()),
        ("ops", Some("seen"))
    );
    assert_eq!(
        store
            .alarms(Some(TargetId(0)), i64::MIN, i64::MAX, 10, true)
            .await
            .unwrap()
            .len(),
        1
    );
    assert_eq!(
        store.alarm_levels(TargetId(0)).await.unwrap(),
        [Level::Alarm, Level::None, Level::None]
    );
    let resets = store.last_link_resets().await.unwrap();
    assert_eq!(
        resets,
        vec![(
            LinkId(0),
            T0_NS + 20,
            Some("ops".into()),
            Some("lens cleaned".into())
        )]
    );
    assert_eq!(
        store.filter_state().await.unwrap(),
        Some(("digest-2".into(), "{\"links\":[1]}".into()))
    );
    drop(inst);
    write.close().await.unwrap();
    store.close().await;
}

/// Retention removes samples and results before its cutoffs (on PostgreSQL by dropping the
/// day partitions wholly before them) and keeps the rollups, so the history still covers the
/// pruned days.
async fn retention_removes_old_rows_and_keeps_rollups(backend: Backend) {
    let (_dir, inst, store, mut write) = open(backend).await;
    // Days ahead of today fall in partitions made at start-up.
    let now_ns = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as i64;
    let day0 = (now_ns / DAY + 1) * DAY;
    let per_day = 500;
    let samples: Vec<NewSample> = (0..3 * per_day)
        .map(|k| sample(k, day0 + k * (DAY / per_day)))
        .collect();
    commit_samples(&mut write, &samples).await;
    let results: Vec<NewResult> = (0..3 * per_day)
        .map(|k| result(k, day0 + k * (DAY / per_day)))
        .collect();
    commit_results(&mut write, &results).await;
    // On PostgreSQL, the partitions of samples of the first two days (named by their start).
    let first_days = || match &inst.server.database {
        brokenray::config::Database::Postgres(url) => {
            let n = crate::common::postgres::cluster().psql(
                url.database_name().unwrap(),
                &format!(
                    "select count(*) from pg_inherits where inhparent = 'samples'::regclass \
                     and inhrelid::regclass::text in ('samples_p{day0}', 'samples_p{}')",
                    day0 + DAY
                ),
            );
            Some(n.parse::<i64>().unwrap())
        }
        brokenray::config::Database::Sqlite(_) => None,
    };
    let first_days_before = first_days();
    let mut tx = write.begin(0).await.unwrap();
    let (gone_samples, gone_results) = tx
        .prune(day0 + 2 * DAY, day0 + DAY + DAY / 2, Default::default())
        .await
        .unwrap();
    tx.commit().await.unwrap();
    assert_eq!(gone_samples, 2 * per_day as u64);
    assert_eq!(gone_results, (per_day + per_day / 2) as u64);
    let left = store
        .samples(LinkId(0), i64::MIN, i64::MAX, i64::MAX)
        .await
        .unwrap();
    assert_eq!(left.len(), per_day as usize);
    assert_eq!(left[0].time_ns, day0 + 2 * DAY);
    assert_eq!(
        store
            .count_results(TargetId(0), ResultSource::Filtered, i64::MIN, i64::MAX)
            .await
            .unwrap(),
        (per_day + per_day / 2) as u64
    );
    if let (Some(before), Some(after)) = (first_days_before, first_days()) {
        assert_eq!(
            (before, after),
            (2, 0),
            "the first two days' partitions dropped"
        );
    }
    let history = store
        .history(TargetId(0), ResultSource::Filtered, i64::MIN, i64::MAX, 100)
        .await
        .unwrap();
    let counted: i64 = history.buckets.iter().map(|b| b.n).sum();
    assert_eq!(counted, 3 * per_day, "the rollups keep the pruned days");
    write.close().await.unwrap();
    store.close().await;
}

/// History read from the rollups (built over several commits) and from the results agree
/// with a direct scan: counts, minima, maxima and means per bucket.
async fn rollups_agree_with_the_results_they_summarise(backend: Backend) {
    let (_dir, _inst, store, mut write) = open(backend).await;
    let n = 20_000;
    for part in 0..4 {
        let rows: Vec<NewResult> = (part * n / 4..(part + 1) * n / 4)
            .map(|k| result(k, T0_NS + k * S / 5))
            .collect();
        commit_results(&mut write, &rows).await;
    }
    let all = store
        .results(
            TargetId(0),
            ResultSource::Filtered,
            i64::MIN,
            i64::MAX,
            i64::MAX,
        )
        .await
        .unwrap();
    for max_points in [40, 5_000] {
        let h = store
            .history(
                TargetId(0),
                ResultSource::Filtered,
                i64::MIN,
                i64::MAX,
                max_points,
            )
            .await
            .unwrap();
        assert_eq!(h.resolution_s.is_some(), max_points == 40);
        let total: i64 = h.buckets.iter().map(|b| b.n).sum();
        assert_eq!(total, n);
        for b in &h.buckets {
            let inside: Vec<f64> = all
                .iter()
                .filter(|r| r.time_ns >= b.start_ns && r.time_ns < b.start_ns + h.bucket_ns)
                .map(|r| r.estimate.whole.pose.translation.vector.x)
                .collect();
            assert_eq!(inside.len() as i64, b.n);
            let min = inside.iter().copied().fold(f64::INFINITY, f64::min);
            let max = inside.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let mean = inside.iter().sum::<f64>() / inside.len() as f64;
            // Component 3 is t_x_mm.
            assert_eq!((b.min[3], b.max[3]), (min, max));
            assert!((b.mean(3).unwrap() - mean).abs() < 1e-9);
        }
    }
    write.close().await.unwrap();
    store.close().await;
}

/// Rows older than the partitions made at start-up (a backfill) land in PostgreSQL's default
/// partition; the maintenance of a retention pass moves them into day partitions of their own,
/// and every row still reads back.
async fn rows_before_the_partitions_are_moved_into_their_own_by_maintenance(backend: Backend) {
    let (_dir, inst, store, mut write) = open(backend).await;
    let samples: Vec<NewSample> = (0..2_000)
        .map(|k| sample(k, T0_NS - 3 * DAY + k * 120 * S))
        .collect();
    commit_samples(&mut write, &samples).await;
    let results: Vec<NewResult> = (0..2_000)
        .map(|k| result(k, T0_NS - 3 * DAY + k * 120 * S))
        .collect();
    commit_results(&mut write, &results).await;
    let in_default = |table: &str| match &inst.server.database {
        brokenray::config::Database::Postgres(url) => Some(
            crate::common::postgres::cluster()
                .psql(
                    url.database_name().unwrap(),
                    &format!("select count(*) from only {table}_default"),
                )
                .parse::<i64>()
                .unwrap(),
        ),
        brokenray::config::Database::Sqlite(_) => None,
    };
    if let Some(n) = in_default("samples") {
        assert_eq!(n, 2_000, "before the partitions: in the default partition");
    }
    let mut tx = write.begin(0).await.unwrap();
    assert_eq!(
        tx.prune(i64::MIN, i64::MIN, Default::default())
            .await
            .unwrap(),
        (0, 0)
    );
    tx.commit().await.unwrap();
    for table in ["samples", "results", "rollups"] {
        if let Some(n) = in_default(table) {
            assert_eq!(n, 0, "{table}: moved out of the default partition");
        }
    }
    let back = store
        .samples(LinkId(0), i64::MIN, i64::MAX, i64::MAX)
        .await
        .unwrap();
    assert_eq!(back.len(), samples.len());
    assert_eq!(
        store
            .count_results(TargetId(0), ResultSource::Filtered, i64::MIN, i64::MAX)
            .await
            .unwrap(),
        2_000
    );
    let history = store
        .history(TargetId(0), ResultSource::Filtered, i64::MIN, i64::MAX, 10)
        .await
        .unwrap();
    assert_eq!(history.buckets.iter().map(|b| b.n).sum::<i64>(), 2_000);
    write.close().await.unwrap();
    store.close().await;
}

/// The installation with `[server] database = url` (the built-in one otherwise).
fn at(url: &str) -> Installation {
    installation_at(url, Some(ONE_LINK))
}

/// A URL without a database name or that does not parse is a configuration error naming the
/// field; a server that does not answer, a role that may not create the schema and a second
/// writer are refused at start-up with the reason, and no message shows the password.
#[tokio::test]
async fn postgres_start_up_refusals_name_the_reason() {
    if crate::common::skip_without(
        crate::common::Needs::Postgres,
        concat!(
            module_path!(),
            "::postgres_start_up_refusals_name_the_reason"
        ),
    ) {
        return;
    }
    for (text, expected) in [
        ("postgres://brokenray@127.0.0.1:5432", "names no database"),
        ("postgres://[::1", "not a valid PostgreSQL URL"),
    ] {
        let err = brokenray::config::parse(
            "t.toml",
            &format!("[server]\ndatabase = \"{text}\"\n{ONE_LINK}"),
        )
        .expect_err("refused")
        .to_string();
        assert!(
            err.contains("server.database") && err.contains(expected),
            "{err}"
        );
    }
    // Nothing listens on port 1.
    let down = at("postgres://brokenray:hunter2@127.0.0.1:1/brokenray");
    let err = store::open(&down, T0_NS)
        .await
        .expect_err("refused")
        .to_string();
    assert!(err.contains("cannot connect"), "{err}");
    assert!(!err.contains("hunter2"), "the password leaked: {err}");
    assert!(err.contains("***"), "{err}");

    let cluster = crate::common::postgres::cluster();
    let url = cluster.create_database();
    let name = url.rsplit('/').next().unwrap().to_owned();
    let role = format!("{name}_reader");
    cluster.psql(&name, &format!("create role {role} login"));
    let limited = at(&url.replace("brokenray@", &format!("{role}@")));
    let err = store::open(&limited, T0_NS)
        .await
        .expect_err("refused")
        .to_string();
    assert!(
        err.contains("cannot prepare the schema") && err.contains("permission denied"),
        "{err}"
    );
    // It had taken the writer's lock, and gave it back before it answered: a start-up right
    // after is not refused as a second writer. (The cluster is shared with other tests: only
    // this database's locks count.)
    assert_eq!(
        cluster.psql(
            &name,
            "select count(*) from pg_locks where locktype = 'advisory' and database = \
             (select oid from pg_database where datname = current_database())"
        ),
        "0"
    );

    let inst = at(&url);
    let (store, write) = store::open(&inst, T0_NS).await.expect("the first writer");
    let err = store::open(&inst, T0_NS)
        .await
        .expect_err("a second writer")
        .to_string();
    assert!(err.contains("another brokenray service"), "{err}");
    // A reader (replay) opens beside the writer.
    let reader = store::open_reader(&inst, T0_NS).await.expect("a reader");
    assert!(
        reader
            .latest_result(TargetId(0), ResultSource::Filtered)
            .await
            .unwrap()
            .is_none()
    );
    reader.close().await;
    write.close().await.unwrap();
    store.close().await;
    // The lock goes with the writer's connection.
    let (store, write) = store::open(&inst, T0_NS).await.expect("a writer again");
    write.close().await.unwrap();
    store.close().await;
}
