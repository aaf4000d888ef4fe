//! Manual control for bring-up: one device at a time, outside any run.
//! Every action goes through the same drivers and the same deadlines as a
//! run's steps (the engine's `deadline`, its slack, the homing deadline,
//! the profile's motion model), input is checked before anything moves,
//! and the rig's emergency stop ([`ManualRig::estop`]) covers it.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use rigd_core::geometry::Direction;
use rigd_core::Clock;
use serde::Serialize;

use super::estop::EStop;
use super::{deadline, goto, Lights, Movers, DEADLINE_SLACK_S, HOMING_DEADLINE_S};
use crate::kinematics::{Setpoints, Solver};
use crate::model::profile::{Device, DeviceKind, Profile};
use crate::rig::hal::{DeviceError, Frame, Rig};
use crate::schedule::timing::Timing;

/// Why a manual action was not done.
#[derive(Debug, thiserror::Error)]
pub enum ManualError {
    /// The request names no such device, or asks for what it cannot do
    /// (a jog beyond the soft limits, a lamp that is an axis): nothing was
    /// sent to any device.
    #[error("{0}")]
    BadInput(String),
    /// A device failed or did not answer in time.
    #[error(transparent)]
    Device(#[from] DeviceError),
}

/// How far to jog an axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Jog {
    /// By this many degrees from where it stands.
    By(f64),
    /// To this position, in degrees.
    To(f64),
}

/// Where a manual pose put the rig.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct PoseReached {
    /// Every axis moved, with the position it reports, in degrees.
    pub axes: BTreeMap<String, f64>,
    /// The arm's joints as it reports them, in degrees (gonioreflectometer).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub arm: Option<Vec<f64>>,
    /// The lamp (or laser) the pair is lit by; not switched.
    pub lamp: String,
    /// The camera that sees the pair.
    pub camera: String,
    /// False when the rig cannot reach the pair and went to the nearest
    /// substitute.
    pub feasible: bool,
    /// Why the pair is infeasible, and what was substituted.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

/// The (light, view) pair the rig was last moved to under manual control,
/// as its set-points really produce them: what a test frame from here
/// shows.
#[derive(Debug, Clone, PartialEq)]
pub struct LastPose {
    /// The light direction, sample frame.
    pub light: Direction,
    /// The view direction of `camera`, sample frame.
    pub view: Direction,
    /// The camera the pair is seen by.
    pub camera: String,
    /// The set-points commanded: another camera's view is found from them.
    setpoints: Setpoints,
}

/// A connected rig under manual control.
pub struct ManualRig {
    rig: Rig,
    profile: Profile,
    solver: Arc<Solver>,
    clock: Clock,
    estop: EStop,
    /// Axes and arms homed (or referenced) under manual control: only
    /// these move, since a controller's position means nothing before.
    homed: BTreeSet<String>,
    /// The last pose taken; None before one, and once anything has moved
    /// otherwise (a jog or a homing), since the view is then unknown.
    last_pose: Option<LastPose>,
}

impl ManualRig {
    /// Takes a connected rig; nothing is moved.
    pub fn new(rig: Rig, profile: Profile, solver: Arc<Solver>, clock: Clock) -> ManualRig {
        let estop = EStop::new(rig.stops.clone(), clock.clone());
        ManualRig {
            rig,
            profile,
            solver,
            clock,
            estop,
            homed: BTreeSet::new(),
            last_pose: None,
        }
    }

    /// The (light, view) pair of the last pose, while the rig still
    /// stands there; None before a pose, and after a jog or a homing.
    pub fn last_pose(&self) -> Option<&LastPose> {
        self.last_pose.as_ref()
    }

    /// The view `camera` has of the sample at the last pose: the pose's
    /// own view for the camera that sees the pair, forward kinematics for
    /// another. None before a pose (and after a jog or a homing).
    pub fn posed_view(&self, camera: &str) -> Result<Option<Direction>, ManualError> {
        let Some(pose) = &self.last_pose else {
            return Ok(None);
        };
        if pose.camera == camera {
            return Ok(Some(pose.view));
        }
        let (_, view) = self
            .solver
            .forward(&pose.setpoints, camera)
            .map_err(|e| {
                ManualError::BadInput(format!(
                    "camera `{camera}` at the last pose: {e}; take the frame with `{}`, which sees the pair",
                    pose.camera
                ))
            })?;
        Ok(Some(view))
    }

    /// Refuses to move a device not homed under manual control. An
    /// emergency stop resets the controllers: everything must home again.
    fn need_homed(&mut self, device: &str) -> Result<(), ManualError> {
        if self.estop.is_tripped() {
            self.homed.clear();
            self.estop.rearm();
        }
        if self.homed.contains(device) {
            Ok(())
        } else {
            Err(ManualError::BadInput(format!(
                "home `{device}` first: its position means nothing until it is homed (or, without homing, referenced at its 0° mark); nothing moved"
            )))
        }
    }

    /// The emergency stop of every device of this rig; it acts at once,
    /// also while an action is in flight.
    pub fn estop(&self) -> EStop {
        self.estop.clone()
    }

    fn kind_of(&self, device: &str) -> Result<DeviceKind, ManualError> {
        self.profile
            .devices
            .get(device)
            .map(|d| d.kind())
            .ok_or_else(|| {
                let names: Vec<&str> = self.profile.devices.keys().map(String::as_str).collect();
                ManualError::BadInput(format!(
                    "no device `{}` in profile {} (devices: {})",
                    device.chars().take(64).collect::<String>(),
                    self.profile.name,
                    names.join(", ")
                ))
            })
    }

    fn wrong_kind(device: &str, kind: DeviceKind, wanted: &str) -> ManualError {
        ManualError::BadInput(format!(
            "`{device}` is {}, not {wanted}",
            kind.with_article()
        ))
    }

    /// Homes an axis or the arm (an axis without homing takes its
    /// operator-set zero), under the run's homing deadline. Returns where
    /// it reports it stands: one value for an axis, the joints for an arm.
    pub async fn home(&mut self, device: &str) -> Result<Vec<f64>, ManualError> {
        let clock = self.clock.clone();
        match self.kind_of(device)? {
            DeviceKind::Axis => {
                let axis = self
                    .rig
                    .axes
                    .get_mut(device)
                    .ok_or_else(|| not_connected(device))?;
                // Until it answers, its position is unknown again, and so
                // is the view.
                self.homed.remove(device);
                self.last_pose = None;
                let at = deadline(&clock, device, HOMING_DEADLINE_S, axis.home()).await?;
                self.homed.insert(device.to_string());
                Ok(vec![at])
            }
            DeviceKind::Arm => {
                let arm = self
                    .rig
                    .arms
                    .get_mut(device)
                    .ok_or_else(|| not_connected(device))?;
                self.homed.remove(device);
                self.last_pose = None;
                let at = deadline(&clock, device, HOMING_DEADLINE_S, arm.home()).await?;
                self.homed.insert(device.to_string());
                Ok(at)
            }
            k => Err(Self::wrong_kind(device, k, "an axis or an arm")),
        }
    }

    /// Jogs an axis; a target beyond the profile's soft limits is refused
    /// before anything is sent. Returns the position the axis reports.
    pub async fn jog(&mut self, device: &str, jog: Jog) -> Result<f64, ManualError> {
        let kind = self.kind_of(device)?;
        let Some(axis) = self.profile.devices[device].as_axis() else {
            return Err(Self::wrong_kind(device, kind, "an axis"));
        };
        let limits = axis.limits;
        let motion = rigd_core::Trapezoid::from(axis.motion);
        let step = match jog {
            Jog::By(d) | Jog::To(d) => d,
        };
        if !step.is_finite() {
            return Err(ManualError::BadInput(format!(
                "jog of `{device}`: expected a finite number of degrees, got {step}"
            )));
        }
        self.need_homed(device)?;
        let clock = self.clock.clone();
        let axis = self
            .rig
            .axes
            .get_mut(device)
            .ok_or_else(|| not_connected(device))?;
        let from = deadline(&clock, device, DEADLINE_SLACK_S, axis.position()).await?;
        let target = match jog {
            Jog::By(d) => from + d,
            Jog::To(x) => x,
        };
        if !limits.contains(target) {
            return Err(ManualError::BadInput(format!(
                "jog of `{device}` to {target:.3}° is beyond its soft limits [{}, {}]; nothing moved",
                limits.min, limits.max
            )));
        }
        let budget = motion.move_time(target - from) * 2.0 + DEADLINE_SLACK_S;
        // The rig leaves the pose (a refused jog above moved nothing).
        self.last_pose = None;
        Ok(deadline(&clock, device, budget, axis.move_to(target)).await?)
    }

    /// Moves the axes and the arm to the pose of a (light, view) pair,
    /// all at once, under the run's motion deadline. The lamp is not
    /// switched.
    pub async fn pose(
        &mut self,
        light: Direction,
        view: Direction,
    ) -> Result<PoseReached, ManualError> {
        for (what, d) in [("light", light), ("view", view)] {
            if !(d.theta_deg.is_finite()
                && d.phi_deg.is_finite()
                && (0.0..=90.0).contains(&d.theta_deg))
            {
                return Err(ManualError::BadInput(format!(
                    "{what}: expected θ in 0..=90 and a finite φ, got θ {} φ {}",
                    d.theta_deg, d.phi_deg
                )));
            }
        }
        let pose = self.solver.solve(light, view);
        let to = &pose.setpoints;
        let mut movers: Vec<String> = to.axes.keys().cloned().collect();
        if to.arm.is_some() {
            movers.extend(self.rig.arms.keys().cloned());
        }
        for name in &movers {
            self.need_homed(name)?;
        }
        let clock = self.clock.clone();
        // Where the movers stand now; the lamp and the plate as the pose
        // wants them, so `goto` only moves.
        let mut from = Setpoints {
            axes: BTreeMap::new(),
            arm: None,
            lamp: to.lamp.clone(),
            plate_mm: to.plate_mm,
        };
        for (name, axis) in self.rig.axes.iter_mut() {
            if to.axes.contains_key(name) {
                let at = deadline(&clock, name, DEADLINE_SLACK_S, axis.position()).await?;
                from.axes.insert(name.clone(), at);
            }
        }
        if to.arm.is_some() {
            if let Some((name, arm)) = self.rig.arms.iter_mut().next() {
                from.arm = Some(deadline(&clock, name, DEADLINE_SLACK_S, arm.joints()).await?);
            }
        }
        // Known again only once every mover has arrived.
        self.last_pose = None;
        // The same moves, in parallel and under the same deadline, as a
        // run's step.
        let timing = Timing::new(&self.profile, None);
        let rig = &mut self.rig;
        let movers = Movers {
            axes: &mut rig.axes,
            arms: &mut rig.arms,
            fixture: &mut rig.fixture,
            plate_known: true,
        };
        let mut lights = Lights {
            lamps: &mut rig.lamps,
            lasers: &mut rig.lasers,
        };
        let reached = goto(&clock, &timing, movers, &mut lights, &from, None, to)
            .await
            .map_err(|f| f.error)?;
        self.last_pose = Some(LastPose {
            light: pose.achieved_light,
            view: pose.achieved_view,
            camera: pose.camera.clone(),
            setpoints: to.clone(),
        });
        Ok(PoseReached {
            axes: reached
                .axes
                .into_iter()
                .filter(|(name, _)| to.axes.contains_key(name))
                .collect(),
            arm: reached.arm,
            lamp: to.lamp.clone(),
            camera: pose.camera.clone(),
            feasible: pose.feasible,
            reason: pose.reason.clone(),
        })
    }

    /// Switches a lamp or the laser, confirmed by the coil's read-back.
    pub async fn switch(&mut self, device: &str, on: bool) -> Result<(), ManualError> {
        let clock = self.clock.clone();
        let switch_s = self.profile.devices.get(device).and_then(|d| d.switch_s());
        let budget = switch_s.unwrap_or(0.0) + DEADLINE_SLACK_S;
        match self.kind_of(device)? {
            DeviceKind::Lamp => {
                let lamp = self
                    .rig
                    .lamps
                    .get_mut(device)
                    .ok_or_else(|| not_connected(device))?;
                Ok(deadline(&clock, device, budget, lamp.set(on)).await?)
            }
            DeviceKind::Laser => {
                let laser = self
                    .rig
                    .lasers
                    .get_mut(device)
                    .ok_or_else(|| not_connected(device))?;
                Ok(deadline(&clock, device, budget, laser.set(on)).await?)
            }
            k => Err(Self::wrong_kind(device, k, "a lamp or a laser")),
        }
    }

    /// Takes one frame with a camera (the profile's first if None) at
    /// `exposure_s` (the profile's if None), under the run's exposure and
    /// transfer deadlines; the frame is checked like a run's.
    pub async fn test_frame(
        &mut self,
        camera: Option<&str>,
        exposure_s: Option<f64>,
    ) -> Result<(String, Frame), ManualError> {
        let name = match camera {
            Some(c) => c.to_string(),
            None => self
                .profile
                .camera_names()
                .into_iter()
                .next()
                .ok_or_else(|| ManualError::BadInput("this rig has no camera".into()))?,
        };
        let kind = self.kind_of(&name)?;
        if kind != DeviceKind::Camera {
            return Err(Self::wrong_kind(&name, kind, "a camera"));
        }
        if let Some(e) = exposure_s {
            self.profile
                .check_camera_exposure(&name, e)
                .map_err(ManualError::BadInput)?;
        }
        let exposure = exposure_s.or_else(|| {
            self.profile
                .devices
                .get(&name)
                .and_then(Device::as_camera)
                .map(|c| c.timing.exposure_s)
        });
        let timing = Timing::new(&self.profile, exposure_s);
        let expose_budget = timing.expose_s(&[name.as_str()]) + DEADLINE_SLACK_S;
        let transfer_budget = timing.transfer_s(&[name.as_str()]) * 2.0 + DEADLINE_SLACK_S;
        let clock = self.clock.clone();
        let cam = self
            .rig
            .cameras
            .get_mut(&name)
            .ok_or_else(|| not_connected(&name))?;
        if let Some(e) = exposure {
            deadline(&clock, &name, DEADLINE_SLACK_S, cam.set_exposure(e)).await?;
        }
        deadline(&clock, &name, expose_budget, cam.expose()).await?;
        let frame = deadline(&clock, &name, transfer_budget, cam.transfer()).await?;
        frame.validate(&name)?;
        Ok((name, frame))
    }
}

fn not_connected(device: &str) -> ManualError {
    ManualError::Device(DeviceError::new(
        device,
        crate::rig::hal::ErrorKind::NotReady,
        "not connected",
    ))
}
