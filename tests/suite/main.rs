//! The integration tests, in one binary: each test binary links the whole dependency tree
//! (the Rerun SDK included), so one binary builds in a fraction of the time of one per file.
//! Run one part with a filter, e.g. `cargo test --test suite service::liveness`.

mod architecture;
mod archive;
mod camera_calibration;
mod chain_composition;
mod cli;
mod common;
mod config_errors;
mod crash_safety;
mod deformation_and_stats;
mod detection;
mod filter_bank;
mod filter_behaviour;
mod frames;
mod geometry_properties;
mod hand_eye;
mod pnp;
mod service;
