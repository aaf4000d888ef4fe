//! `/queue`: runs waiting for the rig.

use axum::extract::State;
use axum::http::StatusCode;
use axum::Json;

use super::AppState;
use crate::server::error::{ApiError, ApiJson, ApiPath, ErrorBody};
use crate::server::wire::*;

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
