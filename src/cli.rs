//! The command line: subcommands and their output. `main.rs` only parses and dispatches here.

use crate::chain::Direction;
use crate::config::{self, Installation, LinkKind};
use crate::geometry::{euler_from_rotation, quaternion_wxyz};
use anyhow::Context as _;
use clap::{Parser, Subcommand};
use std::fmt::Write as _;
use std::path::PathBuf;

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
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()
                .context("cannot start the async runtime")?;
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
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .context("cannot start the async runtime")?;
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

/// 32 random bytes from the operating system, as hex.
fn random_token() -> anyhow::Result<String> {
    use std::io::Read as _;
    let mut bytes = [0u8; 32];
    std::fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut bytes))
        .context("cannot read random bytes from /dev/urandom")?;
    Ok(hex::encode(bytes))
}

async fn serve(installation: Installation) -> anyhow::Result<()> {
    let source = installation.source.clone();
    let database = installation.server.database.clone();
    let targets: Vec<String> = installation
        .targets
        .iter()
        .map(|t| t.name.clone())
        .collect();
    let n_links = installation.links.len();
    let app = crate::api::App::build(installation).await?;
    let addr = app.local_addr()?;
    tracing::info!(
        listen = %addr,
        database = %database.display(),
        installation = %source,
        links = n_links,
        targets = ?targets,
        "brokenray serving on http://{addr}/api/v1"
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
    let topo = &inst.topology;
    let _ = writeln!(s, "installation: {} (valid)", inst.source);
    let _ = writeln!(
        s,
        "frames ({}): {}",
        topo.frames().len(),
        topo.frames().join(", ")
    );
    let _ = writeln!(s, "cameras ({}):", inst.cameras.len());
    for c in &inst.cameras {
        let _ = writeln!(
            s,
            "  {:<6} {}x{} px, fx {} fy {} px, pixel sigma {} px",
            c.frame, c.width_px, c.height_px, c.fx_px, c.fy_px, c.pixel_sigma_px
        );
    }
    let _ = writeln!(s, "markers ({}):", inst.markers.len());
    for m in &inst.markers {
        let _ = writeln!(s, "  {:<6} {} points", m.frame, m.points_mm.len());
    }
    let _ = writeln!(s, "links ({}):", inst.links.len());
    for l in &inst.links {
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
    let _ = writeln!(s, "targets ({}):", inst.targets.len());
    for t in &inst.targets {
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
    let composed = crate::chain::compose_path(path, |id| match &inst.link(id).kind {
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
