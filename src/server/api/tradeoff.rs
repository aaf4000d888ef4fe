//! The trade-off report over HTTP: the dashboard shows the plot of
//! `rigd tradeoff` (error against physical capture time, a curve per
//! family) and can ask the daemon to compute it for its own rig.
//!
//! The report lives in `DATA/tradeoff/` (`tradeoff.json`, `.csv`, `.svg`),
//! where `rigd tradeoff --out DATA/tradeoff` also puts it. Computing takes
//! minutes of simulated captures and processing on every core, so it is
//! refused while a run is active (a real rig's device timing must not
//! compete with it) and only one computes at a time.

use std::sync::atomic::Ordering;

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::AppState;
use crate::server::error::{ApiError, ApiJson, ApiQuery, ErrorBody};
use crate::tradeoff::TradeoffConfig;

/// The folder of the data directory the report is kept in.
pub const TRADEOFF_DIR: &str = "tradeoff";

/// `POST /api/v1/tradeoff`: what to compute (all optional).
#[derive(Debug, Clone, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"texture": 8, "held_out": 24, "render_size": [128, 96]}))]
pub struct TradeoffRequest {
    /// Scene of the simulated captures, by name as `/api/v1/sim/scenes`
    /// lists them (default: the profile's sim scene, else corduroy).
    pub scene: Option<String>,
    /// Normtexture side, texels (default 8; 4 … 64 here).
    pub texture: Option<usize>,
    /// Held-out (light, view) pairs (default 24; 1 … 200).
    pub held_out: Option<usize>,
    /// Frame size of the fidelity renders (default [128, 96]; at most 512×512).
    pub render_size: Option<[u32; 2]>,
}

/// The answer to a start.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct TradeoffStarted {
    /// The scene of the simulated captures.
    pub scene: String,
    /// Normtexture side in texels.
    pub texture: usize,
    /// Held-out (light, view) pairs the BTF error is measured on.
    pub held_out: usize,
    /// Frame size of the fidelity renders, `[width, height]` in pixels.
    pub render_size: [u32; 2],
}

fn report_path(d: &AppState, file: &str) -> std::path::PathBuf {
    d.data_dir.join(TRADEOFF_DIR).join(file)
}

async fn read_report_file(d: &AppState, file: &str) -> Result<Vec<u8>, ApiError> {
    match super::read_served(report_path(d, file)).await {
        Ok(bytes) => Ok(bytes),
        Err(e) if e.io_kind() == Some(std::io::ErrorKind::NotFound) => {
            let busy = d.tradeoff_busy.load(Ordering::SeqCst);
            Err(ApiError::not_found(if busy {
                "the trade-off report is being computed; it appears here when done".to_string()
            } else {
                format!(
                    "no trade-off report yet: POST /api/v1/tradeoff, or run `rigd tradeoff --out {}`",
                    d.data_dir.join(TRADEOFF_DIR).display()
                )
            }))
        }
        Err(e) => Err(ApiError::internal(e.to_string())),
    }
}

/// The latest trade-off report (`tradeoff.json`): every row with its
/// images, physical time, bytes, error and unit, and the method notes.
#[utoipa::path(get, path = "/api/v1/tradeoff", tag = "rig",
    responses((status = 200, description = "The report", content_type = "application/json", body = Object),
              (status = 404, description = "No report yet", body = ErrorBody)))]
pub async fn get_report(State(d): State<AppState>) -> Result<Response, ApiError> {
    let bytes = read_report_file(&d, "tradeoff.json").await?;
    Ok(([(header::CONTENT_TYPE, "application/json")], bytes).into_response())
}

/// The latest report's figure, drawn now (so a report written by an older
/// rigd gets the current figure), with the daemon profile's default plan
/// ringed when the report is of this rig.
async fn latest_figure(d: &AppState) -> Result<crate::tradeoff::figure::Figure, ApiError> {
    let bytes = read_report_file(d, "tradeoff.json").await?;
    let report = crate::tradeoff::read_report(&bytes).map_err(ApiError::internal)?;
    let marked = (report.profile == d.profile.name).then(|| d.profile.default_plan.clone());
    tokio::task::spawn_blocking(move || crate::tradeoff::figure::figure(&report, marked.as_deref()))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))
}

/// The report's figure (SVG): a panel per family with its own axes, the
/// Pareto frontier, error bars and the profile's default plan ringed.
#[utoipa::path(get, path = "/api/v1/tradeoff/plot.svg", tag = "rig",
    responses((status = 200, description = "The figure", content_type = "image/svg+xml", body = String),
              (status = 404, description = "No report yet", body = ErrorBody)))]
pub async fn get_plot(State(d): State<AppState>) -> Result<Response, ApiError> {
    let figure = latest_figure(&d).await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/svg+xml"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        figure.svg,
    )
        .into_response())
}

/// The report's figure with its layout: the SVG, each panel's plotting
/// area and every point's position (SVG pixels), row, values and whether
/// it is on the frontier, for an interactive view.
#[utoipa::path(get, path = "/api/v1/tradeoff/figure", tag = "rig",
    responses((status = 200, description = "The figure and its layout", body = crate::tradeoff::figure::Figure),
              (status = 404, description = "No report yet", body = ErrorBody)))]
pub async fn get_figure(
    State(d): State<AppState>,
) -> Result<Json<crate::tradeoff::figure::Figure>, ApiError> {
    latest_figure(&d).await.map(Json)
}

/// `?budget=3h` or `?target=15%` on the choice.
#[derive(Debug, Default, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ChoiceQuery {
    /// The most accurate measured plan whose physical capture time fits
    /// this budget (`3h`, `90m`, `2h30m`, or seconds).
    #[param(example = "3h")]
    pub budget: Option<String>,
    /// The fastest measured plan whose held-out error is at most this
    /// (`15%` or `0.15`).
    pub target: Option<String>,
}

/// The plan that answers a time budget or an error target, from the
/// latest report's `plans` rows, with the Pareto frontier it lies on (as
/// `rigd tradeoff --budget` / `--target` print it).
#[utoipa::path(get, path = "/api/v1/tradeoff/choice", tag = "rig", params(ChoiceQuery),
    responses((status = 200, description = "The plan chosen and the frontier", body = crate::tradeoff::choice::PlanChoice),
              (status = 400, description = "A malformed query", body = ErrorBody),
              (status = 404, description = "No report yet", body = ErrorBody),
              (status = 422, description = "Neither or both of budget and target, a value that does not parse, or no measured plan that fits (named with the nearest)", body = ErrorBody)))]
pub async fn get_choice(
    State(d): State<AppState>,
    ApiQuery(q): ApiQuery<ChoiceQuery>,
) -> Result<Json<crate::tradeoff::choice::PlanChoice>, ApiError> {
    use crate::tradeoff::choice::{choose, Goal};
    let goal = match (&q.budget, &q.target) {
        (Some(b), None) => Goal::budget(b),
        (None, Some(t)) => Goal::target(t),
        _ => Err("give one of `budget` (e.g. 3h) or `target` (e.g. 15%)".to_string()),
    }
    .map_err(ApiError::invalid)?;
    let bytes = read_report_file(&d, "tradeoff.json").await?;
    let rows = crate::tradeoff::read_rows(&bytes).map_err(ApiError::internal)?;
    choose(&crate::tradeoff::plan_points(&rows), goal)
        .map(Json)
        .map_err(|e| ApiError::invalid(e.to_string()))
}

/// Computes the report for the daemon's rig in the background; `tradeoff`
/// events report progress and the end. Refused while a run is active or
/// another computation runs.
#[utoipa::path(post, path = "/api/v1/tradeoff", tag = "rig", request_body = TradeoffRequest,
    security(("bearer" = [])),
    responses((status = 202, description = "Started", body = TradeoffStarted),
              (status = 400, description = "Malformed JSON", body = ErrorBody),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active, or a computation runs", body = ErrorBody),
              (status = 415, description = "Not `Content-Type: application/json`", body = ErrorBody),
              (status = 422, description = "Unknown scene (the detail lists them) or a value out of range", body = ErrorBody)))]
pub async fn start(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<TradeoffRequest>,
) -> Result<(axum::http::StatusCode, Json<TradeoffStarted>), ApiError> {
    let scene = req
        .scene
        .clone()
        .or_else(|| {
            crate::rig::sim::settings(&d.profile.sim)
                .ok()
                .and_then(|s| s.scene)
        })
        .unwrap_or_else(|| "corduroy".to_string());
    // A built-in or the configured scene only: a client's name is never a path.
    crate::rig::sim::shot::offered_scene(&d.profile, Some(&scene))
        .map_err(|e| ApiError::invalid(e.to_string()))?;
    let texture = req.texture.unwrap_or(8);
    let held_out = req.held_out.unwrap_or(24);
    let render_size = req.render_size.unwrap_or([128, 96]);
    if !(4..=64).contains(&texture) {
        return Err(ApiError::invalid(format!(
            "texture {texture}: expected 4 … 64"
        )));
    }
    if !(1..=200).contains(&held_out) {
        return Err(ApiError::invalid(format!(
            "held_out {held_out}: expected 1 … 200"
        )));
    }
    if !(16..=512).contains(&render_size[0]) || !(16..=512).contains(&render_size[1]) {
        return Err(ApiError::invalid(format!(
            "render_size {render_size:?}: expected 16 … 512 each way"
        )));
    }
    if d.inner().active.is_some() {
        return Err(ApiError::conflict(
            "a run is active: the trade-off report is computed when the rig is idle",
        ));
    }
    if d.tradeoff_busy.swap(true, Ordering::SeqCst) {
        return Err(ApiError::conflict(
            "the trade-off report is already being computed",
        ));
    }
    let cfg = TradeoffConfig {
        texture,
        held_out,
        render_size,
        ..TradeoffConfig::default()
    };
    let started = TradeoffStarted {
        scene: scene.clone(),
        texture,
        held_out,
        render_size,
    };
    d.hub.publish(
        None,
        "tradeoff",
        serde_json::json!({"state": "started", "scene": scene}),
    );
    let daemon = d.clone();
    tokio::task::spawn_blocking(move || {
        // Frees the daemon for the next computation however this ends,
        // a panic included.
        struct Busy(AppState);
        impl Drop for Busy {
            fn drop(&mut self) {
                self.0.tradeoff_busy.store(false, Ordering::SeqCst);
            }
        }
        let busy = Busy(daemon.clone());
        let out = daemon.data_dir.join(TRADEOFF_DIR);
        let hub = &daemon.hub;
        let result = crate::tradeoff::run(&daemon.profile, &scene, &cfg, &out, &|what| {
            hub.publish(
                None,
                "tradeoff",
                serde_json::json!({"state": "computing", "step": what}),
            );
        });
        let event = match result {
            Ok(report) => serde_json::json!({"state": "done", "rows": report.rows.len()}),
            Err(e) => {
                tracing::warn!("trade-off report failed: {e}");
                serde_json::json!({"state": "failed", "error": e.to_string()})
            }
        };
        drop(busy);
        hub.publish(None, "tradeoff", event);
    });
    Ok((axum::http::StatusCode::ACCEPTED, Json(started)))
}
