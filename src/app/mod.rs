//! The composition root: the service started, its HTTP state built over it, the cameras opened
//! and their frames taken ([`crate::intake`]), the plant's outputs, a fleet's uploader or a
//! centre's upkeep spawned, the server loop ([`server`]) run, and everything stopped in order
//! at shutdown so that nothing acknowledged is lost.

pub mod server;

use crate::api::{AppState, router};
use crate::config::Installation;
use crate::service::{PipelineHandle, Service};
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

/// Errors of starting the server.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// Listening without tokens on an address others can reach.
    #[error(
        "refusing to listen on {0} without authentication: add [[auth.tokens]] to the configuration \
         (see `brokenray hash-token`), or listen on a loopback address such as 127.0.0.1"
    )]
    UnauthenticatedNonLoopback(SocketAddr),
    /// The address could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The service could not start.
    #[error(transparent)]
    Service(#[from] crate::service::ServiceError),
    /// The frame archive could not be opened.
    #[error(transparent)]
    Archive(#[from] crate::archive::ArchiveError),
    /// An output of the plant's buses could not start.
    #[error(transparent)]
    Output(#[from] crate::outputs::OutputError),
}

/// A bound, started service, ready to run until a shutdown signal.
pub struct App {
    listener: tokio::net::TcpListener,
    service: Service,
    pipeline: PipelineHandle,
    state: AppState,
    acquisition: crate::acquire::Acquisition,
}

/// Starts the centre's upkeep of its sites' copies ([`crate::fleet::upkeep`]).
fn spawn_centre_upkeep(state: &AppState) -> Option<tokio::task::JoinHandle<()>> {
    let centre = Arc::clone(state.centre.as_ref()?);
    Some(crate::fleet::upkeep::spawn(state.service.clone(), centre))
}

/// Starts the uploader of a site that pushes to a centre.
fn spawn_uploader(state: &AppState) -> Option<tokio::task::JoinHandle<()>> {
    let upstream = Arc::clone(state.upstream.as_ref()?);
    Some(state.service.spawn_watched(
        "uploader",
        crate::fleet::uploader::run(state.service.clone(), upstream),
    ))
}

impl App {
    /// Starts the service and binds its address (port 0 picks a free port).
    pub async fn build(installation: Installation) -> Result<App, StartError> {
        let addr = installation.server.listen;
        if installation.auth.tokens.is_empty() && !addr.ip().is_loopback() {
            return Err(StartError::UnauthenticatedNonLoopback(addr));
        }
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|source| StartError::Bind { addr, source })?;
        let centre = match (installation.fleet.central, &installation.server.database) {
            (Some(settings), crate::config::Database::Postgres(url)) => {
                let store = crate::store::Central::open(url)
                    .await
                    .map_err(|e| StartError::Service(crate::service::ServiceError::Storage(e)))?;
                Some(Arc::new(crate::fleet::Centre::new(store, settings)))
            }
            _ => None,
        };
        let (service, pipeline) = Service::start(installation).await?;
        let mut state = AppState::new(service.clone())?;
        state.centre = centre;
        // Cameras are opened once everything else started: their frames have somewhere to go.
        let acquisition = crate::acquire::Acquisition::start(service.installation());
        state.sources = acquisition.sources().into();
        state.outputs = Arc::new(
            crate::outputs::Outputs::start(
                &service,
                Arc::clone(&state.sources),
                crate::api::output_encoders(&service),
            )
            .await?,
        );
        Ok(App {
            listener,
            service,
            pipeline,
            state,
            acquisition,
        })
    }

    /// The bound address.
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// The service (for in-process use).
    pub fn service(&self) -> &Service {
        &self.service
    }

    /// Serves until `shutdown` resolves, then stops accepting, ends live event streams, lets
    /// requests in progress finish (for `[server] shutdown_grace_s`, then cuts them off),
    /// commits the queued writes, checkpoints and closes the database. An error says that the
    /// stop was not clean (the writer failed or the database file was replaced): the last
    /// writes may not be where they belong.
    pub async fn run_until(
        self,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> std::io::Result<()> {
        let settings = &self.service.installation().server;
        let max_connections = settings
            .max_connections
            .unwrap_or_else(|| server::default_max_connections(server::open_files_limit()));
        let limits = server::ServerLimits {
            max_connections,
            max_connections_per_address: settings
                .max_connections_per_address
                .unwrap_or((max_connections / 4).max(16)),
            header_timeout: Duration::from_secs_f64(settings.header_timeout_s),
            shutdown_grace: Duration::from_secs_f64(settings.shutdown_grace_s),
        };
        let state = self.state;
        let webhooks = state.webhooks.clone();
        let outputs = Arc::clone(&state.outputs);
        let store = self.service.store().clone();
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let uploader = spawn_uploader(&state);
        let upkeep = spawn_centre_upkeep(&state);
        let takers = state.intake.spawn_sources(&state.sources);
        let service = self.service.clone();
        tokio::spawn(async move {
            shutdown.await;
            service.begin_shutdown();
            let _ = stop_tx.send(true);
        });
        let metrics = self.service.metrics_handle();
        server::serve(self.listener, router(state), limits, metrics, stop_rx).await;
        // The cameras stop (their threads joined off the async workers), then the frames
        // already taken are ingested before the writer stops.
        let mut acquisition = self.acquisition;
        let _ = tokio::task::spawn_blocking(move || acquisition.stop()).await;
        for taker in takers {
            let _ = taker.await;
        }
        // The outputs end when shutdown begins (an MQTT output says `offline` first).
        outputs.finish(limits.shutdown_grace).await;
        // The uploader holds a service handle; it ends when shutdown begins.
        if let Some(uploader) = uploader {
            let _ = uploader.await;
        }
        if let Some(upkeep) = upkeep {
            let _ = upkeep.await;
        }
        // Handlers are done: dropping the last service handle closes the job queue, and the
        // pipeline commits what is queued before it stops.
        drop(self.service);
        let finished = self.pipeline.finished().await;
        // The pipeline has stopped: the webhooks get what it raised last.
        webhooks.finish(limits.shutdown_grace).await;
        let health = store.health().await;
        store.close().await;
        finished.map_err(std::io::Error::other)?;
        if !health.reachable {
            return Err(std::io::Error::other(
                health
                    .problem
                    .unwrap_or_else(|| "the database is not reachable".into()),
            ));
        }
        Ok(())
    }
}

/// Resolves on Ctrl-C or SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!(error = %e, "cannot listen for Ctrl-C");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for SIGTERM");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => tracing::info!("Ctrl-C: shutting down"),
        () = terminate => tracing::info!("SIGTERM: shutting down"),
    }
}
