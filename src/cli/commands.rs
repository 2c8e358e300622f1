//! The commands that run on an async runtime: the service, the demo, the simulator's feed and
//! replays into a Rerun recording.

use super::progress::progress_bar;
use super::runtime;
use crate::clock::wall_now_ns as now_ns;
use crate::config::Installation;
use anyhow::Context as _;

/// `brokenray replay`: checks the arguments, then writes the recording with a progress bar
/// (on standard error).
pub(super) fn replay(
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
                .target_id(name)
                .ok_or_else(|| anyhow::anyhow!("--target: unknown target `{name}`"))?,
        ],
    };
    anyhow::ensure!(
        !out_file.exists(),
        "{} already exists; choose another --out",
        out_file.display()
    );
    let database = installation.server.database.clone();
    if let Some(path) = database.sqlite_path() {
        anyhow::ensure!(
            path.exists(),
            "no database at {}: nothing was stored yet (see `server.database`)",
            path.display()
        );
    }
    let installation = std::sync::Arc::new(installation);
    let runtime = runtime(false)?;
    runtime.block_on(async {
        let store = crate::store::open_reader(&installation, now_ns())
            .await
            .with_context(|| format!("cannot open {}", database))?;
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

/// `brokenray simulate`.
pub(super) async fn simulate(
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

/// The demo renders its frames with 8 x 8 samples where an edge runs (a few thousandths of a
/// pixel from the exact picture), so that two cores keep up with its default rate.
const DEMO_SAMPLES_PER_SIDE: usize = 8;

/// `brokenray demo`: the service and the simulator in one process, talking HTTP.
pub(super) async fn demo(
    installation: Installation,
    mut settings: crate::sim::SimSettings,
    emit: crate::feed::Emit,
    out: &mut impl std::io::Write,
) -> anyhow::Result<()> {
    if emit == crate::feed::Emit::Frames {
        // Rendered frames cost tens of milliseconds each: a rate the machine cannot hold would
        // put measurement time behind the clock and every target stale. One group is rendered
        // first and the rate held to what leaves a third of the time for the service.
        let mut trial = crate::sim::Simulator::new(&installation.model, settings)?;
        let group = trial.next_group();
        let started = std::time::Instant::now();
        let frames = crate::feed::render_pngs(&trial, &group, DEMO_SAMPLES_PER_SIDE).await?;
        let group_s = started.elapsed().as_secs_f64();
        let holds_hz = (0.67 / group_s.max(1e-3) * 10.0).floor() / 10.0;
        if settings.rate_hz > holds_hz {
            writeln!(
                out,
                "rendering a group's {} frames takes {:.0} ms on this machine: frames at {:.1} Hz, the rate it holds (asked for {} Hz)",
                frames.len(),
                group_s * 1e3,
                holds_hz.max(0.1),
                settings.rate_hz
            )?;
            settings.rate_hz = holds_hz.max(0.1);
        }
    }
    let targets: Vec<String> = installation.model.target_names();
    let recordings = installation.rerun.recordings_dir.clone();
    let database = installation.server.database.clone();
    let mut sim = crate::sim::Simulator::new(&installation.model, settings)?;
    let app = crate::app::App::build(installation).await?;
    let addr = app.local_addr()?;
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let mut server_stop = stop_rx.clone();
    let server = tokio::spawn(app.run_until(async move {
        let _ = server_stop.wait_for(|s| *s).await;
    }));
    writeln!(
        out,
        "brokenray demo: dashboard http://{addr}/\n  API http://{addr}/api/v1 (described at /api/v1/openapi.json)\n  database {}, Rerun recordings in {}/\n  scenario {:?} at {} Hz, the cameras sending {}; the reference is set after 5 s; Ctrl-C stops",
        database,
        recordings.display(),
        settings.scenario,
        settings.rate_hz,
        emit.plural()
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
            emit,
            groups,
            real_time: true,
            groups_per_request: 1,
            render_samples_per_side: DEMO_SAMPLES_PER_SIDE,
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
        "demo stopped after {} groups ({} {}, {} refused); every acknowledged write is on disk",
        summary.groups,
        summary.items,
        emit.plural(),
        summary.refused
    )?;
    Ok(())
}

pub(super) async fn serve(installation: Installation) -> anyhow::Result<()> {
    for w in &installation.warnings {
        tracing::warn!(file = %installation.source, line = ?w.line, "{}", w.message);
    }
    // Past the open-files limit accepting fails and nobody gets in: raise it, and keep the
    // connection cap below it.
    let open_files = crate::app::server::raise_open_files_limit()
        .unwrap_or_else(|_| crate::app::server::open_files_limit());
    if let Some(max) = installation.server.max_connections {
        crate::app::server::check_connections_fit(max, open_files).map_err(anyhow::Error::msg)?;
    }
    tracing::info!(
        open_files,
        max_connections = installation
            .server
            .max_connections
            .unwrap_or_else(|| crate::app::server::default_max_connections(open_files)),
        "open files allowed"
    );
    let source = installation.source.clone();
    let database = installation.server.database.clone();
    let targets: Vec<String> = installation.model.target_names();
    let n_links = installation.model.links.len();
    let app = crate::app::App::build(installation).await?;
    let addr = app.local_addr()?;
    tracing::info!(
        listen = %addr,
        database = %database,
        installation = %source,
        links = n_links,
        targets = ?targets,
        "brokenray serving on http://{addr}/api/v1, dashboard http://{addr}/"
    );
    app.run_until(crate::app::shutdown_signal()).await?;
    tracing::info!("stopped: every acknowledged write is on disk");
    Ok(())
}

/// The time of a simulated run's first group when `--start` is not given: now for a run sent
/// in real time; otherwise (`--fast`, or a file) the run's duration before now, so that its
/// last group is not in the future, which a service refuses.
pub(super) fn default_start_ns(now_ns: i64, duration_s: f64, real_time: bool) -> i64 {
    if real_time {
        now_ns
    } else {
        now_ns.saturating_sub((duration_s * 1e9).round() as i64)
    }
}

#[cfg(test)]
mod tests {
    use super::default_start_ns;

    #[test]
    fn a_run_faster_than_real_time_ends_now_unless_told_otherwise() {
        let now = 1_800_000_000_000_000_000;
        assert_eq!(default_start_ns(now, 300.0, true), now);
        assert_eq!(default_start_ns(now, 300.0, false), now - 300_000_000_000);
        assert_eq!(default_start_ns(now, 0.04, false), now - 40_000_000);
    }
}
