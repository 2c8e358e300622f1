//! Development script: the filtered `G_from_B` of a simulated run measured against the
//! simulator's ground truth, and against the per-axis floor, a causal linear filter of the raw
//! composed series fitted on the truth (least squares over the same data).
//!
//! Run: `cargo run --release --example ship_filter -- [--scenario ship] [--seeds 1,2,3]
//! [--duration-s 300] [--rate-hz 25] [--still-target] [--offset-ms 20] [--floor-s 20]
//! [--model static]`.
//!
//! The built-in installation, its measured links given the model the scenario calls for (as
//! `demo` does: `oscillatory` on a ship; `--model` another), pixel noise only. `--still-target` keeps the target
//! body rigid to the base while the relay stations move (their motion must cancel in
//! `G_from_B`); `--offset-ms D` exposes the cameras at offsets spread over `0..D` ms and stamps
//! each sample with its own exposure time.
//!
//! Prints per seed and axis: the filtered error RMS (arc-seconds, mm), the floor's, their
//! ratio, the mean NEES of the filtered result against its random part (6 expected: the simulated
//! cameras and stations are the configured ones, so the calibrations' part is not drawn) and each axis' z-score variance;
//! the raw results' error RMS; and how many raw and filtered results there were.

use brokenray::bank::{FilterBank, MeasurementUncertainty, Sample};
use brokenray::config;
use brokenray::filter::{FilterTuning, MotionModel};
use brokenray::geometry::{ARCSEC_PER_RAD, Pose, PoseCov, so3_log};
use brokenray::model::{LinkKind, Observer, TargetId};
use brokenray::sim::{Scenario, SimSettings, Simulator};
use nalgebra::{DMatrix, DVector};
use std::collections::HashMap;
use std::sync::Arc;

/// Per axis `[tx, ty, tz (mm), rx, ry, rz (arc-seconds)]` of `estimate` against `truth`:
/// translation difference, and the rotation vector of `R_est * R_truth^T`.
fn error_axes(estimate: &Pose, truth: &Pose) -> [f64; 6] {
    let dt = estimate.translation.vector - truth.translation.vector;
    let dr = so3_log(&(estimate.rotation * truth.rotation.inverse())) * ARCSEC_PER_RAD;
    [dt.x, dt.y, dt.z, dr.x, dr.y, dr.z]
}

/// The left-perturbation error `[rho; phi]` whose NEES the covariance judges.
fn nees(estimate: &PoseCov, truth: &Pose) -> Option<(f64, [f64; 6])> {
    let e = brokenray::geometry::se3_log(&(estimate.pose * truth.inverse()));
    let p_inv = estimate.cov.try_inverse()?;
    let n = (e.transpose() * p_inv * e)[(0, 0)];
    let z = std::array::from_fn(|i| e[i] / estimate.cov[(i, i)].sqrt());
    Some((n, z))
}

/// Least-squares causal FIR of `taps` taps plus a constant from `input` to `target`; returns
/// the residual RMS.
fn fir_floor(input: &[f64], target: &[f64], taps: usize) -> f64 {
    let n = input.len();
    if n <= taps * 2 {
        return f64::NAN;
    }
    let rows = n - taps + 1;
    let mut a = DMatrix::<f64>::zeros(rows, taps + 1);
    let mut b = DVector::<f64>::zeros(rows);
    for r in 0..rows {
        let k = r + taps - 1;
        for j in 0..taps {
            a[(r, j)] = input[k - j];
        }
        a[(r, taps)] = 1.0;
        b[r] = target[k];
    }
    let ata = a.transpose() * &a;
    let atb = a.transpose() * &b;
    let Some(x) = ata.cholesky().map(|c| c.solve(&atb)) else {
        return f64::NAN;
    };
    let res = &a * x - b;
    (res.norm_squared() / rows as f64).sqrt()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

struct Args {
    scenario: Scenario,
    seeds: Vec<u64>,
    duration_s: f64,
    rate_hz: f64,
    still_target: bool,
    offset_ms: f64,
    floor_s: f64,
    model: Option<MotionModel>,
}

fn args() -> Args {
    let mut a = Args {
        scenario: Scenario::Ship,
        seeds: vec![1, 2, 3],
        duration_s: 300.0,
        rate_hz: 25.0,
        still_target: false,
        offset_ms: 0.0,
        floor_s: 20.0,
        model: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(k) = it.next() {
        let mut v = || it.next().expect("a value after the flag");
        match k.as_str() {
            "--scenario" => a.scenario = v().parse().expect("scenario"),
            "--seeds" => a.seeds = v().split(',').map(|s| s.parse().expect("seed")).collect(),
            "--duration-s" => a.duration_s = v().parse().expect("duration"),
            "--rate-hz" => a.rate_hz = v().parse().expect("rate"),
            "--still-target" => a.still_target = true,
            "--offset-ms" => a.offset_ms = v().parse().expect("offset"),
            "--floor-s" => a.floor_s = v().parse().expect("floor length"),
            "--model" => a.model = Some(MotionModel::parse(&v()).expect("model")),
            other => panic!("unknown flag {other}"),
        }
    }
    a
}

fn main() {
    let args = args();
    let mut installation = config::load_or_default(None).expect("built-in installation");
    let motion = args.model.unwrap_or(match args.scenario {
        Scenario::Ship => MotionModel::Oscillatory,
        Scenario::Drift | Scenario::Tunnel => MotionModel::ConstantVelocity,
        Scenario::Static | Scenario::Bump => MotionModel::Static,
    });
    for spec in &mut Arc::make_mut(&mut installation.model).links {
        if let LinkKind::Measured(m) = &mut spec.kind
            && m.tuning.model != motion
        {
            m.tuning = FilterTuning {
                gate_probability: m.tuning.gate_probability,
                reinit_after_outliers: m.tuning.reinit_after_outliers,
                ..FilterTuning::default_for(motion)
            };
        }
    }
    let model = installation.model.clone();
    let observer = Observer::new(&model);
    let target = TargetId(0);
    println!(
        "scenario {:?}, {} s at {} Hz, still target: {}, exposure offsets up to {} ms",
        args.scenario, args.duration_s, args.rate_hz, args.still_target, args.offset_ms
    );
    println!("seed axis   filtered    floor  ratio  raw_rms  z_var");
    for &seed in &args.seeds {
        let settings = SimSettings {
            scenario: args.scenario,
            rate_hz: args.rate_hz,
            start_ns: 1_700_000_000_000_000_000,
            duration_s: Some(args.duration_s),
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed,
        };
        let mut sim = Simulator::new(&model, settings).expect("simulator");
        sim.set_still_target(args.still_target);
        sim.set_exposure_spread_ns((args.offset_ms * 1e6).round() as i64);
        let mut bank = FilterBank::shared(model.clone());
        let n_groups = (args.duration_s * args.rate_hz).round() as usize;
        let mut truth_at: HashMap<i64, Pose> = HashMap::new();
        let mut truths: Vec<(i64, Pose)> = Vec::new();
        let mut raws: Vec<(i64, Pose)> = Vec::new();
        let (mut raw_nees, mut raw_n) = (0.0, 0usize);
        let mut filtered: Vec<(i64, PoseCov)> = Vec::new();
        for _ in 0..n_groups {
            let group = sim.next_group();
            let truth = group.truth[0].1;
            truth_at.insert(group.time_ns, truth);
            truths.push((group.time_ns, truth));
            let mut samples = Vec::new();
            for o in &group.observations {
                let Ok((link, s)) = observer.solve(&o.camera, &o.marker, &o.points_px, None, None)
                else {
                    continue;
                };
                let id = model.topology.link_id(&link.name).expect("link");
                samples.push(Sample {
                    link: id,
                    time_ns: group.time_ns + sim.exposure_offset_ns(&o.camera),
                    parent_from_child: s.camera_from_marker,
                    uncertainty: MeasurementUncertainty::Covariance(s.covariance),
                });
            }
            samples.sort_by_key(|s| (s.time_ns, s.link));
            for s in &samples {
                let out = bank.ingest(s).expect("ingest");
                for r in out.raw_results.iter().filter(|r| r.target == target) {
                    raws.push((r.time_ns, r.target_from_base.whole.pose));
                    let random = r.target_from_base.random();
                    if let Some(truth) = truth_at.get(&r.time_ns)
                        && let Some((n, _)) = nees(&random, truth)
                    {
                        raw_nees += n;
                        raw_n += 1;
                    }
                }
                for f in out.filtered_results.iter().filter(|f| f.target == target) {
                    // Judged by the random part: the simulator's cameras and stations are the
                    // configured ones, so the calibrations' part is an upper bound here.
                    if let Some(p) = f.target_from_base {
                        filtered.push((f.time_ns, p.random()));
                    }
                }
            }
        }
        // The truth at a result's time: exact at a group's time, else the nearest group's.
        let truth_near = |t: i64| -> Pose {
            truth_at.get(&t).copied().unwrap_or_else(|| {
                let i = truths
                    .partition_point(|(tt, _)| *tt < t)
                    .min(truths.len() - 1);
                truths[i].1
            })
        };
        // Skip the first 10 s: the filters settle.
        let settle = truths[0].0 + 10_000_000_000;
        let mut f_err: Vec<[f64; 6]> = Vec::new();
        let mut nees_sum = 0.0;
        let mut z_sq = [0.0; 6];
        let mut n_nees = 0usize;
        for (t, p) in filtered.iter().filter(|(t, _)| *t >= settle) {
            let truth = truth_near(*t);
            f_err.push(error_axes(&p.pose, &truth));
            if let Some((n, z)) = nees(p, &truth) {
                nees_sum += n;
                n_nees += 1;
                for i in 0..6 {
                    z_sq[i] += z[i] * z[i];
                }
            }
        }
        // The floor: raw series -> truth, per axis, about the first truth.
        let origin = truths[0].1;
        let raw_by_t: HashMap<i64, Pose> = raws.iter().copied().collect();
        let mut raw_x: Vec<[f64; 6]> = Vec::new();
        let mut tru_x: Vec<[f64; 6]> = Vec::new();
        let mut raw_err: Vec<[f64; 6]> = Vec::new();
        for (t, truth) in &truths {
            let Some(raw) = raw_by_t.get(t) else { continue };
            raw_x.push(error_axes(raw, &origin));
            tru_x.push(error_axes(truth, &origin));
            if *t >= settle {
                raw_err.push(error_axes(raw, truth));
            }
        }
        let names = ["tx_mm", "ty_mm", "tz_mm", "rx_as", "ry_as", "rz_as"];
        // The floor's taps: `--floor-s` of history.
        let taps = (args.floor_s * args.rate_hz).round() as usize;
        let skip = (10.0 * args.rate_hz) as usize;
        for i in 0..6 {
            let input: Vec<f64> = raw_x.iter().map(|x| x[i]).collect();
            let target: Vec<f64> = tru_x.iter().map(|x| x[i]).collect();
            let floor = if input.len() > skip {
                fir_floor(&input[skip..], &target[skip..], taps)
            } else {
                f64::NAN
            };
            let f = rms(&f_err.iter().map(|e| e[i]).collect::<Vec<_>>());
            let r = rms(&raw_err.iter().map(|e| e[i]).collect::<Vec<_>>());
            let zv = z_sq[i] / n_nees.max(1) as f64;
            println!(
                "{seed:>4} {:<6} {f:>8.3} {floor:>8.3} {:>6.2} {r:>8.3} {zv:>6.2}",
                names[i],
                f / floor
            );
        }
        if let Some(t) = bank.target_tuning(target) {
            let o = &t.tuning.oscillation;
            println!(
                "seed {seed}: tuning at the end: period {:.1} s, rotation {:.1?} arcsec, translation {:.3?} mm, drift {:.3} arcsec/sqrt(s) {:.4} mm/sqrt(s); mean NIS {:.2} over {} (band {:.2} to {:.2})",
                o.period_s,
                o.rotation_arcsec,
                o.translation_mm,
                t.tuning.random_walk_rotation_arcsec_per_sqrt_s,
                t.tuning.random_walk_translation_mm_per_sqrt_s,
                t.consistency.mean_nis,
                t.consistency.samples,
                t.consistency.band.0,
                t.consistency.band.1
            );
        }
        let (mut samples, mut outliers, mut restarts) = (0, 0, 0);
        for l in &model.links {
            let st = bank.link_status(l.id);
            samples += st.n_samples;
            outliers += st.n_outliers;
            restarts += st.n_reinitializations;
        }
        println!(
            "seed {seed}: links: {outliers} outliers and {restarts} restarts in {samples} samples; {} filtered results of {} groups; the target filter {} its data",
            filtered.len(),
            n_groups,
            if bank
                .target_tuning(target)
                .is_some_and(|t| t.consistency.fits())
            {
                "fits"
            } else {
                "does not fit"
            }
        );
        println!(
            "seed {seed}: NEES {:.2} over {n_nees} filtered results, raw {:.2}; {} raw results of {} groups",
            nees_sum / n_nees.max(1) as f64,
            raw_nees / raw_n.max(1) as f64,
            raws.len(),
            n_groups
        );
    }
}
