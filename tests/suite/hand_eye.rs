//! Station calibration `A_i X = X B_i`: recovery from noisy synthetic motions within the
//! reported uncertainty, and the refusals.

use crate::common;

use brokenray::geometry::{ARCSEC_PER_RAD, Pose, Rotation, Twist, Vec3, se3_exp};
use brokenray::vision::{HandEyeOptions, VisionError, solve_hand_eye};
use common::{assert_summed_nees_within, nees, random_pose};
use nalgebra::Translation3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

/// A motion of the station: a rotation of 10 to 40 degrees about `axis`, and a shift.
fn motion(rng: &mut StdRng, axis: Vec3) -> Pose {
    let angle = rng.random_range(10.0f64..40.0).to_radians();
    let t = Vec3::new(
        rng.random_range(-300.0..300.0),
        rng.random_range(-300.0..300.0),
        rng.random_range(-300.0..300.0),
    );
    Pose::from_parts(
        Translation3::from(t),
        Rotation::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle),
    )
}

fn noisy(rng: &mut StdRng, pose: &Pose, sigma_mm: f64, sigma_arcsec: f64) -> Pose {
    let nt = Normal::new(0.0, sigma_mm).expect("sigma");
    let nr = Normal::new(0.0, sigma_arcsec / ARCSEC_PER_RAD).expect("sigma");
    let xi = Twist::new(
        nt.sample(rng),
        nt.sample(rng),
        nt.sample(rng),
        nr.sample(rng),
        nr.sample(rng),
        nr.sample(rng),
    );
    se3_exp(&xi) * pose
}

/// `n` exact motion pairs `(X B X^-1, B)` of a random `X` about random axes.
fn exact_pairs(rng: &mut StdRng, n: usize) -> Vec<(Pose, Pose)> {
    let x = random_pose(rng, 300.0);
    (0..n)
        .map(|_| {
            let axis = random_axis(rng);
            let b = motion(rng, axis);
            (x * b * x.inverse(), b)
        })
        .collect()
}

fn random_axis(rng: &mut StdRng) -> Vec3 {
    Vec3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    )
}

#[test]
fn x_is_recovered_from_noisy_motions_within_its_reported_uncertainty() {
    let mut rng = StdRng::seed_from_u64(71);
    let (sigma_mm, sigma_arcsec) = (0.05, 5.0);
    let options = HandEyeOptions {
        sigma_translation_mm: sigma_mm,
        sigma_rotation_arcsec: sigma_arcsec,
        ..HandEyeOptions::default()
    };
    let trials = 200;
    let mut nees_sum = 0.0;
    for _ in 0..trials {
        let x = random_pose(&mut rng, 200.0);
        let pairs: Vec<(Pose, Pose)> = (0..8)
            .map(|_| {
                let axis = random_axis(&mut rng);
                let b = motion(&mut rng, axis);
                let a = x * b * x.inverse();
                (
                    noisy(&mut rng, &a, sigma_mm, sigma_arcsec),
                    noisy(&mut rng, &b, sigma_mm, sigma_arcsec),
                )
            })
            .collect();
        let s = solve_hand_eye(&pairs, &options).expect("well-spread motions");
        nees_sum += nees(&s.x, &x, &s.covariance);
        // The residuals are of the order of the noise put in.
        assert!(
            s.rms_rotation_arcsec < 6.0 * sigma_arcsec,
            "{}",
            s.rms_rotation_arcsec
        );
        assert!(
            s.rms_translation_mm < 5.0 * sigma_mm,
            "{}",
            s.rms_translation_mm
        );
    }
    assert_summed_nees_within(nees_sum, trials, 0.001);
}

#[test]
fn noise_free_motions_give_x_exactly_and_report_their_spread() {
    let mut rng = StdRng::seed_from_u64(72);
    let x = random_pose(&mut rng, 300.0);
    let axes = [Vec3::x(), Vec3::y(), Vec3::new(1.0, 1.0, 0.2)];
    let pairs: Vec<(Pose, Pose)> = axes
        .iter()
        .map(|axis| {
            let b = motion(&mut rng, *axis);
            (x * b * x.inverse(), b)
        })
        .collect();
    let s = solve_hand_eye(&pairs, &HandEyeOptions::default()).expect("solvable");
    assert!(s.x.rotation.angle_to(&x.rotation) < 1e-10);
    assert!((s.x.translation.vector - x.translation.vector).norm() < 1e-8);
    assert!(
        s.residuals
            .iter()
            .all(|r| r.rotation_arcsec < 1e-5 && r.translation_mm < 1e-8)
    );
    assert!(
        (s.spread.max_axis_angle_deg - 90.0).abs() < 1e-9,
        "{:?}",
        s.spread
    );
    let angles: Vec<f64> = pairs
        .iter()
        .map(|(a, _)| a.rotation.angle().to_degrees())
        .collect();
    let min = angles.iter().copied().fold(f64::INFINITY, f64::min);
    assert!((s.spread.min_rotation_deg - min).abs() < 1e-9);
}

#[test]
fn motions_about_nearly_parallel_axes_are_refused() {
    let mut rng = StdRng::seed_from_u64(73);
    let x = random_pose(&mut rng, 300.0);
    let pairs: Vec<(Pose, Pose)> = (0..5)
        .map(|i| {
            let axis = Vec3::new(0.02 * f64::from(i), 0.0, 1.0);
            let b = motion(&mut rng, axis);
            (x * b * x.inverse(), b)
        })
        .collect();
    let err = solve_hand_eye(&pairs, &HandEyeOptions::default()).expect_err("parallel");
    match err {
        VisionError::ParallelAxes {
            largest_deg,
            min_deg,
        } => {
            let expected = 0.08f64.atan().to_degrees();
            assert!(
                (largest_deg - expected).abs() < 1e-6,
                "{largest_deg} vs {expected}"
            );
            assert_eq!(min_deg, 5.0);
        }
        other => panic!("{other}"),
    }
}

#[test]
fn too_few_small_or_inconsistent_motions_are_refused() {
    let mut rng = StdRng::seed_from_u64(74);
    let x = random_pose(&mut rng, 300.0);
    let good: Vec<(Pose, Pose)> = [Vec3::x(), Vec3::y(), Vec3::z()]
        .iter()
        .map(|axis| {
            let b = motion(&mut rng, *axis);
            (x * b * x.inverse(), b)
        })
        .collect();
    let err = solve_hand_eye(&good[..2], &HandEyeOptions::default()).expect_err("two");
    assert_eq!(
        err,
        VisionError::NotEnoughPoints {
            given: 2,
            needed: 3
        }
    );

    let mut small = good.clone();
    let tiny = Pose::from_parts(
        Translation3::new(5.0, 0.0, 0.0),
        Rotation::from_axis_angle(&Vec3::x_axis(), 0.1f64.to_radians()),
    );
    small[1] = (x * tiny * x.inverse(), tiny);
    let err = solve_hand_eye(&small, &HandEyeOptions::default()).expect_err("small");
    assert!(
        matches!(err, VisionError::MotionTooSmall { index: 1, .. }),
        "{err}"
    );

    let mut mixed = good;
    let other = motion(&mut rng, Vec3::x());
    mixed[2].1 = Pose::from_parts(
        other.translation,
        Rotation::from_axis_angle(
            &Vec3::x_axis(),
            mixed[2].0.rotation.angle() + 2f64.to_radians(),
        ),
    );
    let err = solve_hand_eye(&mixed, &HandEyeOptions::default()).expect_err("inconsistent");
    assert!(
        matches!(err, VisionError::InconsistentMotion { index: 2, .. }),
        "{err}"
    );
}

/// A motion whose two halves rotate by the same angle about axes 51 degrees apart passes the
/// angle check, but not the fit: the solution of all pairs is refused, naming that pair.
#[test]
fn a_pair_that_does_not_fit_the_others_is_refused_naming_it() {
    let mut rng = StdRng::seed_from_u64(73);
    let mut pairs = exact_pairs(&mut rng, 8);
    // Pair 5's B: the same angle about an axis turned 51 degrees away.
    let (a, b) = pairs[5];
    let (axis, angle) = b.rotation.axis_angle().expect("a rotation");
    let perpendicular = axis.cross(&Vec3::new(0.3, -0.7, 0.2)).normalize();
    let turned = Rotation::from_axis_angle(
        &nalgebra::Unit::new_normalize(perpendicular),
        51f64.to_radians(),
    ) * axis.into_inner();
    let bent = Pose::from_parts(
        b.translation,
        Rotation::from_axis_angle(&nalgebra::Unit::new_normalize(turned), angle),
    );
    pairs[5] = (a, bent);
    match solve_hand_eye(&pairs, &HandEyeOptions::default()) {
        Err(VisionError::PairDoesNotFit {
            index,
            residual_deg,
            tolerance_deg,
        }) => {
            assert_eq!(index, 5);
            assert!(residual_deg > tolerance_deg, "{residual_deg}");
        }
        other => panic!("want the pair refused, got {other:?}"),
    }
}

/// A motion whose rotation fits but whose translation is 200 mm off (its second pose read
/// from the wrong marker, say): the solution is refused naming it, as a rotation that does not
/// fit is, instead of a calibration bent towards it.
#[test]
fn a_pair_whose_translation_does_not_fit_is_refused_naming_it() {
    let mut rng = StdRng::seed_from_u64(74);
    let mut pairs = exact_pairs(&mut rng, 8);
    let (a, b) = pairs[3];
    let shifted = Pose::from_parts(
        nalgebra::Translation3::from(a.translation.vector + Vec3::new(200.0, 0.0, 0.0)),
        a.rotation,
    );
    pairs[3] = (shifted, b);
    match solve_hand_eye(&pairs, &HandEyeOptions::default()) {
        Err(VisionError::TranslationDoesNotFit {
            index,
            residual_mm,
            tolerance_mm,
        }) => {
            assert_eq!(index, 3);
            assert!(residual_mm > tolerance_mm, "{residual_mm}");
        }
        other => panic!("want the pair refused, got {other:?}"),
    }
    // The exact pairs alone are taken.
    pairs[3] = (a, b);
    assert!(solve_hand_eye(&pairs, &HandEyeOptions::default()).is_ok());
}
