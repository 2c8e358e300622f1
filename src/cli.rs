//! The command line: subcommands and their output. `main.rs` only parses and dispatches here.

use crate::chain::Direction;
use crate::clock::wall_now_ns as now_ns;
use crate::config::{self, Installation};
use crate::geometry::{euler_from_rotation, quaternion_wxyz};
use crate::model::LinkKind;
use anyhow::Context as _;
use clap::{Parser, Subcommand};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;

/// Broken-ray videometrics: deformation of large structures measured through relay stations.
#[derive(Debug, Parser)]
#[command(name = "brokenray", version, about, long_about = None)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Validate an installation file and print its topology: frames, links, and each target's
    /// resolved path(s).
    CheckConfig {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// Print the built-in installation file, a starting point for your own.
    DefaultConfig,
    /// Run the service: HTTP API on the configured address, SQLite history, filtering.
    Serve {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// Write an online, consistent copy of the database (safe while `serve` runs).
    Backup {
        /// The installation file whose database to copy; the built-in one without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Where to write the copy (must not exist).
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
    },
    /// Rebuild a Rerun recording (.rrd) of a stored period, for review in the Rerun viewer:
    /// every stored result, sample and alarm transition of the period.
    Replay {
        /// The installation file whose database to read; the built-in one without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Start of the period (RFC 3339 or integer ns).
        #[arg(long, value_name = "TIME")]
        from: String,
        /// End of the period (RFC 3339 or integer ns).
        #[arg(long, value_name = "TIME")]
        to: String,
        /// One target only (all without it).
        #[arg(long, value_name = "NAME")]
        target: Option<String>,
        /// The recording to write (must not exist).
        #[arg(long, value_name = "FILE.rrd")]
        out: PathBuf,
    },
    /// Ask a running service's `/healthz` (exit status 0 when it answers 200): the container
    /// health check, which has no HTTP client to call.
    Healthcheck {
        /// The installation file whose `server.listen` to ask; the built-in one without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Give up after this many seconds.
        #[arg(long, value_name = "SECONDS", default_value_t = 5.0)]
        timeout_s: f64,
    },
    /// Generate a scenario (static, drift, ship, tunnel, bump) on an installation: what its
    /// cameras see, posted to a running service (`--to`) or written as NDJSON (`--out`), with
    /// the ground truth (`--truth`).
    Simulate {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// How long a run to generate (60s, 15m, 2h, 1d).
        #[arg(long, value_name = "DURATION", default_value = "60s")]
        duration: String,
        /// Groups (trigger times) per second.
        #[arg(long, value_name = "HZ", default_value_t = 25.0)]
        rate: f64,
        /// static, drift, ship, tunnel or bump.
        #[arg(long, value_name = "NAME", default_value = "ship")]
        scenario: String,
        /// Raw observations (the service runs PnP) or link poses solved here.
        #[arg(long, value_enum, default_value_t = crate::feed::Emit::Observations)]
        emit: crate::feed::Emit,
        /// Pixel noise (px); each camera's `pixel_sigma` without it.
        #[arg(long, value_name = "PX")]
        pixel_sigma: Option<f64>,
        /// Probability that an observation is an outlier (shifted 2 to 5 px).
        #[arg(long, value_name = "P", default_value_t = 0.0)]
        outliers: f64,
        /// Seed of the noise and motion.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Time of the first group (RFC 3339 or integer ns); now without it.
        #[arg(long, value_name = "TIME")]
        start: Option<String>,
        /// A running service to post to (`http://127.0.0.1:7878`), in real time unless `--fast`.
        #[arg(
            long,
            value_name = "URL",
            conflicts_with = "out",
            required_unless_present = "out"
        )]
        to: Option<String>,
        /// Write NDJSON here instead (one observation or sample a line).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
        /// Write the ground truth here (NDJSON, one group a line).
        #[arg(long, value_name = "FILE")]
        truth: Option<PathBuf>,
        /// Post as fast as the service takes it, not in real time.
        #[arg(long)]
        fast: bool,
        /// Bearer token with the `ingest` scope.
        #[arg(long, env = "BROKENRAY_TOKEN", hide_env_values = true)]
        token: Option<String>,
    },
    /// Calibrate a rigid station (hand-eye, `A_i X = X B_i`) from a JSON file of motions
    /// (`{"pairs": [{"a": pose, "b": pose}, ...]}`, as `POST /api/v1/calibration/hand-eye`
    /// takes); prints X with its residuals.
    Calibrate {
        /// The motions (JSON).
        #[arg(long, value_name = "FILE")]
        input: PathBuf,
        /// Write the result here (JSON) as well as printing it.
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
    /// A first look: the service on the built-in installation (or `--config`), fed live by the
    /// simulator (ship flexure, observations through PnP), with a reference set after 5 s and a
    /// Rerun recording. Stop with Ctrl-C.
    Demo {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// static, drift, ship, tunnel or bump.
        #[arg(long, value_name = "NAME", default_value = "ship")]
        scenario: String,
        /// Groups per second.
        #[arg(long, value_name = "HZ", default_value_t = 25.0)]
        rate: f64,
        /// Stop by itself after this long (60s, 15m, ...); runs until Ctrl-C without it.
        #[arg(long, value_name = "DURATION")]
        duration: Option<String>,
    },
    /// Print a new random bearer token and the SHA-256 to put in `[[auth.tokens]]`.
    HashToken {
        /// Hash this token instead of making a new one.
        #[arg(long, value_name = "TOKEN")]
        token: Option<String>,
    },
}

/// Runs a parsed command line, writing its report to `out`.
pub fn run(cli: Cli, out: &mut impl std::io::Write) -> anyhow::Result<()> {
    match cli.command {
        Command::CheckConfig { config } => {
            let installation = config::load_or_default(config.as_deref())?;
            out.write_all(describe_installation(&installation).as_bytes())?;
        }
        Command::DefaultConfig => out.write_all(config::DEFAULT_INSTALLATION_TOML.as_bytes())?,
        Command::Serve { config } => {
            let installation = config::load_or_default(config.as_deref())?;
            let runtime = runtime(true)?;
            runtime.block_on(serve(installation))?;
        }
        Command::Backup {
            config,
            out: out_file,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let database = installation.server.database.clone();
            writeln!(
                out,
                "backing up {} to {} ...",
                database.display(),
                out_file.display()
            )?;
            out.flush()?;
            let runtime = runtime(false)?;
            let started = std::time::Instant::now();
            let bytes = runtime
                .block_on(crate::store::backup(&database, &out_file))
                .with_context(|| format!("backup of {} failed", database.display()))?;
            writeln!(
                out,
                "done: {} ({:.1} MB) in {:.1} s, a consistent copy",
                out_file.display(),
                bytes as f64 / 1e6,
                started.elapsed().as_secs_f64()
            )?;
        }
        Command::Replay {
            config,
            from,
            to,
            target,
            out: out_file,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let summary = replay(installation, &from, &to, target.as_deref(), &out_file)?;
            writeln!(
                out,
                "wrote {}: {} filtered and {} raw results, {} samples, {} alarm transitions",
                out_file.display(),
                summary.filtered,
                summary.raw,
                summary.samples,
                summary.alarms
            )?;
        }
        Command::Healthcheck { config, timeout_s } => {
            let installation = config::load_or_default(config.as_deref())?;
            let answer = healthcheck(installation.server.listen, timeout_s)?;
            writeln!(out, "{answer}")?;
        }
        Command::Simulate {
            config,
            duration,
            rate,
            scenario,
            emit,
            pixel_sigma,
            outliers,
            seed,
            start,
            to,
            out: out_file,
            truth,
            fast,
            token,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let duration_s =
                crate::feed::parse_duration_s(&duration).map_err(anyhow::Error::msg)?;
            let start_ns = match &start {
                Some(t) => crate::clock::parse_query_time(t)
                    .map_err(|e| anyhow::anyhow!("--start: {e}"))?,
                None => now_ns(),
            };
            let settings = crate::sim::SimSettings {
                scenario: scenario.parse().map_err(anyhow::Error::msg)?,
                rate_hz: rate,
                start_ns,
                duration_s: Some(duration_s),
                pixel_sigma_px: pixel_sigma,
                outlier_rate: outliers,
                seed,
            };
            let groups = (duration_s * rate).round() as u64;
            let sink = match (&to, &out_file) {
                (Some(url), _) => crate::feed::Sink::Http(crate::feed::Client::new(url, token)?),
                (None, Some(path)) => {
                    crate::feed::Sink::File(std::io::BufWriter::new(create_new(path)?))
                }
                (None, None) => anyhow::bail!("give --to URL or --out FILE"),
            };
            let truth_file = truth
                .as_deref()
                .map(|p| create_new(p).map(std::io::BufWriter::new))
                .transpose()?;
            let real_time = to.is_some() && !fast;
            let runtime = runtime(true)?;
            let summary = runtime.block_on(simulate(
                &installation,
                settings,
                sink,
                truth_file,
                crate::feed::FeedSettings {
                    rate_hz: rate,
                    progress: progress_bar(Some(groups)),
                    emit,
                    groups: Some(groups),
                    real_time,
                    groups_per_request: 40,
                },
            ))?;
            let target = to.clone().unwrap_or_else(|| {
                out_file
                    .as_ref()
                    .map(|p| p.display().to_string())
                    .unwrap_or_default()
            });
            writeln!(
                out,
                "{} groups ({:.0} s at {rate} Hz, scenario {scenario}): {} {} sent to {target}, {} refused",
                summary.groups,
                duration_s,
                summary.items,
                match emit {
                    crate::feed::Emit::Observations => "observations",
                    crate::feed::Emit::Samples => "samples",
                },
                summary.refused
            )?;
        }
        Command::Calibrate {
            input,
            out: out_file,
        } => {
            let text = std::fs::read(&input)
                .with_context(|| format!("cannot read {}", input.display()))?;
            let request: crate::api::vision::HandEyeIn = crate::api::parse_json_body(&text)
                .map_err(|e| anyhow::anyhow!("{}: {}", input.display(), e.describe()))?;
            let result = request
                .solve()
                .map_err(|e| anyhow::anyhow!("{}: {}", input.display(), e.describe()))?;
            let text = serde_json::to_string_pretty(&result)?;
            if let Some(path) = &out_file {
                std::fs::write(path, &text)
                    .with_context(|| format!("cannot write {}", path.display()))?;
            }
            writeln!(out, "{text}")?;
        }
        Command::Demo {
            config,
            scenario,
            rate,
            duration,
        } => {
            let mut installation = config::load_or_default(config.as_deref())?;
            if !installation.rerun.enabled() {
                installation.rerun.save = true;
            }
            let scenario: crate::sim::Scenario = scenario.parse().map_err(anyhow::Error::msg)?;
            let model = filter_model_for(scenario);
            for spec in &mut Arc::make_mut(&mut installation.model).links {
                if let LinkKind::Measured(m) = &mut spec.kind
                    && m.tuning.model != model
                {
                    m.tuning = crate::filter::FilterTuning {
                        gate_probability: m.tuning.gate_probability,
                        reinit_after_outliers: m.tuning.reinit_after_outliers,
                        ..crate::filter::FilterTuning::default_for(model)
                    };
                }
            }
            writeln!(
                out,
                "measured links filtered with the `{}` model, the one the {scenario:?} scenario calls for",
                model.name()
            )?;
            let duration_s = duration
                .as_deref()
                .map(crate::feed::parse_duration_s)
                .transpose()
                .map_err(anyhow::Error::msg)?;
            let settings = crate::sim::SimSettings {
                scenario,
                rate_hz: rate,
                start_ns: now_ns(),
                duration_s,
                pixel_sigma_px: None,
                outlier_rate: 0.002,
                seed: 1,
            };
            let runtime = runtime(true)?;
            runtime.block_on(demo(installation, settings, out))?;
        }
        Command::HashToken { token } => {
            let token = match token {
                Some(t) => t,
                None => random_token()?,
            };
            writeln!(out, "token:  {token}")?;
            writeln!(out, "sha256: {}", crate::api::auth::sha256_hex(&token))?;
            writeln!(
                out,
                "\nAdd to the configuration (give the token itself only to its holder):\n\n[[auth.tokens]]\nname = \"...\"\nsha256 = \"{}\"\nscopes = [\"read\"]",
                crate::api::auth::sha256_hex(&token)
            )?;
        }
    }
    Ok(())
}

/// `brokenray replay`: checks the arguments, then writes the recording with a progress bar
/// (on standard error).
fn replay(
    installation: Installation,
    from: &str,
    to: &str,
    target: Option<&str>,
    out_file: &std::path::Path,
) -> anyhow::Result<crate::viz::replay::ReplaySummary> {
    let time = |name: &str, text: &str| {
        crate::clock::parse_query_time(text).map_err(|e| anyhow::anyhow!("--{name}: {e}"))
    };
    let (from_ns, to_ns) = (time("from", from)?, time("to", to)?);
    anyhow::ensure!(from_ns <= to_ns, "--to is before --from");
    let targets = match target {
        None => Vec::new(),
        Some(name) => vec![
            installation
                .model
                .targets
                .iter()
                .position(|t| t.name == name)
                .ok_or_else(|| anyhow::anyhow!("--target: unknown target `{name}`"))?,
        ],
    };
    anyhow::ensure!(
        !out_file.exists(),
        "{} already exists; choose another --out",
        out_file.display()
    );
    let database = installation.server.database.clone();
    anyhow::ensure!(
        database.exists(),
        "no database at {}: nothing was stored yet (see `server.database`)",
        database.display()
    );
    let installation = std::sync::Arc::new(installation);
    let runtime = runtime(false)?;
    runtime.block_on(async {
        let (store, write) = crate::store::open(&installation, now_ns())
            .await
            .with_context(|| format!("cannot open {}", database.display()))?;
        drop(write);
        let bar = indicatif::ProgressBar::new(0).with_style(
            indicatif::ProgressStyle::with_template(
                "{msg} [{bar:40}] {pos}/{len} rows ({eta} left)",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        bar.set_message("replaying");
        let summary = crate::viz::replay::replay(
            &installation,
            &store,
            &targets,
            from_ns,
            to_ns,
            out_file,
            &mut |done, total| {
                bar.set_length(total);
                bar.set_position(done);
            },
        )
        .await;
        bar.finish_and_clear();
        store.close().await;
        summary.with_context(|| format!("replay to {} failed", out_file.display()))
    })
}

/// Asks `GET /healthz` of the service listening on `listen` (an unspecified address is asked
/// on loopback) and returns the answer's body when the status is 200.
///
/// One plain HTTP/1.1 request over a std `TcpStream`: the answer is tiny and local, and an HTTP
/// client crate would add a second TLS-capable stack to the binary for this alone.
pub fn healthcheck(listen: std::net::SocketAddr, timeout_s: f64) -> anyhow::Result<String> {
    use std::io::{Read as _, Write as _};
    anyhow::ensure!(
        timeout_s.is_finite() && timeout_s > 0.0,
        "--timeout-s must be a positive number of seconds"
    );
    let timeout = std::time::Duration::from_secs_f64(timeout_s);
    let mut addr = listen;
    if addr.ip().is_unspecified() {
        addr.set_ip(if addr.is_ipv4() {
            std::net::Ipv4Addr::LOCALHOST.into()
        } else {
            std::net::Ipv6Addr::LOCALHOST.into()
        });
    }
    let mut stream = std::net::TcpStream::connect_timeout(&addr, timeout)
        .with_context(|| format!("nothing answers on {addr}"))?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    write!(
        stream,
        "GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = String::new();
    stream
        .read_to_string(&mut response)
        .with_context(|| format!("no complete answer from {addr}"))?;
    let status_line = response.lines().next().unwrap_or_default();
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.trim())
        .unwrap_or_default();
    anyhow::ensure!(
        status_line.split_whitespace().nth(1) == Some("200"),
        "unhealthy: {status_line}: {body}"
    );
    Ok(body.to_owned())
}

/// 32 random bytes from the operating system, as hex.
/// The filter model a scenario's motion calls for: hull flexure oscillates, drift and creep
/// move steadily, the rest stands still.
fn filter_model_for(scenario: crate::sim::Scenario) -> crate::filter::MotionModel {
    use crate::filter::MotionModel;
    use crate::sim::Scenario;
    match scenario {
        Scenario::Ship => MotionModel::Oscillatory,
        Scenario::Drift | Scenario::Tunnel => MotionModel::ConstantVelocity,
        Scenario::Static | Scenario::Bump => MotionModel::Static,
    }
}

/// The async runtime of a subcommand: all cores for the service, one thread for a tool.
fn runtime(multi_thread: bool) -> anyhow::Result<tokio::runtime::Runtime> {
    let mut builder = if multi_thread {
        tokio::runtime::Builder::new_multi_thread()
    } else {
        tokio::runtime::Builder::new_current_thread()
    };
    builder
        .enable_all()
        .build()
        .context("cannot start the async runtime")
}

fn create_new(path: &std::path::Path) -> anyhow::Result<std::fs::File> {
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .with_context(|| format!("cannot create {} (it must not exist)", path.display()))
}

fn progress_bar(groups: Option<u64>) -> indicatif::ProgressBar {
    match groups {
        Some(n) => indicatif::ProgressBar::new(n).with_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {pos}/{len} groups ({per_sec}, eta {eta})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        ),
        None => indicatif::ProgressBar::new_spinner().with_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} {elapsed_precise} {pos} groups sent ({per_sec})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
        ),
    }
}

/// `brokenray simulate`.
async fn simulate(
    installation: &Installation,
    settings: crate::sim::SimSettings,
    sink: crate::feed::Sink,
    truth: Option<std::io::BufWriter<std::fs::File>>,
    feed: crate::feed::FeedSettings,
) -> anyhow::Result<crate::feed::FeedSummary> {
    let mut sim = crate::sim::Simulator::new(&installation.model, settings)?;
    let stop = Box::pin(async {
        let _ = tokio::signal::ctrl_c().await;
    });
    crate::feed::feed(&mut sim, sink, truth, feed, stop, async |_, _| Ok(())).await
}

/// `brokenray demo`: the service and the simulator in one process, talking HTTP.
async fn demo(
    installation: Installation,
    settings: crate::sim::SimSettings,
    out: &mut impl std::io::Write,
) -> anyhow::Result<()> {
    let targets: Vec<String> = installation
        .model
        .targets
        .iter()
        .map(|t| t.name.clone())
        .collect();
    let recordings = installation.rerun.recordings_dir.clone();
    let database = installation.server.database.clone();
    let mut sim = crate::sim::Simulator::new(&installation.model, settings)?;
    let app = crate::api::App::build(installation).await?;
    let addr = app.local_addr()?;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut server_stop = stop_rx.clone();
    let server = tokio::spawn(app.run_until(async move {
        let _ = server_stop.wait_for(|s| *s).await;
    }));
    writeln!(
        out,
        "brokenray demo: dashboard http://{addr}/\n  API http://{addr}/api/v1 (described at /api/v1/openapi.json)\n  database {}, Rerun recordings in {}/\n  scenario {:?} at {} Hz; the reference is set after 5 s; Ctrl-C stops",
        database.display(),
        recordings.display(),
        settings.scenario,
        settings.rate_hz
    )?;
    out.flush()?;
    let client = crate::feed::Client::new(&format!("http://{addr}"), None)?;
    let groups = settings
        .duration_s
        .map(|d| (d * settings.rate_hz).round() as u64);
    let mut feed_stop = stop_rx.clone();
    let stop = Box::pin(async move {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => {}
            _ = feed_stop.wait_for(|s| *s) => {}
        }
    });
    let reference_at = settings.start_ns + 5_000_000_000;
    let mut reference_set = false;
    let result = crate::feed::feed(
        &mut sim,
        crate::feed::Sink::Http(client),
        None,
        crate::feed::FeedSettings {
            rate_hz: settings.rate_hz,
            progress: progress_bar(groups),
            emit: crate::feed::Emit::Observations,
            groups,
            real_time: true,
            groups_per_request: 1,
        },
        stop,
        async |group, sink| {
            if !reference_set && group.time_ns >= reference_at {
                if let crate::feed::Sink::Http(c) = sink {
                    for t in &targets {
                        let body = serde_json::json!({
                            "from": crate::clock::format_ns(settings.start_ns + 1_000_000_000),
                            "to": crate::clock::format_ns(group.time_ns),
                        });
                        c.post(&format!("/api/v1/targets/{t}/reference"), &body)
                            .await?;
                    }
                }
                reference_set = true;
            }
            Ok(())
        },
    )
    .await;
    let _ = stop_tx.send(true);
    server.await.context("the server task failed")??;
    let summary = result?;
    writeln!(
        out,
        "demo stopped after {} groups ({} observations, {} refused); every acknowledged write is on disk",
        summary.groups, summary.items, summary.refused
    )?;
    Ok(())
}

/// 256 random bits as hex, from the thread's generator (a cryptographically secure generator
/// seeded by the operating system), on any platform.
fn random_token() -> anyhow::Result<String> {
    Ok(hex::encode(rand::random::<[u8; 32]>()))
}

async fn serve(installation: Installation) -> anyhow::Result<()> {
    let source = installation.source.clone();
    let database = installation.server.database.clone();
    let targets: Vec<String> = installation
        .model
        .targets
        .iter()
        .map(|t| t.name.clone())
        .collect();
    let n_links = installation.model.links.len();
    let app = crate::api::App::build(installation).await?;
    let addr = app.local_addr()?;
    tracing::info!(
        listen = %addr,
        database = %database.display(),
        installation = %source,
        links = n_links,
        targets = ?targets,
        "brokenray serving on http://{addr}/api/v1, dashboard http://{addr}/"
    );
    app.run_until(crate::api::shutdown_signal()).await?;
    tracing::info!("stopped: every acknowledged write is on disk");
    Ok(())
}

fn fmt3(v: [f64; 3], decimals: usize) -> String {
    let parts: Vec<String> = v.iter().map(|x| format!("{x:.decimals$}")).collect();
    format!("[{}]", parts.join(", "))
}

/// A human-readable report of a validated installation.
pub fn describe_installation(inst: &Installation) -> String {
    let mut s = String::new();
    let topo = &inst.model.topology;
    let _ = writeln!(s, "installation: {} (valid)", inst.source);
    let _ = writeln!(
        s,
        "frames ({}): {}",
        topo.frames().len(),
        topo.frames().join(", ")
    );
    let _ = writeln!(s, "cameras ({}):", inst.model.cameras.len());
    for c in &inst.model.cameras {
        let _ = writeln!(
            s,
            "  {:<6} {}x{} px, fx {} fy {} px, pixel sigma {} px",
            c.frame,
            c.intrinsics.width_px,
            c.intrinsics.height_px,
            c.intrinsics.fx_px,
            c.intrinsics.fy_px,
            c.pixel_sigma_px
        );
    }
    let _ = writeln!(s, "markers ({}):", inst.model.markers.len());
    for m in &inst.model.markers {
        let _ = writeln!(s, "  {:<6} {} points", m.frame, m.points_mm.len());
    }
    let _ = writeln!(s, "links ({}):", inst.model.links.len());
    for l in &inst.model.links {
        match &l.kind {
            LinkKind::Calibrated { parent_from_child } => {
                let sig = parent_from_child.reported_sigmas();
                let _ = writeln!(
                    s,
                    "  {:<14} calibrated  t_mm {} euler_deg {} sigma {} arcsec {} mm",
                    l.name,
                    fmt3(parent_from_child.pose.translation.vector.into(), 1),
                    fmt3(
                        euler_from_rotation(&parent_from_child.pose.rotation).to_degrees(),
                        4
                    ),
                    fmt3(sig.rotation_arcsec, 1),
                    fmt3(sig.translation_mm, 3),
                );
            }
            LinkKind::Measured(m) => {
                let _ = writeln!(
                    s,
                    "  {:<14} measured    model {} at {} Hz, default sigma {} arcsec {} mm",
                    l.name,
                    m.tuning.model.name(),
                    m.expected_rate_hz,
                    fmt3(m.default_sigmas.rotation_arcsec, 1),
                    fmt3(m.default_sigmas.translation_mm, 3),
                );
            }
        }
    }
    let _ = writeln!(s, "targets ({}):", inst.model.targets.len());
    for t in &inst.model.targets {
        let r = &t.resolution;
        let _ = writeln!(
            s,
            "  {} from {}: {} independent path(s){}",
            t.name,
            topo.frame_name(t.base),
            r.paths.len(),
            if r.paths.len() > 1 { ", fused" } else { "" }
        );
        for (i, path) in r.paths.iter().enumerate() {
            let steps: Vec<String> = path
                .steps
                .iter()
                .map(|st| {
                    let name = &topo.link(st.link).name;
                    match st.direction {
                        Direction::Forward => format!("{name} (forward)"),
                        Direction::Inverse => format!("{name} (inverted)"),
                    }
                })
                .collect();
            let _ = writeln!(s, "    path {}: {}", i + 1, steps.join(" -> "));
            let _ = writeln!(
                s,
                "      {}_from_{} = {}",
                t.name,
                topo.frame_name(t.base),
                topo.describe_product(path)
            );
            if let Some(nominal) = nominal_of_path(inst, path) {
                let _ = writeln!(
                    s,
                    "      nominal: t_mm {} euler_deg {} q_wxyz {}",
                    fmt3(nominal.translation.vector.into(), 2),
                    fmt3(euler_from_rotation(&nominal.rotation).to_degrees(), 4),
                    {
                        let q = quaternion_wxyz(&nominal.rotation);
                        format!("[{:.6}, {:.6}, {:.6}, {:.6}]", q[0], q[1], q[2], q[3])
                    }
                );
            }
        }
        for path in &r.dependent_paths {
            let names: Vec<&str> = path.links().map(|l| topo.link(l).name.as_str()).collect();
            let _ = writeln!(
                s,
                "    not fused (shares a link with a path above): {}",
                names.join(" -> ")
            );
        }
    }
    s
}

/// The nominal pose of a path, when every link on it has a known (nominal or calibrated) pose.
fn nominal_of_path(
    inst: &Installation,
    path: &crate::chain::Path,
) -> Option<crate::geometry::Pose> {
    let mut known = true;
    let composed = crate::chain::compose_path(path, |id| match &inst.model.link(id).kind {
        LinkKind::Calibrated { parent_from_child } => *parent_from_child,
        LinkKind::Measured(m) => match m.nominal {
            Some(p) => crate::geometry::PoseCov::exact(p),
            None => {
                known = false;
                crate::geometry::PoseCov::identity()
            }
        },
    });
    known.then_some(composed.pose)
}
