//! Chain composition and its uncertainty, checked against the paper's equations, a Monte Carlo
//! of the same chain, the straight-chain closed form, and redundant-path fusion.

use crate::common;

use approx::assert_relative_eq;
use brokenray::chain::{Topology, compose_path, fuse};
use brokenray::geometry::{
    ARCSEC_PER_RAD, Mat3, Mat6, Pose, PoseCov, Twist, Vec3, rotation_from_euler, se3_log,
};
use common::{perturb, random_covariance, random_pose};
use nalgebra::Translation3;
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::collections::HashMap;

/// The paper's relay: measured links are camera_from_marker, so M_from_C2 and G_from_C3 are
/// walked inverted.
fn paper_topology() -> Topology {
    let mut t = Topology::new();
    for (name, parent, child) in [
        ("C1_from_B", "C1", "B"),
        ("C2_from_C1", "C2", "C1"),
        ("C2_from_M", "C2", "M"),
        ("C3_from_M", "C3", "M"),
        ("C3_from_G", "C3", "G"),
    ] {
        t.add_link(name, parent, child).unwrap();
    }
    t
}

/// `[R^T, -R^T t]`, written out.
fn invert_explicit(r: &Mat3, t: &Vec3) -> (Mat3, Vec3) {
    (r.transpose(), -(r.transpose() * t))
}

fn rt(p: &Pose) -> (Mat3, Vec3) {
    (
        p.rotation.to_rotation_matrix().into_inner(),
        p.translation.vector,
    )
}

#[test]
fn papers_equation_8_term_by_term_equals_the_general_composition() {
    let mut rng = StdRng::seed_from_u64(8);
    let topo = paper_topology();
    let path = &topo.resolve("B", "G").unwrap().paths[0];
    for _ in 0..200 {
        let poses: HashMap<&str, Pose> = [
            "C1_from_B",
            "C2_from_C1",
            "C2_from_M",
            "C3_from_M",
            "C3_from_G",
        ]
        .into_iter()
        .map(|n| (n, random_pose(&mut rng, 3000.0)))
        .collect();
        let general = compose_path(path, |id| {
            PoseCov::exact(poses[topo.link(id).name.as_str()])
        });

        // Paper notation: ^aR_b, ^aT_b for a_from_b.
        let (r_c1_b, t_c1_b) = rt(&poses["C1_from_B"]);
        let (r_c2_c1, t_c2_c1) = rt(&poses["C2_from_C1"]);
        let (r_m_c2, t_m_c2) = {
            let (r, t) = rt(&poses["C2_from_M"]);
            invert_explicit(&r, &t)
        };
        let (r_c3_m, t_c3_m) = rt(&poses["C3_from_M"]);
        let (r_g_c3, t_g_c3) = {
            let (r, t) = rt(&poses["C3_from_G"]);
            invert_explicit(&r, &t)
        };
        // Eq. (7).
        let r_g_b = r_g_c3 * r_c3_m * r_m_c2 * r_c2_c1 * r_c1_b;
        // Eq. (8), term by term.
        let t_g_b = r_g_c3 * r_c3_m * r_m_c2 * r_c2_c1 * t_c1_b
            + r_g_c3 * r_c3_m * r_m_c2 * t_c2_c1
            + r_g_c3 * r_c3_m * t_m_c2
            + r_g_c3 * t_c3_m
            + t_g_c3;
        assert_relative_eq!(
            general.pose.rotation.to_rotation_matrix().into_inner(),
            r_g_b,
            epsilon = 1e-12
        );
        assert_relative_eq!(general.pose.translation.vector, t_g_b, epsilon = 1e-8);
    }
}

#[test]
fn propagated_covariance_agrees_with_a_monte_carlo_of_the_chain() {
    let mut rng = StdRng::seed_from_u64(6);
    let topo = paper_topology();
    let path = topo.resolve("B", "G").unwrap().paths[0].clone();
    let links: Vec<PoseCov> = (0..topo.links().len())
        .map(|_| PoseCov {
            pose: random_pose(&mut rng, 3000.0),
            cov: random_covariance(&mut rng, 30.0, 0.5),
        })
        .collect();
    let propagated = compose_path(&path, |id| links[id.0]);
    let info = propagated.cov.cholesky().unwrap().inverse();

    let trials = 4000;
    let mut nees_sum = 0.0;
    for _ in 0..trials {
        let drawn: Vec<PoseCov> = links
            .iter()
            .map(|l| PoseCov::exact(perturb(&mut rng, &l.pose, &l.cov)))
            .collect();
        let sample = compose_path(&path, |id| drawn[id.0]).pose;
        let e: Twist = se3_log(&(sample * propagated.pose.inverse()));
        nees_sum += (e.transpose() * info * e)[(0, 0)];
    }
    // The summed NEES is chi-square with 6 * trials degrees of freedom.
    common::assert_summed_nees_within(nees_sum, trials, 0.005);
}

/// A straight chain of n links, each `i+1_from_i` a translation of L along z, composed and read
/// as the position of the end frame in the base (`0_from_n`).
fn straight_chain_lateral_sigma_mm(
    n: usize,
    l_mm: f64,
    sigma_t_mm: f64,
    sigma_theta_deg: f64,
) -> f64 {
    let mut topo = Topology::new();
    for i in 0..n {
        topo.add_link(
            &format!("F{}_from_F{}", i + 1, i),
            &format!("F{}", i + 1),
            &format!("F{i}"),
        )
        .unwrap();
    }
    let path = topo
        .resolve("F0", &format!("F{n}"))
        .unwrap()
        .paths
        .remove(0);
    let s_rot = sigma_theta_deg.to_radians().powi(2);
    let s_t = sigma_t_mm * sigma_t_mm;
    let link = PoseCov::new(
        Pose::from_parts(
            Translation3::new(0.0, 0.0, -l_mm),
            rotation_from_euler([0.0; 3]).unwrap(),
        ),
        Mat6::from_diagonal(&Twist::new(s_t, s_t, s_t, s_rot, s_rot, s_rot)),
    )
    .unwrap();
    let end_from_base = compose_path(&path, |_| link);
    let base_from_end = end_from_base.inverse();
    assert_relative_eq!(
        base_from_end.pose.translation.vector.z,
        n as f64 * l_mm,
        epsilon = 1e-9
    );
    base_from_end.reported_sigmas().translation_mm[0]
}

#[test]
fn straight_chain_error_growth_matches_the_closed_form() {
    let (l, st, sth) = (3000.0, 0.5, 0.01);
    for (n, printed) in [(1, 0.50), (2, 0.88), (4, 2.20)] {
        let ours = straight_chain_lateral_sigma_mm(n, l, st, sth);
        let nf = n as f64;
        let closed = (nf * st * st
            + sth.to_radians().powi(2) * l * l * (nf - 1.0) * nf * (2.0 * nf - 1.0) / 6.0)
            .sqrt();
        assert_relative_eq!(ours, closed, max_relative = 1e-9);
        assert!(
            (ours - printed).abs() < 0.005,
            "n = {n}: {ours:.3} mm, the tabulated value is {printed}"
        );
    }
}

/// Two link-disjoint relays from B to G: B-C1-G and B-C4-M-G.
fn redundant_topology() -> Topology {
    let mut t = Topology::new();
    for (name, parent, child) in [
        ("C1_from_B", "C1", "B"),
        ("C1_from_G", "C1", "G"),
        ("C4_from_B", "C4", "B"),
        ("C4_from_M", "C4", "M"),
        ("G_from_M", "G", "M"),
    ] {
        t.add_link(name, parent, child).unwrap();
    }
    t
}

/// Chi-square of the two paths' disagreement for noisy samples of a true installation, with an
/// optional rotation bump applied to `C4_from_M` after sampling.
fn disagreement(rng: &mut StdRng, bump_deg: f64) -> (f64, f64) {
    let topo = redundant_topology();
    let resolution = topo.resolve("B", "G").unwrap();
    assert_eq!(resolution.paths.len(), 2);
    let truth: Vec<Pose> = (0..topo.links().len())
        .map(|_| random_pose(rng, 3000.0))
        .collect();
    // Make the truth consistent: G_from_M closes the loop.
    let exact: Vec<PoseCov> = truth.iter().map(|p| PoseCov::exact(*p)).collect();
    let g_from_b = compose_path(&resolution.paths[0], |id| exact[id.0]).pose;
    let g_m = topo.link_id("G_from_M").unwrap();
    let c4_from_b = truth[topo.link_id("C4_from_B").unwrap().0];
    let c4_from_m = truth[topo.link_id("C4_from_M").unwrap().0];
    let mut truth = truth;
    truth[g_m.0] = g_from_b * c4_from_b.inverse() * c4_from_m;

    let cov = Mat6::from_diagonal(&Twist::new(
        0.3f64.powi(2),
        0.3f64.powi(2),
        0.3f64.powi(2),
        (20.0 / ARCSEC_PER_RAD).powi(2),
        (20.0 / ARCSEC_PER_RAD).powi(2),
        (20.0 / ARCSEC_PER_RAD).powi(2),
    ));
    let bump = rotation_from_euler([bump_deg.to_radians(), 0.0, 0.0]).unwrap();
    let measured: Vec<PoseCov> = truth
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let mut drawn = perturb(rng, p, &cov);
            if topo.links()[i].name == "C4_from_M" {
                drawn = Pose::from_parts(drawn.translation, bump * drawn.rotation);
            }
            PoseCov { pose: drawn, cov }
        })
        .collect();
    let estimates: Vec<PoseCov> = resolution
        .paths
        .iter()
        .map(|p| compose_path(p, |id| measured[id.0]))
        .collect();
    let fused = fuse(&estimates, 0.999).unwrap();
    let c = fused.consistency.unwrap();
    assert_eq!(c.dof, 6);
    (c.chi2, c.threshold)
}

#[test]
fn a_bumped_relay_station_is_detected_by_the_consistency_statistic() {
    let mut rng = StdRng::seed_from_u64(1);
    for _ in 0..20 {
        let (chi2, threshold) = disagreement(&mut rng, 1.0);
        assert!(
            chi2 > 100.0 * threshold,
            "chi2 {chi2:.1} vs threshold {threshold:.2}"
        );
    }
}

#[test]
fn consistent_redundant_paths_pass_the_consistency_test() {
    let mut rng = StdRng::seed_from_u64(2);
    let trials = 400;
    let mut above = 0;
    let mut sum = 0.0;
    for _ in 0..trials {
        let (chi2, threshold) = disagreement(&mut rng, 0.0);
        sum += chi2;
        if chi2 > threshold {
            above += 1;
        }
    }
    // At 99.9 % about 0.4 of 400 trials exceed; allow a handful. The mean is 6 (dof).
    assert!(above <= 4, "{above} of {trials} consistent trials flagged");
    let mean = sum / trials as f64;
    assert!(
        (mean - 6.0).abs() < 1.0,
        "mean chi2 {mean:.2}, expected about 6"
    );
}

#[test]
fn fusing_two_equal_estimates_halves_the_covariance_and_meets_in_the_middle() {
    let mut rng = StdRng::seed_from_u64(3);
    let centre = random_pose(&mut rng, 3000.0);
    let d = Twist::new(0.2, -0.1, 0.3, 2e-5, -1e-5, 3e-5);
    let cov = random_covariance(&mut rng, 20.0, 0.3);
    let a = PoseCov {
        pose: brokenray::geometry::se3_exp(&d) * centre,
        cov,
    };
    let b = PoseCov {
        pose: brokenray::geometry::se3_exp(&(-d)) * centre,
        cov,
    };
    let fused = fuse(&[a, b], 0.999).unwrap();
    // The exact SE(3) Jacobians move the optimum off the midpoint by a term second order in d
    // (|rho| |phi| ~ 1e-5 here); first order it is the midpoint.
    let offset = se3_log(&(fused.estimate.pose * centre.inverse()));
    assert!(offset.amax() < 1e-5, "{offset}");
    assert_relative_eq!(
        fused.estimate.cov,
        cov / 2.0,
        max_relative = 1e-4,
        epsilon = 1e-15
    );
}

#[test]
fn fusion_weights_by_information() {
    // One estimate ten times more certain than the other pulls the result nine tenths of the way.
    let base = Pose::identity();
    let d = Twist::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let tight = Mat6::identity() * 0.01;
    let loose = Mat6::identity() * 0.1;
    let fused = fuse(
        &[
            PoseCov {
                pose: base,
                cov: tight,
            },
            PoseCov {
                pose: brokenray::geometry::se3_exp(&d) * base,
                cov: loose,
            },
        ],
        0.999,
    )
    .unwrap();
    assert_relative_eq!(
        fused.estimate.pose.translation.vector.x,
        1.0 / 11.0,
        epsilon = 1e-9
    );
}
