//! One filter update per model, and a target evaluation over the default 5-link chain.
//!
//! Run: `cargo bench --bench filter`.

use brokenray::bank::{FilterBank, MeasurementUncertainty, Sample};
use brokenray::filter::{FilterTuning, LinkFilter, MotionModel};
use brokenray::geometry::{ARCSEC_PER_RAD, Mat6, Pose, PoseCov, Twist, se3_exp};
use brokenray::model::TargetId;
use brokenray::{config, model};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use std::hint::black_box;

fn lcg(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

/// Pre-generated noisy measurements of a fixed pose, 25 Hz.
fn measurements(n: usize) -> Vec<(i64, PoseCov)> {
    let r_rot = 20.0 / ARCSEC_PER_RAD;
    let cov = Mat6::from_diagonal(&Twist::new(
        0.09,
        0.09,
        0.09,
        r_rot * r_rot,
        r_rot * r_rot,
        r_rot * r_rot,
    ));
    let truth = se3_exp(&Twist::new(10.0, -20.0, 3000.0, 0.1, 0.2, 3.0));
    let mut state = 9;
    (0..n)
        .map(|k| {
            let d = Twist::new(
                0.3 * lcg(&mut state),
                0.3 * lcg(&mut state),
                0.3 * lcg(&mut state),
                r_rot * lcg(&mut state),
                r_rot * lcg(&mut state),
                r_rot * lcg(&mut state),
            );
            (
                k as i64 * 40_000_000,
                PoseCov {
                    pose: se3_exp(&d) * truth,
                    cov,
                },
            )
        })
        .collect()
}

fn bench_update(c: &mut Criterion) {
    let data = measurements(4096);
    let mut group = c.benchmark_group("filter_update");
    for model in [
        MotionModel::Static,
        MotionModel::ConstantVelocity,
        MotionModel::Oscillatory,
    ] {
        group.bench_with_input(
            BenchmarkId::from_parameter(model.name()),
            &model,
            |b, &model| {
                let mut filter = LinkFilter::new(FilterTuning::default_for(model));
                let mut i = 0usize;
                let mut offset = 0i64;
                b.iter(|| {
                    let (t, z) = &data[i % data.len()];
                    if i.is_multiple_of(data.len()) && i > 0 {
                        offset += data.len() as i64 * 40_000_000;
                    }
                    i += 1;
                    black_box(filter.update(t + offset, black_box(z)))
                })
            },
        );
    }
    group.finish();
}

fn bench_evaluate(c: &mut Criterion) {
    let inst = config::default_installation();
    let mut bank = FilterBank::new(&inst.model);
    let names = ["C1_from_B", "C2_from_M", "C3_from_G"];
    for k in 0..50i64 {
        for name in names {
            let id = inst.model.topology.link_id(name).expect("link");
            let pose: Pose = match &inst.model.link(id).kind {
                model::LinkKind::Measured(m) => m.nominal.expect("nominal"),
                model::LinkKind::Calibrated { .. } => unreachable!("measured"),
            };
            bank.ingest(&Sample {
                link: id,
                time_ns: k * 40_000_000,
                parent_from_child: pose,
                uncertainty: MeasurementUncertainty::Default,
            })
            .expect("ingest");
        }
    }
    c.bench_function("evaluate_target_default_chain", |b| {
        b.iter(|| {
            bank.evaluate(TargetId(0), black_box(49 * 40_000_000 + 20_000_000))
                .expect("evaluate")
        })
    });
}

criterion_group!(benches, bench_update, bench_evaluate);
criterion_main!(benches);
