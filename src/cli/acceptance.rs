//! `brokenray acceptance`: the acceptance procedure run against a service, guiding its
//! operator step by step (`/api/v1/acceptance/run`): it says what to do, waits for Enter,
//! says when the step settles and is measured, and prints the record. With `--simulate` the
//! simulator is the rig and the operator: it posts what the installation's cameras see of a
//! still scene and makes each stated move itself.
//!
//! The exit status is 0 when the acceptance passed, 1 when it failed (or could not run).

use crate::acceptance::Displacement;
use crate::feed::Client;
use anyhow::{Context as _, bail};
use serde_json::{Value, json};
use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

/// `brokenray acceptance`'s arguments.
#[derive(Debug, clap::Args)]
pub struct AcceptanceArgs {
    /// Who runs it (recorded).
    #[arg(long, value_name = "NAME")]
    by: String,
    /// A note for the record.
    #[arg(long, value_name = "TEXT")]
    note: Option<String>,
    /// The service.
    #[arg(long, value_name = "URL", default_value = "http://127.0.0.1:7878")]
    service: String,
    /// Write the acceptance's certificate here once it is recorded (an HTML page to print
    /// and sign; the file must not exist).
    #[arg(long, value_name = "FILE.html")]
    certificate: Option<PathBuf>,
    /// Bearer token with the `admin` scope (and `ingest` with `--simulate`).
    #[arg(long, env = "BROKENRAY_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// The simulator plays the rig and the operator: it posts the cameras' view of a still
    /// scene and makes each move itself.
    #[arg(long)]
    simulate: bool,
    /// With `--simulate`: the installation the simulated world is built from (the
    /// built-in one without it); it may differ from the service's, as a real rig differs
    /// from its calibration.
    #[arg(long, value_name = "FILE", requires = "simulate")]
    config: Option<PathBuf>,
    /// With `--simulate`: groups (trigger times) per second.
    #[arg(long, value_name = "HZ", default_value_t = 25.0, requires = "simulate")]
    rate: f64,
    /// With `--simulate`: seed of the noise.
    #[arg(long, default_value_t = 1, requires = "simulate")]
    seed: u64,
    /// With `--simulate`: post as fast as the service takes it, the run's times an hour in
    /// the past, instead of in real time.
    #[arg(long, requires = "simulate")]
    fast: bool,
}

/// How far in the past a fast simulated run starts: longer than any procedure takes.
const FAST_START_BEFORE_NS: i64 = 3_600_000_000_000;

/// The simulator as the rig and the operator.
struct SimulatedRig {
    sim: crate::sim::Simulator,
    period: Duration,
    fast: bool,
}

impl SimulatedRig {
    /// Posts the next groups: a second's worth in real time, or a batch as fast as taken.
    async fn run_for_a_while(&mut self, client: &Client) -> anyhow::Result<()> {
        let groups = (1.0 / self.period.as_secs_f64()).ceil().max(1.0) as usize;
        let mut items = Vec::new();
        for _ in 0..groups {
            items.extend(crate::feed::observation_items(&self.sim.next_group()));
            if !self.fast {
                tokio::time::sleep(self.period).await;
            }
        }
        client
            .post("/api/v1/observations", &json!({ "observations": items }))
            .await?;
        Ok(())
    }
}

/// Who places each step.
enum Operator {
    /// A person at the terminal.
    Person,
    /// The simulator.
    Simulator(Box<SimulatedRig>),
}

impl Operator {
    /// Places a step (keeps still, or moves `target` by `stated`); false when the person
    /// closed the input.
    async fn place(&mut self, target: Option<&str>, stated: &Displacement) -> anyhow::Result<bool> {
        match self {
            Operator::Person => {
                let line = tokio::task::spawn_blocking(|| {
                    let mut line = String::new();
                    std::io::stdin().read_line(&mut line).map(|n| n > 0)
                })
                .await??;
                Ok(line)
            }
            Operator::Simulator(rig) => {
                match target {
                    Some(t) => rig.sim.displace_target(t, stated)?,
                    None => {
                        for t in rig.sim.target_names() {
                            rig.sim.displace_target(&t, &Displacement::ZERO)?;
                        }
                    }
                }
                Ok(true)
            }
        }
    }

    /// What the rig measures once a step is placed, before the operator says so: the
    /// simulator posts a second of it (a person's rig measures by itself).
    async fn after_placing(&mut self, client: &Client) -> anyhow::Result<()> {
        if let Operator::Simulator(rig) = self {
            rig.run_for_a_while(client).await?;
        }
        Ok(())
    }

    /// Lets time pass while a step is measured.
    async fn wait(&mut self, client: &Client) -> anyhow::Result<()> {
        match self {
            Operator::Person => tokio::time::sleep(Duration::from_secs(1)).await,
            Operator::Simulator(rig) => rig.run_for_a_while(client).await?,
        }
        Ok(())
    }
}

/// Runs `brokenray acceptance`.
pub(super) fn run(args: AcceptanceArgs, out: &mut impl Write) -> anyhow::Result<()> {
    let client = Client::new(&args.service, args.token.clone())?;
    if let Some(path) = &args.certificate {
        anyhow::ensure!(
            !path.exists(),
            "{} exists: a certificate is written to a new file",
            path.display()
        );
    }
    let mut operator = if args.simulate {
        let installation = crate::config::load_or_default(args.config.as_deref())?;
        anyhow::ensure!(
            args.rate.is_finite() && args.rate > 0.0 && args.rate <= 1000.0,
            "--rate must lie in (0, 1000] groups per second, not {}",
            args.rate
        );
        let now = crate::clock::Clock::now_ns(&crate::clock::SystemClock);
        let start_ns = if args.fast {
            now - FAST_START_BEFORE_NS
        } else {
            now
        };
        let sim = crate::sim::Simulator::new(
            &installation.model,
            crate::sim::SimSettings {
                scenario: crate::sim::Scenario::Static,
                rate_hz: args.rate,
                start_ns,
                duration_s: None,
                pixel_sigma_px: None,
                outlier_rate: 0.0,
                seed: args.seed,
            },
        )?;
        Operator::Simulator(Box::new(SimulatedRig {
            sim,
            period: Duration::from_secs_f64(1.0 / args.rate),
            fast: args.fast,
        }))
    } else {
        Operator::Person
    };
    let passed = super::runtime(false)?.block_on(async {
        tokio::select! {
            r = guide(&client, &args, &mut operator, out) => r,
            _ = tokio::signal::ctrl_c() => {
                let _ = client.delete("/api/v1/acceptance/run").await;
                bail!("interrupted: the acceptance was abandoned, nothing recorded")
            }
        }
    })?;
    if !passed {
        bail!("the acceptance failed");
    }
    Ok(())
}

/// The axes of a figure, as text.
fn axes(v: &Value, digits: usize) -> String {
    let a: Vec<String> = (0..6)
        .map(|i| format!("{:.digits$}", v[i].as_f64().unwrap_or(f64::NAN)))
        .collect();
    format!("[{}] arcsec [{}] mm", a[..3].join(" "), a[3..].join(" "))
}

/// Guides the run to its end: whether it passed.
async fn guide(
    client: &Client,
    args: &AcceptanceArgs,
    operator: &mut Operator,
    out: &mut impl Write,
) -> anyhow::Result<bool> {
    let run = client
        .post(
            "/api/v1/acceptance/run",
            &json!({"by": args.by, "note": args.note}),
        )
        .await?;
    let steps = run["steps"].as_array().map_or(0, Vec::len);
    writeln!(out, "acceptance started by {} ({steps} steps)", args.by)?;
    let mut shown = String::new();
    loop {
        let run = client.get_json("/api/v1/acceptance/run").await?;
        let say = format!("{} {} {}", run["phase"], run["step"], run["slides"]);
        let fresh = say != shown;
        shown = say;
        match run["phase"].as_str() {
            Some("awaiting_operator") => {
                let k = run["step"].as_u64().context("no current step")? as usize;
                let step = &run["steps"][k];
                let stated: Displacement = serde_json::from_value(step["stated"].clone())?;
                let who = match operator {
                    Operator::Person => "press Enter when done",
                    Operator::Simulator(_) => "the simulator does it",
                };
                writeln!(
                    out,
                    "step {}/{steps} `{}`: {} ({who})",
                    k + 1,
                    step["name"].as_str().unwrap_or(""),
                    run["instruction"].as_str().unwrap_or("")
                )?;
                out.flush()?;
                if !operator.place(step["target"].as_str(), &stated).await? {
                    let _ = client.delete("/api/v1/acceptance/run").await;
                    bail!("the input closed: the acceptance was abandoned, nothing recorded");
                }
                operator.after_placing(client).await?;
                let run = client
                    .post("/api/v1/acceptance/run/ready", &json!({}))
                    .await?;
                writeln!(
                    out,
                    "  settling, then measuring {} to {}",
                    run["window"]["from"].as_str().unwrap_or("?"),
                    run["window"]["to"].as_str().unwrap_or("?")
                )?;
            }
            Some("measuring") => {
                if fresh && run["slides"].as_u64().unwrap_or(0) > 0 {
                    writeln!(
                        out,
                        "  the results had not settled: the window slid on to {} to {}",
                        run["window"]["from"].as_str().unwrap_or("?"),
                        run["window"]["to"].as_str().unwrap_or("?")
                    )?;
                }
                operator.wait(client).await?;
            }
            Some("finished") => {
                let id = run["acceptance_id"].as_i64().context("no acceptance id")?;
                let a = client.get_json(&format!("/api/v1/acceptance/{id}")).await?;
                print_record(&a, out)?;
                if let Some(path) = &args.certificate {
                    let page = client
                        .get_text(
                            &format!("/api/v1/acceptance/{id}/certificate"),
                            &[],
                            Duration::from_secs(60),
                        )
                        .await?;
                    let mut file = super::create_new(path)?;
                    file.write_all(page.as_bytes())?;
                    file.sync_all()?;
                    writeln!(out, "wrote the certificate to {}", path.display())?;
                }
                return Ok(a["passed"].as_bool().unwrap_or(false));
            }
            _ => bail!("the service answered an unknown phase: {run}"),
        }
    }
}

/// Prints a recorded acceptance: each step's figures against its limits.
fn print_record(a: &Value, out: &mut impl Write) -> anyhow::Result<()> {
    for step in a["record"]["steps"].as_array().into_iter().flatten() {
        let verdict = if step["passed"] == true {
            "pass"
        } else {
            "FAIL"
        };
        writeln!(out, "{verdict}  {}", step["name"].as_str().unwrap_or(""))?;
        if let Some(problem) = step["problem"].as_str() {
            writeln!(out, "      {problem}")?;
        }
        for s in step["still"].as_array().into_iter().flatten() {
            writeln!(
                out,
                "      {}: {} results; rms {} (expected {}; limit {}); scatter chi-square {:.0} of at most {:.0}",
                s["target"].as_str().unwrap_or(""),
                s["count"],
                axes(&s["rms"], 3),
                axes(&s["expected_rms"], 3),
                axes(&s["limit"], 3),
                s["chi2"].as_f64().unwrap_or(f64::NAN),
                s["threshold"].as_f64().unwrap_or(f64::NAN),
            )?;
        }
        if step["moved"].is_object() {
            let m = &step["moved"];
            writeln!(
                out,
                "      {} results; deviation {} +- {} (u); |deviation| + 2u within {}",
                m["count"],
                axes(&m["deviation"], 3),
                axes(&m["uncertainty"], 3),
                axes(&m["limit"], 3),
            )?;
        }
    }
    let failed: Vec<&str> = a["failed"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_str)
        .collect();
    if failed.is_empty() {
        writeln!(
            out,
            "acceptance {} PASSED; reverify by {}",
            a["id"],
            a["due"].as_str().unwrap_or("?")
        )?;
    } else {
        writeln!(out, "acceptance {} FAILED: {}", a["id"], failed.join(", "))?;
    }
    Ok(())
}
