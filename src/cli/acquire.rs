//! `brokenray acquire --to URL`: the installation's camera sources acquired in a process of
//! their own (a camera computer beside the rig, or a deployment that keeps camera drivers out of
//! the service's process), each frame posted to `/api/v1/frames` of a running service with the
//! time its source settled. A camera's newest four frames wait while one is being posted; an
//! older one is dropped and counted. A frame the service refuses (4xx) or cannot take (5xx,
//! unreachable) is counted with the reason; the camera's thread never waits for the service.

use crate::acquire::{Acquisition, SourceState};
use crate::config::Installation;
use crate::feed::Client;
use crate::imagefile::{FrameFormat, encode};
use std::sync::Arc;
use std::time::Duration;

/// Acquires until `stop` resolves; a status line per camera every `every`.
pub(super) async fn acquire(
    installation: &Installation,
    client: Arc<Client>,
    every: Duration,
    stop: impl std::future::Future<Output = ()>,
) -> anyhow::Result<()> {
    if installation.sources.is_empty() {
        anyhow::bail!(
            "{}: no camera has a [cameras.source]: nothing to acquire",
            installation.source
        );
    }
    let mut acquisition = Acquisition::start(installation);
    let posters: Vec<_> = acquisition
        .sources()
        .iter()
        .map(|state| {
            let (state, client) = (Arc::clone(state), Arc::clone(&client));
            tokio::spawn(async move { post_frames(&state, &client).await })
        })
        .collect();
    let sources: Vec<Arc<SourceState>> = acquisition.sources().to_vec();
    let report = async {
        let mut tick = tokio::time::interval(every);
        tick.tick().await;
        loop {
            tick.tick().await;
            for s in &sources {
                eprintln!("{}", status_line(s));
            }
        }
    };
    tokio::select! {
        () = stop => {}
        () = report => {}
    }
    tokio::task::spawn_blocking(move || {
        acquisition.stop();
        acquisition
    })
    .await?;
    for p in posters {
        let _ = p.await;
    }
    for s in &sources {
        eprintln!("{}", status_line(s));
    }
    Ok(())
}

/// One line of a source's state.
fn status_line(s: &SourceState) -> String {
    let r = s.report();
    let mut line = format!(
        "{} {} {}: {} received, {} posted, {} dropped, {} incomplete, {} refused for their time, {} not taken",
        r.camera,
        r.address,
        r.detail.status,
        r.received,
        r.ingested,
        r.dropped,
        r.incomplete,
        r.refused_time,
        r.failed
    );
    if let Some((error, at)) = &r.detail.last_error {
        line.push_str(&format!(
            "; last error at {}: {error}",
            crate::clock::format_ns(*at)
        ));
    }
    line
}

async fn post_frames(state: &SourceState, client: &Client) {
    let camera = state.source.camera.clone();
    while let Some(frame) = state.next().await {
        let time_ns = frame.time_ns;
        let encoded = tokio::task::spawn_blocking(move || encode(&frame.image, FrameFormat::Pgm))
            .await
            .map_err(|e| e.to_string())
            .and_then(|r| r.map_err(|e| e.to_string()));
        let bytes = match encoded {
            Ok(bytes) => bytes,
            Err(e) => {
                state.failed(
                    format!("cannot encode the frame: {e}"),
                    crate::clock::wall_now_ns(),
                );
                continue;
            }
        };
        match client
            .post_frame(&camera, time_ns, FrameFormat::Pgm, bytes)
            .await
        {
            Ok((status, _)) if status.is_success() => {
                state.ingested((crate::clock::wall_now_ns() - time_ns) as f64 / 1e9);
            }
            Ok((status, answer)) => state.failed(
                format!("the service answered {status}: {answer}"),
                crate::clock::wall_now_ns(),
            ),
            Err(e) => state.failed(format!("{e:#}"), crate::clock::wall_now_ns()),
        }
    }
}
