//! The `/api/v1` handlers, one module per resource, and their OpenAPI
//! description.

pub mod contract;
pub mod daemon;
pub mod frames;
pub mod manual;
pub mod peers;
pub mod plans;
pub mod process;
pub mod queue;
pub mod rig;
pub mod runs;
#[cfg(feature = "sim")]
pub mod sim;
#[cfg(feature = "sim")]
pub mod tradeoff;
pub mod viewer;

use std::sync::Arc;

use utoipa::OpenApi;

use super::error::{ApiError, ErrorBody};
use super::events::DaemonEvent;
use super::supervisor::Daemon;
use super::wire::*;

/// What every handler gets: the daemon.
pub type AppState = Arc<Daemon>;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "rigd API",
        description = "Control daemon for BTF measurement rigs. Mutating routes need \
`Authorization: Bearer <token>`; reads are open to loopback clients. Errors are JSON `{error, detail}`. \
Every route may also answer 408 (the body did not arrive in time), 413 (a body over 64 KiB), 431 \
(a head over 32 KiB) or 503 (every connection busy, too many event streams, shutting down); \
names in a request are looked up, never used as paths (docs/api.md, \"Security\").",
    ),
    paths(
        daemon::health, rig::rig, rig::check, plans::plans, plans::plan_detail, runs::list_runs,
        runs::create_run, runs::get_run, runs::run_steps, runs::run_manifest, runs::pause_run,
        runs::resume_run, runs::abort_run, rig::estop, daemon::events_sse, frames::frame_raw,
        frames::frame_preview, queue::get_queue, queue::post_queue, queue::delete_queue,
        viewer::btf_manifest, viewer::btf_data, viewer::btf_mesh, viewer::mdf_manifest, viewer::mdf_data, manual::home, manual::jog,
        manual::pose, manual::lamp, manual::take_frame, manual::last_frame, manual::holder_check, manual::release,
        process::submit, process::get_job, process::cancel, peers::list_peers, peers::pause_peer,
        peers::abort_peer
    ),
    components(schemas(
        ErrorBody, Health, RigView, DeviceView, PlanList, PlanSummary, PolicyEstimate, PlanDetail, PlanStep, Dir,
        RunRequest, PlanSpec, InlinePlan, PairDto, RunView, PaceView, RunList, CommandAck, RunSteps, RunStep,
        QueueItem, QueueView, Enqueued, EstopAnswer, DaemonEvent, super::events::SseMessage,
        crate::rig::check::RigCheck, crate::rig::check::DeviceCheck, manual::DeviceRequest,
        manual::JogRequest, manual::PoseRequest, manual::SwitchRequest, manual::FrameRequest,
        manual::Reached, manual::Switched, manual::TestFrame, crate::engine::manual::PoseReached,
        crate::postprocess::holder_check::HolderCheck,
        crate::postprocess::holder_check::MarkerCheck,
        crate::postprocess::holder_check::AreaReading,
        crate::server::wire::ProcessJob, crate::server::wire::StepStatus,
        crate::server::wire::JobState, crate::postprocess::pipeline::ProcessOptions,
        crate::postprocess::pipeline::ProcessStep, crate::postprocess::pipeline::RectifyOptions,
        crate::postprocess::pipeline::BtfOptions, crate::postprocess::pipeline::FitOptions,
        crate::postprocess::pipeline::MdfOptions, crate::postprocess::pipeline::PsOptions,
        crate::server::peers::PeerList, crate::server::peers::PeerView,
        crate::server::peers::PeerRun
    )),
    modifiers(&BearerAuth),
    tags(
        (name = "daemon", description = "Health and the event stream"),
        (name = "rig", description = "The rig and its plans"),
        (name = "manual", description = "Manual control for bring-up: 409 while a run is active"),
        (name = "runs", description = "Runs, their steps, frames and manifests"),
        (name = "queue", description = "Runs waiting for the rig"),
        (name = "peers", description = "The other rigs' daemons (`rigd serve --peers FILE`): their state in one view, pause and abort of their runs"),
        (name = "sim", description = "The scene simulator: one frame on request"),
    )
)]
/// The routes every build serves; [`openapi`] adds the simulator's.
pub struct ApiDoc;

/// The routes that need the simulator (`sim` feature): one rendered frame,
/// the scenes, and the trade-off report.
#[cfg(feature = "sim")]
#[derive(OpenApi)]
#[openapi(
    paths(
        sim::sim_render,
        sim::sim_scenes,
        tradeoff::get_report,
        tradeoff::get_plot,
        tradeoff::get_figure,
        tradeoff::get_choice,
        tradeoff::start
    ),
    components(schemas(
        sim::SceneView,
        tradeoff::TradeoffRequest,
        tradeoff::TradeoffStarted,
        crate::tradeoff::choice::PlanChoice,
        crate::tradeoff::figure::Figure,
        crate::tradeoff::figure::Panel,
        crate::tradeoff::figure::FigurePoint,
        crate::tradeoff::choice::PlanPoint,
        crate::tradeoff::choice::Goal
    ))
)]
pub struct SimApiDoc;

/// The OpenAPI description this build serves at `/api/v1/openapi.json`.
pub fn openapi() -> utoipa::openapi::OpenApi {
    let mut doc = ApiDoc::openapi();
    #[cfg(feature = "sim")]
    doc.merge(SimApiDoc::openapi());
    // After the merge, so that the simulator's routes get it too.
    utoipa::Modify::modify(&contract::Contract, &mut doc);
    doc
}

/// [`openapi`] as JSON, as `/api/v1/openapi.json` serves it.
pub fn openapi_json() -> serde_json::Value {
    contract::served(&openapi())
}

struct BearerAuth;

impl utoipa::Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
        let components = openapi.components.get_or_insert_with(Default::default);
        components.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// Largest file the daemon serves from a run directory or its data
/// directory (a frame, a manifest, the trade-off report): far above any
/// camera's file, far below what would strain the daemon.
pub const SERVED_FILE_LIMIT: u64 = 512 << 20;

/// Reads a file the daemon serves, off the async threads and bounded
/// ([`rigd_core::read::read_bounded`]): a device, a FIFO or a huge file
/// put in the data directory is refused, never streamed into memory.
async fn read_served(path: std::path::PathBuf) -> Result<Vec<u8>, rigd_core::read::ReadError> {
    let at = path.clone();
    tokio::task::spawn_blocking(move || rigd_core::read::read_bounded(&path, SERVED_FILE_LIMIT))
        .await
        .unwrap_or_else(|e| {
            Err(rigd_core::read::ReadError {
                path: at,
                reason: rigd_core::read::ReadFailure::Io(std::io::Error::other(e.to_string())),
            })
        })
}

/// 404 for a run id, shortened so a hostile id cannot flood the answer.
fn not_found_run(id: &str) -> ApiError {
    ApiError::not_found(format!(
        "no run `{}`",
        id.chars().take(64).collect::<String>()
    ))
}
