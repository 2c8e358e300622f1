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
//! * [`geometry`]: SE(3) poses, Exp/Log, adjoint, rotation conversions, covariance, averaging.
//! * [`chain`]: the frame/link graph, path resolution, composition with covariance, fusion of
//!   redundant paths with a consistency statistic.
//! * [`config`]: the TOML installation file, parsed into validated domain types, and the
//!   built-in laboratory installation.
//! * [`filter`]: per-link error-state Kalman filters on SE(3) (static, constant-velocity,
//!   oscillatory), outlier gating, and the bank that evaluates targets at a time.
//! * [`deformation`]: references, deformation `G0_from_G` and correction `G_from_G0`.
//! * [`alarms`]: alarm levels of a target with hysteresis, dwell, rate of change and stale data.
//! * [`stats`]: the paper's Table 4/5 statistics over a set of results.
//! * [`vision`]: the camera model, PnP (IPPE / SQPnP + Levenberg-Marquardt) and hand-eye
//!   station calibration.
//! * [`sim`]: the scenario simulator (static, drift, ship flexure, tunnel creep, a bumped
//!   station): ground truth and what the cameras see.
//! * [`feed`]: the simulator's output as request bodies and NDJSON, and the HTTP client that
//!   feeds a service with it.
//! * [`clock`]: the server's clock (wall time for liveness and stamps), settable in tests.
//! * [`cli`]: the command line (the binary in `main.rs` only calls it).
//!
//! The core (`geometry`, `chain`, `filter`, `deformation`, `stats`, `alarms`, `vision`, `sim`)
//! is pure and synchronous: no IO, no clock (times are passed in; the server's clock is
//! [`clock`]'s), no async runtime. Adapters (`config`, `store`, `service`, `api`, `viz`, `feed`,
//! `cli`) do the IO around it; ARCHITECTURE.md has the map. Conventions are in the module docs
//! of [`geometry`], the mathematics in `docs/method.md`.

#![warn(clippy::unwrap_used, clippy::expect_used)]

pub mod alarms;
pub mod api;
pub mod chain;
pub mod cli;
pub mod clock;
pub mod config;
pub mod deformation;
pub mod feed;
pub mod filter;
pub mod geometry;
pub mod service;
pub mod sim;
pub mod stats;
pub mod store;
pub mod vision;
pub mod viz;
