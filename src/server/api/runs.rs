//! `/runs`: the run history, new runs, a run's steps and manifest, and the
//! operator's commands (pause, resume, abort).

use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::not_found_run;
use super::AppState;
use crate::engine::command::Command;
use crate::model::run_state::RunState;
use crate::server::error::{ApiError, ApiJson, ApiPath, ApiQuery, ErrorBody};
use crate::server::history::{
    decode_cursor, encode_cursor, parse_bound, parse_limit, parse_state, Bound, HistoryQuery,
    QueryError, RunFilter,
};
use crate::server::supervisor::Daemon;
use crate::server::wire::*;

/// The query of `GET /api/v1/runs`: a page size, where to go on, and
/// filters (each one given must hold; an empty one is no filter).
#[derive(Debug, Default, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct RunsQuery {
    /// Runs per page, 1 to 1000; 50 if not given.
    #[param(minimum = 1, maximum = 1000)]
    pub limit: Option<u64>,
    /// Where to go on: the `next` of the previous page, as it is (opaque;
    /// it stays valid across restarts of this daemon, not on another data
    /// directory). The first page without it.
    pub cursor: Option<String>,
    /// Text the sample name contains, case-insensitive.
    pub sample: Option<String>,
    /// Runs in this state only.
    #[param(value_type = Option<RunState>)]
    pub state: Option<String>,
    /// Runs of this plan only (its exact name).
    pub plan: Option<String>,
    /// Runs captured on this rig profile only (its exact name).
    pub profile: Option<String>,
    /// Runs started at or after this RFC 3339 date (`2026-12-01`, from its
    /// midnight UTC) or date-time (`2026-12-01T08:00:00Z`, `…+01:00`).
    pub from: Option<String>,
    /// Runs started at or before this RFC 3339 date (to its end, UTC) or
    /// date-time.
    pub to: Option<String>,
}

/// Reads the query into what the history pages by.
fn history_query(d: &Daemon, q: RunsQuery) -> Result<HistoryQuery, QueryError> {
    let given = |s: Option<String>| s.filter(|s| !s.is_empty());
    let filter = RunFilter {
        sample: given(q.sample).map(|s| s.to_lowercase()),
        state: given(q.state).as_deref().map(parse_state).transpose()?,
        plan: given(q.plan),
        profile: given(q.profile),
        from: given(q.from)
            .map(|s| parse_bound("from", &s, Bound::From))
            .transpose()?,
        until: given(q.to)
            .map(|s| parse_bound("to", &s, Bound::To))
            .transpose()?,
    };
    Ok(HistoryQuery {
        filter,
        limit: parse_limit(q.limit)?,
        after: given(q.cursor)
            .map(|c| decode_cursor(&d.history_id, &c))
            .transpose()?,
    })
}

/// The run history, one page at a time, newest first, filtered.
#[utoipa::path(get, path = "/api/v1/runs", tag = "runs", params(RunsQuery),
    responses((status = 200, description = "One page of the run history and how many runs match", body = RunList),
              (status = 400, description = "A malformed query: `limit` not 1 to 1000, a malformed cursor or one from another data directory, an unknown `state`, a `from`/`to` that is not an RFC 3339 date or date-time", body = ErrorBody)))]
pub async fn list_runs(
    State(d): State<AppState>,
    ApiQuery(q): ApiQuery<RunsQuery>,
) -> Result<Json<RunList>, ApiError> {
    let q = history_query(&d, q).map_err(|e| ApiError::bad_request(e.to_string()))?;
    let (page, active) = {
        let inner = d.inner();
        (
            inner.runs.page(&q),
            inner.active.as_ref().map(|a| a.id.clone()),
        )
    };
    let mut runs = page.runs;
    for run in &mut runs {
        mark_processed(&d, run);
    }
    Ok(Json(RunList {
        runs,
        active,
        next: page.next.map(|p| encode_cursor(&d.history_id, &p)),
        total: page.total,
    }))
}

/// Fills `processed` from what lies on disk now (`rigd process` runs
/// outside the daemon).
pub(super) fn mark_processed(d: &Daemon, run: &mut RunView) {
    run.processed = d
        .run_root(&run.id)
        .and_then(|root| crate::postprocess::viewer::processed_kind(&root))
        .map(str::to_string);
    run.processing = d.jobs.get(&run.id);
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
        Ok::<_, ApiError>((s, crate::server::data_dir::journaled(&root)))
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
    match super::read_served(root.join(crate::store::MANIFEST_FILE)).await {
        Ok(bytes) => Ok((
            [(axum::http::header::CONTENT_TYPE, "application/json")],
            bytes,
        )
            .into_response()),
        Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => Err(ApiError::not_found(
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
              (status = 409, description = "Not pausable in its state", body = ErrorBody),
              (status = 503, description = "The engine has too many commands waiting, or the daemon is shutting down", body = ErrorBody)))]
pub async fn pause_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    command(d, id, Command::Pause).await
}

/// `?reference_confirmed=true` on a resume.
#[derive(Debug, Default, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ResumeQuery {
    /// The operator confirms that every axis without homing (`homing =
    /// false`) stands at its 0° mark with its controller zeroed there:
    /// required to resume on a rig with such an axis, since no homing can
    /// restore its reference.
    #[serde(default)]
    pub reference_confirmed: bool,
}

/// Resumes a paused run, or an interrupted/detached one from its directory.
/// On a rig with an axis without homing, the operator must confirm its
/// reference (`?reference_confirmed=true`).
#[utoipa::path(post, path = "/api/v1/runs/{id}/resume", tag = "runs",
    params(("id" = String, Path, description = "Run id"), ResumeQuery), security(("bearer" = [])),
    responses((status = 200, description = "Restarted from its run directory (a new engine)", body = CommandAck),
              (status = 202, description = "Sent to the live engine", body = CommandAck),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run", body = ErrorBody),
              (status = 400, description = "A malformed query", body = ErrorBody),
              (status = 409, description = "Not resumable, another run is active, or an axis without homing whose reference is not confirmed", body = ErrorBody),
              (status = 503, description = "The engine has too many commands waiting, or the daemon is shutting down", body = ErrorBody)))]
pub async fn resume_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<ResumeQuery>,
) -> Result<Response, ApiError> {
    if d.view(&id).is_none() {
        return Err(not_found_run(&id));
    }
    if !q.reference_confirmed {
        let unhomed = d.profile.axes_without_homing();
        if !unhomed.is_empty() {
            return Err(ApiError::conflict(format!(
                "{} {} no homing: set {} at its 0° mark and zero the controller there, then resume with ?reference_confirmed=true",
                unhomed.join(", "),
                if unhomed.len() == 1 { "has" } else { "have" },
                if unhomed.len() == 1 { "it" } else { "each" },
            )));
        }
    }
    command(d, id, Command::Resume).await
}

/// Aborts a run (the live engine writes the manifest; a run with no live engine is marked aborted).
#[utoipa::path(post, path = "/api/v1/runs/{id}/abort", tag = "runs",
    params(("id" = String, Path, description = "Run id")), security(("bearer" = [])),
    responses((status = 200, description = "Marked aborted on disk", body = CommandAck),
              (status = 202, description = "Sent to the live engine", body = CommandAck),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run", body = ErrorBody),
              (status = 409, description = "Already final", body = ErrorBody),
              (status = 503, description = "The engine has too many commands waiting, or the daemon is shutting down", body = ErrorBody)))]
pub async fn abort_run(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    command(d, id, Command::Abort).await
}
