//! `/health` and `/events`: liveness, and every engine and daemon event as
//! Server-Sent Events.

use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::AppState;
use crate::server::error::{ApiError, ErrorBody};
use crate::server::events::{self, SseMessage};
use crate::server::wire::*;

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

/// Server-Sent Events: every engine event (wrapped with its run id) and
/// daemon event; `Last-Event-ID` replays the recent ones (up to 4096).
#[utoipa::path(get, path = "/api/v1/events", tag = "daemon",
    params(("Last-Event-ID" = Option<String>, Header, description = "Replay events after this id")),
    responses((status = 200, description = "text/event-stream: each message's `data:` is a DaemonEvent as JSON, its `id:` the DaemonEvent's id",
               content_type = "text/event-stream", body = SseMessage),
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
