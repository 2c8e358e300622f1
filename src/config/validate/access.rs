//! `[[auth.tokens]]` and `[[notify.webhooks]]`: who may call the service, and who is told of
//! its alarms.

use super::*;

impl Validator {
    pub(super) fn notify(&mut self, raw: &RawFile) -> NotifySettings {
        let mut webhooks = Vec::new();
        for (i, spanned) in raw.notify.webhooks.iter().enumerate() {
            let at = spanned.span().start;
            let w = spanned.get_ref();
            let what = format!("notify.webhooks[{i}]");
            let mut ok = true;
            let scheme_ok = ["http://", "https://"]
                .iter()
                .any(|p| w.url.len() > p.len() && w.url[..p.len()].eq_ignore_ascii_case(p));
            if !scheme_ok || w.url.chars().any(char::is_whitespace) {
                self.problem(
                    at,
                    format!(
                        "{what}.url must be an http:// or https:// URL, not `{}`",
                        w.url
                    ),
                );
                ok = false;
            }
            if w.secret.is_empty() {
                self.problem(
                    at,
                    format!("{what}.secret is empty: the receiver checks the signature with it"),
                );
                ok = false;
            }
            let min_level = match w.min_level.as_deref() {
                None | Some("warn") => NotifyLevel::Warn,
                Some("alarm") => NotifyLevel::Alarm,
                Some(other) => {
                    self.problem(
                        at,
                        format!("{what}.min_level `{other}` is not one of warn, alarm"),
                    );
                    ok = false;
                    NotifyLevel::Warn
                }
            };
            let timeout_s = w.timeout_s.unwrap_or(10.0);
            ok &= self.duration(at, &format!("{what}.timeout_s"), timeout_s, 0.01, 3600.0);
            let max_attempts = w.max_attempts.unwrap_or(8);
            if !(1..=100).contains(&max_attempts) {
                self.problem(
                    at,
                    format!("{what}.max_attempts must be from 1 to 100, not {max_attempts}"),
                );
                ok = false;
            }
            if ok {
                webhooks.push(WebhookSpec {
                    url: w.url.clone(),
                    secret: w.secret.clone(),
                    min_level,
                    timeout_s,
                    max_attempts,
                });
            }
        }
        NotifySettings { webhooks }
    }

    pub(super) fn auth(&mut self, raw: &RawFile) -> AuthSettings {
        let mut tokens: Vec<TokenSpec> = Vec::new();
        for spanned in &raw.auth.tokens {
            let at = spanned.span().start;
            let t = spanned.get_ref();
            let hex = t.sha256.to_ascii_lowercase();
            if hex.len() != 64 || !hex.chars().all(|c| c.is_ascii_hexdigit()) {
                self.problem(
                    at,
                    format!("token `{}`: sha256 must be 64 hexadecimal digits", t.name),
                );
                continue;
            }
            if tokens.iter().any(|o| o.sha256_hex == hex) {
                self.problem(
                    at,
                    format!("token `{}`: the same sha256 is listed twice", t.name),
                );
                continue;
            }
            let mut scopes = Vec::new();
            for s in &t.scopes {
                match s.as_str() {
                    "read" => scopes.push(Scope::Read),
                    "ingest" => scopes.push(Scope::Ingest),
                    "admin" => scopes.push(Scope::Admin),
                    "sync" => scopes.push(Scope::Sync),
                    other => self.problem(
                        at,
                        format!(
                            "token `{}`: scope `{other}` is not one of read, ingest, admin, sync",
                            t.name
                        ),
                    ),
                }
            }
            if t.scopes.is_empty() {
                self.problem(
                    at,
                    format!(
                        "token `{}`: no scopes; give at least one of read, ingest, admin",
                        t.name
                    ),
                );
                continue;
            }
            let site = match &t.site {
                None => None,
                Some(name) => {
                    let parsed = SiteName::parse(name);
                    if parsed.is_none() {
                        self.problem(
                            at,
                            format!("token `{}`: site `{name}` is not a site name", t.name),
                        );
                        continue;
                    }
                    parsed
                }
            };
            if scopes.contains(&Scope::Sync) != site.is_some() {
                self.problem(
                    at,
                    format!(
                        "token `{}`: a `sync` token names the one site it uploads for (`site = \"...\"`), and only a sync token names a site",
                        t.name
                    ),
                );
                continue;
            }
            tokens.push(TokenSpec {
                name: t.name.clone(),
                sha256_hex: hex,
                scopes,
                site,
            });
        }
        AuthSettings { tokens }
    }
}
