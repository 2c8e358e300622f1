//! The centre's upkeep of its sites' copies: retention per tier and partitions, at start and
//! then every ten minutes until the service stops. A failed pass is logged, counted and kept as
//! the centre's problem (`/healthz` `centre_problem`: per site, or the whole pass); the next
//! pass tries again.

use super::Centre;
use crate::service::Service;
use std::sync::Arc;
use std::time::Duration;

/// Starts the centre's upkeep of its sites' copies (retention per tier, partitions): at start,
/// then every ten minutes, until the service stops. A failed pass is logged and counted, and
/// the next one tries again.
pub fn spawn(service: Service, centre: Arc<Centre>) -> tokio::task::JoinHandle<()> {
    let mut stopping = service.stopping();
    let watched = service.clone();
    watched.spawn_watched("centre upkeep", async move {
        let mut every = tokio::time::interval(Duration::from_secs(600));
        every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = every.tick() => {}
                _ = stopping.changed() => return,
            }
            if *stopping.borrow() {
                return;
            }
            let settings = centre.settings;
            let pass = centre.store.maintain(service.now_ns(), settings.raw_days, settings.results_days);
            match pass.await {
                Ok(sites) => {
                    let failed: Vec<String> = sites
                        .iter()
                        .filter_map(|s| {
                            let why = s.failed.as_ref()?;
                            tracing::warn!(site = %s.site, error = %why,
                                "the centre's upkeep of a site failed; the others went on, and it is tried again in ten minutes");
                            Some(format!("site `{}`: {why}", s.site))
                        })
                        .collect();
                    service
                        .metrics()
                        .centre_upkeep_failed
                        .fetch_add(failed.len() as u64, std::sync::atomic::Ordering::Relaxed);
                    centre.set_upkeep_problem((!failed.is_empty()).then(|| {
                        format!("the centre's upkeep failed for {}", failed.join("; "))
                    }));
                    let pruned: u64 = sites
                        .iter()
                        .map(|s| s.samples + s.raw_results + s.results)
                        .sum();
                    service
                        .metrics()
                        .centre_rows_pruned
                        .fetch_add(pruned, std::sync::atomic::Ordering::Relaxed);
                    for s in sites
                        .iter()
                        .filter(|s| s.samples + s.raw_results + s.results > 0)
                    {
                        tracing::info!(site = %s.site, samples = s.samples, raw_results = s.raw_results,
                            results = s.results, "the centre's retention pruned a site's old rows");
                    }
                }
                Err(e) => {
                    service
                        .metrics()
                        .centre_upkeep_failed
                        .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    tracing::warn!(error = %e, "the centre's upkeep of its sites failed; trying again in ten minutes");
                    centre.set_upkeep_problem(Some(format!("the centre's upkeep failed: {e}")));
                }
            }
        }
    })
}
