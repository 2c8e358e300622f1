//! The release or test binary as a separate process, for tests and benchmarks that need a real
//! process (SIGKILL, SIGTERM, its memory). Shared by `tests/suite` and `benches/robustness.rs`
//! (included there by path).

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// A running `brokenray serve`; killed when dropped.
pub struct Server {
    /// The process.
    pub child: Child,
    /// `http://ADDR`, where it said it listens.
    pub base: String,
}

impl Server {
    /// SIGKILL, and wait for the process to be gone.
    pub fn kill(mut self) {
        self.child.kill().expect("SIGKILL");
        self.child.wait().expect("the killed process");
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        // Already gone after `kill` or a wait; otherwise the test or bench ended early.
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts `brokenray serve --config CONFIG` with `RUST_LOG=rust_log` and waits (at most
/// `wait`) for the line that says where it listens. With `echo`, its log is copied to standard
/// error, prefixed `server:`.
pub fn start(config: &std::path::Path, rust_log: &str, echo: bool, wait: Duration) -> Server {
    let mut child = Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(["serve", "--config", config.to_str().expect("utf-8 path")])
        .env("RUST_LOG", rust_log)
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("the binary starts");
    let stderr = child.stderr.take().expect("piped stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut sent = false;
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if echo {
                eprintln!("server: {line}");
            }
            if !sent && let Some(rest) = line.split("serving on http://").nth(1) {
                let addr = rest.split('/').next().unwrap_or(rest).to_owned();
                let _ = tx.send(addr);
                sent = true;
            }
        }
    });
    let addr = rx
        .recv_timeout(wait)
        .expect("the server says where it listens");
    Server {
        child,
        base: format!("http://{addr}"),
    }
}
