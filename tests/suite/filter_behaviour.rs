//! The link filters against simulated truth: consistency (NEES) per model, noise reduction,
//! outliers, steps, flexure tracking, covariance health, out-of-order samples.
//!
//! Truth is simulated independently of the filter's discretisation: the random walk exactly,
//! the dynamic models by Euler-Maruyama with 1 ms substeps.

use crate::common;

use brokenray::chain::chi_square_quantile;
use brokenray::filter::{CV_RATE_PRIOR_S, Disposition, FilterTuning, LinkFilter, MotionModel};
use brokenray::geometry::{ARCSEC_PER_RAD, Mat6, Pose, PoseCov, Twist, se3_exp, se3_log};
use common::{perturb, random_pose, sample_twist};
use proptest::prelude::*;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

const NS: i64 = 1_000_000_000;

/// A measurement covariance: 20 arc-seconds and 0.3 mm per axis, uncorrelated.
fn measurement_cov() -> Mat6 {
    let r = (20.0 / ARCSEC_PER_RAD).powi(2);
    let t = 0.3f64.powi(2);
    Mat6::from_diagonal(&Twist::new(t, t, t, r, r, r))
}

fn nees(truth: &Pose, estimate: &PoseCov) -> f64 {
    let e = se3_log(&(truth * estimate.pose.inverse()));
    let info = estimate
        .cov
        .cholesky()
        .expect("positive definite")
        .inverse();
    (e.transpose() * info * e)[(0, 0)]
}

fn gaussian(rng: &mut StdRng) -> f64 {
    StandardNormal.sample(rng)
}

/// The truth of one run of a model, advanced over irregular steps.
enum Truth {
    Static(Pose),
    ConstantVelocity { pose: Pose, nu: Twist },
    Oscillatory { mean: Pose, x: Twist, v: Twist },
}

impl Truth {
    fn start(model: MotionModel, tuning: &FilterTuning, rng: &mut StdRng) -> Self {
        let pose = random_pose(rng, 3000.0);
        match model {
            MotionModel::Static => Truth::Static(pose),
            MotionModel::ConstantVelocity => {
                let q = acceleration_density(tuning);
                let nu = Twist::from_fn(|i, _| (q[i] * CV_RATE_PRIOR_S).sqrt() * gaussian(rng));
                Truth::ConstantVelocity { pose, nu }
            }
            MotionModel::Oscillatory => {
                let (var_x, w0_sq, _) = oscillator(tuning);
                let x = Twist::from_fn(|i, _| var_x[i].sqrt() * gaussian(rng));
                let v = Twist::from_fn(|i, _| (var_x[i] * w0_sq).sqrt() * gaussian(rng));
                Truth::Oscillatory { mean: pose, x, v }
            }
        }
    }

    fn pose(&self) -> Pose {
        match self {
            Truth::Static(p) => *p,
            Truth::ConstantVelocity { pose, .. } => *pose,
            Truth::Oscillatory { mean, x, .. } => se3_exp(x) * mean,
        }
    }

    fn advance(&mut self, tuning: &FilterTuning, dt_s: f64, rng: &mut StdRng) {
        let rw = random_walk_density(tuning);
        match self {
            Truth::Static(p) => {
                let w = Twist::from_fn(|i, _| (rw[i] * dt_s).sqrt() * gaussian(rng));
                *p = se3_exp(&w) * *p;
            }
            Truth::ConstantVelocity { pose, nu } => {
                let q = acceleration_density(tuning);
                let steps = (dt_s / 1e-3).round().max(1.0) as usize;
                let h = dt_s / steps as f64;
                for _ in 0..steps {
                    *pose = se3_exp(&(*nu * h)) * *pose;
                    *nu += Twist::from_fn(|i, _| (q[i] * h).sqrt() * gaussian(rng));
                }
            }
            Truth::Oscillatory { mean, x, v } => {
                let (var_x, w0_sq, mu) = oscillator(tuning);
                let steps = (dt_s / 1e-3).round().max(1.0) as usize;
                let h = dt_s / steps as f64;
                for _ in 0..steps {
                    for i in 0..6 {
                        let q = var_x[i] * 4.0 * mu * w0_sq;
                        // Semi-implicit Euler-Maruyama: rate first, then position.
                        v[i] +=
                            (-w0_sq * x[i] - 2.0 * mu * v[i]) * h + (q * h).sqrt() * gaussian(rng);
                        x[i] += v[i] * h;
                    }
                    let w = Twist::from_fn(|i, _| (rw[i] * h).sqrt() * gaussian(rng));
                    *mean = se3_exp(&w) * *mean;
                }
            }
        }
    }
}

fn density(rotation_arcsec: f64, translation_mm: f64) -> Twist {
    let r = (rotation_arcsec / ARCSEC_PER_RAD).powi(2);
    let t = translation_mm * translation_mm;
    Twist::new(t, t, t, r, r, r)
}

fn random_walk_density(t: &FilterTuning) -> Twist {
    density(
        t.random_walk_rotation_arcsec_per_sqrt_s,
        t.random_walk_translation_mm_per_sqrt_s,
    )
}

fn acceleration_density(t: &FilterTuning) -> Twist {
    density(
        t.acceleration_rotation_arcsec_per_s_sqrt_s,
        t.acceleration_translation_mm_per_s_sqrt_s,
    )
}

/// `(stationary variance of x per axis, w0^2, mu)` of the oscillator.
fn oscillator(t: &FilterTuning) -> (Twist, f64, f64) {
    let o = &t.oscillation;
    let mu = 1.0 / o.correlation_time_s;
    let lambda = 2.0 * std::f64::consts::PI / o.period_s;
    let r = o.rotation_arcsec.map(|s| (s / ARCSEC_PER_RAD).powi(2));
    let tr = o.translation_mm.map(|s| s * s);
    (
        Twist::new(tr[0], tr[1], tr[2], r[0], r[1], r[2]),
        mu * mu + lambda * lambda,
        mu,
    )
}

/// Independent runs of a model: the NEES of each run's final estimate, summed, and how many
/// samples the gate refused.
fn summed_final_nees(model: MotionModel, runs: usize, steps: usize, seed: u64) -> (f64, usize) {
    let tuning = FilterTuning::default_for(model);
    let r = measurement_cov();
    let mut rng = StdRng::seed_from_u64(seed);
    let mut sum = 0.0;
    let mut gated = 0;
    for _ in 0..runs {
        let mut truth = Truth::start(model, &tuning, &mut rng);
        let mut filter = LinkFilter::new(tuning);
        let mut t_ns = 1_700_000_000 * NS;
        for k in 0..steps {
            if k > 0 {
                // Irregular steps between 20 and 60 ms.
                let dt_ns = rng.random_range(20_000_000..60_000_000);
                t_ns += dt_ns;
                truth.advance(&tuning, dt_ns as f64 / 1e9, &mut rng);
            }
            let z = PoseCov {
                pose: perturb(&mut rng, &truth.pose(), &r),
                cov: r,
            };
            if filter.update(t_ns, &z).is_outlier() {
                gated += 1;
            }
        }
        let estimate = filter.predict(t_ns).unwrap().unwrap();
        sum += nees(&truth.pose(), &estimate);
    }
    (sum, gated)
}

fn assert_consistent(model: MotionModel, seed: u64) {
    let (runs, steps) = (1000, 40);
    let (sum, gated) = summed_final_nees(model, runs, steps, seed);
    // The 99.9 % gate refuses about 0.1 % of consistent samples (the innovations are
    // chi-square); many more would mean the innovation covariance is too small.
    let gated_fraction = gated as f64 / (runs * steps) as f64;
    assert!(
        gated_fraction < 0.003,
        "{}: {:.3} % of consistent samples gated",
        model.name(),
        100.0 * gated_fraction
    );
    let (lo, hi) = (
        chi_square_quantile(6 * runs, 0.025),
        chi_square_quantile(6 * runs, 0.975),
    );
    assert!(
        (lo..=hi).contains(&sum),
        "{}: summed NEES {sum:.0} over {runs} runs outside its 95 % bounds [{lo:.0}, {hi:.0}] (mean {:.3}, expected 6)",
        model.name(),
        sum / runs as f64
    );
}

#[test]
fn static_filter_is_consistent_with_its_random_walk() {
    assert_consistent(MotionModel::Static, 11);
}

#[test]
fn constant_velocity_filter_is_consistent_with_white_noise_acceleration() {
    assert_consistent(MotionModel::ConstantVelocity, 12);
}

#[test]
fn oscillatory_filter_is_consistent_with_a_gauss_markov_flexure() {
    assert_consistent(MotionModel::Oscillatory, 13);
}

#[test]
fn static_filter_error_is_five_times_below_raw_after_100_samples() {
    let tuning = FilterTuning::default_for(MotionModel::Static);
    let r = measurement_cov();
    let mut rng = StdRng::seed_from_u64(21);
    let (mut raw_sq, mut filtered_sq) = (0.0, 0.0);
    let trials = 200;
    for _ in 0..trials {
        let truth = random_pose(&mut rng, 3000.0);
        let mut filter = LinkFilter::new(tuning);
        let mut last_raw = Twist::zeros();
        for k in 0..100 {
            let z = PoseCov {
                pose: perturb(&mut rng, &truth, &r),
                cov: r,
            };
            filter.update(k * 40_000_000, &z);
            last_raw = se3_log(&(z.pose * truth.inverse()));
        }
        let est = filter.predict(99 * 40_000_000).unwrap().unwrap();
        let e = se3_log(&(est.pose * truth.inverse()));
        raw_sq += last_raw.norm_squared();
        filtered_sq += e.norm_squared();
    }
    let ratio = (raw_sq / filtered_sq).sqrt();
    assert!(
        ratio >= 5.0,
        "filtered error only {ratio:.2} times below raw"
    );
}

#[test]
fn gross_outliers_are_all_flagged_and_the_estimate_stays_within_three_sigma() {
    let tuning = FilterTuning::default_for(MotionModel::Static);
    let r = measurement_cov();
    let mut rng = StdRng::seed_from_u64(31);
    let truth = random_pose(&mut rng, 3000.0);
    let mut filter = LinkFilter::new(tuning);
    let (mut planted, mut flagged_planted, mut outside, mut checks) = (0, 0, 0, 0);
    for k in 0..2000i64 {
        let gross = k > 10 && rng.random_bool(0.02);
        let pose = if gross {
            planted += 1;
            // 100 sigma in a random direction of the measurement's own metric.
            let dir = sample_twist(&mut rng, &r);
            let scale =
                100.0 / (dir.transpose() * r.cholesky().unwrap().inverse() * dir)[(0, 0)].sqrt();
            se3_exp(&(dir * scale)) * truth
        } else {
            perturb(&mut rng, &truth, &r)
        };
        let d = filter.update(k * 40_000_000, &PoseCov { pose, cov: r });
        if gross && d.is_outlier() {
            flagged_planted += 1;
        }
        assert!(
            !matches!(d, Disposition::Reinitialized { .. }),
            "isolated outliers restarted the filter"
        );
        if k > 10 {
            let est = filter.predict(k * 40_000_000).unwrap().unwrap();
            let e = se3_log(&(truth * est.pose.inverse()));
            for i in 0..6 {
                checks += 1;
                let sigma = est.cov[(i, i)].sqrt();
                assert!(
                    e[i].abs() < 5.0 * sigma,
                    "error {} is {:.1} sigma",
                    i,
                    e[i] / sigma
                );
                if e[i].abs() > 3.0 * sigma {
                    outside += 1;
                }
            }
        }
    }
    assert!(planted > 20, "only {planted} outliers planted");
    assert_eq!(flagged_planted, planted, "every gross error is flagged");
    // A consistent estimate is outside 3 sigma 0.27 % of the time per component.
    let fraction = outside as f64 / checks as f64;
    assert!(
        fraction < 0.01,
        "{:.2} % of components outside 3 sigma",
        100.0 * fraction
    );
}

#[test]
fn a_genuine_step_is_followed_after_a_bounded_run_of_outliers() {
    let tuning = FilterTuning::default_for(MotionModel::Static);
    let r = measurement_cov();
    let mut rng = StdRng::seed_from_u64(41);
    let before = random_pose(&mut rng, 3000.0);
    // 50 sigma along every axis of the measurement noise.
    let step = Twist::from_fn(|i, _| 50.0 * r[(i, i)].sqrt());
    let after = se3_exp(&step) * before;
    let mut filter = LinkFilter::new(tuning);
    let mut restarted_at = None;
    for k in 0..300i64 {
        let truth = if k < 200 { before } else { after };
        let d = filter.update(
            k * 40_000_000,
            &PoseCov {
                pose: perturb(&mut rng, &truth, &r),
                cov: r,
            },
        );
        if let Disposition::Reinitialized { run_length, .. } = d {
            assert_eq!(run_length, tuning.reinit_after_outliers);
            restarted_at.get_or_insert(k);
        }
        if k >= 200 + tuning.reinit_after_outliers as i64 + 5 {
            let est = filter.predict(k * 40_000_000).unwrap().unwrap();
            let e = se3_log(&(truth * est.pose.inverse()));
            for i in 0..6 {
                assert!(
                    e[i].abs() < 4.0 * est.cov[(i, i)].sqrt(),
                    "not following the step at sample {k}"
                );
            }
        }
    }
    let k = restarted_at.expect("the step restarted the filter");
    assert!(
        k >= 200 && k < 200 + tuning.reinit_after_outliers as i64 + 2,
        "restart at sample {k}"
    );
}

/// RMS rotation error (arc-seconds) of a model tracking a two-frequency flexure.
fn flexure_rms_arcsec(tuning: FilterTuning, seed: u64) -> f64 {
    let r = measurement_cov();
    let mut rng = StdRng::seed_from_u64(seed);
    let base = random_pose(&mut rng, 3000.0);
    let amp = 60.0 / ARCSEC_PER_RAD;
    let mut filter = LinkFilter::new(tuning);
    let (mut sum_sq, mut n) = (0.0, 0);
    for k in 0..(25 * 180) {
        let t = k as f64 / 25.0;
        let flex = Twist::new(
            0.0,
            0.0,
            0.0,
            amp * (2.0 * std::f64::consts::PI * t / 8.0).sin(),
            amp * (2.0 * std::f64::consts::PI * t / 15.0 + 1.0).sin(),
            0.5 * amp * (2.0 * std::f64::consts::PI * t / 8.0 + 0.3).sin(),
        );
        let truth = se3_exp(&flex) * base;
        let t_ns = (t * 1e9) as i64;
        filter.update(
            t_ns,
            &PoseCov {
                pose: perturb(&mut rng, &truth, &r),
                cov: r,
            },
        );
        if t > 30.0 {
            let est = filter.predict(t_ns).unwrap().unwrap();
            let e = se3_log(&(truth * est.pose.inverse()));
            sum_sq += e.fixed_rows::<3>(3).norm_squared();
            n += 1;
        }
    }
    (sum_sq / n as f64).sqrt() * ARCSEC_PER_RAD
}

#[test]
fn oscillatory_model_tracks_ship_flexure_better_than_constant_velocity() {
    let oscillatory = flexure_rms_arcsec(FilterTuning::default_for(MotionModel::Oscillatory), 51);
    // Give the constant-velocity model its best acceleration noise over a wide range.
    let best_cv = [1.0, 3.0, 10.0, 20.0, 50.0, 100.0, 300.0]
        .iter()
        .map(|&q| {
            let mut t = FilterTuning::default_for(MotionModel::ConstantVelocity);
            t.acceleration_rotation_arcsec_per_s_sqrt_s = q;
            flexure_rms_arcsec(t, 51)
        })
        .fold(f64::INFINITY, f64::min);
    assert!(
        oscillatory < best_cv,
        "oscillatory {oscillatory:.2} arcsec rms, best constant-velocity {best_cv:.2}"
    );
}

#[test]
fn a_sample_older_than_the_filter_is_not_fused() {
    let tuning = FilterTuning::default_for(MotionModel::Static);
    let r = measurement_cov();
    let mut rng = StdRng::seed_from_u64(61);
    let truth = random_pose(&mut rng, 3000.0);
    let mut filter = LinkFilter::new(tuning);
    for k in 0..10 {
        filter.update(
            k * 40_000_000,
            &PoseCov {
                pose: perturb(&mut rng, &truth, &r),
                cov: r,
            },
        );
    }
    let before = filter.predict(9 * 40_000_000).unwrap().unwrap();
    let d = filter.update(
        5 * 40_000_000,
        &PoseCov {
            pose: truth,
            cov: r,
        },
    );
    assert_eq!(d, Disposition::OutOfOrder { behind_s: 0.16 });
    assert_eq!(filter.predict(9 * 40_000_000).unwrap().unwrap(), before);
    assert_eq!(filter.time_ns(), Some(9 * 40_000_000));
    assert!(
        filter.predict(8 * 40_000_000).unwrap().is_err(),
        "no prediction backwards"
    );
}

fn model_strategy() -> impl Strategy<Value = MotionModel> {
    prop_oneof![
        Just(MotionModel::Static),
        Just(MotionModel::ConstantVelocity),
        Just(MotionModel::Oscillatory)
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn covariance_stays_symmetric_positive_definite(
        model in model_strategy(),
        seed in any::<u64>(),
        steps in prop::collection::vec((1u64..2_000_000_000u64, any::<bool>(), 0.01f64..100.0), 1..60),
    ) {
        let mut rng = StdRng::seed_from_u64(seed);
        let truth = random_pose(&mut rng, 3000.0);
        let mut filter = LinkFilter::new(FilterTuning::default_for(model));
        let mut t_ns = 0i64;
        for (dt_ns, gross, scale) in steps {
            t_ns += dt_ns as i64;
            let r = measurement_cov() * scale;
            let pose = if gross { random_pose(&mut rng, 3000.0) } else { perturb(&mut rng, &truth, &r) };
            filter.update(t_ns, &PoseCov { pose, cov: r });
            prop_assert!(filter.covariance_is_positive_definite());
            let p = filter.predict(t_ns + 500_000_000).unwrap().unwrap();
            prop_assert!(p.cov.cholesky().is_some());
        }
    }
}
