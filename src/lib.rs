//! brokenray: broken-ray videometrics for the deformation of large structures.
//!
//! A base body B and a target body G that cannot see each other are joined by relay stations of
//! cameras and cooperative markers. Every camera that sees a marker measures one link by pose
//! estimation; every rigid station contributes one calibrated link; the chain of rigid
//! transforms gives `G_from_B`. Its change against a reference is the deformation, and its
//! inverse the correction that devices on G apply.
//!
//! # Layout
//!
//! The core, bottom up (a module uses only the layers below it; `tests/suite/architecture.rs`
//! checks this and that the core does no IO):
//!
//! * [`geometry`]: SE(3) poses, Exp/Log, adjoint, rotation conversions, covariance, averaging.
//! * [`chain`]: the frame/link graph, path resolution, composition with covariance, fusion of
//!   redundant paths with a consistency statistic. [`deformation`]: references, deformation
//!   `G0_from_G` and correction `G_from_G0`. [`stats`]: the paper's Table 4/5 statistics.
//! * [`filter`]: one measured link's error-state Kalman filter on SE(3) (static,
//!   constant-velocity, oscillatory) with outlier gating. [`vision`]: the camera model, PnP
//!   (IPPE / SQPnP + Levenberg-Marquardt) and hand-eye station calibration. [`alarms`]: alarm
//!   levels of a target with hysteresis, dwell, rate of change and stale data. [`acceptance`]:
//!   the acceptance procedure's figures (zero and displacement deviations with their
//!   uncertainty) and its steps.
//! * [`model`]: an installation's measurement model (frames, links, targets, cameras, markers,
//!   filter and PnP settings), the camera-marker links that solve observations, and the markers
//!   found in a camera's frame.
//! * [`bank`]: one filter per measured link of a model; targets evaluated at a time, raw
//!   results from measurement groups, liveness.
//! * [`sim`]: the scenario simulator (static, drift, ship flexure, tunnel creep, a bumped
//!   station): ground truth and what the cameras see, as pixels or rendered frames.
//!
//! [`clock`] is the one home of the server's clock and of time text; the core never reads it
//! (times are passed in). The adapters do the IO around the core: [`config`] (the installation
//! file: the model plus deployment settings), [`store`] (SQLite and PostgreSQL), [`service`] (the single
//! writer), [`intake`] (a frame's way in, whoever brings it), [`wire`] (the JSON documents more
//! than one door reads or writes: poses, observations, calibrations' requests and results),
//! [`api`] (HTTP), [`app`] (the
//! composition root: start, the spawned tasks, the server loop, shutdown), [`notify`] (webhooks), [`outputs`] (MQTT, Modbus/TCP, NMEA 0183),
//! [`telemetry`] (`/metrics`), [`report`] (HTML reports with SVG pictures), [`acquire`] (cameras), [`imagefile`] (frame files), [`archive`]
//! (the frame archive), [`fleet`] (a site's uploads to a centre), [`viz`] (Rerun), [`feed`]
//! (the simulator's HTTP client) and [`cli`] (the binary in `main.rs` only calls it). ARCHITECTURE.md has the map; conventions are in the
//! module docs of [`geometry`], the mathematics in `docs/method.md`.

#![warn(clippy::unwrap_used, clippy::expect_used)]
#![warn(unreachable_pub)]

pub mod acceptance;
pub mod acquire;
pub mod alarms;
pub mod api;
pub mod app;
pub mod archive;
pub mod bank;
pub mod chain;
pub mod cli;
pub mod clock;
pub mod config;
pub mod deformation;
pub mod feed;
pub mod filter;
pub mod fleet;
pub mod geometry;
pub mod imagefile;
pub mod intake;
pub mod model;
pub mod notify;
pub mod outputs;
pub mod report;
pub mod service;
pub mod sim;
pub mod stats;
pub mod store;
pub mod telemetry;
pub mod vision;
pub mod viz;
pub mod wire;
pub mod words;
