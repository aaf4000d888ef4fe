//! The daemon: `rigd serve`. An HTTP API under `/api/v1` (axum), its
//! OpenAPI spec and Swagger UI, the event stream, and a supervisor that
//! drives one run at a time on the rig and starts queued runs.
//!
//! - [`supervisor`]: the daemon's state: runs, the queue, the engine of the
//!   active run
//! - [`jobs`]: process jobs and the worker that runs them
//! - [`manual_session`]: manual control's rig, held between actions
//! - [`peers`]: the other rigs' daemons (`--peers FILE`), watched
//! - [`plan_cache`]: built-in plans, solved once in the background
//! - [`data_dir`]: the queue file and the run history on disk
//! - [`api`]: the handlers and the OpenAPI description
//! - [`wire`]: the API's JSON types
//! - [`auth`]: the bearer token
//! - [`events`]: Server-Sent Events with replay
//! - [`error`]: `{error, detail}` errors, and the services' refusals
//! - [`http`]: the connections, with their timeouts and limits

pub mod api;
pub mod auth;
pub mod data_dir;
pub mod error;
pub mod events;
pub mod history;
pub mod http;
pub mod jobs;
pub mod manual_session;
pub mod peers;
pub mod plan_cache;
pub mod run_index;
pub mod supervisor;
pub mod wire;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::DefaultBodyLimit;
use axum::http::header;
use axum::response::IntoResponse;
use axum::routing::{delete, get, post};
use axum::Router;
use tokio::task::JoinHandle;

use utoipa_swagger_ui::SwaggerUi;

use api::{daemon, frames, manual, peers as peer_routes, plans, process, queue, rig, runs, viewer};
#[cfg(feature = "sim")]
use api::{sim, tradeoff};

use crate::model::profile::{Profile, DEFAULT_PROFILE};
use crate::model::run_state::RunState;

/// Largest request body accepted.
pub const BODY_LIMIT: usize = 64 * 1024;
/// Default listen address.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:8080";
/// Default data directory.
pub const DEFAULT_DATA: &str = "rigd-data";
/// Default simulation speed: physical seconds per wall second. A demo H1
/// run on the simulated Bonn rig (6561 images, about 10 h 12 min physical)
/// takes about 3 minutes.
pub const DEFAULT_SIM_SPEED: f64 = 200.0;

/// How the daemon is started.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// A profile file or embedded name; None is the embedded default.
    pub profile: Option<String>,
    /// Drive the simulated rig.
    pub sim: bool,
    /// Address to serve HTTP on (default `127.0.0.1:8080`; port 0 takes a free port).
    pub listen: SocketAddr,
    /// The data directory: `runs/`, `queue.json`, the token and the trade-off
    /// report; created if missing.
    pub data_dir: PathBuf,
    /// Physical seconds per wall second of the simulated rig.
    pub sim_speed: f64,
    /// Where the token is; None: `DATA/token`, generated at first start.
    pub token_file: Option<PathBuf>,
    /// Faults injected into the simulated rig of every new run (demos and
    /// tests of fault handling).
    pub sim_faults: Vec<crate::rig::FaultRule>,
    /// The other rigs' daemons, shown with this one in `GET /api/v1/peers`
    /// and the dashboard (`--peers FILE`, read by [`peers::load`]); names
    /// must be unique. Empty: this rig alone.
    pub peers: Vec<peers::Peer>,
    /// Where process jobs run: here, or on a Slurm cluster (the
    /// `[processing]` table of `rigd serve --config FILE`).
    pub processing: crate::postprocess::executor::ProcessingConfig,
    /// Timeouts and limits of the HTTP server (the `[http]` table of
    /// `rigd serve --config FILE`).
    pub http: http::HttpLimits,
}

impl ServerConfig {
    /// The defaults, with a data directory.
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        ServerConfig {
            profile: None,
            sim: true,
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            data_dir: data_dir.into(),
            sim_speed: DEFAULT_SIM_SPEED,
            token_file: None,
            sim_faults: Vec::new(),
            peers: Vec::new(),
            processing: Default::default(),
            http: http::HttpLimits::default(),
        }
    }
}

/// Why the daemon cannot start.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    /// The profile could not be read, parsed or validated.
    #[error(transparent)]
    Profile(#[from] crate::model::profile::ProfileError),
    /// `--sim-speed` is not a positive finite number.
    #[error("--sim-speed {0}: expected a positive number")]
    Speed(f64),
    /// The data directory (or its `runs/`) cannot be created.
    #[error("data directory {path}: {why}")]
    DataDir {
        /// The directory.
        path: PathBuf,
        /// The operating system's error.
        why: String,
    },
    /// The token file cannot be read or written, or holds no usable token
    /// (one line of at least 16 visible characters).
    #[error("token file {path}: {why}")]
    Token {
        /// The token file.
        path: PathBuf,
        /// What is wrong with it.
        why: String,
    },
    /// Two peers of [`ServerConfig::peers`] have the same name.
    #[error("peers: the name `{0}` is used twice")]
    Peers(String),
    /// The processing executor's configuration cannot work (Slurm's
    /// commands missing, the data directory not on a shared path, an
    /// unknown partition).
    #[error("[processing]: {0}")]
    Processing(crate::postprocess::slurm::SlurmError),
    /// A value of the `[http]` table is out of range.
    #[error("[http] {0}")]
    Http(String),
    /// The listen address cannot be bound.
    #[error("cannot listen on {addr}: {why}")]
    Listen {
        /// The address asked for.
        addr: SocketAddr,
        /// The operating system's error.
        why: String,
    },
}

/// A running daemon.
pub struct ServerHandle {
    /// The daemon's state and run supervisor.
    pub daemon: Arc<supervisor::Daemon>,
    /// The API token and the file it is kept in.
    pub token: auth::Token,
    server: JoinHandle<()>,
}

impl ServerHandle {
    /// Graceful shutdown: the active run is detached (paused, resumable),
    /// its engine ends, event streams close, then the server stops.
    pub async fn shutdown(self) {
        self.daemon.shutdown().await;
        let mut server = self.server;
        if tokio::time::timeout(Duration::from_secs(10), &mut server)
            .await
            .is_err()
        {
            tracing::warn!("connections still open after 10 s; closing them");
            server.abort();
        }
    }
}

const INDEX_HTML: &str = include_str!("dashboard/index.html");
const APP_JS: &str = include_str!("dashboard/app.js");
const HEMISPHERE_JS: &str = include_str!("dashboard/hemisphere.js");
const STYLE_CSS: &str = include_str!("dashboard/style.css");

/// The router of a daemon (the token is needed for the auth layer).
pub fn router(daemon: Arc<supervisor::Daemon>, token: auth::Token) -> Router {
    let v1 = Router::new()
        .route("/rig", get(rig::rig))
        .route("/rig/check", get(rig::check))
        .route("/rig/manual/home", post(manual::home))
        .route("/rig/manual/jog", post(manual::jog))
        .route("/rig/manual/pose", post(manual::pose))
        .route("/rig/manual/lamp", post(manual::lamp))
        .route(
            "/rig/manual/frame",
            get(manual::last_frame).post(manual::take_frame),
        )
        .route("/rig/manual/holder-check", post(manual::holder_check))
        .route("/rig/manual/release", post(manual::release))
        .route("/plans", get(plans::plans))
        .route("/plans/{name}", get(plans::plan_detail))
        .route("/runs", get(runs::list_runs).post(runs::create_run))
        .route("/runs/{id}", get(runs::get_run))
        .route("/runs/{id}/steps", get(runs::run_steps))
        .route("/runs/{id}/manifest", get(runs::run_manifest))
        .route("/runs/{id}/pause", post(runs::pause_run))
        .route("/runs/{id}/resume", post(runs::resume_run))
        .route("/runs/{id}/abort", post(runs::abort_run))
        .route(
            "/runs/{id}/process",
            get(process::get_job).post(process::submit),
        )
        .route("/runs/{id}/process/cancel", post(process::cancel))
        .route("/runs/{id}/frames/{index}", get(frames::frame_raw))
        .route(
            "/runs/{id}/frames/{index}/preview",
            get(frames::frame_preview),
        )
        .route("/estop", post(rig::estop))
        .route("/peers", get(peer_routes::list_peers))
        .route("/peers/{name}/pause", post(peer_routes::pause_peer))
        .route("/peers/{name}/abort", post(peer_routes::abort_peer))
        .route("/events", get(daemon::events_sse))
        .route("/queue", get(queue::get_queue).post(queue::post_queue))
        .route("/queue/{item}", delete(queue::delete_queue))
        .route("/runs/{id}/btf", get(viewer::btf_manifest))
        .route("/runs/{id}/btf/data", get(viewer::btf_data))
        .route("/runs/{id}/btf/mesh/{kind}", get(viewer::btf_mesh))
        .route("/runs/{id}/mdf", get(viewer::mdf_manifest))
        .route("/runs/{id}/mdf/data", get(viewer::mdf_data));
    #[cfg(feature = "sim")]
    let v1 = v1
        .route("/tradeoff", get(tradeoff::get_report).post(tradeoff::start))
        .route("/tradeoff/plot.svg", get(tradeoff::get_plot))
        .route("/tradeoff/figure", get(tradeoff::get_figure))
        .route("/tradeoff/choice", get(tradeoff::get_choice))
        .route("/sim/render", get(sim::sim_render))
        .route("/sim/scenes", get(sim::sim_scenes));
    let v1 = v1
        .route_layer(axum::middleware::from_fn_with_state(
            token,
            auth::require_token,
        ))
        .route("/health", get(daemon::health))
        .method_not_allowed_fallback(error::method_not_allowed)
        .with_state(daemon);
    Router::new()
        .nest("/api/v1", v1)
        .merge(
            SwaggerUi::new("/api/docs")
                .external_url_unchecked("/api/v1/openapi.json", api::openapi_json()),
        )
        .route(
            "/",
            get(|| async { static_file("text/html; charset=utf-8", INDEX_HTML) }),
        )
        .route(
            "/app.js",
            get(|| async { static_file("text/javascript; charset=utf-8", APP_JS) }),
        )
        .route(
            "/hemisphere.js",
            get(|| async { static_file("text/javascript; charset=utf-8", HEMISPHERE_JS) }),
        )
        .route("/viewer/{run}", get(viewer::page))
        .route(
            "/viewer.js",
            get(|| async { static_file("text/javascript; charset=utf-8", viewer::VIEWER_JS) }),
        )
        .route(
            "/style.css",
            get(|| async { static_file("text/css; charset=utf-8", STYLE_CSS) }),
        )
        .fallback(error::not_found)
        .method_not_allowed_fallback(error::method_not_allowed)
        .layer(DefaultBodyLimit::max(BODY_LIMIT))
}

fn static_file(content_type: &'static str, body: &'static str) -> axum::response::Response {
    ([(header::CONTENT_TYPE, content_type)], body).into_response()
}

/// Loads the profile, opens the data directory (marking runs that were
/// active when the daemon died as interrupted), binds and serves.
pub async fn start(config: ServerConfig) -> Result<(SocketAddr, ServerHandle), ServerError> {
    if !(config.sim_speed.is_finite() && config.sim_speed > 0.0) {
        return Err(ServerError::Speed(config.sim_speed));
    }
    if let Some(name) = peers::file::duplicate_name(&config.peers) {
        return Err(ServerError::Peers(name.to_string()));
    }
    config.http.check().map_err(ServerError::Http)?;
    let source = config
        .profile
        .clone()
        .unwrap_or_else(|| DEFAULT_PROFILE.to_string());
    let profile = crate::rig::load_profile(&source)?;
    let profile_source = Profile::origin(&source);
    std::fs::create_dir_all(&config.data_dir).map_err(|e| ServerError::DataDir {
        path: config.data_dir.clone(),
        why: e.to_string(),
    })?;
    match config.processing.check(&config.data_dir) {
        Err(e) if e.is_bad_config() => return Err(ServerError::Processing(e)),
        // The cluster may come back; each job checks again before it queues.
        Err(e) => tracing::warn!("processing on Slurm: {e}"),
        Ok(()) => {}
    }
    let token = auth::load_or_create(config.token_file.as_deref(), &config.data_dir)?;
    tracing::info!(path = %token.path.display(), "API token");
    // Before anything is opened for clients: their connections are then
    // capped against the limit the run will have.
    let fd_limit = http::raise_fd_limit();
    let limits = config.http;
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .map_err(|e| ServerError::Listen {
            addr: config.listen,
            why: e.to_string(),
        })?;
    let addr = listener.local_addr().map_err(|e| ServerError::Listen {
        addr: config.listen,
        why: e.to_string(),
    })?;
    let daemon = supervisor::Daemon::new(config, profile, profile_source)?;
    jobs::start_worker(daemon.clone()).map_err(|why| ServerError::DataDir {
        path: daemon.data_dir.clone(),
        why: format!("cannot start the processing worker: {why}"),
    })?;
    daemon.peers.set_local_url(format!("http://{addr}"));
    peers::start(&daemon.peers, daemon.shutdown_tx.subscribe());
    let app = router(daemon.clone(), token.clone());
    let stop = daemon.shutdown_tx.subscribe();
    let server = tokio::spawn(http::serve(listener, app, limits, fd_limit, stop));
    // The queue goes on by itself unless a run was cut short: then the
    // operator decides (resume or abort it) first.
    let interrupted = daemon
        .inner()
        .runs
        .values()
        .any(|v| matches!(v.state, RunState::Interrupted | RunState::Paused));
    if !interrupted {
        daemon.pump_queue();
    }
    Ok((
        addr,
        ServerHandle {
            daemon,
            token,
            server,
        },
    ))
}

/// `rigd serve`: runs until SIGINT/SIGTERM, then shuts down gracefully.
pub async fn serve(config: ServerConfig) -> Result<(), ServerError> {
    let sim_speed = config.sim_speed;
    let (addr, handle) = start(config).await?;
    eprintln!(
        "rigd serving profile `{}` on http://{addr}/ (API http://{addr}/api/v1, docs http://{addr}/api/docs); simulation speed {sim_speed}x; token in {}",
        handle.daemon.profile.name,
        handle.token.path.display()
    );
    for p in handle.daemon.peers.views() {
        eprintln!("watching peer `{}` at {}", p.name, p.url);
    }
    wait_for_signal().await;
    eprintln!("shutting down: pausing the active run (resumable)");
    handle.shutdown().await;
    eprintln!("stopped");
    Ok(())
}

/// Waits for SIGINT (Ctrl-C) or SIGTERM.
pub async fn wait_for_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        if let Ok(mut term) = signal(SignalKind::terminate()) {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            return;
        }
    }
    let _ = tokio::signal::ctrl_c().await;
}
