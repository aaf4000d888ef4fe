//! `/peers`: every rig of the lab in one view (`rigd serve --peers FILE`),
//! and pause or abort forwarded to a peer's active run.

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::AppState;
use crate::server::error::{ApiError, ApiPath, ErrorBody};
use crate::server::peers::{
    distinct_faults, ForwardError, PeerCommand, PeerList, PeerRun, RigSummary, LOCAL_NAME,
};
use crate::server::wire::CommandAck;

/// This rig first (`local`, name `this rig`), then every peer of the peers
/// file as of its last poll (once a second): reachable or not with the
/// error and when it was last seen, its state, active run, queue length
/// and faults. Never waits for a peer.
#[utoipa::path(get, path = "/api/v1/peers", tag = "peers",
    responses((status = 200, description = "This rig and its peers", body = PeerList),
              (status = 401, description = "Token needed (non-loopback client)", body = ErrorBody)))]
pub async fn list_peers(State(d): State<AppState>) -> Json<PeerList> {
    let rig = super::rig::rig(State(d.clone())).await.0;
    let (queue_length, active_run) = {
        let inner = d.inner();
        let run = rig
            .active_run
            .as_ref()
            .and_then(|id| inner.runs.get(id))
            .map(|v| PeerRun {
                id: v.id.clone(),
                sample: v.sample.clone(),
                plan: v.plan.clone(),
                state: v.state,
                steps_done: v.steps_done,
                steps_total: v.steps_total,
                reason: v.reason.clone(),
                eta_wall_s: v.eta_wall_s,
            });
        (inner.queue.len(), run)
    };
    let local = RigSummary {
        faults: distinct_faults(rig.devices.iter().filter_map(|x| x.fault.as_deref())),
        profile: rig.profile,
        sim: rig.sim,
        state: rig.state,
        active_run,
        queue_length,
    }
    .view(LOCAL_NAME, d.peers.local_url(), true);
    let mut peers = vec![local];
    peers.extend(d.peers.views());
    Json(PeerList { peers })
}

async fn forward(d: AppState, name: String, cmd: PeerCommand) -> Result<Response, ApiError> {
    match d.peers.forward(&name, cmd).await {
        // The peer's own answer, as it gave it: its CommandAck, or its
        // refusal ({error, detail}).
        Ok((status, body)) => {
            Ok((status, [(header::CONTENT_TYPE, "application/json")], body).into_response())
        }
        Err(e @ ForwardError::UnknownPeer(_)) => {
            let names: Vec<String> = d.peers.views().into_iter().map(|p| p.name).collect();
            Err(ApiError::not_found(if names.is_empty() {
                format!("{e}: this daemon watches no peers")
            } else {
                format!("{e} (peers: {})", names.join(", "))
            }))
        }
        Err(e @ ForwardError::NoActiveRun(_)) => Err(ApiError::conflict(e.to_string())),
        Err(e @ ForwardError::Timeout { .. }) => Ok(peer_error(
            StatusCode::GATEWAY_TIMEOUT,
            "peer_timeout",
            e.to_string(),
        )),
        Err(e @ ForwardError::BadGateway { .. }) => Ok(peer_error(
            StatusCode::BAD_GATEWAY,
            "peer_unreachable",
            e.to_string(),
        )),
    }
}

fn peer_error(status: StatusCode, error: &str, detail: String) -> Response {
    (
        status,
        Json(ErrorBody {
            error: error.to_string(),
            detail,
        }),
    )
        .into_response()
}

/// Pauses a peer's active run: asks the peer which run is active and posts
/// `/runs/{id}/pause` to it with the peer's token; answers with the peer's
/// status and body.
#[utoipa::path(post, path = "/api/v1/peers/{name}/pause", tag = "peers",
    params(("name" = String, Path, description = "The peer's name in the peers file")),
    security(("bearer" = [])),
    responses((status = 202, description = "The peer sent it to its engine", body = CommandAck),
              (status = 200, description = "The peer did it on disk (its run had no live engine)", body = CommandAck),
              (status = 401, description = "Missing or wrong token (this daemon's)", body = ErrorBody),
              (status = 404, description = "No such peer (or the peer no longer knows its run)", body = ErrorBody),
              (status = 409, description = "The peer has no active run, or its run is not pausable in its state", body = ErrorBody),
              (status = 502, description = "`peer_unreachable`: the peer cannot be reached, refused the peers file's token, or answered no JSON", body = ErrorBody),
              (status = 503, description = "The peer's own refusal: its engine has too many commands waiting, or it is shutting down", body = ErrorBody),
              (status = 504, description = "`peer_timeout`: the peer did not answer within 1.5 s", body = ErrorBody)))]
pub async fn pause_peer(
    State(d): State<AppState>,
    ApiPath(name): ApiPath<String>,
) -> Result<Response, ApiError> {
    forward(d, name, PeerCommand::Pause).await
}

/// Aborts a peer's active run: asks the peer which run is active and posts
/// `/runs/{id}/abort` to it with the peer's token; answers with the peer's
/// status and body.
#[utoipa::path(post, path = "/api/v1/peers/{name}/abort", tag = "peers",
    params(("name" = String, Path, description = "The peer's name in the peers file")),
    security(("bearer" = [])),
    responses((status = 202, description = "The peer sent it to its engine", body = CommandAck),
              (status = 200, description = "The peer marked its run aborted on disk", body = CommandAck),
              (status = 401, description = "Missing or wrong token (this daemon's)", body = ErrorBody),
              (status = 404, description = "No such peer (or the peer no longer knows its run)", body = ErrorBody),
              (status = 409, description = "The peer has no active run, or its run is already final", body = ErrorBody),
              (status = 502, description = "`peer_unreachable`: the peer cannot be reached, refused the peers file's token, or answered no JSON", body = ErrorBody),
              (status = 503, description = "The peer's own refusal: its engine has too many commands waiting, or it is shutting down", body = ErrorBody),
              (status = 504, description = "`peer_timeout`: the peer did not answer within 1.5 s", body = ErrorBody)))]
pub async fn abort_peer(
    State(d): State<AppState>,
    ApiPath(name): ApiPath<String>,
) -> Result<Response, ApiError> {
    forward(d, name, PeerCommand::Abort).await
}
