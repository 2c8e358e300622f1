//! The whole uncertainty against the truth: sigmas that include the cameras' calibrations, and
//! an error budget that adds up.
//!
//! The Monte Carlo over calibrations: the built-in cameras are calibrated 50 times from
//! rendered plate views (12 views each, the same poses, each calibration its own sensor
//! noise), and each calibration is put into the installation with its covariance (the
//! calibrated links each drawn from their own covariance, as 50 calibrations of the stations
//! would give them). The same rendered frames of a still installation are detected once and
//! measured through each installation: the filtered `G_from_B`'s error against the truth,
//! judged by its whole covariance, must be chi-square with 6 degrees of freedom per
//! installation; judged by the random part alone (what a filter that averages every error
//! would claim) it is far outside.

use brokenray::bank::{FilterBank, MeasurementUncertainty, ResultSource, Sample};
use brokenray::chain::{Contributor, IntrinsicsCovariance, chi_square_quantile};
use brokenray::config;
use brokenray::geometry::{Mat6, Pose, PoseCov, Twist, mean_pose, se3_exp, se3_log};
use brokenray::model::{LinkKind, Model, Observer, TargetId, observe_frame};
use brokenray::sim::plate::{plate_light, plate_poses};
use brokenray::sim::render::{RenderSettings, scene_light};
use brokenray::sim::{Scenario, SimSettings, Simulator};
use brokenray::vision::{
    CalibrationOptions, CalibrationView, CameraCalibration, DetectSettings, Intrinsic, Plate,
    Polarity, calibrate_camera, detect,
};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};

/// Independent calibrations of the built-in cameras.
const CALIBRATIONS: usize = 50;
/// Plate views per calibration.
const VIEWS: usize = 12;
/// Measurement groups of the still installation (25 Hz).
const GROUPS: usize = 40;
const T0_NS: i64 = 1_790_000_000_000_000_000;

/// One marker found in one frame: what every installation solves again.
struct Found {
    time_ns: i64,
    camera: String,
    marker: String,
    points_px: Vec<[f64; 2]>,
    ids: Vec<u32>,
    sigma_px: Vec<f64>,
}

/// `x^T P^-1 x`.
fn mahalanobis(x: &Twist, p: &Mat6) -> f64 {
    let info = p.try_inverse().expect("an invertible covariance");
    (x.transpose() * info * x)[(0, 0)]
}

/// `CALIBRATIONS` calibrations of each camera of `model`, in camera order.
fn calibrations(model: &Model) -> Vec<Vec<CameraCalibration>> {
    let plate = Plate::new(7, 9, 15.0, 7.5, true, Polarity::Dark).expect("a valid plate");
    let settings = RenderSettings {
        samples_per_side: 16,
        ..RenderSettings::default()
    };
    let options = CalibrationOptions {
        fixed: vec![Intrinsic::K3],
        ..CalibrationOptions::default()
    };
    let mut out = vec![Vec::new(); CALIBRATIONS];
    for (k, camera) in model.cameras.iter().enumerate() {
        let truth = camera.intrinsics;
        // The light of each view once; each calibration exposes it with its own noise.
        let lights: Vec<_> = plate_poses(&truth, &plate, VIEWS, 500 + k as u64)
            .iter()
            .map(|pose| plate_light(&truth, &plate, pose, &settings))
            .collect();
        let detect_settings = DetectSettings {
            polarity: plate.polarity(),
            gain_e_per_dn: camera.gain_e_per_dn,
            ..DetectSettings::default()
        };
        for (c, calibrations) in out.iter_mut().enumerate() {
            let views: Vec<CalibrationView> = lights
                .iter()
                .enumerate()
                .map(|(v, light)| {
                    let seed = ((c * 10 + k) * 100 + v) as u64 + 1;
                    let found = plate
                        .find(&detect(&light.expose(seed), &detect_settings))
                        .expect("the whole plate in every view");
                    CalibrationView {
                        ids: found.ids,
                        points_px: found.points_px,
                        sigmas_px: Some(found.sigmas_px),
                    }
                })
                .collect();
            calibrations.push(
                calibrate_camera(&plate, truth.width_px, truth.height_px, &views, &options)
                    .expect("calibrated"),
            );
        }
    }
    out
}

/// The still laboratory of `model` at 25 Hz, its noise drawn with `seed`.
fn laboratory(model: &Model, seed: u64) -> Simulator {
    Simulator::new(
        model,
        SimSettings {
            scenario: Scenario::Static,
            rate_hz: 25.0,
            start_ns: T0_NS,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed,
        },
    )
    .expect("a simulator")
}

/// The markers of `GROUPS` rendered frames per camera of the still installation, found once,
/// with the true `G_from_B`.
fn measured_frames(model: &Model) -> (Vec<Found>, Pose) {
    let mut sim = laboratory(model, 3);
    let settings = RenderSettings {
        samples_per_side: 16,
        ..RenderSettings::default()
    };
    let groups: Vec<_> = (0..GROUPS).map(|_| sim.next_group()).collect();
    let first = sim.frame_scenes(&groups[0]);
    // Nothing moves: each camera's light is the same in every group.
    let lights: Vec<_> = first
        .iter()
        .map(|s| scene_light(&s.model, &s.discs, &[], &settings))
        .collect();
    let mut found = Vec::new();
    for group in &groups {
        for (scene, light) in sim.frame_scenes(group).iter().zip(&lights) {
            let image = light.expose(scene.seed);
            let truth_of = |name: &str| {
                group
                    .link_truth
                    .iter()
                    .find(|(n, _)| n == name)
                    .map(|(_, p)| *p)
            };
            let seen = observe_frame(sim.observer(), &scene.camera, &image, |l| {
                truth_of(&l.name).into_iter().collect()
            })
            .expect("observed");
            for m in seen.markers {
                let f = m.result.expect("every marker found");
                found.push(Found {
                    time_ns: group.time_ns,
                    camera: m.link.camera_frame.clone(),
                    marker: m.link.marker_frame.clone(),
                    points_px: f.points_px,
                    ids: f.ids,
                    sigma_px: f.sigma_px,
                });
            }
        }
    }
    (found, groups[0].truth[0].1)
}

/// The installation a set of calibrations makes: each camera's calibrated intrinsics with
/// their covariance, each calibrated link drawn from its covariance about the truth.
fn installation_of(truth: &Model, calibrated: &[CameraCalibration], rng: &mut StdRng) -> Model {
    let mut m = truth.clone();
    for (camera, c) in m.cameras.iter_mut().zip(calibrated) {
        camera.intrinsics = c.camera;
        camera.intrinsics_covariance =
            Some(IntrinsicsCovariance::from_fn(|i, j| c.covariance[i][j]));
        // The detector's own sigma describes rendered frames; the camera adds next to nothing.
        camera.pixel_sigma_px = 0.002;
    }
    for link in &mut m.links {
        if let LinkKind::Calibrated { parent_from_child } = &mut link.kind {
            let l = parent_from_child.cov.cholesky().expect("a covariance").l();
            let z = Twist::from_fn(|_, _| StandardNormal.sample(rng));
            parent_from_child.pose = se3_exp(&(l * z)) * parent_from_child.pose;
        }
    }
    m
}

/// Measures `found` through `model`: the filtered `G_from_B` at the last group (with its
/// systematic part) and every raw result with its random covariance.
fn measure(model: &Model, found: &[Found]) -> ((PoseCov, Mat6), Vec<PoseCov>) {
    let observer = Observer::new(model);
    let mut bank = FilterBank::new(model);
    let mut raw = Vec::new();
    for f in found {
        let (link, solution) = observer
            .solve(
                &f.camera,
                &f.marker,
                &f.points_px,
                Some(&f.ids),
                Some(&f.sigma_px),
            )
            .expect("solved");
        let outcome = bank
            .ingest(&Sample {
                link: link.link,
                time_ns: f.time_ns,
                parent_from_child: solution.camera_from_marker,
                uncertainty: MeasurementUncertainty::Covariance(solution.covariance),
            })
            .expect("ingested");
        raw.extend(
            outcome
                .raw_results
                .iter()
                .map(|r| r.target_from_base.random()),
        );
    }
    let last = found.last().expect("frames").time_ns;
    let e = bank.evaluate(TargetId(0), last).expect("evaluated");
    let filtered = e.target_from_base.expect("a result");
    ((filtered.whole, filtered.systematic_cov), raw)
}

#[test]
fn over_fifty_calibrations_the_whole_sigma_covers_the_truth_and_the_random_part_the_scatter() {
    let truth: Model = (*config::default_installation().model).clone();
    let calibrations = calibrations(&truth);
    let (found, g_from_b) = measured_frames(&truth);
    let mut rng = StdRng::seed_from_u64(11);
    let (mut nees_whole, mut nees_random) = (0.0, 0.0);
    let mut systematic_share = 0.0;
    for (k, calibrated) in calibrations.iter().enumerate() {
        let model = installation_of(&truth, calibrated, &mut rng);
        let ((filtered, systematic), raw) = measure(&model, &found);
        let e = se3_log(&(filtered.pose * g_from_b.inverse()));
        nees_whole += mahalanobis(&e, &filtered.cov);
        nees_random += mahalanobis(&e, &(filtered.cov - systematic));
        systematic_share += systematic.trace() / filtered.cov.trace() / CALIBRATIONS as f64;
        if k == 0 {
            // Within one installation the raw results scatter about their mean as their random
            // part says: the calibration's error is common to all of them.
            assert_eq!(raw.len(), GROUPS);
            let poses: Vec<Pose> = raw.iter().map(|r| r.pose).collect();
            let mean = mean_pose(&poses).expect("a mean").mean.pose;
            let scatter: f64 = raw
                .iter()
                .map(|r| mahalanobis(&se3_log(&(r.pose * mean.inverse())), &r.cov))
                .sum();
            let dof = 6 * (GROUPS - 1);
            let (lo, hi) = (
                chi_square_quantile(dof, 0.001),
                chi_square_quantile(dof, 0.999),
            );
            eprintln!("scatter within one installation: {scatter:.1} in [{lo:.1}, {hi:.1}]");
            assert!(
                (lo..=hi).contains(&scatter),
                "the raw results' scatter {scatter:.1} against their random covariance is outside [{lo:.1}, {hi:.1}] of chi2({dof})"
            );
        }
    }
    let dof = 6 * CALIBRATIONS;
    let (lo, hi) = (
        chi_square_quantile(dof, 0.001),
        chi_square_quantile(dof, 0.999),
    );
    eprintln!(
        "NEES over {CALIBRATIONS} calibrations: whole covariance {nees_whole:.1}, random part alone {nees_random:.1}, band [{lo:.1}, {hi:.1}]; systematic share of the variance {systematic_share:.3}"
    );
    assert!(
        (lo..=hi).contains(&nees_whole),
        "the summed NEES {nees_whole:.1} of the filtered G_from_B against its whole covariance is outside [{lo:.1}, {hi:.1}] of chi2({dof})"
    );
    // Judged by the random part alone, as a filter that averages every error would report it,
    // the truth is far outside: the calibration's error dominates.
    assert!(
        nees_random > 10.0 * hi,
        "the random part alone gives {nees_random:.1}, not far over {hi:.1}"
    );
}

/// Samples of the built-in installation's simulated laboratory, solved from its observations.
fn laboratory_samples(model: &Model, groups: usize) -> Vec<Sample> {
    let mut sim = laboratory(model, 5);
    let mut out = Vec::new();
    for _ in 0..groups {
        let g = sim.next_group();
        for o in &g.observations {
            let (link, s) = sim
                .observer()
                .solve(&o.camera, &o.marker, &o.points_px, None, None)
                .expect("solved");
            out.push(Sample {
                link: link.link,
                time_ns: g.time_ns,
                parent_from_child: s.camera_from_marker,
                uncertainty: MeasurementUncertainty::Covariance(s.covariance),
            });
        }
    }
    out
}

/// The budget of `model` after `samples`, raw and filtered.
fn budgets(model: &Model, samples: &[Sample]) -> [(i64, brokenray::chain::Budget); 2] {
    let mut bank = FilterBank::new(model);
    for s in samples {
        bank.ingest(s).expect("ingested");
    }
    [ResultSource::Raw, ResultSource::Filtered]
        .map(|source| bank.budget(TargetId(0), source).expect("a budget"))
}

#[test]
fn the_budget_adds_up_and_a_contributor_removed_takes_its_share_with_it() {
    let model: Model = (*config::default_installation().model).clone();
    let samples = laboratory_samples(&model, 30);
    let [(_, raw), (_, filtered)] = budgets(&model, &samples);
    for (what, budget) in [("raw", &raw), ("filtered", &filtered)] {
        let sigma = |v: &[f64; 6]| {
            let s: Vec<String> = v
                .iter()
                .enumerate()
                .map(|(a, x)| {
                    let s = x.sqrt();
                    if a < 3 {
                        format!("{:.2}\"", s * brokenray::geometry::ARCSEC_PER_RAD)
                    } else {
                        format!("{s:.3} mm")
                    }
                })
                .collect();
            s.join(" ")
        };
        eprintln!("{what} budget: total {}", sigma(&budget.total));
        for line in &budget.lines {
            eprintln!("  {:?}: {}", line.contributor, sigma(&line.variance));
        }
    }
    for budget in [&raw, &filtered] {
        for a in 0..6 {
            let sum: f64 = budget.lines.iter().map(|l| l.variance[a]).sum();
            assert!(
                (sum - budget.total[a]).abs() <= 1e-9 * budget.total[a],
                "axis {a}: the lines add to {sum:e}, the total is {:e}",
                budget.total[a]
            );
        }
    }
    // Each axis' shares add up to one, its two parts to the total; the largest share first.
    for budget in [&raw, &filtered] {
        let random = budget.part_variance(brokenray::chain::UncertaintyPart::Random);
        let systematic = budget.part_variance(brokenray::chain::UncertaintyPart::Systematic);
        let lines = budget.lines_by_share();
        for a in 0..6 {
            let shares: f64 = lines.iter().map(|(_, s)| s[a]).sum();
            assert!(
                (shares - 1.0).abs() < 1e-9,
                "axis {a}: shares add to {shares}"
            );
            let parts = random[a] + systematic[a];
            assert!(
                (parts - budget.total[a]).abs() <= 1e-9 * budget.total[a],
                "axis {a}: the parts add to {parts:e}, the total is {:e}",
                budget.total[a]
            );
        }
        let largest = |s: &[f64; 6]| s.iter().copied().fold(0.0, f64::max);
        assert!(
            lines
                .windows(2)
                .all(|w| largest(&w[0].1) >= largest(&w[1].1))
        );
    }
    // Every kind of contributor is there: three links' noise, three cameras, two calibrations.
    let count =
        |f: fn(&Contributor) -> bool| raw.lines.iter().filter(|l| f(&l.contributor)).count();
    assert_eq!(count(|c| matches!(c, Contributor::Noise(_))), 3);
    assert_eq!(count(|c| matches!(c, Contributor::Intrinsics(_))), 3);
    assert_eq!(count(|c| matches!(c, Contributor::Calibration(_))), 2);

    // A camera known exactly, then a calibrated link known exactly: the total falls by what
    // their lines held, on every axis of both budgets.
    let camera = 1;
    let mut exact_camera = model.clone();
    exact_camera.cameras[camera].intrinsics_covariance = Some(IntrinsicsCovariance::zeros());
    let station = model
        .links
        .iter()
        .position(|l| matches!(l.kind, LinkKind::Calibrated { .. }))
        .expect("a calibrated link");
    let mut exact_station = model.clone();
    if let LinkKind::Calibrated { parent_from_child } = &mut exact_station.links[station].kind {
        parent_from_child.cov = Mat6::zeros();
    }
    for (changed, removed) in [
        (&exact_camera, Contributor::Intrinsics(camera)),
        (
            &exact_station,
            Contributor::Calibration(model.links[station].id),
        ),
    ] {
        let after = budgets(changed, &samples);
        for (before, (_, after)) in [&raw, &filtered].into_iter().zip(&after) {
            let share = before
                .lines
                .iter()
                .find(|l| l.contributor == removed)
                .expect("the contributor's line")
                .variance;
            for (a, share) in share.iter().enumerate() {
                let expected = before.total[a] - share;
                assert!(
                    (after.total[a] - expected).abs() <= 1e-6 * before.total[a],
                    "{removed:?} axis {a}: the total went from {:e} to {:e}, not to {expected:e}",
                    before.total[a],
                    after.total[a]
                );
            }
        }
    }
}
