//! Every installation-file error names the file, the line and the problem.

use brokenray::config;
use brokenray::model::LinkKind;

const VALID: &str = r#"
[[links]]
name = "C1_from_B"
kind = "measured"
sigma = { rotation_arcsec = 20.0, translation_mm = 0.5 }
expected_rate_hz = 25.0

[[links]]
name = "C1_from_G"
kind = "measured"
sigma = { rotation_arcsec = 20.0, translation_mm = [0.1, 0.1, 0.5] }
expected_rate_hz = 25.0

[[targets]]
name = "G"
base = "B"
"#;

/// Parses `text` and returns the error text, failing the test if it parsed.
fn error_of(text: &str) -> String {
    match config::parse("site.toml", text) {
        Ok(_) => panic!("expected an error for:\n{text}"),
        Err(e) => e.to_string(),
    }
}

/// The 1-based line of the first line containing `needle`.
fn line_of(text: &str, needle: &str) -> usize {
    text.lines()
        .position(|l| l.contains(needle))
        .expect("needle in text")
        + 1
}

/// Each case's text is refused with its message, at the line of its first line holding `at`.
fn assert_each_refused_at_its_line(cases: Vec<(String, &str, &str)>) {
    for (text, at, message) in cases {
        let e = error_of(&text);
        assert!(e.contains(message), "want `{message}` in: {e}");
        assert!(
            e.contains(&format!("site.toml:{}:", line_of(&text, at))),
            "want the line of `{at}` in: {e}"
        );
    }
}

#[test]
fn a_minimal_file_is_valid() {
    let inst = config::parse("site.toml", VALID).unwrap();
    assert_eq!(inst.model.targets.len(), 1);
    assert_eq!(inst.model.targets[0].resolution.paths[0].steps.len(), 2);
}

#[test]
fn the_built_in_installation_is_valid_and_resolves_the_papers_chain() {
    let inst = config::parse(
        config::DEFAULT_SOURCE_NAME,
        config::DEFAULT_INSTALLATION_TOML,
    )
    .unwrap();
    assert_eq!(inst.model.cameras.len(), 3);
    assert_eq!(inst.model.markers.len(), 3);
    let g = inst.model.target("G").unwrap();
    assert_eq!(
        inst.model.topology.describe_product(&g.resolution.paths[0]),
        "G_from_C3 * C3_from_M * M_from_C2 * C2_from_C1 * C1_from_B"
    );
    let sizes: Vec<(u32, u32)> = inst
        .model
        .cameras
        .iter()
        .map(|c| (c.intrinsics.width_px, c.intrinsics.height_px))
        .collect();
    assert!(sizes.contains(&(1280, 1024)) && sizes.contains(&(1392, 1040)));
    assert!(matches!(
        inst.model.link_by_name("C2_from_C1").unwrap().kind,
        LinkKind::Calibrated { .. }
    ));
}

#[test]
fn an_unknown_key_names_its_line_and_the_key() {
    let text = VALID.replace(
        "expected_rate_hz = 25.0\n\n[[links]]",
        "expected_rate_hz = 25.0\nrate = 3\n\n[[links]]",
    );
    let err = error_of(&text);
    let line = line_of(&text, "rate = 3");
    assert!(err.starts_with(&format!("site.toml:{line}:")), "{err}");
    assert!(err.contains("unknown field `rate`"), "{err}");
}

#[test]
fn a_link_whose_frames_do_not_match_its_name_is_refused() {
    let text = VALID.replace(
        "name = \"C1_from_G\"",
        "name = \"C1_from_G\"\nparent = \"C9\"",
    );
    let err = error_of(&text);
    // A table's problems are reported at its `[[links]]` header, the line before its name.
    let line = line_of(&text, "name = \"C1_from_G\"") - 1;
    assert!(err.contains(&format!("site.toml:{line}:")), "{err}");
    assert!(err.contains("does not match its frames"), "{err}");
    assert!(err.contains("`C9`"), "{err}");
}

#[test]
fn a_link_name_without_from_is_refused() {
    let text = VALID.replace("C1_from_G", "C1toG");
    let err = error_of(&text);
    assert!(
        err.contains("`C1toG` is not of the form <parent>_from_<child>"),
        "{err}"
    );
}

#[test]
fn an_unreachable_target_names_target_base_and_line() {
    let text = format!(
        "{VALID}\n[[links]]\nname = \"X_from_Y\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 20.0, translation_mm = 0.5 }}\nexpected_rate_hz = 5.0\n\n[[targets]]\nname = \"X\"\nbase = \"B\"\n"
    );
    let err = error_of(&text);
    let line = line_of(&text, "name = \"X\"");
    assert!(
        err.contains("target `X` is unreachable from base `B`"),
        "{err}"
    );
    assert!(err.contains(&format!("site.toml:{}:", line - 1)), "{err}");
}

#[test]
fn a_non_rotation_pose_is_refused_with_its_line() {
    let text = format!(
        "{VALID}\n[[links]]\nname = \"C2_from_C1\"\nkind = \"calibrated\"\npose = {{ t_mm = [0, 0, -150], r = [[1, 0, 0], [0, 1, 0.2], [0, 0, 1]] }}\nsigma = {{ rotation_arcsec = 5.0, translation_mm = 0.05 }}\n"
    );
    let err = error_of(&text);
    let line = line_of(&text, "C2_from_C1");
    assert!(err.contains("matrix is not a rotation"), "{err}");
    assert!(err.contains(&format!("site.toml:{}:", line - 1)), "{err}");
}

#[test]
fn a_non_unit_quaternion_and_a_non_finite_translation_are_refused() {
    let q = format!(
        "{VALID}\n[[links]]\nname = \"C2_from_C1\"\nkind = \"calibrated\"\npose = {{ t_mm = [0, 0, -150], q_wxyz = [1, 0.5, 0, 0] }}\nsigma = {{ rotation_arcsec = 5.0, translation_mm = 0.05 }}\n"
    );
    assert!(
        error_of(&q).contains("quaternion norm is 1.118034"),
        "{}",
        error_of(&q)
    );
    let nan = q.replace(
        "[0, 0, -150], q_wxyz = [1, 0.5, 0, 0]",
        "[0, nan, -150], q_wxyz = [1, 0, 0, 0]",
    );
    assert!(
        error_of(&nan).contains("t_mm[1] is not a finite number (NaN)"),
        "{}",
        error_of(&nan)
    );
}

#[test]
fn a_duplicate_link_names_the_second_occurrence() {
    let text = format!(
        "{VALID}\n[[links]]\nname = \"C1_from_B\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 20.0, translation_mm = 0.5 }}\nexpected_rate_hz = 25.0\n"
    );
    let err = error_of(&text);
    let second = text.rfind("name = \"C1_from_B\"").unwrap();
    let line = text[..second].lines().count();
    assert!(
        err.contains(&format!("site.toml:{line}: duplicate link `C1_from_B`")),
        "{err}"
    );
}

#[test]
fn every_problem_is_reported_not_only_the_first() {
    let text = VALID
        .replace(
            "expected_rate_hz = 25.0\n\n[[links]]\nname = \"C1_from_G\"",
            "expected_rate_hz = -1.0\n\n[[links]]\nname = \"C1_from_G\"",
        )
        .replace("base = \"B\"", "base = \"Q\"");
    let err = error_of(&text);
    assert_eq!(err.lines().count(), 2, "{err}");
    assert!(
        err.contains("expected_rate_hz must lie in [0.0001, 100000], not -1"),
        "{err}"
    );
    assert!(err.contains("frame `Q` is not introduced"), "{err}");
}

#[test]
fn a_calibrated_link_without_sigma_is_refused() {
    let text = format!(
        "{VALID}\n[[links]]\nname = \"C2_from_C1\"\nkind = \"calibrated\"\npose = {{ t_mm = [0, 0, -150], euler_deg = [0, 180, 0] }}\n"
    );
    assert!(error_of(&text).contains("needs `sigma`"));
}

#[test]
fn a_syntax_error_names_line_and_column() {
    let err = error_of("[server]\nlisten = \"127.0.0.1:7878\nx = 1\n");
    assert!(err.starts_with("site.toml:2:"), "{err}");
}

#[test]
fn bad_enumerations_list_the_allowed_values() {
    let model = VALID.replacen(
        "kind = \"measured\"",
        "kind = \"measured\"\nmodel = \"wobbly\"",
        1,
    );
    assert!(
        error_of(&model)
            .contains("model `wobbly` is not one of static, constant_velocity, oscillatory")
    );
    let mode = format!("[rerun]\nmode = \"stream\"\n{VALID}");
    assert!(
        error_of(&mode).starts_with("site.toml:2: rerun.mode `stream`"),
        "{}",
        error_of(&mode)
    );
}

#[test]
fn warn_levels_must_be_below_alarm_levels() {
    let text = format!(
        "{VALID}[targets.alarms]\nwarn_rotation_arcsec = 100.0\nalarm_rotation_arcsec = 50.0\n"
    );
    assert!(
        error_of(&text).contains("rotation warn level (100) must be below the alarm level (50)")
    );
}

#[test]
fn load_names_a_missing_file() {
    let err = config::load(std::path::Path::new("/nonexistent/site.toml")).unwrap_err();
    assert!(
        err.to_string()
            .starts_with("/nonexistent/site.toml: cannot read the file"),
        "{err}"
    );
}

#[test]
fn filter_tuning_is_read_per_link_and_checked_against_the_model() {
    let text = VALID.replacen(
        "kind = \"measured\"",
        "kind = \"measured\"\nmodel = \"oscillatory\"\noscillation = { period_s = 8.0, correlation_time_s = 30.0, rotation_arcsec = [40.0, 60.0, 20.0], translation_mm = 0.4 }",
        1,
    );
    let inst = config::parse("site.toml", &text).unwrap();
    let LinkKind::Measured(m) = &inst.model.link_by_name("C1_from_B").unwrap().kind else {
        panic!("measured");
    };
    assert_eq!(m.tuning.model, brokenray::filter::MotionModel::Oscillatory);
    assert_eq!(m.tuning.oscillation.period_s, 8.0);
    assert_eq!(m.tuning.oscillation.rotation_arcsec, [40.0, 60.0, 20.0]);

    let wrong = VALID.replacen(
        "kind = \"measured\"",
        "kind = \"measured\"\noscillation = { period_s = 8.0, correlation_time_s = 30.0, rotation_arcsec = 40.0, translation_mm = 0.4 }",
        1,
    );
    let err = error_of(&wrong);
    assert!(
        err.contains("`oscillation` applies to the oscillatory model"),
        "{err}"
    );
    assert!(err.starts_with("site.toml:2:"), "{err}");
}

#[test]
fn filter_section_values_are_checked_with_their_line() {
    let text = format!("{VALID}\n[filter]\ngate_probability = 2.0\nreinit_after_outliers = 3\n");
    let err = error_of(&text);
    let line = line_of(&text, "[filter]");
    assert!(
        err.contains(&format!(
            "site.toml:{line}: filter.gate_probability must be a probability"
        )),
        "{err}"
    );
    let ok = format!(
        "{VALID}\n[filter]\ngate_probability = 0.99\nreinit_after_outliers = 3\nstale_after_periods = 10\n"
    );
    let inst = config::parse("site.toml", &ok).unwrap();
    assert_eq!(inst.model.filter.stale_after_periods, 10.0);
    let LinkKind::Measured(m) = &inst.model.link_by_name("C1_from_B").unwrap().kind else {
        panic!("measured");
    };
    assert_eq!(m.tuning.reinit_after_outliers, 3);
    assert_eq!(m.tuning.gate_probability, 0.99);
}

#[test]
fn an_installation_without_targets_is_refused() {
    let err = error_of("# an empty file\n");
    assert!(err.contains("the installation has no [[targets]]"), "{err}");
    // The links alone are not enough either.
    let links_only = brokenray::config::DEFAULT_INSTALLATION_TOML
        .split("[[targets]]")
        .next()
        .unwrap()
        .to_owned();
    assert!(error_of(&links_only).contains("no [[targets]]"));
}

/// The disc targets of markers: a wrong kind, size, polarity or normal is an error at the
/// marker's line; discs too small to image 4 px across at the nominal pose are a warning.
#[test]
fn marker_targets_are_validated_and_small_discs_warned_of() {
    // A calibration known exactly: no warning about a missing covariance.
    let exact = vec!["0.0"; 81].join(", ");
    let marker = |target: &str, normals: &str| {
        format!(
            "[[cameras]]\nframe = \"C1\"\nwidth = 1280\nheight = 1024\nfx = 4800.0\nfy = 4800.0\ncx = 640.0\ncy = 512.0\ndistortion = [0.0, 0.0, 0.0, 0.0, 0.0]\npixel_sigma = 0.05\nintrinsics_covariance = [{exact}]\n\n\
             [[markers]]\nframe = \"B\"\npoints_mm = [[0, 0, 0], [100, 0, 0], [0, 100, 0], [130, 100, 0]]\n{target}\n{normals}\n\n\
             [[links]]\nname = \"C1_from_B\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 20.0, translation_mm = 0.5 }}\nexpected_rate_hz = 25.0\nnominal = {{ t_mm = [0, 0, 3000], euler_deg = [180, 0, 0] }}\n\n\
             [[links]]\nname = \"C1_from_G\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 20.0, translation_mm = 0.5 }}\nexpected_rate_hz = 25.0\n\n\
             [[targets]]\nname = \"G\"\nbase = \"B\"\n"
        )
    };
    let good = marker(
        r#"target = { kind = "disc", diameter_mm = 20.0, polarity = "dark" }"#,
        "normals = [[0, 0, 1], [0, 0, 2], [0, 0.1, 1], [0, 0, 1]]",
    );
    let inst = config::parse("site.toml", &good).expect("valid");
    let m = inst.model.marker("B").expect("marker B");
    let t = m.target.expect("a disc target");
    assert_eq!(t.diameter_mm, 20.0);
    assert_eq!(t.polarity, brokenray::vision::Polarity::Dark);
    assert_eq!(m.normals[1], [0.0, 0.0, 1.0], "normals are made unit");
    assert!((m.normals[2][1] - 0.1 / 1.01f64.sqrt()).abs() < 1e-12);
    assert!(inst.warnings.is_empty(), "{:?}", inst.warnings);
    // A square maps onto itself under a quarter turn: it cannot be identified with no prior.
    let square = good.replace("[130, 100, 0]", "[100, 100, 0]");
    let inst = config::parse("site.toml", &square).expect("valid");
    assert_eq!(inst.warnings.len(), 1, "{:?}", inst.warnings);
    assert!(
        inst.warnings[0].message.contains("maps onto itself"),
        "{}",
        inst.warnings[0].message
    );
    assert_eq!(inst.warnings[0].line, Some(line_of(&square, "[[markers]]")));

    let marker_line = line_of(&good, "[[markers]]");
    for (target, normals, expected) in [
        (
            r#"target = { kind = "square", diameter_mm = 20.0 }"#,
            "",
            "target kind `square`",
        ),
        (
            r#"target = { kind = "disc", diameter_mm = 0.0 }"#,
            "",
            "target.diameter_mm must be a positive number",
        ),
        (
            r#"target = { kind = "disc", diameter_mm = 20.0, polarity = "grey" }"#,
            "",
            "polarity `grey`",
        ),
        (
            r#"target = { kind = "disc", diameter_mm = 20.0 }"#,
            "normals = [[0, 0, 1]]",
            "1 normals for 4 points",
        ),
        (
            r#"target = { kind = "disc", diameter_mm = 20.0 }"#,
            "normals = [[0, 0, 1], [0, 0, 0], [0, 0, 1], [0, 0, 1]]",
            "normals[1] must be a finite, non-zero vector",
        ),
    ] {
        let text = marker(target, normals);
        let err = error_of(&text);
        assert!(
            err.contains(&format!("site.toml:{marker_line}:")) && err.contains(expected),
            "{expected}: {err}"
        );
    }

    // 1 mm at 3 m through a 4800 px lens: 1.6 px.
    let small = marker(r#"target = { kind = "disc", diameter_mm = 1.0 }"#, "");
    let inst = config::parse("site.toml", &small).expect("valid, with a warning");
    assert_eq!(inst.warnings.len(), 1, "{:?}", inst.warnings);
    assert_eq!(inst.warnings[0].line, Some(marker_line));
    assert!(
        inst.warnings[0].message.contains("1.6 px across"),
        "{}",
        inst.warnings[0].message
    );
}

#[test]
fn the_built_in_markers_are_20_mm_bright_discs_without_warnings() {
    let inst = config::default_installation();
    assert!(inst.warnings.is_empty(), "{:?}", inst.warnings);
    for m in &inst.model.markers {
        let t = m.target.expect("a disc target");
        assert_eq!(t.diameter_mm, 20.0);
        assert_eq!(t.polarity, brokenray::vision::Polarity::Bright);
        assert!(m.normals.iter().all(|n| *n == [0.0, 0.0, 1.0]));
    }
}

#[test]
fn the_frame_archive_settings_default_and_refuse_what_cannot_work() {
    let plain = config::parse("site.toml", VALID).expect("valid");
    assert_eq!(plain.frames.archive_dir, None, "no archive unless asked");
    assert_eq!(plain.frames.archive_every_s, 60.0);
    assert_eq!(plain.frames.archive_max_mb, 1024.0);
    let text = format!(
        "{VALID}\n[frames]\narchive_dir = \"/var/lib/brokenray/frames\"\narchive_every_s = 10\n"
    );
    let set = config::parse("site.toml", &text).expect("valid");
    assert_eq!(
        set.frames.archive_dir.as_deref(),
        Some(std::path::Path::new("/var/lib/brokenray/frames"))
    );
    assert_eq!(set.frames.archive_every_s, 10.0);

    let text = format!("{VALID}\n[frames]\narchive_dir = \"frames\"\narchive_max_mb = 0\n");
    let e = error_of(&text);
    assert!(
        e.contains("frames.archive_max_mb must lie in [0.001, 1000000000], not 0"),
        "{e}"
    );
    assert!(
        e.contains(&format!("site.toml:{}", line_of(&text, "[frames]"))),
        "{e}"
    );
    let e = error_of(&format!("{VALID}\n[frames]\narchive_dir = \"\"\n"));
    assert!(e.contains("archive_dir is empty"), "{e}");
    let e = error_of(&format!("{VALID}\n[frames]\narchive_every = 5\n"));
    assert!(e.contains("archive_every"), "{e}");
}

/// A fleet's settings: a site that pushes names itself and keeps an SQLite outbox, a centre
/// runs on PostgreSQL, a `sync` token names its one site; each mistake is named at its line.
#[test]
fn fleet_settings_are_checked_and_each_mistake_named() {
    let site = format!(
        "{VALID}\n[site]\nname = \"ship-1\"\n\n[upstream]\nurl = \"http://central:7878\"\ntoken = \"t\"\nraw_kbit_s = 64\n"
    );
    let inst = config::parse("site.toml", &site).unwrap();
    let up = inst.fleet.upstream.as_ref().unwrap();
    assert_eq!(inst.fleet.site.as_ref().unwrap().as_str(), "ship-1");
    assert_eq!(up.raw_kbit_s, 64.0);
    assert_eq!(up.token.as_deref(), Some("t"));
    assert!(
        !format!("{up:?}").contains("\"t\""),
        "the token is never printed"
    );

    let cases: Vec<(String, &str, &str)> = vec![
        (
            format!("{VALID}\n[upstream]\nurl = \"http://central:7878\"\n"),
            "[upstream]",
            "needs the site's name",
        ),
        (
            format!("{VALID}\n[site]\nname = \"Ship 1\"\n"),
            "[site]",
            "is not a site name",
        ),
        (
            format!("{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"ftp://x\"\n"),
            "[upstream]",
            "is not an http:// or https:// URL",
        ),
        (
            format!(
                "[server]\ndatabase = \"postgres://u@h/db\"\n{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"http://c\"\n"
            ),
            "[upstream]",
            "needs an SQLite database",
        ),
        (
            format!("{VALID}\n[central]\nenabled = true\n"),
            "[central]",
            "needs a PostgreSQL database",
        ),
        (
            format!(
                "[server]\ndatabase = \"postgres://u@h/db\"\n{VALID}\n[central]\nenabled = true\nraw_days = 400\n"
            ),
            "[central]",
            "central.raw_days (400) is longer than central.results_days (365)",
        ),
        (
            format!(
                "[server]\ndatabase = \"postgres://u@h/db\"\n{VALID}\n[retention]\ndisk_budget_mb = 500\n"
            ),
            "[retention]",
            "retention.disk_budget_mb applies to an SQLite file",
        ),
        (
            format!("{VALID}\n[reports]\nevery_days = 0.01\nfolder = \"r\"\n"),
            "[reports]",
            "reports.every_days must lie in [1/24, 366] days",
        ),
        (
            format!("{VALID}\n[reports]\nevery_days = 7\nfolder = \" \"\nmin_gap_s = 0\n"),
            "[reports]",
            "reports.folder must name a folder",
        ),
        (
            format!("{VALID}\n[reports]\nevery_days = 7\nfolder = \"r\"\nmin_gap_s = 0\n"),
            "[reports]",
            "reports.min_gap_s must lie in",
        ),
        (
            format!("{VALID}\n[reports]\nfolder = \"r\"\n"),
            "[reports]",
            "missing field `every_days`",
        ),
        (
            format!("{VALID}\n[retention]\ndisk_budget_mb = 0\n"),
            "[retention]",
            "retention.disk_budget_mb must be a positive number",
        ),
        (
            format!(
                "[server]\ndatabase = \"postgres://u@h/db\"\n{VALID}\n[central]\nenabled = true\nresults_days = -1\n"
            ),
            "[central]",
            "central.results_days must be a positive number",
        ),
        (
            format!(
                "{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"http://c\"\ntoken = \"a\"\ntoken_file = \"b\"\n"
            ),
            "[upstream]",
            "give token or token_file, not both",
        ),
        (
            format!(
                "{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"http://c\"\ntoken_file = \"/nonexistent/token\"\n"
            ),
            "[upstream]",
            "cannot be read",
        ),
        (
            format!(
                "{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"http://c\"\ntoken = \" \"\n"
            ),
            "[upstream]",
            "upstream.token is empty",
        ),
        (
            format!(
                "{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"http://c\"\nbatch_rows = 100000000\n"
            ),
            "[upstream]",
            "upstream.batch_rows must lie in",
        ),
        (
            format!(
                "{VALID}\n[site]\nname = \"s\"\n[upstream]\nurl = \"http://c\"\nbatch_mb = 1e9\n"
            ),
            "[upstream]",
            "upstream.batch_mb must lie in",
        ),
        (
            format!(
                "{VALID}\n[[auth.tokens]]\nname = \"x\"\nsha256 = \"{}\"\nscopes = [\"sync\"]\n",
                "a".repeat(64)
            ),
            "[[auth.tokens]]",
            "a `sync` token names the one site",
        ),
        (
            format!(
                "{VALID}\n[[auth.tokens]]\nname = \"x\"\nsha256 = \"{}\"\nscopes = [\"read\"]\nsite = \"s\"\n",
                "a".repeat(64)
            ),
            "[[auth.tokens]]",
            "only a sync token names a site",
        ),
    ];
    assert_each_refused_at_its_line(cases);
}

/// Values that pass as numbers but would kill a task long after start (a wait of centuries, a
/// period of zero, a budget of terabytes): each refused by name at its line, never clamped.
#[test]
fn numbers_that_would_kill_a_task_later_are_refused_at_start() {
    let site = "[site]\nname = \"s\"\n";
    for (section, key, value) in [
        (
            "[upstream]\nurl = \"http://127.0.0.1:1\"\n",
            "heartbeat_s",
            "1e20",
        ),
        (
            "[upstream]\nurl = \"http://127.0.0.1:1\"\n",
            "raw_kbit_s",
            "1e-300",
        ),
        (
            "[[notify.webhooks]]\nurl = \"http://127.0.0.1:1/h\"\nsecret = \"s\"\n",
            "timeout_s",
            "1e20",
        ),
        ("[frames]\narchive_dir = \"f\"\n", "archive_every_s", "1e20"),
        ("[rerun]\n", "series_hz", "1e-300"),
    ] {
        let text = format!("{VALID}\n{site}{section}{key} = {value}\n");
        let e = error_of(&text);
        assert!(e.contains(key) && e.contains("must lie in"), "{key}: {e}");
    }
    let central = format!(
        "{VALID}\n[server]\ndatabase = \"postgres://u@127.0.0.1/db\"\n\n\
         [central]\nenabled = true\nmax_sync_mb = 2e13\n"
    );
    let e = error_of(&central);
    assert!(e.contains("central.max_sync_mb must lie in"), "{e}");
    for (key, value) in [
        ("max_body_bytes", "10"),
        ("max_connections", "3"),
        ("max_heavy_reads", "0"),
        ("header_timeout_s", "1e20"),
        ("shutdown_grace_s", "-1"),
    ] {
        let text = format!("{VALID}\n[server]\n{key} = {value}\n");
        let e = error_of(&text);
        assert!(
            e.contains(&format!("server.{key} must lie in")),
            "{key} is refused, not clamped: {e}"
        );
        let line = line_of(&text, &format!("{key} = {value}"));
        assert!(
            e.contains(&format!("site.toml:{line}:")),
            "server.{key} is reported at its line {line}: {e}"
        );
    }
}

/// A centre's URL with credentials in it is never shown with them (the log, `/upstream`).
#[test]
fn credentials_in_a_url_are_not_shown() {
    let shown = config::redacted_url(&url::Url::parse("http://ship:s3cret@centre:7878/").unwrap());
    assert!(
        !shown.contains("s3cret") && !shown.contains("ship"),
        "{shown}"
    );
    assert!(shown.contains("centre:7878"), "{shown}");
    let plain = config::redacted_url(&url::Url::parse("http://centre:7878/").unwrap());
    assert_eq!(plain, "http://centre:7878/");
    // A key in the query is not shown either.
    let keyed = config::redacted_url(
        &url::Url::parse("http://u:p@centre:7878/fleet?key=s3cret#k").unwrap(),
    );
    assert_eq!(keyed, "http://<credentials>@centre:7878/fleet?<redacted>");
}

/// A camera's `intrinsics_covariance`: 81 finite numbers of a symmetric positive semi-definite
/// matrix, or an error naming the camera and what is wrong; a camera without one is taken as
/// exact and the installation says so as a warning at the camera's line.
#[test]
fn a_cameras_intrinsics_covariance_is_checked_and_its_absence_warned_of() {
    let built_in = brokenray::config::DEFAULT_INSTALLATION_TOML;
    let start = built_in
        .find("intrinsics_covariance = [")
        .expect("the built-in has one");
    let end = start + built_in[start..].find(']').expect("closed") + 1;
    let first = &built_in[start..end];
    let with = |replacement: &str| built_in.replacen(first, replacement, 1);

    let inst = config::parse("site.toml", &with("")).expect("valid, with a warning");
    assert_eq!(inst.warnings.len(), 1, "{:?}", inst.warnings);
    assert!(
        inst.warnings[0].message.contains("camera `C1`")
            && inst.warnings[0].message.contains("taken as exact"),
        "{}",
        inst.warnings[0].message
    );
    assert_eq!(
        inst.warnings[0].line,
        Some(line_of(built_in, "[[cameras]]"))
    );
    assert!(inst.model.cameras[0].intrinsics_covariance.is_none());
    assert!(inst.model.cameras[1].intrinsics_covariance.is_some());

    let nine: Vec<String> = (0..9).map(|i| format!("{}.0", i + 1)).collect();
    let diagonal = |i: usize, j: usize| if i == j { "1.0" } else { "0.0" };
    let matrix = |cell: &dyn Fn(usize, usize) -> String| {
        let cells: Vec<String> = (0..9)
            .flat_map(|i| (0..9).map(move |j| (i, j)))
            .map(|(i, j)| cell(i, j))
            .collect();
        format!("intrinsics_covariance = [{}]", cells.join(", "))
    };
    for (replacement, expected) in [
        (
            format!("intrinsics_covariance = [{}]", nine.join(", ")),
            "must have 81 numbers",
        ),
        (
            matrix(&|i, j| {
                if (i, j) == (0, 1) {
                    "0.5".into()
                } else {
                    diagonal(i, j).into()
                }
            }),
            "is not symmetric (row 1, column 0",
        ),
        (
            matrix(&|i, j| {
                if i == 2 && j == 2 {
                    "-1.0".into()
                } else {
                    diagonal(i, j).into()
                }
            }),
            "is not positive semi-definite",
        ),
    ] {
        let err = error_of(&with(&replacement));
        assert!(
            err.contains("camera `C1`: intrinsics_covariance") && err.contains(expected),
            "{expected}: {err}"
        );
    }
    // The 9 x 9 reads row-major into the camera.
    let inst = config::parse(
        "site.toml",
        &with(&matrix(&|i, j| {
            if i == j {
                format!("{}.0", i + 1)
            } else if i + j == 1 {
                "0.25".into()
            } else {
                "0.0".into()
            }
        })),
    )
    .expect("valid");
    let cov = inst.model.cameras[0].intrinsics_covariance.expect("read");
    assert_eq!(
        (cov[(0, 0)], cov[(8, 8)], cov[(0, 1)], cov[(1, 0)]),
        (1.0, 9.0, 0.25, 0.25)
    );
}

/// The built-in installation with `source` lines added to camera C1's table (and C2's when
/// given).
fn with_sources(c1: &str, c2: Option<&str>) -> String {
    let mut text = config::DEFAULT_INSTALLATION_TOML.replacen(
        "[[cameras]]\nframe = \"C1\"",
        &format!("[[cameras]]\nframe = \"C1\"\nsource = {c1}"),
        1,
    );
    if let Some(c2) = c2 {
        text = text.replacen(
            "[[cameras]]\nframe = \"C2\"",
            &format!("[[cameras]]\nframe = \"C2\"\nsource = {c2}"),
            1,
        );
    }
    text
}

#[test]
fn a_camera_source_is_read_with_its_defaults() {
    let inst = config::parse(
        "site.toml",
        &with_sources(
            r#"{ address = "192.168.10.11", features = ["BalanceWhiteAuto=Off", "Width = 1280"] }"#,
            Some(r#"{ address = "usb:Basler:acA1300:2201", trigger = "software", timestamp = "ptp", pixel_format = "Mono12", rate_hz = 25, exposure_us = 1500, tai_offset_s = 0 }"#),
        ),
    )
    .unwrap();
    let [c1, c2] = &inst.sources[..] else {
        panic!("two sources: {:?}", inst.sources)
    };
    assert_eq!(c1.camera, "C1");
    assert_eq!(
        c1.address,
        config::CameraAddress::Gige([192, 168, 10, 11].into())
    );
    assert_eq!(c1.pixel_format, config::PixelFormat::Mono8);
    assert_eq!(c1.trigger, config::TriggerMode::FreeRun);
    assert_eq!(c1.timestamp, config::TimestampMode::HostFit);
    assert_eq!(
        (c1.rate_hz, c1.tolerance_ms, c1.tai_offset_s),
        (10.0, 100.0, 37.0)
    );
    assert_eq!(c1.features.len(), 2);
    assert_eq!(
        (c1.features[1].name.as_str(), c1.features[1].value.as_str()),
        ("Width", "1280")
    );
    // Half the exposure from the stamp (its start) to the middle, unless told otherwise.
    assert_eq!(c1.stamp_offset_ns(2000.0), 1_000_000);
    assert_eq!(c2.address.to_string(), "usb:Basler:acA1300:2201");
    assert_eq!(c2.trigger, config::TriggerMode::Software);
    assert_eq!(c2.timestamp, config::TimestampMode::Ptp);
    assert_eq!(c2.pixel_format, config::PixelFormat::Mono12);
    assert_eq!(c2.tai_offset_s, 0.0);
}

/// Each wrong key of a source is named with the camera and the line; a broadcast address, a
/// host name (which would need a search) and a word outside a vocabulary are refused.
#[test]
fn a_camera_source_s_errors_name_the_camera_the_key_and_the_line() {
    for (source, expected) in [
        (
            r#"{ address = "cam1.local" }"#,
            "source.address `cam1.local` is neither an IPv4 address",
        ),
        (
            r#"{ address = "255.255.255.255" }"#,
            "is not one camera's address",
        ),
        (
            r#"{ address = "usb:Basler:acA1300" }"#,
            "is not `usb:VENDOR:MODEL:SERIAL`",
        ),
        (
            r#"{ address = "192.168.10.255" }"#,
            "that is the broadcast address, no camera's",
        ),
        (
            r#"{ address = "usb:Basler:acA1300:22\u000001" }"#,
            "three parts of 1 to 64 printable characters",
        ),
        (
            r#"{ address = "usb:Basler:acA1300:2201234567890123456789012345678901234567890123456789012345678901234567890" }"#,
            "three parts of 1 to 64 printable characters",
        ),
        (
            r#"{ address = "10.0.0.2", pixel_format = "RGB8" }"#,
            "source.pixel_format `RGB8` is not one of `Mono8`, `Mono10`, `Mono12`, `Mono16`",
        ),
        (
            r#"{ address = "10.0.0.2", trigger = "hardware" }"#,
            "source.trigger `hardware` is not one of `free_run`, `software`, `line`",
        ),
        (
            r#"{ address = "10.0.0.2", timestamp = "ntp" }"#,
            "source.timestamp `ntp` is not one of `ptp`, `host_fit`, `host`",
        ),
        (r#"{ address = "10.0.0.2", rate_hz = 0 }"#, "source.rate_hz"),
        (
            r#"{ address = "10.0.0.2", rate_hz = 100, exposure_us = 20000 }"#,
            "source.exposure_us 20000 does not fit in a frame period at rate_hz 100",
        ),
        (
            r#"{ address = "10.0.0.2", features = ["Width"] }"#,
            "source.features `Width` is not `Name=value`",
        ),
        (
            r#"{ address = "10.0.0.2", features = ["2Width=3"] }"#,
            "`2Width` is not a GenICam feature name",
        ),
        (
            r#"{ address = "10.0.0.2", packet_size_bytes = 100 }"#,
            "source.packet_size_bytes 100 is outside 576 to 16384",
        ),
        (
            r#"{ address = "10.0.0.2", tolerance_ms = 0 }"#,
            "source.tolerance_ms",
        ),
        (r#"{ address = "10.0.0.2", colour = true }"#, "colour"),
    ] {
        let text = with_sources(source, None);
        let error = error_of(&text);
        assert!(
            error.contains("camera `C1`: ") || expected == "colour",
            "{source}: {error}"
        );
        assert!(error.contains(expected), "{source}: {error}");
        assert!(
            error.contains(&format!(":{}", line_of(&text, "source = "))),
            "{source}: {error}"
        );
    }
}

#[test]
fn two_sources_may_not_share_an_address_nor_a_group_its_trigger() {
    let error = error_of(&with_sources(
        r#"{ address = "10.0.0.2" }"#,
        Some(r#"{ address = "10.0.0.2" }"#),
    ));
    assert!(
        error.contains("camera `C2`: source.address `10.0.0.2` is camera `C1`'s already"),
        "{error}"
    );
    let error = error_of(&with_sources(
        r#"{ address = "10.0.0.2", trigger = "software", rate_hz = 10 }"#,
        Some(r#"{ address = "10.0.0.3", trigger = "software", rate_hz = 20 }"#),
    ));
    assert!(error.contains("camera `C2`: source.trigger_group `default` has camera `C1` with trigger `software` at 10 Hz"), "{error}");
    // Another group may run at its own rate.
    config::parse(
        "site.toml",
        &with_sources(
            r#"{ address = "10.0.0.2", trigger = "software", rate_hz = 10 }"#,
            Some(r#"{ address = "10.0.0.3", trigger = "software", rate_hz = 20, trigger_group = "b" }"#),
        ),
    )
    .unwrap();
}

#[test]
fn a_host_timestamp_is_valid_but_warned_about() {
    let text = with_sources(r#"{ address = "10.0.0.2", timestamp = "host" }"#, None);
    let inst = config::parse("site.toml", &text).unwrap();
    let warning = inst
        .warnings
        .iter()
        .find(|w| w.message.contains("timestamp `host`"))
        .expect("a warning");
    assert_eq!(warning.line, Some(line_of(&text, "source = ")));
}

/// Sigmas, noise strengths and a camera's intrinsics covariance have upper bounds (the API's
/// on posted sigmas): a value far beyond them would make every result of the targets it
/// reaches huge or not finite, long after `check-config` said the file was fine.
#[test]
fn sigmas_noise_and_intrinsics_covariances_are_bounded_above() {
    for (tuning, key) in [
        (
            "model = \"static\"\nrandom_walk = { rotation_arcsec_per_sqrt_s = 1e300, translation_mm_per_sqrt_s = 0.02 }",
            "random_walk.rotation_arcsec_per_sqrt_s",
        ),
        (
            "model = \"static\"\nrandom_walk = { rotation_arcsec_per_sqrt_s = 2.0, translation_mm_per_sqrt_s = 1e100 }",
            "random_walk.translation_mm_per_sqrt_s",
        ),
        (
            "model = \"constant_velocity\"\nacceleration_noise = { rotation_arcsec_per_s_sqrt_s = 1e9, translation_mm_per_s_sqrt_s = 1.0 }",
            "acceleration_noise.rotation_arcsec_per_s_sqrt_s",
        ),
        (
            "model = \"oscillatory\"\noscillation = { period_s = 8.0, correlation_time_s = 30.0, rotation_arcsec = 40.0, translation_mm = 1e20 }",
            "oscillation.translation_mm",
        ),
    ] {
        let text = VALID.replacen(
            "kind = \"measured\"",
            &format!("kind = \"measured\"\n{tuning}"),
            1,
        );
        let e = error_of(&text);
        assert!(
            e.contains(key)
                && e.contains("beyond the plausible limit")
                && e.starts_with("site.toml:2:"),
            "{key}: {e}"
        );
        let fit = if tuning.contains("oscillatory") {
            ""
        } else {
            "fit_from_data = false\n"
        };
        let target = format!("{VALID}\n[targets.filter]\n{fit}{tuning}\n");
        let e = error_of(&target);
        assert!(
            e.contains("target `G` filter")
                && e.contains(key)
                && e.contains("beyond the plausible limit"),
            "target filter {key}: {e}"
        );
    }
    let sigma = VALID.replacen("rotation_arcsec = 20.0", "rotation_arcsec = 1e100", 1);
    let e = error_of(&sigma);
    assert!(
        e.contains("sigma.rotation_arcsec") && e.contains("beyond the plausible limit"),
        "{e}"
    );

    // A camera's intrinsics covariance: the built-in one with one entry changed.
    let builtin = config::DEFAULT_INSTALLATION_TOML;
    let first = "  1.0437e-1, 1.0100e-1,";
    assert!(
        builtin.contains(first),
        "the built-in camera's covariance starts so"
    );
    let huge = builtin.replacen(first, "  1e300, 1.0100e-1,", 1);
    let e = error_of(&huge);
    assert!(
        e.contains("intrinsics_covariance has a variance of 1e300 for fx"),
        "{e}"
    );
    // A negative eigenvalue of -1e-4 beside a variance of 1e6: refused whatever the scale
    // (a tolerance relative to the largest entry took it for rounding).
    let indefinite = builtin
        .replacen(first, "  1e6, 1.0100e-1,", 1)
        .replace("6.6263e-11", "1e-4");
    let e = error_of(&indefinite);
    assert!(
        e.contains("intrinsics_covariance is not positive semi-definite"),
        "{e}"
    );
    assert!(
        config::parse("site.toml", builtin).is_ok(),
        "the built-in one passes"
    );
}

#[test]
fn outputs_that_cannot_reach_one_receiver_are_refused_naming_their_key() {
    for (outputs, key, says) in [
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://255.255.255.255:1883\"",
            "outputs.mqtt[0].url",
            "cannot be a broker",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://0.0.0.0\"",
            "outputs.mqtt[0].url",
            "cannot be a broker",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://239.1.2.3\"",
            "outputs.mqtt[0].url",
            "cannot be a broker",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"http://broker.example:1883\"",
            "outputs.mqtt[0].url",
            "mqtt:// or mqtts://",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://user:secret@broker.example\"",
            "outputs.mqtt[0].url",
            "carries credentials",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://broker.example\"\nqos = 2",
            "outputs.mqtt[0].qos",
            "0 or 1",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://broker.example\"\ntopic_prefix = \"ship/#\"",
            "outputs.mqtt[0].topic_prefix",
            "without `+`, `#`",
        ),
        (
            "[[outputs.mqtt]]\nurl = \"mqtt://broker.example\"\nrate_hz = 0",
            "outputs.mqtt[0].rate_hz",
            "must lie in",
        ),
        (
            "[[outputs.nmea]]\nto = \"192.168.1.255:10110\"",
            "outputs.nmea[0].to",
            "broadcast or multicast",
        ),
        (
            "[[outputs.nmea]]\nto = \"239.192.0.1:60001\"",
            "outputs.nmea[0].to",
            "allow_broadcast = true",
        ),
        (
            "[[outputs.nmea]]\nto = \"127.0.0.1:10110\"\ntalker = \"yx\"",
            "outputs.nmea[0].talker",
            "two capital letters",
        ),
        (
            "[[outputs.modbus]]\nlisten = \"localhost\"",
            "outputs.modbus[0].listen",
            "address and port",
        ),
        (
            "[[outputs.modbus]]\nlisten = \"127.0.0.1:5020\"\n\n[[outputs.modbus]]\nlisten = \"127.0.0.1:5020\"",
            "outputs.modbus[1].listen",
            "named twice",
        ),
    ] {
        let text = format!("{VALID}\n{outputs}\n");
        let e = error_of(&text);
        assert!(e.contains(key) && e.contains(says), "{outputs}: {e}");
    }
    // What is meant passes: a multicast group allowed, a broker by name with TLS and
    // credentials.
    let text = format!(
        "{VALID}\n[[outputs.nmea]]\nto = \"239.192.0.1:60001\"\nallow_broadcast = true\n\n\
         [[outputs.mqtt]]\nurl = \"mqtts://broker.example\"\nusername = \"ship\"\npassword = \"p\"\n"
    );
    let inst = config::parse("site.toml", &text).expect("valid");
    assert_eq!(inst.outputs.mqtt[0].port, 8883);
    assert!(inst.outputs.mqtt[0].tls);
    assert!(!format!("{:?}", inst.outputs.mqtt[0]).contains("\"p\""));
}

/// A camera of a wider lens model: OpenCV's 8 or 12 distortion coefficients, with a covariance
/// of 12 x 12 or 16 x 16 to match; a length OpenCV does not define, or a covariance of another
/// model's size, is refused naming what it takes.
#[test]
fn a_camera_of_the_rational_or_prism_model_takes_a_covariance_of_its_size() {
    let built_in = brokenray::config::DEFAULT_INSTALLATION_TOML;
    let brown = "distortion = [-0.092, 0.151, 0.0004, -0.0003, 0.0]";
    let start = built_in
        .find("intrinsics_covariance = [")
        .expect("the built-in has one");
    let end = start + built_in[start..].find(']').expect("closed") + 1;
    let first = &built_in[start..end];
    let with = |distortion: &str, n: usize| {
        let cells: Vec<String> = (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                if i == j {
                    format!("{:e}", 1e-6 * (i + 1) as f64)
                } else {
                    "0.0".into()
                }
            })
            .collect();
        built_in.replacen(brown, distortion, 1).replacen(
            first,
            &format!("intrinsics_covariance = [{}]", cells.join(", ")),
            1,
        )
    };
    let rational = "distortion = [-0.092, 0.151, 0.0004, -0.0003, 0.0, 0.02, 0.0, 0.0]";
    let inst = config::parse("site.toml", &with(rational, 12)).expect("valid");
    let c1 = &inst.model.cameras[0];
    assert_eq!(
        c1.intrinsics.lens_model(),
        brokenray::vision::LensModel::Rational
    );
    assert_eq!(c1.intrinsics.distortion[5], 0.02);
    let cov = c1.intrinsics_covariance.expect("read");
    assert_eq!((cov[(11, 11)], cov[(12, 12)]), (12e-6, 0.0));

    let prism =
        "distortion = [-0.092, 0.151, 0.0004, -0.0003, 0.0, 0.02, 0.0, 0.0, 0.001, 0.0, 0.0, 0.0]";
    let inst = config::parse("site.toml", &with(prism, 16)).expect("valid");
    let cov = inst.model.cameras[0].intrinsics_covariance.expect("read");
    assert_eq!(cov[(15, 15)], 16e-6);

    let err = error_of(&with(rational, 9));
    assert!(
        err.contains("camera `C1`: intrinsics_covariance must have 144 numbers")
            && err.contains("k4 k5 k6"),
        "{err}"
    );
    let err = error_of(&with("distortion = [0.1, 0.0, 0.0, 0.0, 0.0, 0.0]", 9));
    assert!(
        err.contains("camera `C1`: distortion has 6 numbers") && err.contains("4, 5, 8 or 12"),
        "{err}"
    );
}

/// `[acceptance]`: the procedure parsed into its plan; each mistake named at its line.
#[test]
fn acceptance_settings_are_checked_and_each_mistake_named() {
    const LIMITS: &str =
        "still_rms_arcsec = 100\nstill_rms_mm = 1\nmove_arcsec = 40\nmove_mm = 0.4\n";
    let good = format!(
        "{VALID}\n[acceptance]\nstep_s = 15\n{LIMITS}\n[[acceptance.moves]]\nname = \"up\"\ntranslation_mm = [0, 0, 50]\n"
    );
    let inst = config::parse("site.toml", &good).unwrap();
    let a = inst.acceptance.as_ref().unwrap();
    assert_eq!(a.plan.step_ns, 15_000_000_000);
    assert_eq!(a.plan.still_ns, 30_000_000_000, "the default still window");
    assert_eq!(a.reverify_every_ns, 365 * 86_400 * 1_000_000_000);
    assert_eq!(a.plan.moves[0].target, 0, "the only target");
    assert_eq!(
        a.plan.moves[0].displacement.translation_mm,
        [0.0, 0.0, 50.0]
    );
    assert_eq!(a.plan.limits.move_mm, 0.4);

    let moved = |name: &str, rest: &str| {
        format!("{VALID}\n[acceptance]\n{LIMITS}\n[[acceptance.moves]]\nname = \"{name}\"\n{rest}")
    };
    let cases: Vec<(String, &str, &str)> = vec![
        (
            format!("{VALID}\n[acceptance]\n{LIMITS}"),
            "[acceptance]",
            "needs at least one known move",
        ),
        (
            moved("up", "target = \"H\"\ntranslation_mm = [0, 0, 1]\n"),
            "[[acceptance.moves]]",
            "acceptance.moves.target `H` is not a target (targets: G)",
        ),
        (
            moved("still", "translation_mm = [0, 0, 1]\n"),
            "[[acceptance.moves]]",
            "is taken",
        ),
        (
            moved("far", "translation_mm = [0, 0, 5000]\n"),
            "[[acceptance.moves]]",
            "acceptance.moves.translation_mm of `far` must lie in [-1000, 1000], not 5000",
        ),
        (
            moved("up", "translation_mm = [0, 0, 1]\n").replace("move_mm = 0.4", "move_mm = 0"),
            "[acceptance]",
            "acceptance.move_mm must be a positive number",
        ),
        (
            moved("up", "translation_mm = [0, 0, 1]\n")
                .replace("[acceptance]\n", "[acceptance]\nreverify_every_days = 0\n"),
            "[acceptance]",
            "acceptance.reverify_every_days must lie in [1, 3660] days",
        ),
        (
            moved("up", "translation_mm = [0, 0, 1]\n")
                .replace("[acceptance]\n", "[acceptance]\nstep_s = 0\n"),
            "[acceptance]",
            "acceptance.step_s must lie in",
        ),
    ];
    assert_each_refused_at_its_line(cases);
}
