//! `/rig` and `/estop`: the rig's devices and state, and the emergency stop.

use axum::extract::State;
use axum::Json;

use super::AppState;
use crate::model::profile::Device;
use crate::model::run_state::RunState;
use crate::rig::check::RigCheck;
use crate::server::error::{ApiError, ErrorBody};
use crate::server::wire::*;

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
    let world = LiveState::of(sim);
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
            kind: serde_json::to_value(dev.kind())
                .ok()
                .and_then(|k| k.as_str().map(str::to_string))
                .unwrap_or_default(),
            protocol: dev.protocol().to_string(),
            connected: d.config.sim,
            homed: None,
            homing: dev.as_axis().map(|a| a.homing),
            busy,
            fault: fault_for(name),
            position_deg: None,
            joints: None,
            on: None,
            camera: None,
        };
        match dev {
            Device::Axis(_) => {
                let p = world.as_ref().and_then(|w| w.axis(name));
                v.homed = Some(p.is_some());
                v.position_deg = p;
            }
            Device::Arm(arm) => {
                let q = world.as_ref().and_then(|w| w.arm());
                v.homed = Some(q.is_some());
                if let Some(q) = q {
                    let m: serde_json::Map<String, serde_json::Value> = arm
                        .joints
                        .iter()
                        .zip(q)
                        .map(|(j, x)| (j.name.clone(), serde_json::json!(x)))
                        .collect();
                    v.joints = Some(serde_json::Value::Object(m));
                }
            }
            Device::Lamp(_) => {
                let on = world.as_ref().and_then(|w| w.lamp(name)).unwrap_or(false);
                v.on = Some(on);
                lamps.insert(name.clone(), serde_json::json!(on));
            }
            Device::Camera(camera) => {
                let (intrinsics, timing) = (camera.intrinsics, camera.timing);
                v.camera = Some(serde_json::json!({
                    "resolution": intrinsics.resolution,
                    "bit_depth": intrinsics.bit_depth,
                    "focal_px": intrinsics.focal_px,
                    "exposure_s": exposure.unwrap_or(timing.exposure_s),
                    "readout_s": timing.readout_s,
                    "transfer_s": timing.transfer_s,
                    "sim_frame_size": d.profile.sim.frame_size,
                }));
            }
            Device::Laser(_) => {}
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

/// Bring-up without moving anything: every device connected through the
/// same drivers and deadlines as a run and reported on one line (identity,
/// firmware, controller settings against the profile, homing mode, position
/// or state), usable or not with the fix. A run started meanwhile waits.
#[utoipa::path(get, path = "/api/v1/rig/check", tag = "rig",
    responses((status = 200, description = "One verdict per device; `usable` is true only when every device is", body = RigCheck),
              (status = 401, description = "Token needed (non-loopback client)", body = ErrorBody),
              (status = 409, description = "A run holds the rig", body = ErrorBody)))]
pub async fn check(State(d): State<AppState>) -> Result<Json<RigCheck>, ApiError> {
    Ok(Json(d.check_rig().await?))
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

/// What the rig's devices report of themselves: on the simulated rig its
/// world; the hardware drivers report through the run, so nothing here.
struct LiveState {
    #[cfg(feature = "sim")]
    world: crate::rig::sim::World,
}

impl LiveState {
    fn of(sim: Option<crate::rig::SimHandle>) -> Option<LiveState> {
        #[cfg(feature = "sim")]
        return sim.map(|s| LiveState { world: s.world() });
        #[cfg(not(feature = "sim"))]
        return sim.map(|s| match s {});
    }

    fn axis(&self, name: &str) -> Option<f64> {
        #[cfg(feature = "sim")]
        return self.world.axes.get(name).copied();
        #[cfg(not(feature = "sim"))]
        return {
            let _ = name;
            None
        };
    }

    fn arm(&self) -> Option<Vec<f64>> {
        #[cfg(feature = "sim")]
        return self.world.arm.clone();
        #[cfg(not(feature = "sim"))]
        return None;
    }

    fn lamp(&self, name: &str) -> Option<bool> {
        #[cfg(feature = "sim")]
        return self.world.lamps_on.get(name).copied();
        #[cfg(not(feature = "sim"))]
        return {
            let _ = name;
            None
        };
    }
}
