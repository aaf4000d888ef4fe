//! `/rig/manual/…`: manual control for bring-up, one device at a time,
//! through the same drivers and deadlines as a run; 409 while a run is
//! active; `POST /estop` stops it.

use axum::extract::State;
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::AppState;
use crate::engine::manual::{Jog, PoseReached};
use crate::postprocess::holder_check::{
    check_frame, frame_image, FramePose, HolderCheck, HolderCheckError,
};
use crate::rig::hal::encode_png;
use crate::server::api::frames::{make_preview, PREVIEW_MAX};
use crate::server::error::{ApiError, ApiJson, ErrorBody};
use crate::server::wire::Dir;

/// One device, by its name in the profile.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"device": "rail"}))]
pub struct DeviceRequest {
    /// The device (an axis or the arm).
    pub device: String,
}

/// A jog: by a step or to a position (exactly one of them).
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"device": "rail", "by_deg": 5.0}))]
pub struct JogRequest {
    /// The axis.
    pub device: String,
    /// Degrees to move from where it stands.
    #[serde(default)]
    pub by_deg: Option<f64>,
    /// Position to move to, in degrees.
    #[serde(default)]
    pub to_deg: Option<f64>,
}

/// A (light, view) pair whose pose the rig takes.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"light": {"theta_deg": 30.0, "phi_deg": 0.0}, "view": {"theta_deg": 20.0, "phi_deg": 180.0}}))]
pub struct PoseRequest {
    /// The light direction in the sample frame.
    pub light: Dir,
    /// The view direction in the sample frame.
    pub view: Dir,
}

/// A lamp or the laser, on or off.
#[derive(Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"device": "hmi", "on": true}))]
pub struct SwitchRequest {
    /// The lamp or laser.
    pub device: String,
    /// Relay closed (true) or open.
    pub on: bool,
}

/// A test frame.
#[derive(Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FrameRequest {
    /// The camera; the profile's first when absent.
    #[serde(default)]
    pub camera: Option<String>,
    /// Exposure in seconds; the camera's profile exposure when absent.
    #[serde(default)]
    pub exposure_s: Option<f64>,
}

/// Where a device stands after a manual action.
#[derive(Debug, Serialize, ToSchema)]
pub struct Reached {
    /// The device.
    pub device: String,
    /// Where it reports it stands, in degrees: one value for an axis,
    /// the joints for an arm.
    pub position_deg: Vec<f64>,
}

/// A lamp's or laser's relay after a manual switch.
#[derive(Debug, Serialize, ToSchema)]
pub struct Switched {
    /// The device.
    pub device: String,
    /// The relay's state, read back from the module.
    pub on: bool,
}

/// A test frame's numbers; the frame itself is at `GET /api/v1/rig/manual/frame`.
#[derive(Debug, Serialize, ToSchema)]
pub struct TestFrame {
    /// The camera that took it.
    pub camera: String,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Bits per sample.
    pub bit_depth: u8,
    /// Darkest sample.
    pub min: u16,
    /// Brightest sample.
    pub max: u16,
    /// Mean sample value.
    pub mean: f64,
    /// Fraction of samples at the sensor's full scale.
    pub saturated: f64,
}

const REFUSED: &str =
    "Refused: no such device, the wrong kind, or beyond its soft limits (nothing moved)";

/// Homes an axis or the arm (an axis without homing takes its operator-set zero).
#[utoipa::path(post, path = "/api/v1/rig/manual/home", tag = "manual", security(("bearer" = [])),
    request_body = DeviceRequest,
    responses((status = 200, description = "Where it stands after homing", body = Reached),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active", body = ErrorBody),
              (status = 422, description = REFUSED, body = ErrorBody),
              (status = 502, description = "The device failed or did not answer in time", body = ErrorBody)))]
pub async fn home(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<DeviceRequest>,
) -> Result<Json<Reached>, ApiError> {
    let device = req.device.clone();
    let position_deg = d
        .manual(move |rig| Box::pin(async move { rig.home(&req.device).await }))
        .await?;
    Ok(Json(Reached {
        device,
        position_deg,
    }))
}

/// Jogs an axis by a step or to a position; a target beyond its soft limits is refused and nothing moves.
#[utoipa::path(post, path = "/api/v1/rig/manual/jog", tag = "manual", security(("bearer" = [])),
    request_body = JogRequest,
    responses((status = 200, description = "Where the axis stands", body = Reached),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active", body = ErrorBody),
              (status = 422, description = REFUSED, body = ErrorBody),
              (status = 502, description = "The device failed or did not answer in time", body = ErrorBody)))]
pub async fn jog(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<JogRequest>,
) -> Result<Json<Reached>, ApiError> {
    let jog = match (req.by_deg, req.to_deg) {
        (Some(by), None) => Jog::By(by),
        (None, Some(to)) => Jog::To(to),
        _ => {
            return Err(ApiError::invalid(
                "give exactly one of `by_deg` and `to_deg`",
            ))
        }
    };
    let device = req.device.clone();
    let at = d
        .manual(move |rig| Box::pin(async move { rig.jog(&req.device, jog).await }))
        .await?;
    Ok(Json(Reached {
        device,
        position_deg: vec![at],
    }))
}

/// Moves the axes and the arm to the pose of a (light, view) pair; the lamp is not switched.
#[utoipa::path(post, path = "/api/v1/rig/manual/pose", tag = "manual", security(("bearer" = [])),
    request_body = PoseRequest,
    responses((status = 200, description = "Where the devices stand, and which lamp and camera the pair uses", body = PoseReached),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active", body = ErrorBody),
              (status = 422, description = "A direction outside the hemisphere (nothing moved)", body = ErrorBody),
              (status = 502, description = "A device failed or did not answer in time", body = ErrorBody)))]
pub async fn pose(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<PoseRequest>,
) -> Result<Json<PoseReached>, ApiError> {
    let direction = |d: Dir| rigd_core::geometry::Direction {
        theta_deg: d.theta_deg,
        phi_deg: d.phi_deg,
    };
    let (light, view) = (direction(req.light), direction(req.view));
    let reached = d
        .manual(move |rig| Box::pin(async move { rig.pose(light, view).await }))
        .await?;
    Ok(Json(reached))
}

/// Switches a lamp or the laser; the relay is read back before the answer.
#[utoipa::path(post, path = "/api/v1/rig/manual/lamp", tag = "manual", security(("bearer" = [])),
    request_body = SwitchRequest,
    responses((status = 200, description = "The relay's state", body = Switched),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active", body = ErrorBody),
              (status = 422, description = REFUSED, body = ErrorBody),
              (status = 502, description = "The module failed or did not answer in time", body = ErrorBody)))]
pub async fn lamp(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<SwitchRequest>,
) -> Result<Json<Switched>, ApiError> {
    let (device, on) = (req.device.clone(), req.on);
    d.manual(move |rig| Box::pin(async move { rig.switch(&req.device, req.on).await }))
        .await?;
    Ok(Json(Switched { device, on }))
}

/// Takes a test frame; `GET` on the same path returns it as an 8-bit preview.
#[utoipa::path(post, path = "/api/v1/rig/manual/frame", tag = "manual", security(("bearer" = [])),
    request_body = FrameRequest,
    responses((status = 200, description = "The frame's numbers", body = TestFrame),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active", body = ErrorBody),
              (status = 422, description = "No such camera, or an exposure out of range", body = ErrorBody),
              (status = 502, description = "The camera failed or did not answer in time", body = ErrorBody)))]
pub async fn take_frame(
    State(d): State<AppState>,
    ApiJson(req): ApiJson<FrameRequest>,
) -> Result<Json<TestFrame>, ApiError> {
    let (camera, frame) = d
        .manual(move |rig| {
            Box::pin(async move { rig.test_frame(req.camera.as_deref(), req.exposure_s).await })
        })
        .await?;
    let full_scale = frame.full_scale();
    let n = frame.pixels.len().max(1) as f64;
    let answer = TestFrame {
        camera,
        width: frame.width,
        height: frame.height,
        bit_depth: frame.bit_depth,
        min: frame.pixels.iter().copied().min().unwrap_or(0),
        max: frame.pixels.iter().copied().max().unwrap_or(0),
        mean: frame.pixels.iter().map(|&v| f64::from(v)).sum::<f64>() / n,
        saturated: frame.pixels.iter().filter(|&&v| v >= full_scale).count() as f64 / n,
    };
    let png = encode_png(&frame).map_err(ApiError::internal)?;
    d.manual.keep_frame(png);
    Ok(Json(answer))
}

/// What a holder check answers when the rig has not been posed since it
/// connected, or has moved since.
pub const NOT_POSED: &str = "move to a pose first: POST /api/v1/rig/manual/pose; the holder check needs the view (a jog or a homing since the last pose makes it unknown)";

/// Takes a test frame at the last pose and checks the profile's holder in it.
///
/// As `rigd holder check` does: every marker looked for where the camera
/// model puts it at the last pose's view, the frame registered by those
/// found, each colour patch and white area read and checked for clipping.
/// A check that finds problems is still 200, with `ok` false and one line
/// per problem in `problems`. The frame becomes the last test frame
/// (`GET /api/v1/rig/manual/frame`).
#[utoipa::path(post, path = "/api/v1/rig/manual/holder-check", tag = "manual", security(("bearer" = [])),
    request_body(content = Option<FrameRequest>, description = "The camera and exposure, as for a test frame; no body (or `null`): the profile's first camera at its exposure"),
    responses((status = 200, description = "What the check found; `ok` false names each problem", body = HolderCheck),
              (status = 401, description = "Missing or wrong token", body = ErrorBody),
              (status = 409, description = "A run is active, or the rig has not been posed (or has moved since): the check needs the view", body = ErrorBody),
              (status = 415, description = "A body that is not `Content-Type: application/json`", body = ErrorBody),
              (status = 422, description = "No such camera, an exposure out of range, a view at the horizon, or a holder the check cannot use", body = ErrorBody),
              (status = 500, description = "The check failed inside the daemon", body = ErrorBody),
              (status = 502, description = "The camera failed, did not answer in time, or sent a frame that cannot be read", body = ErrorBody)))]
pub async fn holder_check(
    State(d): State<AppState>,
    req: Option<ApiJson<Option<FrameRequest>>>,
) -> Result<Json<HolderCheck>, ApiError> {
    let req = req.and_then(|ApiJson(r)| r).unwrap_or_default();
    // The view is asked for first: without one no frame is taken.
    let taken = d
        .manual(move |rig| {
            Box::pin(async move {
                if rig.last_pose().is_none() {
                    return Ok(None);
                }
                let (camera, frame) = rig
                    .test_frame(req.camera.as_deref(), req.exposure_s)
                    .await?;
                let view = rig.posed_view(&camera)?;
                Ok(view.map(|view| (camera, frame, view)))
            })
        })
        .await?;
    let Some((camera, frame, view)) = taken else {
        return Err(ApiError::conflict(NOT_POSED));
    };
    let profile = d.profile.clone();
    let (png, checked) = tokio::task::spawn_blocking(move || {
        let png = encode_png(&frame);
        let checked = frame_image(&frame, &profile, &camera)
            .map_err(|e| {
                ApiError::new(
                    axum::http::StatusCode::BAD_GATEWAY,
                    format!("camera `{camera}` sent a frame that cannot be read: {e}"),
                )
            })
            .and_then(|image| {
                let pose = FramePose {
                    view,
                    camera: Some(camera),
                    focal_px: None,
                };
                check_frame(&profile, &image, &pose).map_err(holder_check_error)
            });
        (png, checked)
    })
    .await
    .map_err(|e| ApiError::internal(e.to_string()))?;
    d.manual.keep_frame(png.map_err(ApiError::internal)?);
    Ok(Json(checked?))
}

/// Why the check could not be made: the profile's holder or camera, or
/// the view, cannot be used (422).
fn holder_check_error(e: HolderCheckError) -> ApiError {
    match e {
        HolderCheckError::Holder(_)
        | HolderCheckError::Camera(_)
        | HolderCheckError::Invalid(_) => ApiError::invalid(e.to_string()),
        // Only `read_frame` reads files; a frame in memory has no path.
        HolderCheckError::Frame { .. } => ApiError::internal(e.to_string()),
    }
}

/// The last test frame as an 8-bit PNG, stretched to its brightest pixel.
#[utoipa::path(get, path = "/api/v1/rig/manual/frame", tag = "manual",
    responses((status = 200, description = "The preview", content_type = "image/png"),
              (status = 401, description = "Token needed (non-loopback client)", body = ErrorBody),
              (status = 404, description = "No test frame taken yet", body = ErrorBody)))]
pub async fn last_frame(State(d): State<AppState>) -> Result<Response, ApiError> {
    let png = d.manual.last_frame().ok_or_else(|| {
        ApiError::not_found("no test frame taken yet (POST /api/v1/rig/manual/frame)")
    })?;
    let preview = tokio::task::spawn_blocking(move || make_preview(&png, PREVIEW_MAX))
        .await
        .map_err(|e| ApiError::internal(e.to_string()))?
        .map_err(ApiError::internal)?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        preview,
    )
        .into_response())
}

/// Lets go of the manual-control rig (its ports close); a run does this itself.
#[utoipa::path(post, path = "/api/v1/rig/manual/release", tag = "manual", security(("bearer" = [])),
    responses((status = 204, description = "Released (or nothing held)"),
              (status = 401, description = "Missing or wrong token", body = ErrorBody)))]
pub async fn release(State(d): State<AppState>) -> axum::http::StatusCode {
    let _gate = d.start_gate.lock().await;
    d.manual.release().await;
    axum::http::StatusCode::NO_CONTENT
}
