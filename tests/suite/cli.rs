//! The `brokenray` binary, run as a user runs it.

use std::process::Command;

fn brokenray(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(args)
        .output()
        .expect("the binary runs")
}

/// Every line of an NDJSON file.
fn read_ndjson(path: &std::path::Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn check_config_prints_the_built_in_topology_with_link_directions() {
    let out = brokenray(&["check-config"]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("frames (6): "), "{text}");
    assert!(text.contains(
        "path 1: C1_from_B (forward) -> C2_from_C1 (forward) -> C2_from_M (inverted) -> C3_from_M (forward) -> C3_from_G (inverted)"
    ), "{text}");
    assert!(text.contains("G_from_B = G_from_C3 * C3_from_M * M_from_C2 * C2_from_C1 * C1_from_B"));
}

#[test]
fn default_config_round_trips_through_check_config() {
    let dir = std::env::temp_dir().join(format!("brokenray-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("site.toml");
    std::fs::write(&file, brokenray(&["default-config"]).stdout).unwrap();
    let out = brokenray(&["check-config", "--config", file.to_str().unwrap()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        String::from_utf8(out.stdout)
            .unwrap()
            .contains(&format!("installation: {} (valid)", file.display()))
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_bad_file_fails_with_its_line_on_stderr() {
    let dir = std::env::temp_dir().join(format!("brokenray-cli-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("bad.toml");
    std::fs::write(
        &file,
        "[[links]]\nname = \"A_from_B\"\nkind = \"measured\"\n",
    )
    .unwrap();
    let out = brokenray(&["check-config", "--config", file.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains(&format!(
            "{}:1: measured link `A_from_B` needs `sigma`",
            file.display()
        )),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_modbus_map_gives_every_field_of_every_target_its_address() {
    let out = brokenray(&["modbus-map"]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    let rows: Vec<Vec<&str>> = text
        .lines()
        .filter(|l| l.starts_with(|c: char| c.is_ascii_digit()))
        .map(|l| l.split('\t').collect())
        .collect();
    let names = brokenray::config::parse("x.toml", brokenray::config::DEFAULT_INSTALLATION_TOML)
        .unwrap()
        .model
        .targets
        .len();
    let fields = brokenray::outputs::modbus::FIELDS.len();
    assert_eq!(rows.len(), 3 + names * fields, "{text}");
    assert!(rows.iter().all(|r| r.len() == 5), "{text}");
    assert!(text.contains("0\tu16\tservice.map_version"), "{text}");
    assert!(text.contains("100\tu16\tG.status"), "{text}");
    assert!(
        text.contains("112\tf32\tG.deformation_rx\tarcsec"),
        "{text}"
    );
}

#[test]
fn help_lists_only_working_subcommands() {
    let text = String::from_utf8(brokenray(&["--help"]).stdout).unwrap();
    let commands: Vec<&str> = text
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| !l.is_empty())
        .filter_map(|l| l.split_whitespace().next())
        .collect();
    assert_eq!(
        commands,
        [
            "check-config",
            "default-config",
            "modbus-map",
            "serve",
            "backup",
            "new-generation",
            "replay",
            "healthcheck",
            "simulate",
            "render-plate",
            "render-station",
            "calibrate",
            "calibrate-camera",
            "calibrate-station",
            "detect",
            "acquire",
            "watch",
            "demo",
            "report",
            "acceptance",
            "hash-token",
            "help"
        ]
    );
}

/// The container's installation is the built-in one with container paths, listening on all
/// interfaces and streaming to the compose file's viewer; and the Dockerfile runs and checks
/// the file it copies.
#[test]
fn the_container_installation_is_the_default_with_container_paths() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("docker/installation.toml")).unwrap();
    let inst = brokenray::config::parse("docker/installation.toml", &text).expect("valid");
    assert_eq!(inst.server.listen.to_string(), "0.0.0.0:7878");
    assert_eq!(
        inst.server.database,
        brokenray::config::Database::Sqlite("/var/lib/brokenray/brokenray.db".into())
    );
    let topology = |t: &str| t[t.find("[[cameras]]").expect("cameras")..].to_owned();
    assert_eq!(
        topology(&text),
        topology(brokenray::config::DEFAULT_INSTALLATION_TOML),
        "docker/installation.toml's topology drifted from src/config/default.toml"
    );
    // The PostgreSQL variant: the same file but for the database, which is the compose file's
    // server with the compose file's password.
    let pg = std::fs::read_to_string(root.join("docker/installation.postgres.toml")).unwrap();
    let pg_inst =
        brokenray::config::parse("docker/installation.postgres.toml", &pg).expect("valid");
    let compose = std::fs::read_to_string(root.join("docker/compose.postgres.yaml")).unwrap();
    match &pg_inst.server.database {
        brokenray::config::Database::Postgres(url) => {
            let url = url::Url::parse(url.secret()).unwrap();
            assert_eq!(url.host_str(), Some("postgres"));
            let password = url.password().expect("a password");
            assert!(compose.contains(&format!("POSTGRES_PASSWORD: {password}")));
        }
        other => panic!("docker/installation.postgres.toml names {other}"),
    }
    assert_eq!(
        topology(&pg),
        topology(&text),
        "docker/installation.postgres.toml's topology drifted from docker/installation.toml"
    );
    let dockerfile = std::fs::read_to_string(root.join("docker/Dockerfile")).unwrap();
    assert!(dockerfile.contains("COPY docker/installation.toml /etc/brokenray/installation.toml"));
    for line in ["HEALTHCHECK", "CMD [\"serve\""] {
        let l = dockerfile
            .lines()
            .skip_while(|l| !l.starts_with(line))
            .take(2)
            .collect::<String>();
        assert!(
            l.contains("/etc/brokenray/installation.toml"),
            "{line}: {l}"
        );
    }
}

#[test]
fn simulate_writes_observations_or_samples_with_the_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run.ndjson");
    let truth = dir.path().join("truth.ndjson");
    let run = brokenray(&[
        "simulate",
        "--scenario",
        "tunnel",
        "--duration",
        "2s",
        "--rate",
        "10",
        "--start",
        "2026-11-21T10:00:00Z",
        "--out",
        out.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let lines = read_ndjson(&out);
    // 20 groups of the three camera-marker links.
    assert_eq!(lines.len(), 60);
    assert_eq!(lines[0]["time"], "2026-11-21T10:00:00Z");
    assert_eq!(lines[59]["time"], "2026-11-21T10:00:01.9Z");
    assert_eq!(lines[1]["points_px"].as_array().unwrap().len(), 7);
    let truth_lines = read_ndjson(&truth);
    assert_eq!(truth_lines.len(), 20);
    // Tunnel creep moves the target: 20 um/s over 1.9 s.
    let t = |k: usize, i: usize| truth_lines[k]["targets"]["G"]["t_mm"][i].as_f64().unwrap();
    let moved = ((t(19, 0) - t(0, 0)).powi(2)
        + (t(19, 1) - t(0, 1)).powi(2)
        + (t(19, 2) - t(0, 2)).powi(2))
    .sqrt();
    assert!(moved > 0.01 && moved < 0.2, "{moved}");

    // The same file is not overwritten.
    let again = brokenray(&[
        "simulate",
        "--duration",
        "1s",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("must not exist"));

    let samples = dir.path().join("samples.ndjson");
    let run = brokenray(&[
        "simulate",
        "--emit",
        "samples",
        "--duration",
        "1s",
        "--rate",
        "5",
        "--out",
        samples.to_str().unwrap(),
    ]);
    assert!(run.status.success());
    let first = read_ndjson(&samples).swap_remove(0);
    assert_eq!(first["link"], "C1_from_B");
    assert_eq!(first["covariance"].as_array().unwrap().len(), 36);
    assert!(first["quality"]["reprojection_rms_px"].as_f64().unwrap() < 0.5);
}

/// Without `--start`, a run that is not sent in real time ends now (a service refuses
/// measurements from its future), and says so.
#[test]
fn a_simulated_run_faster_than_real_time_ends_now() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run.ndjson");
    let wall_ns = || {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos() as i64
    };
    let before_ns = wall_ns();
    let run = brokenray(&[
        "simulate",
        "--duration",
        "60s",
        "--rate",
        "2",
        "--emit",
        "samples",
        "--out",
        out.to_str().unwrap(),
    ]);
    let after_ns = wall_ns();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(
        String::from_utf8_lossy(&run.stderr).contains("so that it ends now"),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let lines = read_ndjson(&out);
    let time = |v: &serde_json::Value| {
        brokenray::clock::parse_query_time(v["time"].as_str().unwrap()).unwrap()
    };
    let (first, last) = (time(&lines[0]), time(lines.last().unwrap()));
    // 120 groups, 0.5 s apart: the last half a period before the run's now.
    assert_eq!(last - first, 59_500_000_000);
    assert!(last <= after_ns, "the last group is not in the future");
    assert!(
        last >= before_ns - 1_000_000_000,
        "the run ends now: {}",
        (before_ns - last) as f64 / 1e9
    );
}

#[test]
fn simulated_frames_are_detected_into_observations_of_the_true_poses() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    let run = brokenray(&[
        "simulate",
        "--emit",
        "frames",
        "--scenario",
        "ship",
        "--duration",
        "0.6s",
        "--rate",
        "5",
        "--start",
        "2026-11-21T10:00:00Z",
        "--out",
        frames.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(String::from_utf8_lossy(&run.stdout).contains("9 frames sent"));
    // Named by their time, fixed width: the names sort in time order.
    let mut c1: Vec<std::path::PathBuf> = std::fs::read_dir(frames.join("C1"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    c1.sort();
    let names: Vec<String> = c1
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        names,
        [
            "2026-11-21T10:00:00.000000000Z.png",
            "2026-11-21T10:00:00.200000000Z.png",
            "2026-11-21T10:00:00.400000000Z.png"
        ]
    );
    let truth = read_ndjson(&frames.join("truth.ndjson"));
    assert_eq!(truth.len(), 3);

    let mut args = vec!["detect", "--camera", "C1"];
    args.extend(c1.iter().map(|p| p.to_str().unwrap()));
    let run = brokenray(&args);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8(run.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3, "one observation per frame");
    for (k, line) in lines.iter().enumerate() {
        assert_eq!(line["camera"], "C1");
        assert_eq!(line["marker"], "B");
        assert_eq!(line["time"], truth[k]["time"]);
        assert_eq!(line["ids"].as_array().unwrap().len(), 8);
        let sigmas = line["sigma_px"].as_array().unwrap();
        assert!(sigmas.iter().all(|s| s.as_f64().unwrap() < 0.05), "{line}");
        // The observation solves to the true pose (the service's own PnP on its pixels).
        let points: Vec<[f64; 2]> = serde_json::from_value(line["points_px"].clone()).unwrap();
        let ids: Vec<u32> = serde_json::from_value(line["ids"].clone()).unwrap();
        let sigma_px: Vec<f64> = serde_json::from_value(line["sigma_px"].clone()).unwrap();
        let inst = brokenray::config::default_installation();
        let observer = brokenray::model::Observer::new(&inst.model);
        let (_, solved) = observer
            .solve("C1", "B", &points, Some(&ids), Some(&sigma_px))
            .unwrap();
        let t_true = &truth[k]["links"]["C1_from_B"]["t_mm"];
        let error = (0..3)
            .map(|i| {
                (solved.camera_from_marker.translation.vector[i] - t_true[i].as_f64().unwrap())
                    .powi(2)
            })
            .sum::<f64>()
            .sqrt();
        assert!(error < 0.1, "frame {k}: {error} mm from the truth");
    }
    assert!(
        String::from_utf8_lossy(&run.stderr)
            .contains("3 frame(s): 3 observation(s), 0 marker(s) not found")
    );

    // A frame of another camera's size, and a camera that is not configured, are named.
    let c3 = std::fs::read_dir(frames.join("C3"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let run = brokenray(&["detect", "--camera", "C1", c3.to_str().unwrap()]);
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(
        err.contains("1392 x 1040 px but 1280 x 1024 px was expected"),
        "{err}"
    );
    let run = brokenray(&["detect", "--camera", "C9", c3.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&run.stderr).contains("unknown camera `C9`"));
    // --time stamps a single frame.
    let mut args = vec!["detect", "--camera", "C1", "--time", "2026-11-21T10:00:00Z"];
    args.extend(c1.iter().map(|p| p.to_str().unwrap()));
    let run = brokenray(&args);
    assert!(String::from_utf8_lossy(&run.stderr).contains("--time stamps one frame"));
}

#[test]
fn calibrate_solves_a_file_of_motions_and_refuses_parallel_axes() {
    let dir = tempfile::tempdir().unwrap();
    // X: 90 degrees about z and (10, 20, 30) mm; B_i about x, y and z; A_i = X B_i X^-1.
    // For these three the conjugates are written out: X maps x to y, y to -x.
    let pose = |t: [f64; 3], axis: [f64; 3], deg: f64| {
        let h = (deg.to_radians() / 2.0).sin();
        let c = (deg.to_radians() / 2.0).cos();
        serde_json::json!({"t_mm": t, "q_wxyz": [c, axis[0] * h, axis[1] * h, axis[2] * h]})
    };
    let x_t = [10.0, 20.0, 30.0];
    let conj = |bt: [f64; 3], axis: [f64; 3], deg: f64| {
        // R_X = Rz(90): (x, y, z) -> (-y, x, z). A = X B X^-1: R_A = R_X R_B R_X^T,
        // t_A = R_X t_B + t_X - R_A t_X.
        let rx = |v: [f64; 3]| [-v[1], v[0], v[2]];
        let a_axis = rx(axis);
        let (s, c) = deg.to_radians().sin_cos();
        let k = a_axis;
        let v = x_t;
        let kxv = [
            k[1] * v[2] - k[2] * v[1],
            k[2] * v[0] - k[0] * v[2],
            k[0] * v[1] - k[1] * v[0],
        ];
        let kdv = k[0] * v[0] + k[1] * v[1] + k[2] * v[2];
        let rv: Vec<f64> = (0..3)
            .map(|i| v[i] * c + kxv[i] * s + k[i] * kdv * (1.0 - c))
            .collect();
        let rb = rx(bt);
        let t = [
            rb[0] + v[0] - rv[0],
            rb[1] + v[1] - rv[1],
            rb[2] + v[2] - rv[2],
        ];
        pose(t, a_axis, deg)
    };
    let motions = [
        ([50.0, 0.0, 0.0], [1.0, 0.0, 0.0], 30.0),
        ([0.0, 80.0, 10.0], [0.0, 1.0, 0.0], 25.0),
        ([5.0, -5.0, 60.0], [0.0, 0.0, 1.0], 40.0),
    ];
    let pairs: Vec<serde_json::Value> = motions
        .iter()
        .map(|(t, axis, deg)| serde_json::json!({"a": conj(*t, *axis, *deg), "b": pose(*t, *axis, *deg)}))
        .collect();
    let input = dir.path().join("motions.json");
    std::fs::write(&input, serde_json::json!({ "pairs": pairs }).to_string()).unwrap();
    let result = dir.path().join("x.json");
    let out = brokenray(&[
        "calibrate",
        "--input",
        input.to_str().unwrap(),
        "--out",
        result.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let x: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    for (k, expected) in x_t.iter().enumerate() {
        assert!(
            (x["x"]["t_mm"][k].as_f64().unwrap() - expected).abs() < 1e-6,
            "{x}"
        );
    }
    assert!(
        (x["x"]["euler_deg"][2].as_f64().unwrap() - 90.0).abs() < 1e-6,
        "{x}"
    );

    let same_axis: Vec<serde_json::Value> = [20.0, 30.0, 40.0]
        .iter()
        .map(|deg| serde_json::json!({"a": conj([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], *deg), "b": pose([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], *deg)}))
        .collect();
    std::fs::write(
        &input,
        serde_json::json!({ "pairs": same_axis }).to_string(),
    )
    .unwrap();
    let out = brokenray(&["calibrate", "--input", input.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("motions.json") && err.contains("nearly parallel"),
        "{err}"
    );
}

#[test]
fn demo_serves_the_simulated_installation_and_records_it() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("demo.toml");
    let text = String::from_utf8(brokenray(&["default-config"]).stdout)
        .unwrap()
        .replace("listen = \"127.0.0.1:7878\"", "listen = \"127.0.0.1:0\"")
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{}\"", dir.path().join("demo.db").display()),
        )
        .replace(
            "recordings_dir = \"recordings\"",
            &format!("recordings_dir = \"{}\"", dir.path().join("rec").display()),
        );
    std::fs::write(&config, text).unwrap();
    let out = brokenray(&[
        "demo",
        "--config",
        config.to_str().unwrap(),
        "--duration",
        "6s",
    ]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("demo stopped after 150 groups (450 observations, 0 refused)"),
        "{stdout}"
    );
    let recordings: Vec<_> = std::fs::read_dir(dir.path().join("rec")).unwrap().collect();
    assert_eq!(recordings.len(), 1);
    // The reference was set after 5 s: the stored history has deformation to show.
    let db = rusqlite::Connection::open(dir.path().join("demo.db")).unwrap();
    let samples: i64 = db
        .query_row("select count(*) from samples", [], |r| r.get(0))
        .unwrap();
    assert_eq!(samples, 450);
    // The ship scenario is filtered with the oscillatory model: the hull's motion is followed,
    // not rejected (0.2 % of the observations are simulated outliers).
    assert!(
        stdout.contains("filtered with the `oscillatory` model"),
        "{stdout}"
    );
    let outliers: i64 = db
        .query_row("select count(*) from samples where outlier = 1", [], |r| {
            r.get(0)
        })
        .unwrap();
    assert!(outliers <= 5, "{outliers} of 450 samples flagged");
    let references: i64 = db
        .query_row("select count(*) from target_references", [], |r| r.get(0))
        .unwrap();
    assert_eq!(references, 1);
}

/// `hash-token` without a token makes one: 64 hex digits, different each time, printed with
/// its SHA-256 (checked against an independent hash) and the configuration block.
#[test]
fn hash_token_generates_a_fresh_token_and_its_hash() {
    use sha2::Digest as _;
    let made = |_: usize| {
        let out = brokenray(&["hash-token"]);
        assert!(out.status.success(), "{out:?}");
        let text = String::from_utf8(out.stdout).unwrap();
        let field = |name: &str| {
            text.lines()
                .find_map(|l| l.strip_prefix(name))
                .map(|v| v.trim().to_owned())
                .unwrap_or_else(|| panic!("no `{name}` in {text}"))
        };
        let (token, hash) = (field("token:"), field("sha256:"));
        assert!(
            token.len() == 64 && token.chars().all(|c| c.is_ascii_hexdigit()),
            "{token}"
        );
        assert_eq!(hash, hex::encode(sha2::Sha256::digest(token.as_bytes())));
        assert!(text.contains(&format!("sha256 = \"{hash}\"")), "{text}");
        token
    };
    let tokens: Vec<String> = (0..3).map(made).collect();
    assert!(
        tokens[0] != tokens[1] && tokens[1] != tokens[2] && tokens[0] != tokens[2],
        "{tokens:?}"
    );
}

/// The built-in installation for a service of this test on a free loopback port, its database
/// `NAME.db` in `dir`, written to `dir/NAME.toml`: the file, its text and the port.
fn service_installation(dir: &std::path::Path, name: &str) -> (std::path::PathBuf, String, u16) {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace(
            "listen = \"127.0.0.1:7878\"",
            &format!("listen = \"127.0.0.1:{port}\""),
        )
        .replace(
            "database = \"brokenray.db\"",
            &format!(
                "database = \"{}\"",
                dir.join(format!("{name}.db")).display()
            ),
        );
    let config = dir.join(format!("{name}.toml"));
    std::fs::write(&config, &text).unwrap();
    (config, text, port)
}

/// `watch`: frames written into `DIR/<camera>/` while the service is down stay there; once it is
/// up every frame is posted, stored and removed, and the refused ones (an unreadable file, an
/// unknown camera) are moved aside with the service's answer beside them.
#[test]
fn watch_posts_a_folders_frames_through_an_outage_and_sets_refusals_aside() {
    use crate::common::process;
    use brokenray::imagefile::{FrameFormat, encode};
    use brokenray::sim::render::RenderSettings;
    use brokenray::sim::{Scenario, SimSettings, Simulator};

    let dir = tempfile::tempdir().unwrap();
    let inbox = dir.path().join("inbox");
    // A free port for the service that is not up yet.
    let (config, text, port) = service_installation(dir.path(), "watch");
    let inst = brokenray::config::parse("watch.toml", &text).unwrap();

    // Three groups of the three cameras, ten seconds ago, named by their time.
    let now_ns = brokenray::clock::wall_now_ns();
    let mut sim = Simulator::new(
        &inst.model,
        SimSettings {
            scenario: Scenario::Static,
            rate_hz: 25.0,
            start_ns: now_ns - 10_000_000_000,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed: 11,
        },
    )
    .unwrap();
    let render = RenderSettings {
        samples_per_side: 8,
        ..RenderSettings::default()
    };
    for _ in 0..3 {
        let group = sim.next_group();
        for (camera, frame) in sim.render_frames(&group, &render) {
            std::fs::create_dir_all(inbox.join(&camera)).unwrap();
            let name = format!("{}.png", brokenray::clock::format_ns_fixed(group.time_ns));
            std::fs::write(
                inbox.join(&camera).join(name),
                encode(&frame, FrameFormat::Png).unwrap(),
            )
            .unwrap();
        }
    }
    let stamp = brokenray::clock::format_ns_fixed(now_ns - 5_000_000_000);
    std::fs::write(inbox.join("C1").join(format!("{stamp}.png")), b"not a png").unwrap();
    std::fs::create_dir_all(inbox.join("C7")).unwrap();
    std::fs::copy(
        std::fs::read_dir(inbox.join("C2"))
            .unwrap()
            .next()
            .unwrap()
            .unwrap()
            .path(),
        inbox.join("C7").join(format!("{stamp}.png")),
    )
    .unwrap();
    // Files that cannot be frames, beside the good ones: each set aside with its reason, the
    // others delivered all the same.
    let old = inbox.join("C2").join("old.png");
    std::fs::write(&old, b"from before 1970").unwrap();
    let touched = Command::new("touch")
        .args(["-d", "1960-01-01T00:00:00Z", old.to_str().unwrap()])
        .status()
        .unwrap();
    assert!(touched.success());
    let huge = inbox.join("C2").join("huge.png");
    // Sparse: no disk taken, and never read.
    std::fs::File::create(&huge)
        .unwrap()
        .set_len(3 << 30)
        .unwrap();
    let not_utf8 = {
        use std::os::unix::ffi::OsStrExt;
        inbox
            .join("C2")
            .join(std::ffi::OsStr::from_bytes(b"\xff\xfe.png"))
    };
    std::fs::write(&not_utf8, b"x").unwrap();
    let frame_files = |camera: &str| -> usize {
        std::fs::read_dir(inbox.join(camera))
            .map(|d| {
                d.filter_map(Result::ok)
                    .filter(|e| e.path().extension().is_some_and(|x| x == "png"))
                    .count()
            })
            .unwrap_or(0)
    };

    let mut watch = Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args([
            "watch",
            inbox.to_str().unwrap(),
            "--settle-ms",
            "0",
            "--poll-ms",
            "50",
        ])
        .args(["--to", &format!("http://127.0.0.1:{port}")])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The service is down: nothing is removed.
    std::thread::sleep(std::time::Duration::from_millis(1500));
    assert_eq!(
        frame_files("C1"),
        4,
        "nothing taken while the service is down"
    );
    assert_eq!(frame_files("C3"), 3);

    let server = process::start(
        &config,
        "warn,brokenray=info",
        false,
        std::time::Duration::from_secs(60),
    );
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while ["C1", "C2", "C3", "C7"].iter().any(|c| frame_files(c) > 0) {
        assert!(
            std::time::Instant::now() < deadline,
            "the inbox did not empty"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    watch.kill().unwrap();
    let output = watch.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(log.contains("the service cannot take frames now"), "{log}");

    // Every good frame stored: three samples a link.
    let db = rusqlite::Connection::open(dir.path().join("watch.db")).unwrap();
    let samples: i64 = db
        .query_row("select count(*) from samples", [], |r| r.get(0))
        .unwrap();
    assert_eq!(samples, 9, "{log}");
    drop(server);
    // The files that cannot be frames, each aside with why.
    let aside = inbox.join("C2").join("refused");
    for (name, says) in [
        (std::ffi::OsString::from("old.png"), "1970"),
        (
            std::ffi::OsString::from("huge.png"),
            "bytes, more than a frame",
        ),
        (not_utf8.file_name().unwrap().to_owned(), "not UTF-8"),
    ] {
        let mut error_name = name.clone();
        error_name.push(".error.json");
        let error = std::fs::read_to_string(aside.join(&error_name))
            .unwrap_or_else(|e| panic!("{name:?}: {e}\n{log}"));
        assert!(error.contains(says), "{name:?}: {error}");
        assert!(aside.join(&name).exists(), "{name:?} moved aside");
    }
    // The refusals, each with the answer naming what is wrong.
    for (camera, field) in [("C1", "body"), ("C7", "camera")] {
        let aside = inbox.join(camera).join("refused");
        let error = std::fs::read_to_string(aside.join(format!("{stamp}.png.error.json"))).unwrap();
        let error: serde_json::Value = serde_json::from_str(&error).unwrap();
        assert_eq!(error["status"], 422, "{error}");
        assert_eq!(
            error["answer"]["error"]["details"][0]["field"], field,
            "{error}"
        );
        assert!(aside.join(format!("{stamp}.png")).exists());
    }
}

/// `report`: a running service's report of the last minute written to a new file (the
/// built-in installation's targets, their pictures, the simulated run's results); a file that
/// exists is not overwritten, and the service's refusal of a query is told.
#[test]
fn report_writes_a_running_service_s_period_into_a_new_file() {
    use crate::common::process;
    let dir = tempfile::tempdir().unwrap();
    let (config, _, port) = service_installation(dir.path(), "report");
    let url = format!("http://127.0.0.1:{port}");
    let server = process::start(
        &config,
        "warn,brokenray=info",
        false,
        std::time::Duration::from_secs(60),
    );
    let run = brokenray(&[
        "simulate",
        "--duration",
        "10s",
        "--rate",
        "5",
        "--scenario",
        "static",
        "--fast",
        "--to",
        &url,
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let from = brokenray::clock::format_ns(brokenray::clock::wall_now_ns() - 60_000_000_000);
    let out = dir.path().join("minute.html");
    let args = [
        "report",
        "--service",
        &url,
        "--from",
        &from,
        "--out",
        out.to_str().unwrap(),
    ];
    let written = brokenray(&args);
    let stdout = String::from_utf8_lossy(&written.stdout);
    assert!(
        written.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&written.stderr)
    );
    assert!(
        stdout.starts_with(&format!("wrote {}", out.display())),
        "{stdout}"
    );
    let page = std::fs::read_to_string(&out).unwrap();
    assert!(page.starts_with("<!DOCTYPE html>"), "{page}");
    assert!(page.contains("<h2>Target G</h2>"), "{page}");
    assert!(page.contains("The period holds 50 raw results"), "{page}");
    assert_eq!(page.matches("<svg").count(), 6, "six pictures of G");

    // Written once: a second report to the same file is refused and the first kept.
    let again = brokenray(&args);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("exists"));
    assert_eq!(std::fs::read_to_string(&out).unwrap(), page);
    // The service's refusal is told with what it names.
    let other = dir.path().join("other.html");
    let refused = brokenray(&[
        "report",
        "--service",
        &url,
        "--min-gap-s",
        "0",
        "--out",
        other.to_str().unwrap(),
    ]);
    assert!(!refused.status.success());
    let err = String::from_utf8_lossy(&refused.stderr);
    assert!(err.contains("422") && err.contains("min_gap_s"), "{err}");
    assert!(!other.exists(), "nothing written");
    drop(server);
}

const PLATE_TOML: &str = "rows = 7\ncols = 9\nspacing_mm = 15.0\ndiameter_mm = 7.5\nasymmetric = true\npolarity = \"dark\"\n";

#[test]
fn rendered_plate_views_calibrate_a_camera_into_a_block_the_installation_takes() {
    let dir = tempfile::tempdir().unwrap();
    let plate = dir.path().join("plate.toml");
    std::fs::write(&plate, PLATE_TOML).unwrap();
    let views = dir.path().join("views");
    let out = brokenray(&[
        "render-plate",
        "--camera",
        "C1",
        "--plate",
        plate.to_str().unwrap(),
        "--views",
        "12",
        "--seed",
        "4",
        "--out",
        views.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(views.join("truth.json")).unwrap()).unwrap();
    assert_eq!(truth["views"].as_array().unwrap().len(), 12);
    // A frame without the plate is left out with the reason, not used.
    let blank = brokenray::vision::GreyImage::new(
        1280,
        1024,
        brokenray::vision::BitDepth::Eight,
        vec![200; 1280 * 1024],
    )
    .unwrap();
    let blank_file = views.join("blank.png");
    std::fs::write(
        &blank_file,
        brokenray::imagefile::encode(&blank, brokenray::imagefile::FrameFormat::Png).unwrap(),
    )
    .unwrap();
    let mut frames: Vec<String> = (0..12)
        .map(|k| {
            views
                .join(format!("view_{k:02}.png"))
                .to_str()
                .unwrap()
                .to_owned()
        })
        .collect();
    frames.push(blank_file.to_str().unwrap().to_owned());
    let block = dir.path().join("c1.toml");
    let block_report = dir.path().join("c1-report");
    let mut args = vec![
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        "--fix",
        "k3",
        "--json",
        "--camera",
        "C1",
        "--out",
        block.to_str().unwrap(),
        "--report",
        block_report.to_str().unwrap(),
    ];
    args.extend(frames.iter().map(String::as_str));
    let out = brokenray(&args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("blank.png: left out: plate not found: 0 disc(s) detected"),
        "{stderr}"
    );
    let body: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(body["views"].as_array().unwrap().len(), 12);
    for name in ["fx", "fy", "cx", "cy"] {
        let error =
            body["camera"][name].as_f64().unwrap() - truth["camera"][name].as_f64().unwrap();
        let sigma = body["sigma"][name].as_f64().unwrap();
        assert!(
            error.abs() < 4.0 * sigma,
            "{name}: {error} against sigma {sigma}"
        );
    }
    // The block replaces C1's in the built-in installation, which then validates.
    let block_text = std::fs::read_to_string(&block).unwrap();
    assert!(
        block_text.contains("[[cameras]]\nframe = \"C1\"\nwidth = 1280\nheight = 1024\n"),
        "{block_text}"
    );
    // It names the report, wherever the service runs from.
    let page = std::fs::canonicalize(block_report.join("calibration.html")).unwrap();
    assert!(
        block_text.contains(&format!(
            "\ncalibration_report = {:?}\n",
            page.display().to_string()
        )),
        "{block_text}"
    );
    let default = String::from_utf8(brokenray(&["default-config"]).stdout).unwrap();
    let start = default.find("[[cameras]]\nframe = \"C1\"").unwrap();
    let end = start + default[start..].find("\n\n").unwrap();
    let site = format!(
        "{}{}{}",
        &default[..start],
        block_text.trim_end(),
        &default[end..]
    );
    let site_file = dir.path().join("site.toml");
    std::fs::write(&site_file, site).unwrap();
    let check = brokenray(&["check-config", "--config", site_file.to_str().unwrap()]);
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stderr)
    );
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&check.stdout),
        String::from_utf8_lossy(&check.stderr)
    );
    assert!(!said.contains("calibration_report"), "{said}");
    // The text report names the parameters with their sigmas; `--report` writes the page.
    let report = dir.path().join("report");
    let mut args = vec![
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ];
    args.extend(frames[..12].iter().map(String::as_str));
    let text = String::from_utf8(brokenray(&args).stdout).unwrap();
    assert!(text.contains("report written to "), "{text}");
    let page = std::fs::read_to_string(report.join("calibration.html")).unwrap();
    for part in [
        "<h2>Intrinsics</h2>",
        "aria-label=\"residual vectors of every view over the image\"",
        "aria-label=\"coverage of the image by plate points\"",
        "aria-label=\"binned mean residual over the image\"",
        "aria-label=\"uncertainty of projection over the image (px)\"",
        "<h2>Cross-validation</h2>",
        "<h2>The plate's shape</h2>",
        "view_11.png",
    ] {
        assert!(page.contains(part), "{part} missing from the report");
    }
    // One arrow per point in the residual picture: 12 views of 63 points.
    let residuals = page
        .split("aria-label=\"residual vectors")
        .nth(1)
        .and_then(|rest| rest.split("</svg>").next())
        .unwrap();
    assert_eq!(residuals.matches("<line ").count(), 12 * 63);
    // The page is never overwritten.
    let again = brokenray(&args);
    assert!(!again.status.success());
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(stderr.contains("must not exist"), "{stderr}");
    assert!(
        text.contains("camera calibration: 12 views (0 frames left out)"),
        "{text}"
    );
    assert!(text.contains("  fx ") && text.contains(" +- "), "{text}");
    assert!(text.contains("  plate fitted "), "{text}");
    assert!(text.contains("  lens model brown\n"), "{text}");
    assert!(text.contains("  the residuals have "), "{text}");
    assert!(!text.contains("  k4 "), "{text}");
    // The rational model on this narrow lens (4800 px): where the distortion is small its
    // numerator and denominator cancel, and the weak prior holds the terms the views do not
    // determine (k1 and k4 move together, their sigmas the prior's width).
    let mut args = vec![
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        "--model",
        "rational",
        "--fix",
        "k3,k6",
    ];
    args.extend(frames[..12].iter().map(String::as_str));
    let out = brokenray(&args);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(text.contains("  lens model rational\n"), "{text}");
    assert!(text.contains("  k5 ") && text.contains("  k6 "), "{text}");
    assert!(!text.contains("  s1 "), "{text}");
    assert!(text.contains("  correlation k1 - k4: +"), "{text}");
    let mut args = vec![
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        "--model",
        "fisheye",
    ];
    args.extend(frames[..12].iter().map(String::as_str));
    let out = brokenray(&args);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("\"fisheye\" is not a lens model: one of brown, rational, rational_prism"),
        "{stderr}"
    );
    // A plate shape that is not one of the words is refused, naming them.
    let mut args = vec![
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        "--plate-shape",
        "bent",
    ];
    args.extend(frames[..12].iter().map(String::as_str));
    let out = brokenray(&args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("\"bent\" is not a plate shape: one of auto, flat, warped"),
        "{stderr}"
    );
}

#[test]
fn calibrate_camera_refuses_too_few_views_and_a_bad_plate_file() {
    let dir = tempfile::tempdir().unwrap();
    let plate = dir.path().join("plate.toml");
    std::fs::write(
        &plate,
        "rows = 7\ncols = 9\nspacing_mm = 15.0\ndiameter_mm = 7.5\nshape = \"round\"\n",
    )
    .unwrap();
    let out = brokenray(&[
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        "x.png",
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("unknown field `shape`"), "{stderr}");
    std::fs::write(&plate, PLATE_TOML).unwrap();
    let views = dir.path().join("views");
    let out = brokenray(&[
        "render-plate",
        "--camera",
        "C2",
        "--plate",
        plate.to_str().unwrap(),
        "--views",
        "2",
        "--out",
        views.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let out = brokenray(&[
        "calibrate-camera",
        "--plate",
        plate.to_str().unwrap(),
        views.join("view_00.png").to_str().unwrap(),
        views.join("view_01.png").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("2 view(s): at least 3 are needed"),
        "{stderr}"
    );
}

mod station {
    //! `render-station` then `calibrate-station`: a station's link from rendered frames of the
    //! station moved to six positions, against the installation's (true) link.

    use super::{PLATE_TOML, brokenray};
    use brokenray::geometry::Pose;
    use nalgebra::{Quaternion, Translation3, UnitQuaternion};

    fn pose_of(v: &serde_json::Value) -> Pose {
        let t: Vec<f64> = (0..3).map(|k| v["t_mm"][k].as_f64().unwrap()).collect();
        let q: Vec<f64> = (0..4).map(|k| v["q_wxyz"][k].as_f64().unwrap()).collect();
        Pose::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])),
        )
    }

    fn calibrate_and_check(link: &str, plate_cameras: &[&str]) {
        let dir = tempfile::tempdir().unwrap();
        let plate_file = dir.path().join("plate.toml");
        std::fs::write(&plate_file, PLATE_TOML).unwrap();
        let plates: Vec<String> = plate_cameras
            .iter()
            .flat_map(|c| {
                [
                    "--plate".to_owned(),
                    format!("{c}={}", plate_file.display()),
                ]
            })
            .collect();
        let session = dir.path().join("session");
        let mut args = vec![
            "render-station",
            "--link",
            link,
            "--out",
            session.to_str().unwrap(),
        ];
        args.extend(plates.iter().map(String::as_str));
        let out = brokenray(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let truth: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(session.join("truth.json")).unwrap())
                .unwrap();
        let positions: Vec<String> = (0..6)
            .map(|i| {
                session
                    .join(format!("position_{i:02}"))
                    .to_str()
                    .unwrap()
                    .to_owned()
            })
            .collect();
        let mut args = vec!["calibrate-station", "--link", link];
        args.extend(plates.iter().map(String::as_str));
        args.extend(positions.iter().map(String::as_str));
        let out = brokenray(&args);
        let stdout = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{stderr}");
        assert!(
            stdout.contains(&format!("{link}: 5 motions from 6 positions (0 left out)")),
            "{stdout}{stderr}"
        );
        let json_end = stdout.rfind("}\n").unwrap() + 1;
        let body: serde_json::Value = serde_json::from_str(&stdout[..json_end]).unwrap();
        let x = pose_of(&body["x"]);
        let cov: Vec<f64> = body["covariance"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        let cov = brokenray::geometry::Mat6::from_row_slice(&cov);
        let nees = crate::common::nees(&x, &pose_of(&truth["parent_from_child"]), &cov);
        let bound = brokenray::chain::chi_square_quantile(6, 0.999);
        assert!(nees < bound, "NEES {nees:.1} over {bound:.1}: {body}");
        // Motions of a few degrees leave X's rotation known to arc-minutes, not seconds:
        // what matters is that the sigmas say so.
        let sigma_arcsec = body["sigma"]["rotation_arcsec"][0].as_f64().unwrap();
        assert!(sigma_arcsec > 5.0 && sigma_arcsec < 600.0, "{sigma_arcsec}");
    }

    #[test]
    fn two_cameras_back_to_back_each_looking_at_a_plate() {
        calibrate_and_check("C2_from_C1", &["C1", "C2"]);
    }

    #[test]
    fn a_camera_looking_at_a_plate_and_a_marker_seen_by_the_installation() {
        calibrate_and_check("C3_from_M", &["C3"]);
    }

    #[test]
    fn a_camera_without_its_plate_or_a_measured_link_is_refused() {
        let out = brokenray(&["calibrate-station", "--link", "C2_from_C1", "x"]);
        assert!(!out.status.success());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains("camera C2 of the station needs its plate: --plate C2=PLATE.toml"),
            "{stderr}"
        );
        let out = brokenray(&["calibrate-station", "--link", "C1_from_B", "x"]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains("`C1_from_B` is a measured link"),
            "{stderr}"
        );
    }
}

/// `acceptance --simulate`: the simulator as rig and operator against a real `serve`: the
/// guide says each step, the record is printed and it passes (exit 0); against a rig whose
/// C3 has a focal length 1 % longer than the service's, it fails naming the move along C3's
/// line of sight (exit 1).
#[test]
fn acceptance_guides_the_simulated_operator_and_fails_a_rig_with_a_wrong_focal_length() {
    use crate::common::process;
    let dir = tempfile::tempdir().unwrap();
    for (name, world, passes) in [
        ("good", None, true),
        ("wrong", Some("fx = 5423.7\nfy = 5423.7"), false),
    ] {
        let (config, text, port) = service_installation(dir.path(), name);
        let url = format!("http://127.0.0.1:{port}");
        let server = process::start(
            &config,
            "warn,brokenray=info",
            false,
            std::time::Duration::from_secs(60),
        );
        let mut args = vec![
            "acceptance".to_owned(),
            "--simulate".into(),
            "--fast".into(),
            "--service".into(),
            url.clone(),
            "--by".into(),
            "Ada".into(),
            "--certificate".into(),
            dir.path()
                .join(format!("{name}.html"))
                .display()
                .to_string(),
        ];
        if let Some(focal) = world {
            let world_file = dir.path().join(format!("{name}-world.toml"));
            let wrong = text.replacen("fx = 5370.0\nfy = 5370.0", focal, 1);
            assert_ne!(wrong, text);
            std::fs::write(&world_file, wrong).unwrap();
            args.extend(["--config".into(), world_file.display().to_string()]);
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let run = brokenray(&args);
        let stdout = String::from_utf8_lossy(&run.stdout);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.success(), passes, "{stdout}{stderr}");
        assert!(
            stdout.contains("step 1/6 `still`: keep every target still"),
            "{stdout}"
        );
        assert!(
            stdout.contains("step 4/6 `z +100 mm`: move target G"),
            "{stdout}"
        );
        assert!(stdout.contains("settling, then measuring"), "{stdout}");
        let certificate = std::fs::read_to_string(dir.path().join(format!("{name}.html"))).unwrap();
        assert!(certificate.starts_with("<!DOCTYPE html>"), "{certificate}");
        assert!(
            certificate.contains("<h1>Acceptance certificate 1</h1>"),
            "{certificate}"
        );
        assert!(
            certificate.contains("Accepted for the owner by"),
            "{certificate}"
        );
        assert_eq!(
            certificate
                .matches("<td class=\"l\">z +100 mm</td>")
                .count(),
            1
        );
        if passes {
            assert!(
                stdout.contains("acceptance 1 PASSED; reverify by"),
                "{stdout}"
            );
        } else {
            assert!(
                stdout.contains("acceptance 1 FAILED: ") && stdout.contains("z +100 mm"),
                "{stdout}"
            );
            assert!(stdout.contains("FAIL  z +100 mm"), "{stdout}");
            assert!(stderr.contains("the acceptance failed"), "{stderr}");
        }
        drop(server);
    }
}
