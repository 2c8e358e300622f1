//! The service in process: the router on a real SQLite file.

mod acceptance;
mod access;
mod alarms;
mod calibrated_cameras;
mod calibration;
mod cameras;
pub(crate) mod dashboard;
mod frames;
mod hardening;
pub mod helpers;
mod history;
mod ingest_errors;
mod liveness;
mod observations;
mod openapi;
mod outputs;
mod pipelining;
mod recordings;
mod reports;
mod results;
mod webhooks;
