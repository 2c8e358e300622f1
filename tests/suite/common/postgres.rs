//! A throwaway PostgreSQL cluster for tests and benchmarks: `initdb` in a temporary folder,
//! a server on a free loopback port, one fresh database per caller. Started once per process
//! on first use; a watchdog stops it and removes its folder when the process ends, however it
//! ends (a failed test, a SIGKILL). Never uses a server someone left running.
//!
//! PostgreSQL refuses to run as root: as root, the server's programs run as the `postgres`
//! user (`runuser`). The binaries are PostgreSQL 15's as Debian installs them, or those in
//! `BROKENRAY_PG_BIN`; `BROKENRAY_PG_SETTINGS` adds server settings. Shared by `tests/suite` and the benchmarks (included there by path).

#![allow(dead_code, reason = "each includer uses part of it")]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A running throwaway cluster.
pub struct Cluster {
    /// Its port on 127.0.0.1.
    pub port: u16,
    /// The temporary folder: data directory, socket, log.
    pub dir: PathBuf,
    bin: PathBuf,
    as_postgres: bool,
}

static CLUSTER: OnceLock<Cluster> = OnceLock::new();
static DATABASES: AtomicUsize = AtomicUsize::new(0);

/// The process's cluster, started on first use.
pub fn cluster() -> &'static Cluster {
    CLUSTER.get_or_init(Cluster::start_new)
}

/// The URL of a new, empty database in the process's cluster.
pub fn fresh_database() -> String {
    cluster().create_database()
}

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

impl Cluster {
    /// A cluster of the caller's own (for a test that stops and starts its server), stopped
    /// when the process ends.
    pub fn own() -> Cluster {
        Self::start_new()
    }

    fn start_new() -> Cluster {
        // As `common::pg_bin` (this file is also compiled into benches without `common`).
        let bin = std::env::var_os("BROKENRAY_PG_BIN")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("/usr/lib/postgresql/15/bin"));
        assert!(
            bin.join("initdb").exists(),
            "PostgreSQL 15 is not installed (no {}): `scripts/test` installs it \
             (apt-get install postgresql postgresql-15-partman)",
            bin.join("initdb").display()
        );
        let as_postgres = is_root();
        let dir = tempfile::Builder::new()
            .prefix("brokenray-pg-")
            .tempdir()
            .expect("temp dir")
            .keep();
        if as_postgres {
            let ok = Command::new("chown")
                .args(["postgres:postgres", dir.to_str().expect("utf-8")])
                .status()
                .expect("chown")
                .success();
            assert!(ok, "chown of the cluster folder to postgres");
        }
        let port = {
            let l = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port");
            l.local_addr().expect("address").port()
        };
        let cluster = Cluster {
            port,
            dir,
            bin,
            as_postgres,
        };
        let data = cluster.data();
        cluster.run(
            "initdb",
            &[
                "-D",
                &data,
                "-U",
                "brokenray",
                "--auth=trust",
                "-E",
                "UTF8",
                "--no-sync",
            ],
        );
        cluster.start();
        cluster.watch(std::process::id());
        cluster
    }

    fn data(&self) -> String {
        self.dir.join("data").to_string_lossy().into_owned()
    }

    /// Runs one of the server's programs (as `postgres` when this process is root); panics
    /// with its output when it fails.
    fn run(&self, program: &str, args: &[&str]) {
        let exe = self.bin.join(program);
        let mut command = if self.as_postgres {
            let mut c = Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(&exe);
            c
        } else {
            Command::new(&exe)
        };
        let out = command
            .args(args)
            .stdin(Stdio::null())
            .output()
            .unwrap_or_else(|e| panic!("{program} does not run: {e}"));
        assert!(
            out.status.success(),
            "{program} {args:?} failed: {}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }

    /// Starts the server (also after [`Cluster::stop`]), waiting until it accepts connections.
    pub fn start(&self) {
        // `BROKENRAY_PG_SETTINGS` adds server settings, e.g. `-c log_min_duration_statement=5`
        // to see slow statements in the cluster's log.
        let options = format!(
            "-c listen_addresses=127.0.0.1 -p {} -c unix_socket_directories={} {}",
            self.port,
            self.dir.display(),
            std::env::var("BROKENRAY_PG_SETTINGS").unwrap_or_default()
        );
        let log = self.dir.join("server.log").to_string_lossy().into_owned();
        self.run(
            "pg_ctl",
            &[
                "-w",
                "-D",
                &self.data(),
                "-l",
                &log,
                "-o",
                &options,
                "start",
            ],
        );
    }

    /// Stops the server: `fast` rolls back open transactions and shuts down cleanly,
    /// `immediate` is a crash (the server recovers from its log when started again).
    pub fn stop(&self, mode: &str) {
        self.run("pg_ctl", &["-w", "-D", &self.data(), "-m", mode, "stop"]);
    }

    /// A detached watchdog: when process `pid` is gone, stops the server and removes the
    /// folder.
    fn watch(&self, pid: u32) {
        let pg_ctl = self.bin.join("pg_ctl");
        let stop = if self.as_postgres {
            format!(
                "runuser -u postgres -- {} -D {} -m immediate stop",
                pg_ctl.display(),
                self.data()
            )
        } else {
            format!("{} -D {} -m immediate stop", pg_ctl.display(), self.data())
        };
        let script = format!(
            "while kill -0 {pid} 2>/dev/null; do sleep 1; done; {stop} >/dev/null 2>&1; rm -rf {}",
            self.dir.display()
        );
        // Deliberately not waited for: it outlives this process.
        #[allow(clippy::zombie_processes, reason = "the watchdog outlives the process")]
        Command::new("sh")
            .args(["-c", &script])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("the cluster's watchdog");
    }

    /// The URL of database `name` as the cluster's superuser.
    pub fn url(&self, name: &str) -> String {
        format!("postgres://brokenray@127.0.0.1:{}/{name}", self.port)
    }

    /// Runs SQL on database `name` through `psql` (stops at the first error).
    pub fn psql(&self, name: &str, sql: &str) -> String {
        let out = Command::new(self.bin.join("psql"))
            .args(["-X", "-q", "-A", "-t", "-v", "ON_ERROR_STOP=1", "-d"])
            .arg(self.url(name))
            .args(["-c", sql])
            .stdin(Stdio::null())
            .output()
            .expect("psql runs");
        assert!(
            out.status.success(),
            "psql {sql:?} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).trim().to_owned()
    }

    /// A new, empty database; returns its URL.
    pub fn create_database(&self) -> String {
        let name = format!(
            "t{}_{}",
            std::process::id(),
            DATABASES.fetch_add(1, Ordering::Relaxed)
        );
        self.psql("postgres", &format!("create database {name}"));
        self.url(&name)
    }

    /// The server's log so far (for a failing test's message).
    pub fn log(&self) -> String {
        std::fs::read_to_string(Path::new(&self.dir).join("server.log")).unwrap_or_default()
    }
}
