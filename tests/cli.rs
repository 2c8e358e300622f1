//! The `brokenray` binary, run as a user runs it.

use std::process::Command;

fn brokenray(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(args)
        .output()
        .expect("the binary runs")
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
            "serve",
            "backup",
            "replay",
            "healthcheck",
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
        std::path::Path::new("/var/lib/brokenray/brokenray.db")
    );
    let topology = |t: &str| t[t.find("[[cameras]]").expect("cameras")..].to_owned();
    assert_eq!(
        topology(&text),
        topology(brokenray::config::DEFAULT_INSTALLATION_TOML),
        "docker/installation.toml's topology drifted from src/config/default.toml"
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
