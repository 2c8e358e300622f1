//! The command line: subcommands and their output. `main.rs` only parses and dispatches here.
//!
//! This file declares the commands and dispatches them; `commands.rs` runs the service, the
//! simulator and replays on an async runtime, `health.rs` is the container's health probe,
//! `detect.rs` turns frame files into observations and `report.rs` formats what `check-config`
//! prints.

pub mod acceptance;
mod acquire;
mod calibrate;
mod commands;
mod detect;
mod health;
mod period;
mod progress;
mod report;
mod watch;

use commands::{demo, replay, serve, simulate};
pub use detect::{DetectSummary, detect_files};
pub use health::healthcheck;
use progress::{progress_bar, with_frames_bar};
pub use report::describe_installation;

use crate::clock::wall_now_ns as now_ns;
use crate::config;
use crate::model::LinkKind;
use anyhow::Context as _;
use clap::{Parser, Subcommand};
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
        /// Also open every camera that has a `[cameras.source]` (by its address) and apply its
        /// settings, reporting what each camera refuses (a pixel format it lacks, a feature it
        /// does not take, a size other than the calibration's). Needs the `genicam` build.
        #[arg(long)]
        cameras: bool,
    },
    /// Print the built-in installation file, a starting point for your own.
    DefaultConfig,
    /// Print the Modbus/TCP register map of an installation (`[[outputs.modbus]]`): each
    /// field's address, type, name, unit and meaning, one line each, tab-separated.
    ModbusMap {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// Run the service: HTTP API on the configured address, SQLite history, filtering.
    Serve {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// Write an online, consistent copy of the database (safe while `serve` runs). A site's
    /// copy starts a new generation of its outbox, so that restored it never reuses commit
    /// numbers its centre holds.
    Backup {
        /// The installation file whose database to copy; the built-in one without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// Where to write the copy (must not exist).
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
    },
    /// Start a new generation of a site's outbox, for a database restored from a copy that
    /// `backup` did not write (a file-system snapshot): the centre then takes its commits as a
    /// new stream instead of refusing them. Run it with the service stopped.
    NewGeneration {
        /// The installation file whose database to mark; the built-in one without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
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
        /// Raw observations (the service runs PnP), link poses solved here, or rendered frames
        /// (the service detects; `--out` is then a directory).
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
        /// Time of the first group (RFC 3339 or integer ns). Without it: now for a run in real
        /// time; else the duration before now, so that the run ends now.
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
        /// Write NDJSON here instead (one observation or sample a line); with `--emit frames` a
        /// new directory: `<camera>/<time>.png` and `truth.ndjson`.
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
    /// Render views of a calibration plate from random poses as a camera of the installation
    /// sees it (0.6 px blur, 2 DN read noise, shot noise): `DIR/view_NN.png`, and `truth.json`
    /// with the camera and each view's `camera_from_plate`. To try `calibrate-camera`.
    RenderPlate {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// The camera (its frame).
        #[arg(long, value_name = "NAME")]
        camera: String,
        /// The plate (TOML).
        #[arg(long, value_name = "PLATE.toml")]
        plate: PathBuf,
        /// How many views.
        #[arg(long, default_value_t = 15)]
        views: usize,
        /// Seed of the poses and the noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// A new directory for the frames.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
    },
    /// Render a station's calibration session as the installation's cameras see it: the station
    /// of a calibrated link moved to several positions, each camera of the station looking at
    /// its plate, a marker of the station seen by the camera that watches it:
    /// `DIR/position_NN/<camera>.png` and `truth.json`. To try `calibrate-station`.
    RenderStation {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// The calibrated link, `parent_from_child`.
        #[arg(long, value_name = "NAME")]
        link: String,
        /// The plate a camera of the station looks at, `CAMERA=PLATE.toml` (once per camera).
        #[arg(long = "plate", value_name = "CAMERA=PLATE.toml")]
        plates: Vec<String>,
        /// How many positions (the first is the start).
        #[arg(long, default_value_t = 6)]
        positions: usize,
        /// Seed of the motions and the noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// A new directory for the frames.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
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
    /// Calibrate a camera (intrinsics and distortion) from frames of a plate of discs: the plate
    /// found in each frame, Zhang's closed form, then a bundle adjustment; prints the
    /// intrinsics with their sigmas, each view's fit and what could be better.
    CalibrateCamera {
        /// The plate (TOML: rows, cols, spacing_mm, diameter_mm, asymmetric, polarity).
        #[arg(long, value_name = "PLATE.toml")]
        plate: PathBuf,
        /// Parameters kept fixed (distortion terms at zero, cx/cy at the image centre), e.g.
        /// `k3,p1,p2`.
        #[arg(long, value_name = "PARAMS", value_delimiter = ',')]
        fix: Vec<String>,
        /// The plate's shape: `auto` fits a sag along each axis and keeps it when it is
        /// significant, `warped` keeps it always, `flat` takes the plate as flat.
        #[arg(long, value_name = "SHAPE", default_value = "auto", value_parser = parse_word::<crate::vision::PlateShape>)]
        plate_shape: crate::vision::PlateShape,
        /// The lens model: `brown` (`k1 k2 p1 p2 k3`), `rational` (with `k4 k5 k6`) or
        /// `rational_prism` (with the thin prism `s1 s2 s3 s4` too), as OpenCV defines them.
        #[arg(long, value_name = "MODEL", default_value = "brown", value_parser = parse_word::<crate::vision::LensModel>)]
        model: crate::vision::LensModel,
        /// Print the result as `POST /api/v1/calibration/camera` answers it.
        #[arg(long)]
        json: bool,
        /// Write a `[[cameras]]` block for the installation file here (must not exist).
        #[arg(long, value_name = "FILE", requires = "camera")]
        out: Option<PathBuf>,
        /// The camera's frame name in the installation, for `--out`'s block.
        #[arg(long, value_name = "NAME")]
        camera: Option<String>,
        /// Write the calibration's report (`calibration.html`, one page with its pictures)
        /// into this folder, made if missing (the page must not exist).
        #[arg(long, value_name = "DIR")]
        report: Option<PathBuf>,
        /// The frames (PNG, JPEG, TIFF, PGM), one view of the plate each.
        #[arg(required = true, value_name = "FRAME")]
        frames: Vec<PathBuf>,
    },
    /// Calibrate a rigid station's link (`C2_from_C1`, `C3_from_M`) from frames taken with the
    /// station at several positions: each camera of the station looks at a plate fixed in the
    /// world, a marker of the station is seen by the installation's camera that watches it;
    /// their poses give the motions, and `A_i X = X B_i` gives the link.
    CalibrateStation {
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// The calibrated link, `parent_from_child`.
        #[arg(long, value_name = "NAME")]
        link: String,
        /// The plate a camera of the station looks at, `CAMERA=PLATE.toml` (once per camera).
        #[arg(long = "plate", value_name = "CAMERA=PLATE.toml")]
        plates: Vec<String>,
        /// Write the result (JSON, as `POST /api/v1/calibration/hand-eye` answers) here too.
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
        /// One directory per position of the station, holding `<camera>.png` (or .pgm, .tif)
        /// of each camera involved.
        #[arg(required = true, value_name = "POSITION_DIR")]
        positions: Vec<PathBuf>,
    },
    /// Detect a camera's markers in frame files (PNG, JPEG, TIFF, PGM) and print the observations as
    /// NDJSON lines ready for `POST /api/v1/observations`; markers not found are reported on
    /// stderr with the reason.
    Detect {
        /// The camera (its frame).
        #[arg(long, value_name = "NAME")]
        camera: String,
        /// The installation file (TOML); the built-in laboratory installation without it.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// The frame's time (RFC 3339 or integer ns), with one file; else each file's name
        /// (`2026-11-21T10:00:00.040Z.png`) or modification time.
        #[arg(long, value_name = "TIME")]
        time: Option<String>,
        /// The frames, in time order.
        #[arg(required = true, value_name = "FILE")]
        files: Vec<PathBuf>,
    },
    /// Take frames from the installation's cameras (`[cameras.source]`, GigE Vision or USB3
    /// Vision, opened by address) and post each to a running service with its exposure's time.
    /// Needs the `genicam` build. Runs until Ctrl-C, a status line per camera every interval.
    Acquire {
        /// The installation file (TOML) naming the cameras' sources.
        #[arg(long, value_name = "FILE")]
        config: PathBuf,
        /// The service.
        #[arg(long, value_name = "URL", default_value = "http://127.0.0.1:7878")]
        to: String,
        /// Bearer token with the `ingest` scope.
        #[arg(long, env = "BROKENRAY_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// Seconds between status lines.
        #[arg(long, value_name = "S", default_value_t = 10.0)]
        status_every_s: f64,
    },
    /// Post the frames camera software writes into `DIR/<camera>/` to a running service, oldest
    /// first, removing each once the service took it; refused ones are moved into
    /// `DIR/<camera>/refused/` with the answer beside them. A frame's time is its file name's
    /// (`2026-11-21T10:00:00.040Z.png`) or else its modification time. While the service is
    /// unreachable nothing is removed and delivery is retried.
    Watch {
        /// The folder holding one subfolder per camera.
        #[arg(value_name = "DIR")]
        dir: PathBuf,
        /// The service.
        #[arg(long, value_name = "URL", default_value = "http://127.0.0.1:7878")]
        to: String,
        /// Bearer token with the `ingest` scope.
        #[arg(long, env = "BROKENRAY_TOKEN", hide_env_values = true)]
        token: Option<String>,
        /// Deliver what is there (waiting for the service if it is down), then stop.
        #[arg(long)]
        once: bool,
        /// A file is taken once unchanged for this long (ms); 0 when the camera software
        /// writes each file under another name and renames it into place.
        #[arg(long, value_name = "MS", default_value_t = 300)]
        settle_ms: u64,
        /// Time between scans of the folder (ms).
        #[arg(long, value_name = "MS", default_value_t = 100)]
        poll_ms: u64,
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
        /// Groups per second (25; 5 with `--emit frames`).
        #[arg(long, value_name = "HZ")]
        rate: Option<f64>,
        /// Stop by itself after this long (60s, 15m, ...); runs until Ctrl-C without it.
        #[arg(long, value_name = "DURATION")]
        duration: Option<String>,
        /// What the simulated cameras send: pixel observations, or rendered frames that the
        /// service detects itself (a few frames per second: try `--rate 5`).
        #[arg(long, value_enum, default_value_t = crate::feed::Emit::Observations)]
        emit: crate::feed::Emit,
    },
    /// Write a period's report fetched from a running service: a self-contained HTML page
    /// (pictures in SVG, no script; print it to PDF from a browser) of the installation, its
    /// calibrations and, per target, its deformation, statistics, trend, alarms, gaps and
    /// uncertainty budget.
    Report {
        /// Start (RFC 3339 or integer ns); 30 days before the end without it.
        #[arg(long, value_name = "TIME")]
        from: Option<String>,
        /// End; now without it.
        #[arg(long, value_name = "TIME")]
        to: Option<String>,
        /// A silence between raw results longer than this many seconds is listed as a gap
        /// (the service's default, 60, without it).
        #[arg(long, value_name = "S")]
        min_gap_s: Option<f64>,
        /// The page to write (it must not exist).
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
        /// The service.
        #[arg(long, value_name = "URL", default_value = "http://127.0.0.1:7878")]
        service: String,
        /// Bearer token with the `read` scope.
        #[arg(long, env = "BROKENRAY_TOKEN", hide_env_values = true)]
        token: Option<String>,
    },
    /// Run the installation's acceptance procedure against a running service, guiding its
    /// operator step by step (or with `--simulate`, the simulator as rig and operator); exit
    /// status 1 when it fails.
    Acceptance(acceptance::AcceptanceArgs),
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
        Command::CheckConfig { config, cameras } => {
            let installation = config::load_or_default(config.as_deref())?;
            out.write_all(describe_installation(&installation).as_bytes())?;
            for w in &installation.warnings {
                let line = w.line.map(|l| format!("{l}:")).unwrap_or_default();
                writeln!(out, "warning: {}:{line} {}", installation.source, w.message)?;
            }
            if cameras {
                let mut refused = 0;
                for (camera, result) in crate::acquire::probe(&installation) {
                    match result {
                        Ok(what) => writeln!(out, "camera {camera}: {what}")?,
                        Err(e) => {
                            refused += 1;
                            writeln!(out, "camera {camera}: {e}")?;
                        }
                    }
                }
                if refused > 0 {
                    anyhow::bail!("{refused} camera(s) cannot be used as configured");
                }
            }
        }
        Command::DefaultConfig => out.write_all(config::DEFAULT_INSTALLATION_TOML.as_bytes())?,
        Command::ModbusMap { config } => {
            let installation = config::load_or_default(config.as_deref())?;
            let names: Vec<String> = (installation.model.targets)
                .iter()
                .map(|t| t.name.clone())
                .collect();
            out.write_all(crate::outputs::modbus::describe(&names).as_bytes())?;
        }
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
            writeln!(out, "backing up {} to {} ...", database, out_file.display())?;
            out.flush()?;
            let runtime = runtime(false)?;
            let started = std::time::Instant::now();
            let bytes = runtime
                .block_on(crate::store::backup(&database, &out_file))
                .with_context(|| format!("backup of {} failed", database))?;
            writeln!(
                out,
                "done: {} ({:.1} MB) in {:.1} s, a consistent copy",
                out_file.display(),
                bytes as f64 / 1e6,
                started.elapsed().as_secs_f64()
            )?;
        }
        Command::NewGeneration { config } => {
            let installation = config::load_or_default(config.as_deref())?;
            let config::Database::Sqlite(path) = &installation.server.database else {
                anyhow::bail!(
                    "{} is a PostgreSQL database: only a site's SQLite file has an outbox",
                    installation.server.database
                );
            };
            let identity = runtime(false)?
                .block_on(crate::store::new_outbox_generation(path))
                .with_context(|| format!("cannot start a generation in {}", path.display()))?;
            writeln!(
                out,
                "{}: outbox {} now uploads in generation {} (descending from {})",
                path.display(),
                identity.outbox_id,
                identity.generation,
                identity.lineage.join(", ")
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
                "wrote {}: {} filtered and {} raw results, {} samples, {} alarm transitions, {} archived frames",
                out_file.display(),
                summary.filtered,
                summary.raw,
                summary.samples,
                summary.alarms,
                summary.frames
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
            let real_time = to.is_some() && !fast;
            let start_ns = match &start {
                Some(t) => crate::clock::parse_query_time(t)
                    .map_err(|e| anyhow::anyhow!("--start: {e}"))?,
                None => {
                    let start_ns = commands::default_start_ns(now_ns(), duration_s, real_time);
                    if !real_time {
                        eprintln!(
                            "the run starts at {} ({duration} before now) so that it ends now: a service refuses measurements from its future (give --start to choose)",
                            crate::clock::format_ns(start_ns)
                        );
                    }
                    start_ns
                }
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
                (None, Some(path)) if emit == crate::feed::Emit::Frames => {
                    std::fs::create_dir(path).with_context(|| {
                        format!(
                            "cannot create the directory {} (it must not exist)",
                            path.display()
                        )
                    })?;
                    crate::feed::Sink::Dir(path.clone())
                }
                (None, Some(path)) => {
                    crate::feed::Sink::File(std::io::BufWriter::new(create_new(path)?))
                }
                (None, None) => anyhow::bail!("give --to URL or --out FILE"),
            };
            // Frames written to a directory carry their truth beside them.
            let truth = match (&truth, &out_file) {
                (None, Some(dir)) if emit == crate::feed::Emit::Frames => {
                    Some(dir.join("truth.ndjson"))
                }
                _ => truth,
            };
            let truth_file = truth
                .as_deref()
                .map(|p| create_new(p).map(std::io::BufWriter::new))
                .transpose()?;
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
                    render_samples_per_side: 32,
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
                emit.plural(),
                summary.refused
            )?;
        }
        Command::Calibrate {
            input,
            out: out_file,
        } => {
            let text = std::fs::read(&input)
                .with_context(|| format!("cannot read {}", input.display()))?;
            let request: crate::wire::HandEyeIn = crate::wire::parse(&text)
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
        Command::CalibrateCamera {
            plate,
            fix,
            plate_shape,
            model,
            json,
            out: out_file,
            camera,
            report,
            frames,
        } => {
            let plate = calibrate::read_plate(&plate)?;
            let run = with_frames_bar(|bar| {
                calibrate::calibrate_from_frames(
                    &plate,
                    &frames,
                    &fix,
                    (plate_shape, model),
                    bar,
                    &mut std::io::stderr(),
                )
            });
            let run = run?;
            if json {
                let mut body = crate::wire::CameraCalibrationOut::from(&run.calibration);
                if let Some(message) = run.file_warning() {
                    body.warnings.push(crate::wire::CalibrationWarningOut {
                        kind: crate::vision::WarningKind::LossyFrames,
                        message,
                    });
                }
                writeln!(out, "{}", serde_json::to_string_pretty(&body)?)?;
            } else {
                out.write_all(calibrate::report(&run).as_bytes())?;
            }
            let mut report_page = None;
            if let Some(dir) = report {
                let path = calibrate::write_report(&dir, camera.as_deref(), &plate, &run)?;
                if !json {
                    writeln!(out, "report written to {}", path.display())?;
                }
                // The block names it wherever the service runs from.
                report_page = Some(std::fs::canonicalize(&path).unwrap_or(path));
            }
            if let (Some(path), Some(name)) = (out_file, camera) {
                let block =
                    calibrate::cameras_block(&name, &run.calibration, report_page.as_deref());
                std::io::Write::write_all(&mut create_new(&path)?, block.as_bytes())?;
                if !json {
                    writeln!(out, "\nwritten to {}:\n{block}", path.display())?;
                }
            }
        }
        Command::RenderPlate {
            config,
            camera,
            plate,
            views,
            seed,
            out: dir,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let plate = calibrate::read_plate(&plate)?;
            let written = with_frames_bar(|bar| {
                calibrate::render_plate_views(
                    &installation,
                    &camera,
                    &plate,
                    views,
                    seed,
                    &dir,
                    bar,
                )
            });
            writeln!(
                out,
                "{} views of the plate written to {}",
                written?,
                dir.display()
            )?;
        }
        Command::RenderStation {
            config,
            link,
            plates,
            positions,
            seed,
            out: dir,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let by_camera = calibrate::read_plates(&plates)?;
            let written = with_frames_bar(|bar| {
                calibrate::render_station_views(
                    &installation,
                    &link,
                    &by_camera,
                    positions,
                    seed,
                    &dir,
                    bar,
                )
            });
            writeln!(
                out,
                "{} positions of the station of {link} written to {}",
                written?,
                dir.display()
            )?;
        }
        Command::CalibrateStation {
            config,
            link,
            plates,
            out: out_file,
            positions,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let by_camera = calibrate::read_plates(&plates)?;
            let run = with_frames_bar(|bar| {
                calibrate::calibrate_station(
                    &installation,
                    &link,
                    &by_camera,
                    &positions,
                    bar,
                    &mut std::io::stderr(),
                )
            });
            let run = run?;
            let text = serde_json::to_string_pretty(&run.result)?;
            if let Some(path) = &out_file {
                std::fs::write(path, &text)
                    .with_context(|| format!("cannot write {}", path.display()))?;
            }
            writeln!(out, "{text}")?;
            writeln!(
                out,
                "{link}: {} motions from {} positions ({} left out)",
                run.motions,
                positions.len(),
                run.left_out.len()
            )?;
        }
        Command::Detect {
            camera,
            config,
            time,
            files,
        } => {
            let installation = config::load_or_default(config.as_deref())?;
            let summary = detect_files(
                &installation,
                &camera,
                time.as_deref(),
                &files,
                out,
                &mut std::io::stderr(),
            )?;
            eprintln!(
                "{} frame(s): {} observation(s), {} marker(s) not found",
                summary.frames, summary.observations, summary.not_found
            );
        }
        Command::Acquire {
            config,
            to,
            token,
            status_every_s,
        } => {
            let installation = config::load(&config)?;
            for w in &installation.warnings {
                let line = w.line.map(|l| format!("{l}:")).unwrap_or_default();
                eprintln!("warning: {}:{line} {}", installation.source, w.message);
            }
            if !crate::acquire::SUPPORTED {
                anyhow::bail!(
                    "this build takes no frames from cameras: build with `cargo build --release --features genicam` (needs libaravis-dev and libusb-1.0-0-dev)"
                );
            }
            let client = std::sync::Arc::new(crate::feed::Client::new(&to, token)?);
            let every = std::time::Duration::from_secs_f64(status_every_s.clamp(0.1, 86_400.0));
            runtime(true)?.block_on(acquire::acquire(
                &installation,
                client,
                every,
                crate::app::shutdown_signal(),
            ))?;
        }
        Command::Watch {
            dir,
            to,
            token,
            once,
            settle_ms,
            poll_ms,
        } => {
            let client = crate::feed::Client::new(&to, token)?;
            let progress = indicatif::ProgressBar::new_spinner().with_style(
                indicatif::ProgressStyle::with_template("{spinner} {elapsed_precise} {msg}")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
            );
            progress.set_message(format!("watching {} for {to}", dir.display()));
            let settings = watch::WatchSettings {
                poll: std::time::Duration::from_millis(poll_ms),
                settle: std::time::Duration::from_millis(settle_ms),
                once,
                progress,
            };
            let summary = runtime(false)?.block_on(async {
                let stop = Box::pin(crate::app::shutdown_signal());
                watch::watch(&dir, &client, &settings, stop).await
            })?;
            settings.progress.finish_and_clear();
            eprintln!(
                "{} frame(s) posted, {} refused (moved aside), {} wait(s) for the service",
                summary.posted, summary.refused, summary.retries
            );
        }
        Command::Acceptance(args) => acceptance::run(args, out)?,
        Command::Report {
            from,
            to,
            min_gap_s,
            out: out_file,
            service,
            token,
        } => {
            let query = period::PeriodQuery {
                from,
                to,
                min_gap_s,
            };
            let bytes = period::write_report(&service, token, &query, &out_file)?;
            writeln!(out, "wrote {} ({bytes} bytes)", out_file.display())?;
        }
        Command::Demo {
            config,
            scenario,
            rate,
            duration,
            emit,
        } => {
            let mut installation = config::load_or_default(config.as_deref())?;
            if !installation.rerun.enabled() {
                installation.rerun.save = true;
            }
            let scenario: crate::sim::Scenario = scenario.parse().map_err(anyhow::Error::msg)?;
            // Three frames a group are rendered on one core: a few groups a second.
            let rate = rate.unwrap_or(if emit == crate::feed::Emit::Frames {
                5.0
            } else {
                25.0
            });
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
            runtime.block_on(demo(installation, settings, emit, out))?;
        }
        Command::HashToken { token } => {
            let token = match token {
                Some(t) => t,
                None => random_token()?,
            };
            writeln!(out, "token:  {token}")?;
            writeln!(out, "sha256: {}", crate::config::sha256_hex(&token))?;
            writeln!(
                out,
                "\nAdd to the configuration (give the token itself only to its holder):\n\n[[auth.tokens]]\nname = \"...\"\nsha256 = \"{}\"\nscopes = [\"read\"]",
                crate::config::sha256_hex(&token)
            )?;
        }
    }
    Ok(())
}

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

/// 256 random bits as hex, from the thread's generator (a cryptographically secure generator
/// seeded by the operating system), on any platform.
fn random_token() -> anyhow::Result<String> {
    Ok(hex::encode(rand::random::<[u8; 32]>()))
}

/// A word of a vocabulary (`--plate-shape`, `--model`).
fn parse_word<T: crate::words::Word>(word: &str) -> Result<T, String> {
    T::ALL
        .iter()
        .copied()
        .find(|w| w.word() == word)
        .ok_or_else(|| {
            format!(
                "{word:?} is not a {}: one of {}",
                T::WHAT,
                T::words().join(", ")
            )
        })
}
