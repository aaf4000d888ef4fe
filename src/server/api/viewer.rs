//! The BTF viewer's routes: the packed material of a processed run, the
//! meshes it is drawn on, and the viewer page itself (`/viewer/{run}`).

use axum::extract::{Path, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use rigd_process::mesh::MeshKind;
use serde::Deserialize;

use super::AppState;
use crate::postprocess::viewer::{self, ViewerError, DEFAULT_DENSITY};
use crate::server::error::{ApiError, ApiPath, ApiQuery};

/// The BTF viewer page, served at `/viewer/{run}`.
pub const VIEWER_HTML: &str = include_str!("../dashboard/viewer.html");
/// The viewer page's script, served at `/viewer.js`.
pub const VIEWER_JS: &str = include_str!("../dashboard/viewer.js");

/// Most components the viewer is sent per slot unless it asks for fewer.
const MAX_COMPONENTS: usize = 64;

/// Query of `GET /api/v1/runs/{id}/btf` and `GET /api/v1/runs/{id}/btf/data`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct BtfQuery {
    /// Send at most this many PCA components per view slot (default: all stored).
    #[param(example = 8)]
    pub components: Option<usize>,
}

/// Query of `GET /api/v1/runs/{id}/btf/mesh/{kind}`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct MeshQuery {
    /// Material tiles per world unit (default 1; the flat sample is 2 units across).
    #[param(example = 1.0)]
    pub density: Option<f64>,
}

fn viewer_error(e: ViewerError) -> ApiError {
    match e {
        ViewerError::NotProcessed { .. }
        | ViewerError::NeedsBtf { .. }
        | ViewerError::NoMdf { .. } => ApiError::not_found(e.to_string()),
        other => ApiError::internal(other.to_string()),
    }
}

/// Runs `work` on the run's directory off the async threads.
async fn on_run<T: Send + 'static>(
    d: &AppState,
    id: &str,
    work: impl FnOnce(&std::path::Path) -> Result<T, ViewerError> + Send + 'static,
) -> Result<T, ApiError> {
    let root = d
        .run_root(id)
        .ok_or_else(|| ApiError::not_found("no such run"))?;
    tokio::task::spawn_blocking(move || work(&root))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(viewer_error)
}

/// The components asked for, at most [`MAX_COMPONENTS`].
fn components(q: &BtfQuery) -> usize {
    q.components.unwrap_or(MAX_COMPONENTS).min(MAX_COMPONENTS)
}

/// The processed run's material for the viewer: the manifest of the blob at
/// `…/btf/data` (a compressed BTF: f16 eigen-textures and f32 weights per
/// view slot, ring tables; or a photometric-stereo run's albedo and
/// normals). The layout is documented in `docs/viewer.md`.
#[utoipa::path(get, path = "/api/v1/runs/{id}/btf", tag = "runs",
    params(("id" = String, Path, description = "Run id"), BtfQuery),
    responses((status = 200, description = "The manifest", content_type = "application/json", body = Object),
              (status = 404, description = "No such run, or not processed yet", body = crate::server::error::ErrorBody)))]
pub async fn btf_manifest(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<BtfQuery>,
) -> Result<Response, ApiError> {
    let max = components(&q);
    let manifest = on_run(&d, &id, move |root| viewer::manifest(root, max)).await?;
    let mut body =
        serde_json::to_value(&manifest).map_err(|e| ApiError::internal(e.to_string()))?;
    body["data_url"] = serde_json::Value::String(format!(
        "/api/v1/runs/{id}/btf/data?components={}",
        manifest.components
    ));
    Ok(axum::Json(body).into_response())
}

/// The blob the manifest describes (`application/octet-stream`).
#[utoipa::path(get, path = "/api/v1/runs/{id}/btf/data", tag = "runs",
    params(("id" = String, Path, description = "Run id"), BtfQuery),
    responses((status = 200, description = "The packed material", content_type = "application/octet-stream", body = Vec<u8>),
              (status = 404, description = "No such run, or not processed yet", body = crate::server::error::ErrorBody)))]
pub async fn btf_data(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<BtfQuery>,
) -> Result<Response, ApiError> {
    let max = components(&q);
    let (_, data) = on_run(&d, &id, move |root| viewer::pack(root, max)).await?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], data).into_response())
}

/// A viewer mesh (`flat`, `cylinder` or `cloth`): a grid with positions,
/// normals, tangents, texture coordinates and triangles, plus per vertex
/// the visibility of each of the run's measured light directions (Ganster et al.).
#[utoipa::path(get, path = "/api/v1/runs/{id}/btf/mesh/{kind}", tag = "runs",
    params(("id" = String, Path, description = "Run id"),
           ("kind" = String, Path, description = "flat, cylinder, cloth or sphere"), MeshQuery),
    responses((status = 200, description = "The mesh", content_type = "application/json", body = Object),
              (status = 404, description = "No such run or mesh, or not processed yet", body = crate::server::error::ErrorBody),
              (status = 422, description = "Density out of range", body = crate::server::error::ErrorBody)))]
pub async fn btf_mesh(
    State(d): State<AppState>,
    ApiPath((id, kind)): ApiPath<(String, String)>,
    ApiQuery(q): ApiQuery<MeshQuery>,
) -> Result<Response, ApiError> {
    let kind: MeshKind = kind
        .parse()
        .map_err(|e: rigd_process::mesh::MeshError| ApiError::not_found(e.to_string()))?;
    let density = q.density.unwrap_or(DEFAULT_DENSITY);
    if !(density.is_finite() && density > 0.0 && density <= 64.0) {
        return Err(ApiError::invalid(format!(
            "density {density}: expected more than 0 and at most 64 tiles per unit"
        )));
    }
    let view = on_run(&d, &id, move |root| viewer::mesh_view(root, kind, density)).await?;
    Ok(axum::Json(view).into_response())
}

/// The run's MDF in texture space (`rigd process mdf-texture`) for the
/// viewer's MDF silhouettes and shadows: the manifest of the blob at
/// `…/mdf/data` (view table, texture side, tile size; `docs/viewer.md`).
#[utoipa::path(get, path = "/api/v1/runs/{id}/mdf", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    responses((status = 200, description = "The manifest", content_type = "application/json", body = Object),
              (status = 404, description = "No such run, or no MDF texture", body = crate::server::error::ErrorBody)))]
pub async fn mdf_manifest(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    let manifest = on_run(&d, &id, viewer::mdf_manifest).await?;
    let mut body =
        serde_json::to_value(&manifest).map_err(|e| ApiError::internal(e.to_string()))?;
    body["data_url"] = serde_json::Value::String(format!("/api/v1/runs/{id}/mdf/data"));
    Ok(axum::Json(body).into_response())
}

/// The MDF blob the manifest describes: little-endian f32, one layer per
/// view, as `texImage3D(TEXTURE_2D_ARRAY, 0, R32F, …, RED, FLOAT, …)`
/// takes it (`application/octet-stream`).
#[utoipa::path(get, path = "/api/v1/runs/{id}/mdf/data", tag = "runs",
    params(("id" = String, Path, description = "Run id")),
    responses((status = 200, description = "The MDF texture", content_type = "application/octet-stream", body = Vec<u8>),
              (status = 404, description = "No such run, or no MDF texture", body = crate::server::error::ErrorBody)))]
pub async fn mdf_data(
    State(d): State<AppState>,
    ApiPath(id): ApiPath<String>,
) -> Result<Response, ApiError> {
    let data = on_run(&d, &id, viewer::mdf_pack).await?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], data).into_response())
}

/// The viewer page; the run id is read by the page from its own path.
pub async fn page(Path(_run): Path<String>) -> Response {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        VIEWER_HTML,
    )
        .into_response()
}
