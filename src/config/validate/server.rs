//! `[server]`, `[rerun]`, `[retention]`, `[frames]`, `[pnp]` and `[filter]`: the deployment's
//! settings and the bank's.

use super::*;

impl Validator {
    pub(super) fn pnp(&mut self, raw: &RawFile) -> Option<PnpSettings> {
        let empty = raw::RawPnp::default();
        let (at, r) = match &raw.pnp {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let max_reprojection_rms_px = r.max_reprojection_rms_px.unwrap_or(1.0);
        let inlier_threshold_px = r.inlier_threshold_px.unwrap_or(2.0);
        let lost_search_interval_s = r.lost_search_interval_s.unwrap_or(1.0);
        let ok = self.positive(at, "pnp.max_reprojection_rms_px", max_reprojection_rms_px)
            & self.positive(at, "pnp.inlier_threshold_px", inlier_threshold_px)
            & self.duration(
                at,
                "pnp.lost_search_interval_s",
                lost_search_interval_s,
                0.0,
                3600.0,
            );
        ok.then_some(PnpSettings {
            max_reprojection_rms_px,
            robust: r.robust.unwrap_or(false),
            inlier_threshold_px,
            lost_search_interval_s,
        })
    }

    /// `[reports]`: `Some(None)` without the section.
    pub(super) fn reports(&mut self, raw: &RawFile) -> Option<Option<ReportSettings>> {
        let Some(section) = &raw.reports else {
            return Some(None);
        };
        let (at, r) = (section.span().start, section.get_ref());
        let mut ok = true;
        if !(r.every_days.is_finite() && (1.0 / 24.0..=366.0).contains(&r.every_days)) {
            self.problem(
                at,
                format!(
                    "reports.every_days must lie in [1/24, 366] days (an hour to a year), not {}",
                    r.every_days
                ),
            );
            ok = false;
        }
        if r.folder.trim().is_empty() {
            self.problem(at, "reports.folder must name a folder".into());
            ok = false;
        }
        let min_gap_s = r.min_gap_s.unwrap_or(60.0);
        ok &= self.duration(at, "reports.min_gap_s", min_gap_s, 1e-3, 86_400.0);
        ok.then(|| {
            Some(ReportSettings {
                every_ns: (r.every_days * 86_400e9).round() as i64,
                folder: std::path::PathBuf::from(&r.folder),
                min_gap_ns: (min_gap_s * 1e9).round() as i64,
            })
        })
    }

    pub(super) fn retention(
        &mut self,
        raw: &RawFile,
        server: Option<&ServerSettings>,
    ) -> Option<RetentionSettings> {
        let empty = raw::RawRetention::default();
        let (at, r) = match &raw.retention {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let samples_days = r.samples_days.unwrap_or(90.0);
        let results_days = r.results_days.unwrap_or(90.0);
        let mut ok = self.positive(at, "retention.samples_days", samples_days)
            & self.positive(at, "retention.results_days", results_days);
        let disk_budget_bytes = match r.disk_budget_mb {
            None => None,
            Some(mb) => {
                ok &= self.positive(at, "retention.disk_budget_mb", mb);
                if server.is_some_and(|s| s.database.sqlite_path().is_none()) {
                    self.problem(
                        at,
                        "retention.disk_budget_mb applies to an SQLite file; a PostgreSQL \
                         server's disk is its own administrator's business"
                            .into(),
                    );
                    ok = false;
                }
                Some((mb * 1e6) as u64)
            }
        };
        ok.then_some(RetentionSettings {
            samples_days,
            results_days,
            disk_budget_bytes,
        })
    }

    pub(super) fn frames(&mut self, raw: &RawFile) -> Option<FrameSettings> {
        let empty = raw::RawFrames::default();
        let (at, f) = match &raw.frames {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let archive_every_s = f.archive_every_s.unwrap_or(60.0);
        let archive_max_mb = f.archive_max_mb.unwrap_or(1024.0);
        let mut ok = self.duration(at, "frames.archive_every_s", archive_every_s, 0.001, 31e6)
            & self.within(at, "frames.archive_max_mb", archive_max_mb, 0.001, 1e9);
        if f.archive_dir.as_deref() == Some("") {
            self.problem(
                at,
                "frames.archive_dir is empty: leave it out to keep no archive".to_owned(),
            );
            ok = false;
        }
        ok.then(|| FrameSettings {
            archive_dir: f.archive_dir.as_ref().map(PathBuf::from),
            archive_every_s,
            archive_max_mb,
        })
    }

    /// The `[filter]` section.
    pub(super) fn bank_settings(&mut self, raw: &RawFile) -> Option<BankSettings> {
        let empty = raw::RawFilter::default();
        let (at, f) = match &raw.filter {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let defaults = BankSettings::default();
        let consistency = self.probability(
            at,
            "filter.consistency_probability",
            f.consistency_probability,
            defaults.consistency_probability,
        );
        let gate = self.probability(at, "filter.gate_probability", f.gate_probability, 0.999);
        let stale = f
            .stale_after_periods
            .unwrap_or(defaults.stale_after_periods);
        let stale_ok = self.positive(at, "filter.stale_after_periods", stale);
        if f.reinit_after_outliers == Some(0) {
            self.problem(at, "filter.reinit_after_outliers must be at least 1".into());
        }
        let tolerance_ok = match f.group_tolerance_ms {
            Some(ms) if !(0.0..=10_000.0).contains(&ms) => {
                self.problem(
                    at,
                    format!("filter.group_tolerance_ms must be from 0 to 10000 (got {ms})"),
                );
                false
            }
            _ => true,
        };
        gate?;
        (stale_ok && tolerance_ok && f.reinit_after_outliers != Some(0)).then_some(BankSettings {
            stale_after_periods: stale,
            consistency_probability: consistency?,
            group_tolerance_ns: f.group_tolerance_ms.map(|ms| (ms * 1e6).round() as i64),
            ..defaults
        })
    }

    /// `server.database`: a `postgres://` URL, or else an SQLite file path.
    pub(super) fn database(
        &mut self,
        raw: Option<&toml::Spanned<String>>,
    ) -> Option<crate::config::Database> {
        use crate::config::{Database, PostgresUrl};
        let Some(s) = raw else {
            return Some(Database::Sqlite(PathBuf::from("brokenray.db")));
        };
        let text = s.get_ref().trim();
        if text.starts_with("postgres:") || text.starts_with("postgresql:") {
            match PostgresUrl::parse(text) {
                Some(url) if url.database_name().is_some() => Some(Database::Postgres(url)),
                Some(_) => {
                    self.problem(
                        s.span().start,
                        "server.database: the PostgreSQL URL names no database; write it like \
                         postgres://user:password@127.0.0.1:5432/brokenray"
                            .into(),
                    );
                    None
                }
                None => {
                    self.problem(
                        s.span().start,
                        "server.database is not a valid PostgreSQL URL; write it like \
                         postgres://user:password@127.0.0.1:5432/brokenray"
                            .into(),
                    );
                    None
                }
            }
        } else if text.is_empty() {
            self.problem(
                s.span().start,
                "server.database is empty: give an SQLite file or a postgres:// URL".into(),
            );
            None
        } else {
            Some(Database::Sqlite(PathBuf::from(text)))
        }
    }

    pub(super) fn server(&mut self, raw: &RawFile) -> Option<ServerSettings> {
        let listen = match &raw.server.listen {
            None => SocketAddr::from(([127, 0, 0, 1], 7878)),
            Some(s) => match s.get_ref().parse() {
                Ok(a) => a,
                Err(_) => {
                    self.problem(
                        s.span().start,
                        format!(
                            "server.listen `{}` is not an address like 127.0.0.1:7878",
                            s.get_ref()
                        ),
                    );
                    return None;
                }
            },
        };
        let r = &raw.server;
        Some(ServerSettings {
            listen,
            database: self.database(r.database.as_ref())?,
            max_body_bytes: self.count(
                "server.max_body_bytes",
                r.max_body_bytes.as_ref(),
                32 * 1024 * 1024,
                1024,
                1 << 34,
            )?,
            max_batch_samples: self.count(
                "server.max_batch_samples",
                r.max_batch_samples.as_ref(),
                100_000,
                1,
                100_000_000,
            )?,
            events_max_hz: match &r.events_max_hz {
                None => 10.0,
                Some(hz) => {
                    let (at, hz) = (hz.span().start, *hz.get_ref());
                    if !self.within(at, "server.events_max_hz", hz, 0.001, 1000.0) {
                        return None;
                    }
                    hz
                }
            },
            max_future_s: self.seconds(
                "server.max_future_s",
                r.max_future_s.as_ref(),
                5.0,
                0.0,
                MAX_DURATION_S,
            )?,
            clock_tolerance_s: self.seconds(
                "server.clock_tolerance_s",
                r.clock_tolerance_s.as_ref(),
                2.0,
                0.0,
                MAX_DURATION_S,
            )?,
            allowed_hosts: r.allowed_hosts.clone().unwrap_or_default(),
            max_connections: match &r.max_connections {
                None => None,
                n => Some(self.count("server.max_connections", n.as_ref(), 0, 16, 1_000_000)?),
            },
            max_connections_per_address: match &r.max_connections_per_address {
                None => None,
                n => Some(self.count(
                    "server.max_connections_per_address",
                    n.as_ref(),
                    0,
                    1,
                    1_000_000,
                )?),
            },
            header_timeout_s: self.seconds(
                "server.header_timeout_s",
                r.header_timeout_s.as_ref(),
                10.0,
                0.0,
                1e6,
            )?,
            shutdown_grace_s: self.seconds(
                "server.shutdown_grace_s",
                r.shutdown_grace_s.as_ref(),
                10.0,
                0.0,
                1e6,
            )?,
            max_heavy_reads: self.count(
                "server.max_heavy_reads",
                r.max_heavy_reads.as_ref(),
                2,
                1,
                1024,
            )?,
        })
    }

    pub(super) fn rerun(&mut self, raw: &RawFile) -> Option<RerunSettings> {
        let r = &raw.rerun;
        let (mut save, mut connect, mut serve) = (false, false, false);
        let mut ok = true;
        if let Some(m) = &r.mode {
            let names: Vec<&str> = match m.get_ref() {
                raw::RawModes::One(s) => vec![s.as_str()],
                raw::RawModes::Several(v) => v.iter().map(String::as_str).collect(),
            };
            for name in &names {
                match RerunMode::parse(name) {
                    Some(RerunMode::Off) if names.len() == 1 => {}
                    Some(RerunMode::Save) => save = true,
                    Some(RerunMode::Connect) => connect = true,
                    Some(RerunMode::Serve) => serve = true,
                    found => {
                        self.problem(
                            m.span().start,
                            if found == Some(RerunMode::Off) {
                                "rerun.mode `off` cannot be combined with other modes".to_owned()
                            } else {
                                format!(
                                    "rerun.mode `{name}` is not one of {}",
                                    RerunMode::WORDS.join(", ")
                                )
                            },
                        );
                        ok = false;
                    }
                }
            }
        }
        // Rates become periods and sizes byte counts: each bounded to what makes sense.
        let mut bounded =
            |v: &Option<toml::Spanned<f64>>, name: &str, default: f64, lo: f64, hi: f64| match v {
                None => Some(default),
                Some(x) => self
                    .within(
                        x.span().start,
                        &format!("rerun.{name}"),
                        *x.get_ref(),
                        lo,
                        hi,
                    )
                    .then_some(*x.get_ref()),
            };
        let memory_mb = bounded(
            &r.serve_memory_limit_mb,
            "serve_memory_limit_mb",
            256.0,
            1.0,
            1e6,
        );
        let rotate_hours = bounded(&r.rotate_hours, "rotate_hours", 24.0, 0.001, 87_600.0);
        let rotate_max_mb = bounded(&r.rotate_max_mb, "rotate_max_mb", 1024.0, 0.001, 1e7);
        let scene_hz = bounded(&r.scene_hz, "scene_hz", 2.0, 0.001, 1e6);
        let series_hz = bounded(&r.series_hz, "series_hz", 10.0, 0.001, 1e6);
        let image_hz = bounded(&r.image_hz, "image_hz", 1.0, 0.001, 1e6);
        let queue_capacity = match &r.queue_capacity {
            None => Some(4096),
            Some(q) if (1..=10_000_000).contains(q.get_ref()) => usize::try_from(*q.get_ref()).ok(),
            Some(q) => {
                self.problem(
                    q.span().start,
                    format!(
                        "rerun.queue_capacity must be between 1 and 10000000, not {}",
                        q.get_ref()
                    ),
                );
                None
            }
        };
        let serve_listen = match &r.serve_listen {
            None => Some(SocketAddr::from(([127, 0, 0, 1], 9876))),
            Some(a) => match a.get_ref().parse::<SocketAddr>() {
                Ok(addr) => Some(addr),
                Err(e) => {
                    self.problem(
                        a.span().start,
                        format!(
                            "rerun.serve_listen `{}` is not an address such as 127.0.0.1:9876: {e}",
                            a.get_ref()
                        ),
                    );
                    None
                }
            },
        };
        if !ok {
            return None;
        }
        Some(RerunSettings {
            save,
            connect,
            serve,
            recordings_dir: PathBuf::from(r.recordings_dir.as_deref().unwrap_or("recordings")),
            url: r
                .url
                .clone()
                .unwrap_or_else(|| "rerun+http://127.0.0.1:9876/proxy".to_owned()),
            serve_listen: serve_listen?,
            serve_memory_limit_bytes: (memory_mb? * 1e6) as u64,
            rotate_after_s: rotate_hours? * 3600.0,
            rotate_max_bytes: (rotate_max_mb? * 1e6) as u64,
            queue_capacity: queue_capacity?,
            scene_hz: scene_hz?,
            series_hz: series_hz?,
            image_hz: image_hz?,
        })
    }
}
