//! The integration tests, in one binary: each test binary links the whole dependency tree
//! (the Rerun SDK included), so one binary builds in a fraction of the time of one per file.
//! Run one part with a filter, e.g. `cargo test --test suite service::liveness`.

/// Runs each named `async fn NAME(backend: Backend)` as two tests, `NAME::sqlite` and
/// `NAME::postgres` (the latter on a fresh database of the throwaway cluster).
macro_rules! on_both_backends {
    (multi_thread: $($name:ident),* $(,)?) => {
        on_both_backends!(@tests [tokio::test(flavor = "multi_thread", worker_threads = 2)] $($name),*);
    };
    (@tests [$test:meta] $($name:ident),*) => {
        $(
            mod $name {
                #[$test]
                async fn sqlite() {
                    super::$name(crate::service::helpers::Backend::Sqlite).await
                }
                #[$test]
                async fn postgres() {
                    if crate::common::skip_without(
                        crate::common::Needs::Postgres,
                        concat!(module_path!(), "::postgres"),
                    ) {
                        return;
                    }
                    super::$name(crate::service::helpers::Backend::Postgres).await
                }
            }
        )*
    };
    ($($name:ident),* $(,)?) => {
        on_both_backends!(@tests [tokio::test] $($name),*);
    };
}

mod architecture;
mod archive;
mod bombs;
mod camera_calibration;
#[cfg(feature = "genicam")]
mod cameras_wire;
mod chain_composition;
mod cli;
mod common;
mod config_errors;
mod crash_safety;
mod deformation_and_stats;
mod detection;
mod filter_bank;
mod filter_behaviour;
mod fleet;
mod frames;
mod geometry_properties;
mod hand_eye;
mod marker_search;
mod pnp;
mod service;
mod store_backends;
mod uncertainty;
