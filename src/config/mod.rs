//! The installation file (TOML) parsed into validated domain types.
//!
//! One file describes one installation: its measurement model (frames, cameras, markers,
//! links, targets, filter and PnP settings: [`crate::model::Model`], all the core sees) and the
//! deployment settings only the adapters read (server, Rerun, auth, notifications, retention;
//! `docs/interface.md`, "Configuration"). Without a file the built-in
//! default describes the paper's laboratory setup (base B, station C1-C2, station M-C3,
//! target G; about 3 m per hop), see [`default_installation`].
//!
//! Validation collects every problem it finds, each with its line: unknown keys, wrong types,
//! a link name that does not match its frames, a duplicate link, a non-finite or non-rotation
//! pose, a target unreachable from its base, and so on.

mod error;
mod outputs;
mod raw;
mod source;
mod validate;

pub use error::{ConfigError, ConfigProblem};
pub use outputs::{
    MAX_MQTT_RATE_HZ, MAX_NMEA_RATE_HZ, ModbusSpec, MqttSpec, NmeaSpec, OutputSettings,
    reaches_many,
};
pub use source::{
    CameraAddress, CameraSource, FeatureSetting, PixelFormat, TimestampMode, TriggerMode,
};

use crate::model::Model;
use error::LineIndex;
use raw::RawFile;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use validate::Validator;

/// The built-in installation, as a file users can copy (`brokenray default-config`).
pub const DEFAULT_INSTALLATION_TOML: &str = include_str!("default.toml");

/// What the built-in installation is called in messages.
pub const DEFAULT_SOURCE_NAME: &str = "<built-in default>";

/// A validated installation.
#[derive(Debug, Clone)]
pub struct Installation {
    /// Where it came from: a file path or [`DEFAULT_SOURCE_NAME`].
    pub source: String,
    /// What the core needs: frames, links, targets, cameras, markers, filter and PnP settings.
    pub model: Arc<Model>,
    /// HTTP server settings.
    pub server: ServerSettings,
    /// Rerun settings.
    pub rerun: RerunSettings,
    /// Bearer tokens.
    pub auth: AuthSettings,
    /// Where alarm transitions are sent.
    pub notify: NotifySettings,
    /// The plant's buses compensations and alarms are published on.
    pub outputs: OutputSettings,
    /// How long raw samples and results are kept (rollups are kept for good).
    pub retention: RetentionSettings,
    /// The reports filed by themselves (`[reports]`); `None`: only those asked for.
    pub reports: Option<ReportSettings>,
    /// The acceptance procedure and its limits (`[acceptance]`); `None`: the installation
    /// states none, and no acceptance can be run.
    pub acceptance: Option<AcceptanceSettings>,
    /// The archive of camera frames.
    pub frames: FrameSettings,
    /// This service in a fleet: a site reporting to a centre, or the centre.
    pub fleet: FleetSettings,
    /// The cameras the service takes frames from itself (`[cameras.source]`), in installation
    /// order.
    pub sources: Vec<CameraSource>,
    /// The calibration report of each camera that names one (`calibration_report`), in
    /// installation order: the dashboard links it.
    pub calibration_reports: Vec<CalibrationReportFile>,
    /// What is valid but probably not meant, each with its line (`check-config` prints them,
    /// `serve` logs them).
    pub warnings: Vec<ConfigProblem>,
}

/// A camera's calibration report: the HTML page `calibrate-camera --report` wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationReportFile {
    /// The camera's frame.
    pub camera: String,
    /// The page, as the installation names it (relative to the service's working directory).
    pub path: PathBuf,
}

/// The archive of camera frames (`[frames]`): one frame per camera every `archive_every_s` of
/// measurement time, plus every frame in which a marker was not found or a link's sample was
/// an outlier, the oldest removed to stay under `archive_max_mb`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSettings {
    /// Where the archive is kept; `None`: frames are not archived.
    pub archive_dir: Option<PathBuf>,
    /// Seconds of measurement time between the frames kept of each camera.
    pub archive_every_s: f64,
    /// The archive's size cap (MB, 10^6 bytes).
    pub archive_max_mb: f64,
}

/// The period's report the service files by itself: one a period, the periods counted from
/// 1970-01-01T00:00:00Z (UTC) so that they do not move with restarts.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportSettings {
    /// The period (ns).
    pub every_ns: i64,
    /// The folder the reports are written into (made when missing).
    pub folder: PathBuf,
    /// A silence between raw results longer than this is a gap (ns).
    pub min_gap_ns: i64,
}

/// The acceptance procedure (`[acceptance]`): its steps and limits, and how long an
/// acceptance holds before the rig is due to be verified again.
#[derive(Debug, Clone, PartialEq)]
pub struct AcceptanceSettings {
    /// The steps, their windows and the limits.
    pub plan: crate::acceptance::Plan,
    /// How long a passed acceptance holds (ns) before reverification is due.
    pub reverify_every_ns: i64,
}

/// How long raw samples and results are kept, counted back from the newest result.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RetentionSettings {
    /// Raw samples (days).
    pub samples_days: f64,
    /// Raw and filtered results (days); rollups stay.
    pub results_days: f64,
    /// The most the SQLite file may hold (bytes in use); past it the oldest samples and raw
    /// results go, then the oldest filtered results, whatever their age or upload (`None`: no
    /// budget).
    pub disk_budget_bytes: Option<u64>,
}

impl RetentionSettings {
    /// The times before which samples and results go, `(samples, results)` (ns), counted back
    /// from the newest result `newest_ns` but never from later than the server's clock
    /// `now_ns` (one result stamped in the future must not make the real history look old);
    /// `None` while there is no result.
    pub fn cutoffs_ns(&self, newest_ns: Option<i64>, now_ns: i64) -> Option<(i64, i64)> {
        let from = newest_ns?.min(now_ns);
        let days = |d: f64| (d * 86_400e9) as i64;
        Some((
            from.saturating_sub(days(self.samples_days)),
            from.saturating_sub(days(self.results_days)),
        ))
    }
}

/// A site's name in a fleet (`[site] name`): 1 to 48 characters, lowercase letters, digits,
/// `-` and `_`, starting with a letter or digit. It names the site at the centre, in URLs and
/// in the centre's database.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct SiteName(String);

impl SiteName {
    /// The longest name.
    pub const MAX_LEN: usize = 48;

    /// The name, when `text` is a valid one.
    pub fn parse(text: &str) -> Option<SiteName> {
        let ok = !text.is_empty()
            && text.len() <= Self::MAX_LEN
            && text
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'_')
            && !text.starts_with(['-', '_']);
        ok.then(|| SiteName(text.to_owned()))
    }

    /// The name as text.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for SiteName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// This service's part in a fleet (`[site]`, `[upstream]`, `[central]`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FleetSettings {
    /// The site's name; `None` for a service that is no fleet's site.
    pub site: Option<SiteName>,
    /// Where the site pushes its history; `None`: it keeps it to itself.
    pub upstream: Option<UpstreamSettings>,
    /// The centre's settings when this service takes sites' uploads.
    pub central: Option<CentralSettings>,
}

/// Where and how a site pushes its history (`[upstream]`).
#[derive(Clone, PartialEq)]
pub struct UpstreamSettings {
    /// The centre's base URL (`http://central:7878`).
    pub url: url::Url,
    /// The bearer token (scope `sync`, this site), from `token` or `token_file`.
    pub token: Option<String>,
    /// The budget for raw samples (kbit/s of compressed upload); 0 sends none unless asked.
    pub raw_kbit_s: f64,
    /// Most rows in one upload (a commit of more rows goes in parts).
    pub batch_rows: usize,
    /// Most bytes of JSON in one upload before compression (the centre's own limit, which it
    /// tells the site, lowers it further).
    pub batch_bytes: usize,
    /// Seconds between status reports when nothing else is sent.
    pub heartbeat_s: f64,
}

/// `url` as it may be shown (logs, the API): without a user name or password it may carry,
/// nor its query and fragment (where a key may travel: `?key=...`), each said to be there.
pub fn redacted_url(url: &url::Url) -> String {
    let mut shown = url.clone();
    let had_query = shown.query().is_some() || shown.fragment().is_some();
    shown.set_query(None);
    shown.set_fragment(None);
    let had_credentials = !shown.username().is_empty() || shown.password().is_some();
    let _ = shown.set_username("");
    let _ = shown.set_password(None);
    let mut text = shown.to_string();
    if had_credentials {
        text = text.replacen("://", "://<credentials>@", 1);
    }
    if had_query {
        text.push_str("?<redacted>");
    }
    text
}

impl std::fmt::Debug for UpstreamSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UpstreamSettings")
            .field("url", &redacted_url(&self.url))
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .field("raw_kbit_s", &self.raw_kbit_s)
            .field("batch_rows", &self.batch_rows)
            .field("batch_bytes", &self.batch_bytes)
            .field("heartbeat_s", &self.heartbeat_s)
            .finish()
    }
}

/// The centre's settings (`[central]`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CentralSettings {
    /// Largest upload once decompressed (bytes).
    pub max_sync_bytes: usize,
    /// Sites' raw tier (samples and raw results) kept this long (days, the centre's clock).
    pub raw_days: f64,
    /// Sites' filtered results kept this long (days); rollups and the events tier stay.
    pub results_days: f64,
}

/// Where the history is kept (`[server] database`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Database {
    /// An SQLite file (created if missing): the embedded default.
    Sqlite(PathBuf),
    /// A PostgreSQL database, by its `postgres://` URL.
    Postgres(PostgresUrl),
}

impl Database {
    /// The SQLite file, when the database is one.
    pub fn sqlite_path(&self) -> Option<&Path> {
        match self {
            Database::Sqlite(p) => Some(p),
            Database::Postgres(_) => None,
        }
    }
}

/// Names the database for people: the file, or the URL without its password.
impl std::fmt::Display for Database {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Database::Sqlite(p) => write!(f, "{}", p.display()),
            Database::Postgres(u) => write!(f, "{u}"),
        }
    }
}

/// A PostgreSQL URL (`postgres://user:password@host:port/database?options`). It prints without
/// its password, so logs and error messages never carry it.
#[derive(Clone, PartialEq, Eq)]
pub struct PostgresUrl(url::Url);

impl PostgresUrl {
    /// Parses a `postgres://` or `postgresql://` URL; `None` when it is not one.
    pub fn parse(text: &str) -> Option<PostgresUrl> {
        let url = url::Url::parse(text).ok()?;
        matches!(url.scheme(), "postgres" | "postgresql").then_some(PostgresUrl(url))
    }

    /// The whole URL, password included, for the driver only.
    pub fn secret(&self) -> &str {
        self.0.as_str()
    }

    /// The database's name (the URL's path), if the URL gives one.
    pub fn database_name(&self) -> Option<&str> {
        Some(self.0.path().trim_start_matches('/')).filter(|n| !n.is_empty())
    }
}

impl std::fmt::Display for PostgresUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let mut shown = self.0.clone();
        if shown.password().is_some() {
            let _ = shown.set_password(Some("***"));
        }
        write!(f, "{shown}")
    }
}

impl std::fmt::Debug for PostgresUrl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "PostgresUrl({self})")
    }
}

/// HTTP server settings.
#[derive(Debug, Clone, PartialEq)]
pub struct ServerSettings {
    /// The address to listen on.
    pub listen: SocketAddr,
    /// Where the history is kept: an SQLite file or a PostgreSQL database.
    pub database: Database,
    /// Largest request body (bytes).
    pub max_body_bytes: usize,
    /// Most samples in one ingest batch.
    pub max_batch_samples: usize,
    /// Most live result events per target and second of measurement time.
    pub events_max_hz: f64,
    /// A sample, observation or frame stamped more than this ahead of the server's clock is
    /// refused (s).
    pub max_future_s: f64,
    /// Skew allowed between the measurement pipeline's clock and the server's when judging
    /// staleness (s).
    pub clock_tolerance_s: f64,
    /// Host names (with or without port) accepted in the `Host` header besides the listen
    /// address, `localhost` and the loopback addresses; checked when no token is configured.
    pub allowed_hosts: Vec<String>,
    /// Most open client connections: past it a newcomer closes the connection that has waited
    /// longest for a request head, or is closed itself when every one is busy. `None`: 4096,
    /// or fewer when the process may not open that many files (said at start).
    pub max_connections: Option<usize>,
    /// Most open connections from one address, enforced the same way (`None`: a quarter of
    /// `max_connections`, at least 16).
    pub max_connections_per_address: Option<usize>,
    /// A client must send a request's headers within this time of connecting or of its
    /// previous answer (s): idle and slow connections are closed after it.
    pub header_timeout_s: f64,
    /// At shutdown, requests in progress get this long to finish before their connections are
    /// cut (s).
    pub shutdown_grace_s: f64,
    /// Most statistics and fine-history reads (each streams over many rows) at once; more wait.
    pub max_heavy_reads: usize,
}

crate::words! {
    /// What goes to Rerun (`[rerun] mode`: one word, or a list of the last three).
    pub enum RerunMode("rerun mode") {
        /// Nothing.
        Off = "off",
        /// A recording file per run.
        Save = "save",
        /// Streamed to a viewer.
        Connect = "connect",
        /// Served to viewers that connect.
        Serve = "serve",
    }
}

/// Rerun settings: which sinks, where, and how much goes to them.
#[derive(Debug, Clone, PartialEq)]
pub struct RerunSettings {
    /// Write a recording per run (rotated) in `recordings_dir`.
    pub save: bool,
    /// Stream to a viewer at `url`.
    pub connect: bool,
    /// Run a gRPC server at `serve_listen` that viewers connect to (late joiners get the
    /// buffered history).
    pub serve: bool,
    /// Where `save` writes recordings.
    pub recordings_dir: PathBuf,
    /// The viewer `connect` streams to.
    pub url: String,
    /// Where `serve` listens.
    pub serve_listen: SocketAddr,
    /// How much history `serve` keeps for late joiners (bytes).
    pub serve_memory_limit_bytes: u64,
    /// A new recording file after this long (s).
    pub rotate_after_s: f64,
    /// ... or once a file reaches this size (bytes).
    pub rotate_max_bytes: u64,
    /// Records waiting for the logger thread; more are dropped (and counted).
    pub queue_capacity: usize,
    /// Most scene updates (frame transforms) per second of measurement time.
    pub scene_hz: f64,
    /// Most points per second of measurement time in each time series.
    pub series_hz: f64,
    /// Most camera frames per camera and second of measurement time.
    pub image_hz: f64,
}

impl RerunSettings {
    /// Whether anything goes to Rerun.
    pub fn enabled(&self) -> bool {
        self.save || self.connect || self.serve
    }
}

crate::words! {
    /// What a bearer token may do.
    pub enum Scope("token scope") {
        /// Read results, history, statistics.
        Read = "read",
        /// Post samples and observations.
        Ingest = "ingest",
        /// Set references and calibrations.
        Admin = "admin",
        /// Upload a site's history to the centre; only for the token's own site.
        Sync = "sync",
    }
}

/// The lowercase hex SHA-256 of a token, as `[[auth.tokens]]`'s `sha256` holds it.
pub fn sha256_hex(token: &str) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(token.as_bytes()))
}

/// A configured bearer token.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TokenSpec {
    /// Who holds it.
    pub name: String,
    /// SHA-256 of the token text, lowercase hex.
    pub sha256_hex: String,
    /// What it may do.
    pub scopes: Vec<Scope>,
    /// The site a `sync` token may upload for.
    pub site: Option<SiteName>,
}

/// Where alarm transitions are sent (`[[notify.webhooks]]`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NotifySettings {
    /// Webhooks, in file order.
    pub webhooks: Vec<WebhookSpec>,
}

crate::words! {
    /// The lowest alarm level a webhook is told about.
    #[derive(PartialOrd, Ord)]
    pub enum NotifyLevel("webhook level") {
        /// Transitions to or from `warn` or `alarm`.
        Warn = "warn",
        /// Transitions to or from `alarm`.
        Alarm = "alarm",
    }
}

/// One webhook: alarm transitions are POSTed to `url`, signed with `secret`.
#[derive(Clone, PartialEq)]
pub struct WebhookSpec {
    /// `http://` or `https://` URL.
    pub url: String,
    /// The HMAC-SHA256 key of the signature header.
    pub secret: String,
    /// Transitions whose higher level (before or after) is below this are not sent.
    pub min_level: NotifyLevel,
    /// Each attempt's time limit (s).
    pub timeout_s: f64,
    /// Attempts before a delivery is given up (counted and logged).
    pub max_attempts: u32,
}

impl WebhookSpec {
    /// `host[:port]` of the URL: what logs and metrics name (a URL may carry credentials or a
    /// token in its path or query).
    pub fn host(&self) -> &str {
        let rest = self
            .url
            .split_once("://")
            .map_or(self.url.as_str(), |(_, r)| r);
        let authority = rest.split(['/', '?', '#']).next().unwrap_or(rest);
        authority.rsplit('@').next().unwrap_or(authority)
    }
}

impl std::fmt::Debug for WebhookSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WebhookSpec")
            .field("host", &self.host())
            .field("secret", &"<redacted>")
            .field("min_level", &self.min_level)
            .field("timeout_s", &self.timeout_s)
            .field("max_attempts", &self.max_attempts)
            .finish()
    }
}

/// Authentication settings.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct AuthSettings {
    /// The tokens; none means the server accepts everything (loopback only).
    pub tokens: Vec<TokenSpec>,
}

/// The built-in laboratory installation.
pub fn default_installation() -> Installation {
    // The embedded file is validated by a test; failing here is a build defect.
    #[allow(clippy::expect_used)]
    parse(DEFAULT_SOURCE_NAME, DEFAULT_INSTALLATION_TOML)
        .expect("the built-in installation is valid")
}

/// Reads and validates an installation file.
pub fn load(path: &Path) -> Result<Installation, ConfigError> {
    let source = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| {
        ConfigError::single(
            &source,
            ConfigProblem {
                line: None,
                column: None,
                message: format!("cannot read the file: {e}"),
            },
        )
    })?;
    parse(&source, &text)
}

/// Loads `path`, or the built-in installation when `None`.
pub fn load_or_default(path: Option<&Path>) -> Result<Installation, ConfigError> {
    match path {
        Some(p) => load(p),
        None => Ok(default_installation()),
    }
}

/// Parses and validates installation text; `source` names it in errors.
pub fn parse(source: &str, text: &str) -> Result<Installation, ConfigError> {
    let lines = LineIndex::new(text);
    let raw: RawFile = toml::from_str(text).map_err(|e| {
        let (line, column) = match e.span() {
            Some(span) => {
                let (l, c) = lines.locate(span.start);
                (Some(l), Some(c))
            }
            None => (None, None),
        };
        ConfigError::single(
            source,
            ConfigProblem {
                line,
                column,
                message: e.message().trim().to_owned(),
            },
        )
    })?;
    let mut v = Validator {
        lines,
        problems: Vec::new(),
        warnings: Vec::new(),
        marker_at: std::collections::HashMap::new(),
    };
    let installation = v.installation(source, raw);
    if v.problems.is_empty()
        && let Some(installation) = installation
    {
        return Ok(installation);
    }
    let mut problems = v.problems;
    problems.sort_by_key(|p| p.line);
    Err(ConfigError {
        file: source.to_owned(),
        problems,
    })
}

#[cfg(test)]
mod tests {
    use super::RetentionSettings;

    #[test]
    fn retention_counts_back_from_the_newest_result_but_never_from_the_future() {
        let r = RetentionSettings {
            samples_days: 1.0,
            results_days: 2.0,
            disk_budget_bytes: None,
        };
        let day = 86_400_000_000_000_i64;
        assert_eq!(r.cutoffs_ns(None, 10 * day), None, "nothing to count from");
        assert_eq!(
            r.cutoffs_ns(Some(5 * day), 10 * day),
            Some((4 * day, 3 * day))
        );
        assert_eq!(
            r.cutoffs_ns(Some(50 * day), 10 * day),
            Some((9 * day, 8 * day)),
            "a result stamped in the future counts from the clock"
        );
        assert_eq!(
            r.cutoffs_ns(Some(i64::MIN + 1), i64::MAX).map(|c| c.0),
            Some(i64::MIN),
            "saturates, never wraps"
        );
    }
}
