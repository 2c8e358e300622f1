//! The centre's upkeep of its sites' copies: retention per tier and partitions, at start and
//! then every ten minutes until the service stops. A failed pass is logged, counted and kept as
//! the centre's problem (`/healthz` `centre_problem`: per site, or the whole pass); the next
//! pass tries again.

use super::Centre;
use crate::service::Service;
use crate::store::{SiteUpkeep, StoreError};
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
            let pass = pass.await;
            match &pass {
                Ok(sites) => {
                    for s in sites {
                        if let Some(why) = &s.failed {
                            tracing::warn!(site = %s.site, error = %why,
                                "the centre's upkeep of a site failed; the others went on, and it is tried again in ten minutes");
                        } else if s.samples + s.raw_results + s.results > 0 {
                            tracing::info!(site = %s.site, samples = s.samples, raw_results = s.raw_results,
                                results = s.results, "the centre's retention pruned a site's old rows");
                        }
                    }
                }
                Err(e) => tracing::warn!(error = %e, "the centre's upkeep of its sites failed; trying again in ten minutes"),
            }
            let verdict = Verdict::of(&pass);
            let metrics = service.metrics();
            metrics
                .centre_upkeep_failed
                .fetch_add(verdict.failures, std::sync::atomic::Ordering::Relaxed);
            metrics
                .centre_rows_pruned
                .fetch_add(verdict.pruned, std::sync::atomic::Ordering::Relaxed);
            centre.set_upkeep_problem(verdict.problem);
        }
    })
}

/// What a pass of the upkeep comes to: the problem `/healthz` shows until a pass succeeds
/// (none when every site's upkeep ran), the failures counted, the rows pruned.
#[derive(Debug, PartialEq, Eq)]
struct Verdict {
    problem: Option<String>,
    failures: u64,
    pruned: u64,
}

impl Verdict {
    fn of(pass: &Result<Vec<SiteUpkeep>, StoreError>) -> Self {
        match pass {
            Err(e) => Self {
                problem: Some(format!("the centre's upkeep failed: {e}")),
                failures: 1,
                pruned: 0,
            },
            Ok(sites) => {
                let failed: Vec<String> = sites
                    .iter()
                    .filter_map(|s| Some(format!("site `{}`: {}", s.site, s.failed.as_ref()?)))
                    .collect();
                Self {
                    failures: failed.len() as u64,
                    problem: (!failed.is_empty())
                        .then(|| format!("the centre's upkeep failed for {}", failed.join("; "))),
                    pruned: sites
                        .iter()
                        .map(|s| s.samples + s.raw_results + s.results)
                        .sum(),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site(name: &str, pruned: u64, failed: Option<&str>) -> SiteUpkeep {
        SiteUpkeep {
            site: name.to_owned(),
            samples: pruned,
            raw_results: 0,
            results: 0,
            failed: failed.map(str::to_owned),
        }
    }

    #[test]
    fn a_pass_that_reaches_no_site_is_the_centres_problem_until_one_succeeds() {
        let failed = Verdict::of(&Err(StoreError::Unreachable("connection refused".into())));
        assert_eq!(failed.failures, 1);
        let problem = failed.problem.expect("a whole failed pass is a problem");
        assert!(
            problem.contains("upkeep failed") && problem.contains("connection refused"),
            "{problem}"
        );
        // The next pass that reaches every site clears it.
        let next = Verdict::of(&Ok(vec![site("a", 3, None), site("b", 4, None)]));
        assert_eq!(
            next,
            Verdict {
                problem: None,
                failures: 0,
                pruned: 7
            }
        );
    }

    #[test]
    fn each_failed_site_is_named_and_counted_and_the_others_pruned() {
        let v = Verdict::of(&Ok(vec![
            site("a", 0, Some("a row of 2262")),
            site("b", 5, None),
            site("c", 0, Some("disk full")),
        ]));
        assert_eq!(v.failures, 2);
        assert_eq!(v.pruned, 5);
        assert_eq!(
            v.problem.as_deref(),
            Some("the centre's upkeep failed for site `a`: a row of 2262; site `c`: disk full")
        );
    }
}
