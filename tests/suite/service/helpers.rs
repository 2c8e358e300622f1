//! A service on a temporary SQLite file (or a fresh PostgreSQL database of the tests'
//! throwaway cluster), driven in process through the router.

use axum::Router;
use axum::body::Body;
use axum::http::{Request, StatusCode};
use brokenray::api::{AppState, router};
use brokenray::clock::{Clock as _, ManualClock};
use brokenray::config::{self, Installation};
use brokenray::service::{PipelineHandle, Service};
use http_body_util::BodyExt;
use serde_json::Value;
use tower::ServiceExt;

/// Which store a test's service runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// A file in the test's temporary directory.
    Sqlite,
    /// A fresh database in the process's throwaway cluster.
    Postgres,
}

impl Backend {
    /// A new database of this backend: its `[server] database` value.
    pub fn database(self, dir: &tempfile::TempDir) -> String {
        match self {
            Backend::Sqlite => dir.path().join("brokenray.db").display().to_string(),
            Backend::Postgres => crate::common::postgres::fresh_database(),
        }
    }
}

pub struct TestApp {
    /// The service's clock: it reads [`START_NS`] until a test moves it.
    pub clock: ManualClock,
    pub dir: tempfile::TempDir,
    pub service: Service,
    pub pipeline: Option<PipelineHandle>,
    pub router: Router,
    /// The `[server] database` value, kept by restarts.
    pub database: String,
    /// The camera sources' states, as `GET /api/v1/cameras` shows them; no camera is opened
    /// (a test sets their state).
    pub sources: Vec<std::sync::Arc<brokenray::acquire::SourceState>>,
}

/// The built-in installation with its database in a fresh temporary directory, plus `extra`
/// TOML appended (or replacing it entirely when `replace` is given).
pub fn installation(dir: &tempfile::TempDir, text: Option<&str>) -> Installation {
    installation_at(&Backend::Sqlite.database(dir), text)
}

/// The built-in installation (or `text`) with `[server] database = database`.
pub fn installation_at(database: &str, text: Option<&str>) -> Installation {
    let base = text.unwrap_or(config::DEFAULT_INSTALLATION_TOML);
    let text = if base.contains("[server]") {
        base.replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{database}\""),
        )
    } else {
        format!("[server]\ndatabase = \"{database}\"\n{base}")
    };
    config::parse("test.toml", &text).expect("valid test installation")
}

impl TestApp {
    pub async fn start(text: Option<&str>) -> TestApp {
        Self::start_on(Backend::Sqlite, text).await
    }

    /// A service on a new database of `backend`.
    pub async fn start_on(backend: Backend, text: Option<&str>) -> TestApp {
        let dir = tempfile::tempdir().expect("temp dir");
        let inst = installation_at(&backend.database(&dir), text);
        Self::start_with(dir, inst).await
    }

    pub async fn start_with(dir: tempfile::TempDir, inst: Installation) -> TestApp {
        Self::start_with_clock(dir, inst, ManualClock::new(START_NS)).await
    }

    pub async fn start_with_clock(
        dir: tempfile::TempDir,
        inst: Installation,
        clock: ManualClock,
    ) -> TestApp {
        let inst_database = inst.server.database.clone();
        let (service, pipeline) =
            Service::start_with_clock(inst, std::sync::Arc::new(clock.clone()))
                .await
                .expect("service starts");
        let mut state = AppState::new(service.clone()).expect("the frame archive");
        let sources: Vec<_> = (service.installation().sources.iter())
            .map(|s| std::sync::Arc::new(brokenray::acquire::SourceState::new(s.clone())))
            .collect();
        state.sources = sources.clone().into();
        // The plant's outputs start as `serve` starts them.
        state.outputs = std::sync::Arc::new(
            brokenray::outputs::Outputs::start(
                &service,
                std::sync::Arc::clone(&state.sources),
                brokenray::api::output_encoders(&service),
            )
            .await
            .expect("the outputs start"),
        );
        let router = router(state);
        let database = match &inst_database {
            config::Database::Sqlite(p) => p.display().to_string(),
            config::Database::Postgres(u) => u.secret().to_owned(),
        };
        TestApp {
            database,
            clock,
            dir,
            service,
            pipeline: Some(pipeline),
            router,
            sources,
        }
    }

    /// Stops the service cleanly and starts it again on the same database.
    pub async fn restart(mut self, text: Option<&str>) -> TestApp {
        let pipeline = self.pipeline.take().expect("running");
        let store = self.service.store().clone();
        drop(self.router);
        drop(self.service);
        pipeline.finished().await.expect("a clean stop");
        store.close().await;
        let inst = installation_at(&self.database, text);
        Self::start_with_clock(self.dir, inst, self.clock).await
    }

    pub async fn request(
        &self,
        method: &str,
        uri: &str,
        body: Option<(&str, String)>,
        token: Option<&str>,
    ) -> (StatusCode, Value) {
        let authorization = token.map(|t| format!("Bearer {t}"));
        let mut headers: Vec<(&str, &str)> = Vec::new();
        if let Some(a) = &authorization {
            headers.push(("authorization", a));
        }
        let text = match body {
            Some((content_type, text)) => {
                headers.push(("content-type", content_type));
                text
            }
            None => String::new(),
        };
        self.request_with_headers(method, uri, &headers, text).await
    }

    /// A request with exactly the given headers (none added); the body as JSON (or as a
    /// string when it is not JSON).
    pub async fn request_with_headers(
        &self,
        method: &str,
        uri: &str,
        headers: &[(&str, &str)],
        body: impl Into<Body>,
    ) -> (StatusCode, Value) {
        let (status, _, bytes) = self.request_raw(method, uri, headers, body).await;
        let value = if bytes.is_empty() {
            Value::Null
        } else {
            serde_json::from_slice(&bytes)
                .unwrap_or_else(|_| Value::String(String::from_utf8_lossy(&bytes).into_owned()))
        };
        (status, value)
    }

    /// A request with exactly the given headers; the answer's status, headers and raw body.
    pub async fn request_raw(
        &self,
        method: &str,
        uri: &str,
        headers: &[(&str, &str)],
        body: impl Into<Body>,
    ) -> (StatusCode, axum::http::HeaderMap, axum::body::Bytes) {
        let mut builder = Request::builder().method(method).uri(uri);
        for (k, v) in headers {
            builder = builder.header(*k, *v);
        }
        let req = builder.body(body.into()).expect("request");
        let resp = self.router.clone().oneshot(req).await.expect("response");
        let (parts, body) = resp.into_parts();
        let bytes = body.collect().await.expect("body").to_bytes();
        (parts.status, parts.headers, bytes)
    }

    pub async fn get(&self, uri: &str) -> (StatusCode, Value) {
        self.request("GET", uri, None, None).await
    }

    pub async fn post_json(&self, uri: &str, body: &Value) -> (StatusCode, Value) {
        self.request(
            "POST",
            uri,
            Some(("application/json", body.to_string())),
            None,
        )
        .await
    }

    /// Posts a batch of samples or observations the way a live feed delivers it: the clock
    /// first moves on to the batch's newest time (never back), so that the data is current
    /// and none of it lies in the future.
    pub async fn post_live(&self, uri: &str, body: &Value) -> (StatusCode, Value) {
        let newest = ["samples", "observations"]
            .iter()
            .filter_map(|k| body[k].as_array())
            .flatten()
            .filter_map(|item| brokenray::clock::parse_json_time(&item["time"]).ok())
            .max();
        if let Some(t) = newest
            && t > self.clock.now_ns()
        {
            self.clock.set_ns(t);
        }
        self.post_json(uri, body).await
    }

    /// Sets target G's reference to `G_from_B` = 3 m along z, unrotated (the pose the alarm
    /// tests turn away from); must be accepted.
    /// Asserts that no link has a stored sample.
    pub async fn assert_nothing_stored(&self) {
        let (_, links) = self.get("/api/v1/links").await;
        for l in links.as_array().expect("links") {
            assert_eq!(l["n_samples"].as_u64().unwrap_or(0), 0, "{l}");
        }
    }

    pub async fn set_straight_reference(&self) {
        let (status, body) = self
            .post_json(
                "/api/v1/targets/G/reference",
                &serde_json::json!({"pose": {"t_mm": [0, 0, 3000], "q_wxyz": [1, 0, 0, 0]}}),
            )
            .await;
        assert_eq!(status, StatusCode::CREATED, "{body}");
    }

    pub async fn post_text(
        &self,
        uri: &str,
        content_type: &str,
        text: &str,
    ) -> (StatusCode, Value) {
        self.request("POST", uri, Some((content_type, text.to_owned())), None)
            .await
    }
}

/// RFC 3339 text of a time `k * 40 ms` after 2026-11-21T10:00:00Z.
pub fn time_text(k: i64) -> String {
    brokenray::clock::format_ns(T0_NS + k * 40_000_000)
}

/// 2026-11-21T10:00:00Z in nanoseconds.
pub const T0_NS: i64 = 1_795_255_200_000_000_000;

/// Where a test service's clock starts: 2 s after [`T0_NS`]. Samples up to `max_future_s` (5 s)
/// later are accepted, and a feed that starts at `T0_NS` is current.
pub const START_NS: i64 = T0_NS + 2_000_000_000;

pub fn pose_json(p: &brokenray::geometry::Pose) -> Value {
    let q = brokenray::geometry::quaternion_wxyz(&p.rotation);
    let t = p.translation.vector;
    serde_json::json!({"t_mm": [t.x, t.y, t.z], "q_wxyz": q})
}

/// A sample of `G_from_B` at `time_ns`: 3 m along z, turned by `arcsec` about x.
pub fn turned_sample(time_ns: i64, arcsec: f64) -> Value {
    let half = (arcsec / 3600.0).to_radians() / 2.0;
    serde_json::json!({"link": "G_from_B", "time": time_ns,
                       "pose": {"t_mm": [0, 0, 3000], "q_wxyz": [half.cos(), half.sin(), 0, 0]}})
}

/// Posts live samples of `G_from_B` at 25 Hz, turned about x by each of `turns_arcsec` for a
/// second each, and gives target G's alarms as `GET /alarms` lists them.
pub async fn alarms_after_turns(app: &TestApp, turns_arcsec: &[f64]) -> Vec<Value> {
    let samples: Vec<Value> = (0..25 * turns_arcsec.len())
        .map(|k| turned_sample(T0_NS + k as i64 * 40_000_000, turns_arcsec[k / 25]))
        .collect();
    let (status, body) = app
        .post_live(
            "/api/v1/samples",
            &serde_json::json!({ "samples": samples }),
        )
        .await;
    assert_eq!(status, axum::http::StatusCode::OK, "{body}");
    let (_, list) = app.get("/api/v1/alarms?target=G").await;
    list["alarms"].as_array().cloned().unwrap_or_default()
}

/// A one-link installation: `G_from_B` measured directly, target G from base B.
/// One measured link `G_from_B` (25 Hz), target G with alarm thresholds of 60 and 120
/// arc-seconds and no dwell (each level is taken at once), and `extra` appended: what the
/// alarm's receivers (webhooks, the plant's outputs) are tested on.
pub fn alarmed_installation(extra: &str) -> String {
    format!(
        r#"
[[links]]
name = "G_from_B"
kind = "measured"
sigma = {{ rotation_arcsec = 5.0, translation_mm = 0.05 }}
expected_rate_hz = 25.0
random_walk = {{ rotation_arcsec_per_sqrt_s = 20.0, translation_mm_per_sqrt_s = 0.1 }}

[[targets]]
name = "G"
base = "B"
[targets.alarms]
warn_rotation_arcsec = 60.0
alarm_rotation_arcsec = 120.0
hysteresis = 0.1
dwell_s = 0.0
{extra}
"#
    )
}

pub const ONE_LINK: &str = r#"
[[links]]
name = "G_from_B"
kind = "measured"
sigma = { rotation_arcsec = 30.0, translation_mm = 1.0 }
expected_rate_hz = 1.0

[[targets]]
name = "G"
base = "B"
"#;

/// A group of the three measured links of the built-in installation at `k * 40 ms` after
/// 2026-11-21T10:00:00Z (poses near the nominal ones).
pub fn nominal_group(k: i64) -> Value {
    let samples: Vec<Value> = ["C1_from_B", "C2_from_M", "C3_from_G"]
        .iter()
        .map(|l| {
            serde_json::json!({"link": l, "time": T0_NS + k * 40_000_000,
                               "pose": {"t_mm": [0.0, 0.0, 3000.0], "q_wxyz": [0, 1, 0, 0]}})
        })
        .collect();
    serde_json::json!({ "samples": samples })
}
