//! `/sim`: the scene simulator, one frame on request, and its scenes.

use axum::extract::State;
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::AppState;
use crate::server::error::{ApiError, ApiQuery, ErrorBody};

/// What `GET /api/v1/sim/render` takes.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct RenderQuery {
    /// A scene's name as `/api/v1/sim/scenes` lists it: a built-in scene or
    /// the profile's configured one (never a path); the profile's if absent.
    pub scene: Option<String>,
    /// Light θ,φ in degrees, sample frame (default 0,0).
    pub light: Option<String>,
    /// View θ,φ in degrees, sample frame (default 0,0).
    pub view: Option<String>,
    /// WIDTHxHEIGHT, at most 2048 each way (default: the profile's sim frame size).
    pub size: Option<String>,
    /// Which camera of the daemon's profile, by name (default: its first).
    pub camera: Option<String>,
    /// Effect switches: `all`, `none`, or `+interreflection,-noise`.
    pub effects: Option<String>,
    /// Seed of the frame's sensor noise (shot and read noise); the same seed
    /// renders the same frame (default 0).
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
              (status = 404, description = "No scene or camera of that name (the detail lists them)", body = ErrorBody),
              (status = 422, description = "A value out of range", body = ErrorBody)))]
pub async fn sim_render(
    State(d): State<AppState>,
    ApiQuery(q): ApiQuery<RenderQuery>,
) -> Result<Response, ApiError> {
    let req = render_request(&q).map_err(ApiError::bad_request)?;
    let profile = d.profile.clone();
    let out =
        tokio::task::spawn_blocking(move || crate::rig::sim::shot::render_offered(&profile, &req))
            .await
            .map_err(|e| ApiError::internal(e.to_string()))?
            .map_err(render_error)?;
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

/// An unknown scene or camera is 404 (the detail names those there are),
/// a value out of range 422.
fn render_error(e: crate::rig::sim::shot::RenderError) -> ApiError {
    use crate::rig::sim::shot::RenderError;
    use crate::rig::sim::SceneError;
    match e {
        RenderError::Scene(SceneError::NotOffered { .. }) | RenderError::UnknownCamera { .. } => {
            ApiError::not_found(e.to_string())
        }
        other => ApiError::invalid(other.to_string()),
    }
}

fn render_request(q: &RenderQuery) -> Result<crate::rig::sim::shot::RenderRequest, String> {
    use crate::model::text::{parse_direction, parse_frame_size};
    use crate::rig::sim::shot::{parse_laser, RenderRequest};
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

/// A scene a client can ask for, and the effects it can show.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct SceneView {
    /// The scene's name, as the `scene` parameter of `/api/v1/sim/render`
    /// takes it: a built-in scene's, or the profile's `[sim] scene` as
    /// written there.
    pub name: String,
    /// What the scene shows, in a line (relief, material).
    pub description: String,
    /// Effects frames of this scene can pay for.
    pub effects: Vec<String>,
}

/// The scenes a client can ask for: the built-in ones, and the profile's
/// configured one when it is a scene file.
#[utoipa::path(get, path = "/api/v1/sim/scenes", tag = "sim",
    responses((status = 200, description = "The scenes", body = Vec<SceneView>)))]
pub async fn sim_scenes(State(d): State<AppState>) -> Result<Json<Vec<SceneView>>, ApiError> {
    let profile = d.profile.clone();
    let views = tokio::task::spawn_blocking(move || {
        crate::rig::sim::shot::offered_scene_names(&profile)
            .into_iter()
            .map(|name| {
                let s = crate::rig::sim::shot::offered_scene(&profile, Some(&name))
                    .map_err(|e| ApiError::internal(e.to_string()))?;
                Ok(SceneView {
                    name,
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
