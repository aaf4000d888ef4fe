//! `/runs/{id}/process`: processing a finished run in the daemon
//! ([`crate::server::jobs`]).

use axum::extract::State;
use axum::http::StatusCode;
use axum::Json;

use super::not_found_run;
use super::AppState;
use crate::postprocess::pipeline::ProcessOptions;
use crate::server::error::{ApiError, ApiJson, ApiPath, ErrorBody};
use crate::server::jobs::{self, Cancelled, Submitted};
use crate::server::wire::ProcessJob;

/// Processes a finished run in the background, one job at a time beside
/// the capture: the steps (`rectify`, `btf`, `fit`, `mdf`,
/// `photometric-stereo`; `{}` picks them from the run) with their options.
/// `process` events report each step's progress and ETA. The job is kept
/// in `RUN/processed/job.json` and resumes after a daemon restart. Asking
/// again with the same options returns the job (200) and does nothing
/// twice; a failed job asked again resumes from its failed step.
#[utoipa::path(post, path = "/api/v1/runs/{id}/process", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    request_body = ProcessOptions,
    security(("bearer" = [])),
    responses((status = 202, description = "Queued", body = ProcessJob),
              (status = 200, description = "The same job is already queued, running or done", body = ProcessJob),
              (status = 400, description = "Malformed JSON", body = ErrorBody),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run", body = ErrorBody),
              (status = 409, description = "The run has not ended, or runs with other options", body = ErrorBody),
              (status = 415, description = "Not `Content-Type: application/json`", body = ErrorBody),
              (status = 422, description = "A step or option the run cannot take (named in `detail`)", body = ErrorBody)))]
pub async fn submit(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiJson(options): ApiJson<ProcessOptions>,
) -> Result<(StatusCode, Json<ProcessJob>), ApiError> {
    // Reading the run's journal and options touches the disk.
    let daemon = d.clone();
    let submitted = tokio::task::spawn_blocking(move || jobs::submit(&*daemon, &id, options))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))??;
    Ok(match submitted {
        Submitted::Queued(job) => (StatusCode::ACCEPTED, Json(job)),
        Submitted::Existing(job) => (StatusCode::OK, Json(job)),
    })
}

/// The run's process job: state, steps with done/total and ETA, the error.
#[utoipa::path(get, path = "/api/v1/runs/{id}/process", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    responses((status = 200, description = "The job", body = ProcessJob),
              (status = 404, description = "No such run, or no job for it", body = ErrorBody)))]
pub async fn get_job(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Json<ProcessJob>, ApiError> {
    if d.run_root(&id).is_none() {
        return Err(not_found_run(&id));
    }
    d.jobs.get(&id).map(Json).ok_or_else(|| {
        ApiError::not_found(format!(
            "run `{id}` has no process job: POST /api/v1/runs/{id}/process"
        ))
    })
}

/// Cancels the run's process job. A queued job is dropped (it ends
/// `failed`, "cancelled by the operator"; asking for it again resumes it).
/// A running job stops: a step on Slurm at once, its job arrays cancelled
/// with `scancel`; a local step at its end. The answer is the job; a
/// running one has `cancelling` true until it stops.
#[utoipa::path(post, path = "/api/v1/runs/{id}/process/cancel", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    security(("bearer" = [])),
    responses((status = 200, description = "Dropped (queued) or stopping (running)", body = ProcessJob),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 404, description = "No such run, or no job for it", body = ErrorBody),
              (status = 409, description = "The job has ended: nothing to cancel", body = ErrorBody)))]
pub async fn cancel(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Json<ProcessJob>, ApiError> {
    // Dropping a queued job rewrites its file.
    let daemon = d.clone();
    let cancelled = tokio::task::spawn_blocking(move || jobs::cancel(&*daemon, &id))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))??;
    Ok(Json(match cancelled {
        Cancelled::Dropped(job) | Cancelled::Stopping(job) => job,
    }))
}
