//! `[site]`, `[upstream]` and `[central]`: this service in a fleet.

use super::*;

impl Validator {
    /// `[site]`, `[upstream]` and `[central]`: a site that pushes names itself and uses an
    /// SQLite file (its outbox); a centre runs on PostgreSQL.
    pub(super) fn fleet(
        &mut self,
        raw: &RawFile,
        server: Option<&ServerSettings>,
    ) -> Option<FleetSettings> {
        let mut ok = true;
        let site = match &raw.site {
            None => None,
            Some(s) => {
                let name = &s.get_ref().name;
                let parsed = SiteName::parse(name);
                if parsed.is_none() {
                    self.problem(
                        s.span().start,
                        format!(
                            "site.name `{name}` is not a site name: 1 to {} lowercase letters, digits, `-` or `_`, starting with a letter or digit",
                            SiteName::MAX_LEN
                        ),
                    );
                    ok = false;
                }
                parsed
            }
        };
        let upstream = match &raw.upstream {
            None => None,
            Some(s) => {
                let at = s.span().start;
                let u = s.get_ref();
                if raw.site.is_none() {
                    self.problem(
                        at,
                        "[upstream] needs the site's name: add `[site] name = \"...\"`".into(),
                    );
                    ok = false;
                }
                if server.is_some_and(|s| s.database.sqlite_path().is_none()) {
                    self.problem(
                        at,
                        "[upstream] needs an SQLite database (server.database): the site's file is its outbox".into(),
                    );
                    ok = false;
                }
                let url = match url::Url::parse(&u.url) {
                    Ok(url) if matches!(url.scheme(), "http" | "https") && url.has_host() => {
                        Some(url)
                    }
                    _ => {
                        self.problem(
                            at,
                            format!("upstream.url `{}` is not an http:// or https:// URL", u.url),
                        );
                        None
                    }
                };
                let token = match (&u.token, &u.token_file) {
                    (Some(_), Some(_)) => {
                        self.problem(at, "upstream: give token or token_file, not both".into());
                        ok = false;
                        None
                    }
                    (Some(t), None) if t.trim().is_empty() => {
                        self.problem(at, "upstream.token is empty".into());
                        ok = false;
                        None
                    }
                    (Some(t), None) => Some(t.trim().to_owned()),
                    (None, Some(f)) => match std::fs::read_to_string(f) {
                        Ok(t) if !t.trim().is_empty() => Some(t.trim().to_owned()),
                        Ok(_) => {
                            self.problem(at, format!("upstream.token_file `{f}` is empty"));
                            ok = false;
                            None
                        }
                        Err(e) => {
                            self.problem(
                                at,
                                format!("upstream.token_file `{f}` cannot be read: {e}"),
                            );
                            ok = false;
                            None
                        }
                    },
                    (None, None) => None,
                };
                let raw_kbit_s = u.raw_kbit_s.unwrap_or(0.0);
                if raw_kbit_s != 0.0 {
                    // The wait after a batch is its bits over this: a tiny budget would make a
                    // wait of centuries (and an uploader that dies computing it).
                    ok &= self.within(at, "upstream.raw_kbit_s (or 0)", raw_kbit_s, 0.01, 1e7);
                }
                let heartbeat_s = u.heartbeat_s.unwrap_or(10.0);
                ok &= self.duration(at, "upstream.heartbeat_s", heartbeat_s, 0.05, 86_400.0);
                let batch_rows = u.batch_rows.unwrap_or(20_000);
                // A batch is read into memory whole: a million rows is gigabytes.
                ok &= self.within(at, "upstream.batch_rows", batch_rows as f64, 1.0, 1e6);
                let batch_mb = u.batch_mb.unwrap_or(0.25);
                ok &= self.within(at, "upstream.batch_mb", batch_mb, 0.01, 1024.0);
                url.map(|url| UpstreamSettings {
                    url,
                    token,
                    raw_kbit_s,
                    batch_rows,
                    batch_bytes: (batch_mb * 1e6) as usize,
                    heartbeat_s,
                })
            }
        };
        let central = match &raw.central {
            Some(s) if s.get_ref().enabled => {
                let at = s.span().start;
                if server.is_some_and(|s| s.database.sqlite_path().is_some()) {
                    self.problem(
                        at,
                        "[central] needs a PostgreSQL database (server.database = \"postgres://...\")".into(),
                    );
                    ok = false;
                }
                let max_sync_mb = s.get_ref().max_sync_mb.unwrap_or(128.0);
                ok &= self.within(at, "central.max_sync_mb", max_sync_mb, 1.0, 4096.0);
                let raw_days = s.get_ref().raw_days.unwrap_or(30.0);
                let results_days = s.get_ref().results_days.unwrap_or(365.0);
                ok &= self.positive(at, "central.raw_days", raw_days);
                ok &= self.positive(at, "central.results_days", results_days);
                if raw_days > results_days {
                    self.problem(
                        at,
                        format!(
                            "central.raw_days ({raw_days}) is longer than central.results_days \
                             ({results_days}): raw results share the results' daily partitions, \
                             which go at results_days"
                        ),
                    );
                    ok = false;
                }
                Some(CentralSettings {
                    max_sync_bytes: (max_sync_mb * 1e6) as usize,
                    raw_days,
                    results_days,
                })
            }
            _ => None,
        };
        (ok && (raw.upstream.is_none() || upstream.is_some())).then_some(FleetSettings {
            site,
            upstream,
            central,
        })
    }
}
