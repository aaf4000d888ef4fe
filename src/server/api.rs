//! The `/api/v1` handlers and their OpenAPI description.

use std::sync::Arc;

use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use utoipa::OpenApi;

use super::error::{ApiError, ApiJson, ApiPath, ErrorBody};
use super::events::{self, DaemonEvent};
use super::model::*;
use super::state::Daemon;
use crate::engine::command::Command;
use crate::model::profile::DeviceKind;
use crate::model::run_state::RunState;
use crate::plan::BUILTIN_PLANS;
use crate::schedule::timing::Timing;
use crate::schedule::Schedule;

pub type AppState = Arc<Daemon>;

#[derive(OpenApi)]
#[openapi(
    info(
        title = "rigd API",
        description = "Control daemon for BTF measurement rigs. Mutating routes need \
`Authorization: Bearer <token>`; reads are open to loopback clients. Errors are JSON `{error, detail}`.",
    ),
    paths(
        health, rig, plans, plan_detail, list_runs, create_run, get_run, run_steps, run_manifest,
        pause_run, resume_run, abort_run, estop, events_sse, frame_raw, frame_preview,
        get_queue, post_queue, delete_queue, sim_render, sim_scenes,
        super::viewer::btf_manifest, super::viewer::btf_data, super::viewer::btf_mesh,
        super::tradeoff::get_report, super::tradeoff::get_plot, super::tradeoff::start
    ),
    components(schemas(
        ErrorBody, Health, RigView, DeviceView, PlanList, PlanSummary, PlanDetail, PlanStep, Dir,
        RunRequest, PlanSpec, InlinePlan, PairDto, RunView, RunList, CommandAck, RunSteps, RunStep,
        QueueItem, QueueView, Enqueued, EstopAnswer, DaemonEvent, SceneView,
        super::tradeoff::TradeoffRequest, super::tradeoff::TradeoffStarted
    )),
    modifiers(&BearerAuth),
    tags(
        (name = "daemon", description = "Health and the event stream"),
        (name = "rig", description = "The rig and its plans"),
        (name = "runs", description = "Runs, their steps, frames and manifests"),
        (name = "queue", description = "Runs waiting for the rig"),
        (name = "sim", description = "The scene simulator: one frame on request"),
    )
)]
pub struct ApiDoc;

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

fn not_found_run(id: &str) -> ApiError {
    ApiError::not_found(format!(
        "no run `{}`",
        id.chars().take(64).collect::<String>()
    ))
}

/// Liveness and what this daemon drives (never needs a token).
#[utoipa::path(get, path = "/api/v1/health", tag = "daemon",
    responses((status = 200, description = "The daemon is up", body = Health)))]
pub async fn health(State(d): State<AppState>) -> Json<Health> {
    Json(Health {
        ok: true,
        version: env!("CARGO_PKG_VERSION").into(),
        profile: d.profile.name.clone(),
        sim: d.config.sim,
        sim_speed: d.speed(),
    })
}

/// The rig: every device with its live state, lamp states and camera settings.
#[utoipa::path(get, path = "/api/v1/rig", tag = "rig",
    responses((status = 200, description = "The rig", body = RigView),
              (status = 401, description = "Token needed (non-loopback client)", body = ErrorBody)))]
pub async fn rig(State(d): State<AppState>) -> Json<RigView> {
    let (active, state, reason, sim, exposure) = {
        let inner = d.inner();
        let a = inner.active.as_ref();
        let exposure = a
            .and_then(|a| inner.runs.get(&a.id))
            .and_then(|v| v.exposure_s);
        let reason = a
            .and_then(|a| inner.runs.get(&a.id))
            .and_then(|v| v.reason.clone());
        (
            a.map(|a| a.id.clone()),
            a.map(|a| a.state),
            reason,
            a.and_then(|a| a.sim.clone())
                .or_else(|| inner.last_sim.clone()),
            exposure,
        )
    };
    let world = sim.map(|s| s.world());
    let busy = matches!(state, Some(RunState::Running | RunState::Preparing));
    let fault_for = |name: &str| {
        (state == Some(RunState::Paused))
            .then(|| reason.clone())
            .flatten()
            .filter(|r| r.contains(name))
    };
    let mut lamps = serde_json::Map::new();
    let mut devices = Vec::new();
    for (name, dev) in &d.profile.devices {
        let mut v = DeviceView {
            name: name.clone(),
            kind: serde_json::to_value(dev.kind)
                .ok()
                .and_then(|k| k.as_str().map(str::to_string))
                .unwrap_or_default(),
            protocol: dev.protocol.clone(),
            connected: d.config.sim,
            homed: None,
            busy,
            fault: fault_for(name),
            position_deg: None,
            joints: None,
            on: None,
            camera: None,
        };
        match dev.kind {
            DeviceKind::Axis => {
                let p = world.as_ref().and_then(|w| w.axes.get(name).copied());
                v.homed = Some(p.is_some());
                v.position_deg = p;
            }
            DeviceKind::Arm => {
                let q = world.as_ref().and_then(|w| w.arm.clone());
                v.homed = Some(q.is_some());
                if let (Some(q), Some(joints)) = (q, &dev.joints) {
                    let m: serde_json::Map<String, serde_json::Value> = joints
                        .iter()
                        .zip(q)
                        .map(|(j, x)| (j.name.clone(), serde_json::json!(x)))
                        .collect();
                    v.joints = Some(serde_json::Value::Object(m));
                }
            }
            DeviceKind::Lamp => {
                let on = world
                    .as_ref()
                    .and_then(|w| w.lamps_on.get(name).copied())
                    .unwrap_or(false);
                v.on = Some(on);
                lamps.insert(name.clone(), serde_json::json!(on));
            }
            DeviceKind::Camera => {
                let timing = dev.timing.as_ref();
                v.camera = Some(serde_json::json!({
                    "resolution": dev.intrinsics.as_ref().map(|i| i.resolution),
                    "bit_depth": dev.intrinsics.as_ref().map(|i| i.bit_depth),
                    "focal_px": dev.intrinsics.as_ref().map(|i| i.focal_px),
                    "exposure_s": exposure.or(timing.map(|t| t.exposure_s)),
                    "readout_s": timing.map(|t| t.readout_s),
                    "transfer_s": timing.map(|t| t.transfer_s),
                    "sim_frame_size": d.profile.sim.frame_size,
                }));
            }
            DeviceKind::Laser => {}
        }
        devices.push(v);
    }
    Json(RigView {
        profile: d.profile.name.clone(),
        description: d.profile.description.clone(),
        sim: d.config.sim,
        sim_speed: d.speed(),
        active_run: active,
        state: state.unwrap_or(RunState::Idle),
        devices,
        lamps: serde_json::Value::Object(lamps),
    })
}

fn summary(d: &Daemon, name: &str, schedule: &Schedule) -> PlanSummary {
    let est = Timing::new(&d.profile, None).estimate_s(schedule, |_| false);
    PlanSummary {
        name: name.into(),
        fits: true,
        error: None,
        steps_total: schedule.images.len(),
        triggers_total: schedule.triggers.len(),
        infeasible_total: schedule.infeasible().count(),
        estimated_physical_s: est,
        estimated_wall_s: est / d.speed(),
    }
}

async fn builtin_schedule(d: &AppState, name: &str) -> Result<Arc<Schedule>, ApiError> {
    let key = format!("plan:{name}");
    if let Some(s) = d.cached_schedule(&key) {
        return Ok(s);
    }
    let profile = d.profile.clone();
    let n = name.to_string();
    let schedule =
        tokio::task::spawn_blocking(move || crate::engine::launch::solve_plan(&profile, &n, None))
            .await
            .map_err(|e| ApiError::internal(e.to_string()))?
            .map_err(|e| ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, e.to_string()))?;
    let s = Arc::new(schedule.2);
    d.cache_schedule(&key, s.clone());
    Ok(s)
}

/// The built-in plans on this rig: size, feasibility and estimated physical duration.
#[utoipa::path(get, path = "/api/v1/plans", tag = "rig",
    responses((status = 200, description = "Every built-in plan", body = PlanList)))]
pub async fn plans(State(d): State<AppState>) -> Json<PlanList> {
    let mut out = Vec::new();
    for name in BUILTIN_PLANS {
        match builtin_schedule(&d, name).await {
            Ok(s) => out.push(summary(&d, name, &s)),
            Err(e) => out.push(PlanSummary {
                name: (*name).into(),
                fits: false,
                error: Some(e.detail),
                steps_total: 0,
                triggers_total: 0,
                infeasible_total: 0,
                estimated_physical_s: 0.0,
                estimated_wall_s: 0.0,
            }),
        }
    }
    Json(PlanList {
        profile: d.profile.name.clone(),
        plans: out,
    })
}

/// One built-in plan with every step: directions, feasibility, set-points.
#[utoipa::path(get, path = "/api/v1/plans/{name}", tag = "rig",
    params(("name" = String, Path, description = "h1, h2, grid12x8 or lamps")),
    responses((status = 200, description = "The plan", body = PlanDetail),
              (status = 404, description = "No such plan", body = ErrorBody),
              (status = 422, description = "The plan does not fit this rig", body = ErrorBody)))]
pub async fn plan_detail(
    State(d): State<AppState>,
    ApiPath(name): ApiPath<String>,
) -> Result<Json<PlanDetail>, ApiError> {
    if !BUILTIN_PLANS.contains(&name.as_str()) {
        return Err(ApiError::not_found(format!(
            "no built-in plan of that name (expected one of {})",
            BUILTIN_PLANS.join(", ")
        )));
    }
    let s = builtin_schedule(&d, &name).await?;
    let steps = s.steps().map(PlanStep::from).collect();
    Ok(Json(PlanDetail {
        summary: summary(&d, &name, &s),
        steps,
    }))
}

/// Every run in the data directory, newest first.
#[utoipa::path(get, path = "/api/v1/runs", tag = "runs",
    responses((status = 200, description = "The run history", body = RunList)))]
pub async fn list_runs(State(d): State<AppState>) -> Json<RunList> {
    let (mut runs, active) = {
        let inner = d.inner();
        let runs: Vec<RunView> = inner.runs.values().cloned().collect();
        (runs, inner.active.as_ref().map(|a| a.id.clone()))
    };
    runs.sort_by(|a, b| b.started_at.cmp(&a.started_at).then(b.id.cmp(&a.id)));
    for run in &mut runs {
        mark_processed(&d, run);
    }
    Json(RunList { runs, active })
}

/// Fills `processed` from what lies on disk now (`rigd process` runs
/// outside the daemon).
fn mark_processed(d: &Daemon, run: &mut RunView) {
    run.processed = d
        .run_root(&run.id)
        .and_then(|root| crate::postprocess::viewer::processed_kind(&root))
        .map(str::to_string);
}

/// Starts a run now.
#[utoipa::path(post, path = "/api/v1/runs", tag = "runs", request_body = RunRequest,
    security(("bearer" = [])),
    responses((status = 201, description = "The run started", body = RunView),
              (status = 400, description = "Malformed JSON", body = ErrorBody),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "Another run is active (named in `detail`)", body = ErrorBody),
              (status = 413, description = "Body over 64 KiB", body = ErrorBody),
              (status = 415, description = "Not `Content-Type: application/json`", body = ErrorBody),
              (status = 422, description = "Invalid fields, unknown plan", body = ErrorBody)))]
pub async fn create_run(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<RunRequest>,
) -> Result<(StatusCode, Json<RunView>), ApiError> {
    let v = d.start_run(req).await?;
    Ok((StatusCode::CREATED, Json(v)))
}

/// One run: state, steps done/total, physical ETA, last error, timestamps.
#[utoipa::path(get, path = "/api/v1/runs/{id}", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    responses((status = 200, description = "The run", body = RunView),
              (status = 404, description = "No such run", body = ErrorBody)))]
pub async fn get_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Json<RunView>, ApiError> {
    let mut run = d.view(&id).ok_or_else(|| not_found_run(&id))?;
    mark_processed(&d, &mut run);
    Ok(Json(run))
}

/// Every image of the run's plan, planned and captured (for hemisphere plots).
#[utoipa::path(get, path = "/api/v1/runs/{id}/steps", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    responses((status = 200, description = "The steps", body = RunSteps),
              (status = 404, description = "No such run", body = ErrorBody)))]
pub async fn run_steps(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Json<RunSteps>, ApiError> {
    let root = d.run_root(&id).ok_or_else(|| not_found_run(&id))?;
    let dd = d.clone();
    let id2 = id.clone();
    let (schedule, done) = tokio::task::spawn_blocking(move || {
        let s = dd.run_schedule(&id2)?;
        Ok::<_, ApiError>((s, super::persist::journaled(&root)))
    })
    .await
    .map_err(|e| ApiError::internal(e.to_string()))??;
    let steps: Vec<RunStep> = schedule
        .images
        .iter()
        .map(|img| RunStep {
            index: img.index,
            trigger: img.trigger,
            camera: img.camera.clone(),
            light: img.light.into(),
            view: img.view.into(),
            achieved_light: img.achieved_light.into(),
            achieved_view: img.achieved_view.into(),
            feasible: img.feasible,
            reason: img.reason.clone(),
            done: done.contains(&img.index),
        })
        .collect();
    Ok(Json(RunSteps {
        run: id,
        steps_total: steps.len(),
        steps_done: steps.iter().filter(|s| s.done).count(),
        steps,
    }))
}

/// The run's manifest.json, once written (at completion or abort).
#[utoipa::path(get, path = "/api/v1/runs/{id}/manifest", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    responses((status = 200, description = "manifest.json", content_type = "application/json", body = Object),
              (status = 404, description = "No such run, or no manifest yet", body = ErrorBody)))]
pub async fn run_manifest(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    let root = d.run_root(&id).ok_or_else(|| not_found_run(&id))?;
    match tokio::fs::read(root.join(crate::store::MANIFEST_FILE)).await {
        Ok(bytes) => Ok((
            [(axum::http::header::CONTENT_TYPE, "application/json")],
            bytes,
        )
            .into_response()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(ApiError::not_found(
            "no manifest yet: it is written when the run completes or is aborted",
        )),
        Err(e) => Err(ApiError::internal(e.to_string())),
    }
}

async fn command(d: AppState, id: String, cmd: Command) -> Result<Response, ApiError> {
    let (sent, run) = d.command(&id, cmd).await?;
    let status = if sent {
        StatusCode::ACCEPTED
    } else {
        StatusCode::OK
    };
    Ok((
        status,
        Json(CommandAck {
            command: format!("{cmd:?}").to_lowercase(),
            sent_to_engine: sent,
            run,
        }),
    )
        .into_response())
}

/// Pauses the active run between steps.
#[utoipa::path(post, path = "/api/v1/runs/{id}/pause", tag = "runs",
    params(("id" = String, Path, description = "Run id")), security(("bearer" = [])),
    responses((status = 202, description = "Sent to the engine", body = CommandAck),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run", body = ErrorBody),
              (status = 409, description = "Not pausable in its state", body = ErrorBody)))]
pub async fn pause_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    command(d, id, Command::Pause).await
}

/// Resumes a paused run, or an interrupted/detached one from its directory.
#[utoipa::path(post, path = "/api/v1/runs/{id}/resume", tag = "runs",
    params(("id" = String, Path, description = "Run id")), security(("bearer" = [])),
    responses((status = 200, description = "Restarted from its run directory (a new engine)", body = CommandAck),
              (status = 202, description = "Sent to the live engine", body = CommandAck),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run", body = ErrorBody),
              (status = 409, description = "Not resumable, or another run is active", body = ErrorBody)))]
pub async fn resume_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    command(d, id, Command::Resume).await
}

/// Aborts a run (the live engine writes the manifest; a run with no live engine is marked aborted).
#[utoipa::path(post, path = "/api/v1/runs/{id}/abort", tag = "runs",
    params(("id" = String, Path, description = "Run id")), security(("bearer" = [])),
    responses((status = 200, description = "Marked aborted on disk", body = CommandAck),
              (status = 202, description = "Sent to the live engine", body = CommandAck),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run", body = ErrorBody),
              (status = 409, description = "Already final", body = ErrorBody)))]
pub async fn abort_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    command(d, id, Command::Abort).await
}

/// Emergency stop: every device stops at once; the active run pauses and re-homes on resume.
#[utoipa::path(post, path = "/api/v1/estop", tag = "rig", security(("bearer" = [])),
    responses((status = 200, description = "What stopped", body = EstopAnswer),
              (status = 401, description = "Missing or wrong token", body = ErrorBody)))]
pub async fn estop(State(d): State<AppState>) -> Json<EstopAnswer> {
    let (run, report) = d.estop().await;
    Json(EstopAnswer {
        run,
        latency_s: report.as_ref().map(|r| r.latency_s),
        all_stopped: report.as_ref().is_none_or(|r| r.all_stopped()),
        devices: report
            .map(|r| {
                r.devices
                    .iter()
                    .map(|a| serde_json::to_value(a).unwrap_or_default())
                    .collect()
            })
            .unwrap_or_default(),
    })
}

/// Server-Sent Events: every engine event (wrapped with its run id) and
/// daemon event; `Last-Event-ID` replays the recent ones (up to 4096).
#[utoipa::path(get, path = "/api/v1/events", tag = "daemon",
    params(("Last-Event-ID" = Option<String>, Header, description = "Replay events after this id")),
    responses((status = 200, description = "text/event-stream of DaemonEvent JSON; `id:` is DaemonEvent.id",
               content_type = "text/event-stream", body = DaemonEvent),
              (status = 400, description = "Last-Event-ID is not an integer", body = ErrorBody)))]
pub async fn events_sse(
    State(d): State<AppState>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let last = match headers.get("last-event-id") {
        None => None,
        Some(v) => Some(
            v.to_str()
                .ok()
                .and_then(|s| s.trim().parse::<u64>().ok())
                .ok_or_else(|| ApiError::bad_request("Last-Event-ID must be an integer"))?,
        ),
    };
    Ok(events::sse_stream(&d.hub, last, d.shutdown_tx.subscribe()).into_response())
}

/// The raw frame: a greyscale PNG holding the sensor values (16-bit for >8-bit cameras).
#[utoipa::path(get, path = "/api/v1/runs/{id}/frames/{index}", tag = "runs",
    params(("id" = String, Path, description = "Run id"), ("index" = u64, Path, description = "Image index")),
    responses((status = 200, description = "The frame", content_type = "image/png", body = Vec<u8>),
              (status = 400, description = "Index not a non-negative integer", body = ErrorBody),
              (status = 404, description = "No such run or frame not taken", body = ErrorBody)))]
pub async fn frame_raw(
    State(d): State<AppState>,
    ApiPath((id, index)): ApiPath<(String, String)>,
) -> Result<Response, ApiError> {
    super::frames::raw(&d, &id, &index).await
}

/// An 8-bit preview PNG of a frame, downscaled to at most 256 px on its longer side
/// and stretched to the frame's own maximum.
#[utoipa::path(get, path = "/api/v1/runs/{id}/frames/{index}/preview", tag = "runs",
    params(("id" = String, Path, description = "Run id"), ("index" = u64, Path, description = "Image index")),
    responses((status = 200, description = "The preview", content_type = "image/png", body = Vec<u8>),
              (status = 400, description = "Index not a non-negative integer", body = ErrorBody),
              (status = 404, description = "No such run or frame not taken", body = ErrorBody)))]
pub async fn frame_preview(
    State(d): State<AppState>,
    ApiPath((id, index)): ApiPath<(String, String)>,
) -> Result<Response, ApiError> {
    super::frames::preview(&d, &id, &index).await
}

/// The queue, in order.
#[utoipa::path(get, path = "/api/v1/queue", tag = "queue",
    responses((status = 200, description = "The queue", body = QueueView)))]
pub async fn get_queue(State(d): State<AppState>) -> Json<QueueView> {
    Json(QueueView {
        items: d.inner().queue.clone(),
    })
}

/// Queues a run; it starts when the rig is free (at once if it is free now).
#[utoipa::path(post, path = "/api/v1/queue", tag = "queue", request_body = RunRequest,
    security(("bearer" = [])),
    responses((status = 201, description = "Queued (and maybe started)", body = Enqueued),
              (status = 400, description = "Malformed JSON", body = ErrorBody),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "The queue is full", body = ErrorBody),
              (status = 413, description = "Body over 64 KiB", body = ErrorBody),
              (status = 415, description = "Not `Content-Type: application/json`", body = ErrorBody),
              (status = 422, description = "Invalid fields, unknown plan", body = ErrorBody)))]
pub async fn post_queue(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<RunRequest>,
) -> Result<(StatusCode, Json<Enqueued>), ApiError> {
    let (item, started_run) = d.enqueue(req).await?;
    Ok((StatusCode::CREATED, Json(Enqueued { item, started_run })))
}

/// Removes a queued run.
#[utoipa::path(delete, path = "/api/v1/queue/{item}", tag = "queue",
    params(("item" = String, Path, description = "Queue item id")), security(("bearer" = [])),
    responses((status = 204, description = "Removed"),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such item", body = ErrorBody)))]
pub async fn delete_queue(
    State(d): State<AppState>,
    ApiPath(item): ApiPath<String>,
) -> Result<StatusCode, ApiError> {
    d.dequeue(&item)?;
    Ok(StatusCode::NO_CONTENT)
}

/// What `GET /api/v1/sim/render` takes.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct RenderQuery {
    /// A built-in scene (see /api/v1/sim/scenes); the profile's default if absent.
    pub scene: Option<String>,
    /// Light θ,φ in degrees, sample frame (default 0,0).
    pub light: Option<String>,
    /// View θ,φ in degrees, sample frame (default 0,0).
    pub view: Option<String>,
    /// WIDTHxHEIGHT, at most 2048 each way (default: the profile's sim frame size).
    pub size: Option<String>,
    /// Which camera of the daemon's profile (default: its first).
    pub camera: Option<String>,
    /// Effect switches: `all`, `none`, or `+interreflection,-noise`.
    pub effects: Option<String>,
    pub seed: Option<u64>,
    /// Exposure relative to nominal.
    pub exposure: Option<f64>,
    /// Laser plane: `X` or `X,TILT` (mm, degrees).
    pub laser: Option<String>,
    /// Lamp off (laser-only frame).
    pub lamp_off: Option<bool>,
    /// Focal length multiplier (default 1).
    pub zoom: Option<f64>,
}

/// Renders one frame of a scene as the daemon's rig's camera sees it: a
/// greyscale PNG at the camera's bit depth. `X-Rigd-Effects` lists the
/// effects the frame paid for, `X-Rigd-Render-Ms` what it cost.
#[utoipa::path(get, path = "/api/v1/sim/render", tag = "sim", params(RenderQuery),
    responses((status = 200, description = "The frame", content_type = "image/png", body = Vec<u8>),
              (status = 400, description = "A parameter is malformed", body = ErrorBody),
              (status = 422, description = "Unknown scene or camera, or a value out of range", body = ErrorBody)))]
pub async fn sim_render(
    State(d): State<AppState>,
    query: Result<axum::extract::Query<RenderQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let axum::extract::Query(q) = query.map_err(|e| ApiError::bad_request(e.body_text()))?;
    let req = render_request(&q).map_err(ApiError::bad_request)?;
    let profile = d.profile.clone();
    let out = tokio::task::spawn_blocking(move || crate::rig::shot::render(&profile, &req))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(|e| ApiError::invalid(e.to_string()))?;
    let png = out.png().map_err(ApiError::internal)?;
    let headers = [
        (axum::http::header::CONTENT_TYPE, "image/png".to_string()),
        (
            axum::http::header::HeaderName::from_static("x-rigd-effects"),
            out.rendered.plan.live.to_string(),
        ),
        (
            axum::http::header::HeaderName::from_static("x-rigd-render-ms"),
            format!("{:.2}", out.render_ms),
        ),
    ];
    Ok((headers, png).into_response())
}

fn render_request(q: &RenderQuery) -> Result<crate::rig::shot::RenderRequest, String> {
    use crate::rig::shot::{parse_direction, parse_frame_size, parse_laser, RenderRequest};
    let dir = |v: &Option<String>, what: &str| match v {
        Some(s) => parse_direction(s)
            .map(Some)
            .map_err(|e| format!("{what}: {e}")),
        None => Ok(None),
    };
    let size = match &q.size {
        Some(s) => {
            let size = parse_frame_size(s).map_err(|e| format!("size: {e}"))?;
            if size[0] > 2048 || size[1] > 2048 {
                return Err(format!("size: `{s}`: the API renders at most 2048x2048"));
            }
            Some(size)
        }
        None => None,
    };
    let defaults = RenderRequest::default();
    Ok(RenderRequest {
        scene: q.scene.clone(),
        camera: q.camera.clone(),
        light: dir(&q.light, "light")?.unwrap_or(defaults.light),
        view: dir(&q.view, "view")?.unwrap_or(defaults.view),
        size,
        effects: q
            .effects
            .as_deref()
            .unwrap_or("")
            .parse()
            .map_err(|e| format!("effects: {e}"))?,
        seed: q.seed.unwrap_or(0),
        exposure: q.exposure.unwrap_or(1.0),
        laser: q
            .laser
            .as_deref()
            .map(parse_laser)
            .transpose()
            .map_err(|e| format!("laser: {e}"))?,
        lamp_off: q.lamp_off.unwrap_or(false),
        zoom: q.zoom.unwrap_or(1.0),
    })
}

/// A built-in scene and the effects it can show.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct SceneView {
    pub name: String,
    pub description: String,
    /// Effects frames of this scene can pay for.
    pub effects: Vec<String>,
}

/// The built-in scenes.
#[utoipa::path(get, path = "/api/v1/sim/scenes", tag = "sim",
    responses((status = 200, description = "The scenes", body = Vec<SceneView>)))]
pub async fn sim_scenes() -> Result<Json<Vec<SceneView>>, ApiError> {
    let views = tokio::task::spawn_blocking(|| {
        rigd_sim::scene::Scene::builtin_names()
            .into_iter()
            .map(|name| {
                let s = rigd_sim::scene::Scene::load(name)
                    .map_err(|e| ApiError::internal(e.to_string()))?;
                Ok(SceneView {
                    name: s.name.clone(),
                    description: s.description.clone(),
                    effects: s
                        .capabilities()
                        .names()
                        .into_iter()
                        .map(String::from)
                        .collect(),
                })
            })
            .collect::<Result<Vec<_>, ApiError>>()
    })
    .await
    .map_err(|e| ApiError::internal(e.to_string()))??;
    Ok(Json(views))
}
