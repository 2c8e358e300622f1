//! The filter bank on an installation: target evaluation, statuses, raw results.

use approx::assert_relative_eq;
use brokenray::bank::{FilterBank, MeasurementUncertainty, Sample, TargetStatus};
use brokenray::config::{self, Installation};
use brokenray::geometry::{Pose, se3_log};
use brokenray::model::LinkKind;
use brokenray::model::TargetId;

const T0: i64 = 1_790_000_000_000_000_000;
const PERIOD_NS: i64 = 40_000_000;

fn nominal(inst: &Installation, name: &str) -> Pose {
    match &inst.model.link_by_name(name).unwrap().kind {
        LinkKind::Measured(m) => m.nominal.unwrap(),
        LinkKind::Calibrated { parent_from_child } => parent_from_child.pose,
    }
}

fn sample(inst: &Installation, name: &str, time_ns: i64, pose: Pose) -> Sample {
    Sample {
        link: inst.model.topology.link_id(name).unwrap(),
        time_ns,
        parent_from_child: pose,
        uncertainty: MeasurementUncertainty::Default,
    }
}

const MEASURED: [&str; 3] = ["C1_from_B", "C2_from_M", "C3_from_G"];

#[test]
fn noise_free_nominal_samples_give_the_papers_chain_product() {
    let inst = config::default_installation();
    let mut bank = FilterBank::new(&inst.model);
    for k in 0..20 {
        for name in MEASURED {
            bank.ingest(&sample(
                &inst,
                name,
                T0 + k * PERIOD_NS,
                nominal(&inst, name),
            ))
            .unwrap();
        }
    }
    let t = T0 + 19 * PERIOD_NS;
    let est = bank.evaluate(TargetId(0), t).unwrap();
    assert_eq!(est.status, TargetStatus::Ok);
    assert_eq!(est.age_s, 0.0);
    // G_from_B = G_from_C3 * C3_from_M * M_from_C2 * C2_from_C1 * C1_from_B, written out.
    let expected = nominal(&inst, "C3_from_G").inverse()
        * nominal(&inst, "C3_from_M")
        * nominal(&inst, "C2_from_M").inverse()
        * nominal(&inst, "C2_from_C1")
        * nominal(&inst, "C1_from_B");
    let e = se3_log(&(est.target_from_base.unwrap().whole.pose * expected.inverse()));
    assert!(e.amax() < 1e-9, "{e}");
}

#[test]
fn a_group_with_every_measured_link_gives_one_raw_result() {
    let inst = config::default_installation();
    let mut bank = FilterBank::new(&inst.model);
    let t = T0;
    let a = bank
        .ingest(&sample(&inst, "C1_from_B", t, nominal(&inst, "C1_from_B")))
        .unwrap();
    let b = bank
        .ingest(&sample(&inst, "C2_from_M", t, nominal(&inst, "C2_from_M")))
        .unwrap();
    assert!(a.raw_results.is_empty() && b.raw_results.is_empty());
    // Another link exposed farther away than the group tolerance (half the 40 ms period)
    // does not complete the group.
    assert_eq!(bank.group_tolerance_ns(), 20_000_000);
    let c = bank
        .ingest(&sample(
            &inst,
            "C3_from_G",
            t + 30_000_000,
            nominal(&inst, "C3_from_G"),
        ))
        .unwrap();
    assert!(c.raw_results.is_empty());
    let d = bank
        .ingest(&sample(&inst, "C3_from_G", t, nominal(&inst, "C3_from_G")))
        .unwrap();
    assert_eq!(d.raw_results.len(), 1);
    assert_eq!(d.raw_results[0].time_ns, t);
    // Out of order for the filter (t < t + 30 ms) but still completes its group.
    assert!(matches!(
        d.disposition,
        brokenray::filter::Disposition::OutOfOrder { .. }
    ));
    // The same group is not reported twice.
    let again = bank
        .ingest(&sample(&inst, "C1_from_B", t, nominal(&inst, "C1_from_B")))
        .unwrap();
    assert!(again.raw_results.is_empty());
}

#[test]
fn statuses_follow_the_data() {
    let inst = config::default_installation();
    let mut bank = FilterBank::new(&inst.model);
    assert_eq!(
        bank.evaluate(TargetId(0), T0).unwrap().status,
        TargetStatus::Initializing
    );
    bank.ingest(&sample(&inst, "C1_from_B", T0, nominal(&inst, "C1_from_B")))
        .unwrap();
    let partial = bank.evaluate(TargetId(0), T0).unwrap();
    assert_eq!(partial.status, TargetStatus::Initializing);
    assert!(partial.target_from_base.is_none());
    for name in &MEASURED[1..] {
        bank.ingest(&sample(&inst, name, T0, nominal(&inst, name)))
            .unwrap();
    }
    assert_eq!(
        bank.evaluate(TargetId(0), T0).unwrap().status,
        TargetStatus::Ok
    );
    // 0.1 s later: a prediction, with its age.
    let later = bank.evaluate(TargetId(0), T0 + 100_000_000).unwrap();
    assert_eq!(later.status, TargetStatus::Predicted);
    assert_relative_eq!(later.age_s, 0.1, epsilon = 1e-12);
    // Covariance grows with the prediction.
    let now_cov = bank
        .evaluate(TargetId(0), T0)
        .unwrap()
        .target_from_base
        .unwrap()
        .whole
        .cov;
    assert!(later.target_from_base.unwrap().whole.cov.trace() > now_cov.trace());
    // Five expected periods (5 / 25 Hz = 0.2 s) without a sample: stale.
    assert_eq!(
        bank.evaluate(TargetId(0), T0 + 250_000_000).unwrap().status,
        TargetStatus::Stale
    );
    assert!(
        bank.evaluate(TargetId(0), T0 - 1).is_err(),
        "no evaluation before the filters' time"
    );
}

#[test]
fn redundant_paths_that_disagree_degrade_the_target() {
    let text = format!(
        "{}\n[[links]]\nname = \"C4_from_B\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 20.0, translation_mm = 0.3 }}\nexpected_rate_hz = 25.0\n\n[[links]]\nname = \"C4_from_G\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 20.0, translation_mm = 0.3 }}\nexpected_rate_hz = 25.0\n",
        config::DEFAULT_INSTALLATION_TOML
    );
    let inst = config::parse("redundant.toml", &text).unwrap();
    assert_eq!(inst.model.targets[0].resolution.paths.len(), 2);
    let g_from_b = nominal(&inst, "C3_from_G").inverse()
        * nominal(&inst, "C3_from_M")
        * nominal(&inst, "C2_from_M").inverse()
        * nominal(&inst, "C2_from_C1")
        * nominal(&inst, "C1_from_B");
    let c4_from_b = brokenray::geometry::se3_exp(&brokenray::geometry::Twist::new(
        100.0, -50.0, 2800.0, 3.0, 0.1, -0.2,
    ));
    let c4_from_g = c4_from_b * g_from_b.inverse();
    for (bump_deg, expected) in [(0.0_f64, TargetStatus::Ok), (1.0, TargetStatus::Degraded)] {
        let mut bank = FilterBank::new(&inst.model);
        let bump =
            brokenray::geometry::rotation_from_euler([0.0, bump_deg.to_radians(), 0.0]).unwrap();
        let bumped = Pose::from_parts(c4_from_g.translation, bump * c4_from_g.rotation);
        for name in MEASURED {
            bank.ingest(&sample(&inst, name, T0, nominal(&inst, name)))
                .unwrap();
        }
        bank.ingest(&sample(&inst, "C4_from_B", T0, c4_from_b))
            .unwrap();
        let out = bank
            .ingest(&sample(&inst, "C4_from_G", T0, bumped))
            .unwrap();
        assert_eq!(out.raw_results.len(), 1);
        let est = bank.evaluate(TargetId(0), T0).unwrap();
        assert_eq!(est.paths_used, 2);
        assert_eq!(est.status, expected, "bump of {bump_deg} degree");
    }
}

#[test]
fn a_sample_on_a_calibrated_link_is_refused() {
    let inst = config::default_installation();
    let mut bank = FilterBank::new(&inst.model);
    let err = bank
        .ingest(&sample(&inst, "C2_from_C1", T0, Pose::identity()))
        .unwrap_err();
    assert_eq!(err.to_string(), "`C2_from_C1` is not a measured link");
}

/// With the target still and the relay stations swaying as on a ship, the stations' motion
/// cancels in the filtered `G_from_B` as it does in the raw one: the target is filtered from
/// its composed raw results, not composed from links each filtered with its own lag (which
/// left tens of arc-seconds of wobble here).
#[test]
fn station_motion_cancels_in_the_filtered_result() {
    use brokenray::filter::{FilterTuning, MotionModel};
    use brokenray::geometry::ARCSEC_PER_RAD;
    use brokenray::sim::{Scenario, SimSettings, Simulator};
    let mut inst = config::default_installation();
    for spec in &mut std::sync::Arc::make_mut(&mut inst.model).links {
        if let LinkKind::Measured(m) = &mut spec.kind {
            m.tuning = FilterTuning::default_for(MotionModel::Oscillatory);
        }
    }
    let settings = SimSettings {
        scenario: Scenario::Ship,
        rate_hz: 25.0,
        start_ns: T0,
        duration_s: Some(60.0),
        pixel_sigma_px: Some(0.0),
        outlier_rate: 0.0,
        seed: 5,
    };
    let mut sim = Simulator::new(&inst.model, settings).unwrap();
    sim.set_still_target(true);
    let mut bank = FilterBank::shared(inst.model.clone());
    let (mut worst_arcsec, mut worst_mm, mut results) = (0.0f64, 0.0f64, 0);
    let mut station_swing_arcsec = 0.0f64;
    let first = sim.next_group();
    let c1_from_b0 = first.link_truth[0].1;
    for g in std::iter::once(first).chain((1..1500).map(|_| sim.next_group())) {
        let truth = g.truth[0].1;
        station_swing_arcsec = station_swing_arcsec.max(
            brokenray::geometry::so3_log(
                &(g.link_truth[0].1.rotation * c1_from_b0.rotation.inverse()),
            )
            .norm()
                * ARCSEC_PER_RAD,
        );
        for (name, pose) in &g.link_truth {
            let out = bank.ingest(&sample(&inst, name, g.time_ns, *pose)).unwrap();
            for f in &out.filtered_results {
                let e = se3_log(&(f.target_from_base.unwrap().whole.pose * truth.inverse()));
                worst_arcsec = worst_arcsec.max(e.fixed_rows::<3>(3).norm() * ARCSEC_PER_RAD);
                worst_mm = worst_mm.max(
                    (f.target_from_base.unwrap().whole.pose.translation.vector
                        - truth.translation.vector)
                        .norm(),
                );
                results += 1;
            }
        }
    }
    assert_eq!(results, 1500, "one filtered result per group");
    assert!(
        station_swing_arcsec > 60.0,
        "the stations swing {station_swing_arcsec} arcsec"
    );
    assert!(
        worst_arcsec < 0.01,
        "filtered G_from_B wobbles {worst_arcsec} arcsec"
    );
    assert!(worst_mm < 1e-4, "filtered G_from_B wobbles {worst_mm} mm");
}

/// Cameras that expose 7 ms apart, each sample stamped with its own exposure, still make one
/// raw result per group (the default tolerance is half the 40 ms period); with a tolerance
/// tighter than their spread no group completes, and every link says so.
#[test]
fn cameras_that_expose_apart_make_raw_results_within_the_tolerance() {
    let run = |tolerance_ns: Option<i64>| {
        let mut inst = config::default_installation();
        std::sync::Arc::make_mut(&mut inst.model)
            .filter
            .group_tolerance_ns = tolerance_ns;
        let mut bank = FilterBank::shared(inst.model.clone());
        let mut raw = 0;
        for k in 0..200 {
            for (i, name) in MEASURED.iter().enumerate() {
                let t = T0 + k * PERIOD_NS + i as i64 * 7_000_000;
                let out = bank
                    .ingest(&sample(&inst, name, t, nominal(&inst, name)))
                    .unwrap();
                raw += out.raw_results.len();
                for r in &out.raw_results {
                    // The group's time is its first exposure's.
                    assert_eq!((r.time_ns - T0) % PERIOD_NS, 0);
                }
            }
        }
        let problems = MEASURED
            .iter()
            .filter(|n| {
                let id = inst.model.topology.link_id(n).unwrap();
                bank.link_status(id).grouping_problem().is_some()
            })
            .count();
        (raw, problems, bank.group_tolerance_ns())
    };
    assert_eq!(run(None), (200, 0, 20_000_000));
    let (raw, problems, _) = run(Some(1_000_000));
    assert_eq!(raw, 0);
    assert_eq!(
        problems, 3,
        "every link reports that its samples make no group"
    );
}

/// On a ship, each target's filter says whether its model fits: the `oscillatory` model with
/// its strengths fitted from the data keeps its normalised innovations in their band, and
/// fits the motion's period; `static`, which cannot follow a hull's flexure, leaves it.
#[test]
fn a_target_filter_says_whether_its_model_fits_the_ship() {
    use brokenray::bank::CONSISTENCY_JUDGED_FROM;
    use brokenray::filter::{FilterTuning, MotionModel};
    use brokenray::model::Observer;
    use brokenray::sim::{Scenario, SimSettings, Simulator};
    let run = |model: MotionModel| {
        let mut inst = config::default_installation();
        for spec in &mut std::sync::Arc::make_mut(&mut inst.model).links {
            if let LinkKind::Measured(m) = &mut spec.kind {
                m.tuning = FilterTuning::default_for(model);
            }
        }
        let settings = SimSettings {
            scenario: Scenario::Ship,
            rate_hz: 25.0,
            start_ns: T0,
            duration_s: Some(120.0),
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed: 9,
        };
        let mut sim = Simulator::new(&inst.model, settings).unwrap();
        let observer = Observer::new(&inst.model);
        let mut bank = FilterBank::shared(inst.model.clone());
        for _ in 0..3000 {
            let g = sim.next_group();
            for o in &g.observations {
                let (link, s) = observer
                    .solve(&o.camera, &o.marker, &o.points_px, None, None)
                    .unwrap();
                bank.ingest(&Sample {
                    link: link.link,
                    time_ns: g.time_ns,
                    parent_from_child: s.camera_from_marker,
                    uncertainty: MeasurementUncertainty::Covariance(s.covariance),
                })
                .unwrap();
            }
        }
        bank.target_tuning(TargetId(0)).unwrap()
    };
    let fitted = run(MotionModel::Oscillatory);
    let c = fitted.consistency;
    assert!(c.samples >= CONSISTENCY_JUDGED_FROM);
    assert!(c.fits(), "oscillatory on a ship: {c:?}");
    let fit = fitted.fit.expect("a fit after two minutes");
    // The hull's motion is an 8 s and a 15 s oscillation: one oscillator fits between them.
    assert!(
        (8.0..=15.0).contains(&fit.oscillation.period_s),
        "period {}",
        fit.oscillation.period_s
    );
    let c = run(MotionModel::Static).consistency;
    assert!(c.samples >= CONSISTENCY_JUDGED_FROM);
    assert!(
        !c.fits(),
        "static on a ship must not look as if it fits: {c:?}"
    );
    assert!(c.mean_nis > c.band.1);
}

/// A target's filter set in the installation is the one its bank runs, kept as set when it is
/// not to be fitted; a fit asked of a model that has no oscillation is refused by name.
#[test]
fn a_target_filter_set_in_the_installation_is_used_and_a_wrong_one_refused() {
    use brokenray::filter::MotionModel;
    let text = format!(
        "{}\n[targets.filter]\nmodel = \"oscillatory\"\nfit_from_data = false\noscillation = {{ period_s = 9.0, correlation_time_s = 12.0, rotation_arcsec = 80.0, translation_mm = 0.3 }}\n",
        config::DEFAULT_INSTALLATION_TOML
    );
    let inst = config::parse("target-filter.toml", &text).unwrap();
    let set = inst.model.targets[0].filter.expect("the target's filter");
    assert!(!set.fit_from_data);
    let bank = FilterBank::shared(inst.model.clone());
    let t = bank.target_tuning(TargetId(0)).unwrap();
    assert_eq!(t.tuning.model, MotionModel::Oscillatory);
    assert_eq!(t.tuning.oscillation.period_s, 9.0);
    assert_eq!(t.tuning.oscillation.rotation_arcsec, [80.0; 3]);
    assert!(t.fit.is_none());
    let wrong = format!(
        "{}\n[targets.filter]\nmodel = \"static\"\nfit_from_data = true\n",
        config::DEFAULT_INSTALLATION_TOML
    );
    let err = config::parse("wrong.toml", &wrong).unwrap_err().to_string();
    assert!(
        err.contains("target `G` filter: `fit_from_data` applies to the oscillatory model"),
        "{err}"
    );
}
