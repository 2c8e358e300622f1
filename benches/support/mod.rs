//! What several benches share: a database filled with synthetic filtered results.

use brokenray::bank::ResultSource;
use brokenray::config::Installation;
use brokenray::geometry::{Mat6, Pose, PoseCov, rotation_from_euler};
use brokenray::store::{self, NewResult};
use nalgebra::Translation3;

/// The first result's time: 2026-11-21T10:00:00Z.
pub const T0: i64 = 1_795_255_200_000_000_000;
/// 25 Hz.
pub const PERIOD_NS: i64 = 40_000_000;

/// Writes `n` filtered results of target 0 at 25 Hz from [`T0`] (a slow sway of a few mm and a
/// few arc-seconds) into the installation's database, 200,000 per transaction.
pub async fn fill_filtered_results(inst: &Installation, n: i64) {
    let (store, mut write) = store::open(inst, 0).await.expect("open");
    let chunk = 200_000;
    for start in (0..n).step_by(chunk) {
        let rows: Vec<NewResult> = (start..(start + chunk as i64).min(n))
            .map(|k| {
                let t = k as f64 / 25.0;
                NewResult {
                    target: brokenray::model::TargetId(0),
                    source: ResultSource::Filtered,
                    time_ns: T0 + k * PERIOD_NS,
                    estimate: brokenray::deformation::MeasuredPose {
                        whole: PoseCov {
                            pose: Pose::from_parts(
                                Translation3::new(
                                    (t / 8.0).sin(),
                                    -2952.0,
                                    532.0 + (t / 15.0).cos(),
                                ),
                                rotation_from_euler([
                                    -0.0718,
                                    0.026,
                                    2.87 + 1e-5 * (t / 8.0).sin(),
                                ])
                                .expect("rotation"),
                            ),
                            cov: Mat6::identity() * 1e-6,
                        },
                        systematic_cov: Mat6::identity() * 1e-7,
                        calibration: Some(brokenray::deformation::CalibrationStamp(0)),
                    },
                    status: brokenray::bank::TargetStatus::Ok,
                    age_s: 0.0,
                    chi2: None,
                    deformation: None,
                }
            })
            .collect();
        let mut tx = write.begin(0).await.expect("begin");
        tx.insert_results(&[&rows]).await.expect("insert");
        tx.commit().await.expect("commit");
    }
    write.close().await.expect("close");
    store.close().await;
}
