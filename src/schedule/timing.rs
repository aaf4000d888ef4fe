//! The one model of physical capture time: per trigger, every axis, the
//! arm and the lamp change run in parallel and overlap the previous
//! trigger's transfer; exposure plus readout stand alone; the first lamp's
//! warm-up comes before anything moves. `rigd plan show` estimates with it,
//! the trigger order minimises it, and the engine's pipeline follows it.

use crate::kinematics::Setpoints;
use crate::model::exposure::ExposurePolicy;
use crate::model::profile::{DeviceKind, Profile};
use crate::schedule::Schedule;

pub use crate::model::profile::{check_exposure_s, MAX_EXPOSURE_S};

/// [`check_exposure_s`] of a command-line value.
pub fn parse_exposure_s(text: &str) -> Result<f64, String> {
    let exposure_s: f64 = text
        .trim()
        .parse()
        .map_err(|_| format!("{text}: expected a number of seconds"))?;
    check_exposure_s(exposure_s)
}

/// What the estimate allows an operator to place or remove the laser
/// calibration plate (an estimate: the engine waits for the operator; the
/// simulated operator takes exactly this).
pub const PLATE_CHANGE_S: f64 = 30.0;

/// The timing model shared by the estimate and the engine's pipeline.
#[derive(Debug, Clone)]
pub struct Timing<'a> {
    profile: &'a Profile,
    exposure_override_s: Option<f64>,
    /// A `brackets` run's series: every step takes these exposures at its
    /// pose, each transferred before the next.
    brackets_s: Option<Vec<f64>>,
}

impl<'a> Timing<'a> {
    /// The model of `profile`, with every camera's exposure replaced by
    /// `exposure_override_s` (seconds) when given (`--exposure`).
    pub fn new(profile: &'a Profile, exposure_override_s: Option<f64>) -> Timing<'a> {
        Timing {
            profile,
            exposure_override_s,
            brackets_s: None,
        }
    }

    /// The model of a run under `policy`: a `brackets` run's steps take
    /// their whole series, each exposure read out and transferred before
    /// the next. An `auto` run is estimated as if nothing clipped (a lower
    /// bound): what it retakes depends on the sample.
    pub fn with_exposure_policy(mut self, policy: &ExposurePolicy) -> Timing<'a> {
        self.brackets_s = match policy {
            ExposurePolicy::Brackets { exposures_s } => Some(exposures_s.clone()),
            _ => None,
        };
        self
    }

    /// Set-points right after homing: every axis and joint at its home.
    pub fn home_setpoints(&self) -> Setpoints {
        let mut s = Setpoints {
            axes: Default::default(),
            arm: None,
            lamp: String::new(),
            plate_mm: None,
        };
        for (name, d) in &self.profile.devices {
            match d.kind {
                DeviceKind::Axis => {
                    s.axes.insert(name.clone(), d.home_deg.unwrap_or(0.0));
                }
                DeviceKind::Arm => {
                    s.arm = Some(d.joints.iter().flatten().map(|j| j.home_deg).collect());
                }
                _ => {}
            }
        }
        s
    }

    /// Time for all axes and joints to reach `to` from `from`, in parallel.
    pub fn motion_s(&self, from: &Setpoints, to: &Setpoints) -> f64 {
        let mut t: f64 = 0.0;
        for (name, &target) in &to.axes {
            let start = from.axes.get(name).copied().unwrap_or(target);
            if let Some(d) = self.profile.devices.get(name) {
                t = t.max(
                    rigd_core::Trapezoid::from(d.motion_or_default()).move_time(target - start),
                );
            }
        }
        if let (Some(a), Some(b)) = (&from.arm, &to.arm) {
            if let Some(arm) = self
                .profile
                .devices
                .values()
                .find(|d| d.kind == DeviceKind::Arm)
            {
                for ((j, qa), qb) in arm.joints.iter().flatten().zip(a).zip(b) {
                    t = t.max(rigd_core::Trapezoid::from(j.motion).move_time(qb - qa));
                }
            }
        }
        t
    }

    /// Switching from lamp `from` to lamp `to` (either may be none): relay
    /// off, relay on, then warm-up.
    pub fn lamp_change_s(&self, from: &str, to: &str) -> f64 {
        if from == to {
            return 0.0;
        }
        let dev = |n: &str| self.profile.devices.get(n);
        let off = dev(from).and_then(|d| d.switch_s).unwrap_or(0.0);
        let on = dev(to)
            .map(|d| d.switch_s.unwrap_or(0.0) + d.warm_up_s.unwrap_or(0.0))
            .unwrap_or(0.0);
        off + on
    }

    /// The exposure of `camera`, seconds: the override if any, else the
    /// profile's `timing.exposure_s` (0 for a device without timing).
    pub fn exposure_s(&self, camera: &str) -> f64 {
        let nominal = self
            .profile
            .devices
            .get(camera)
            .and_then(|d| d.timing)
            .map_or(0.0, |t| t.exposure_s);
        self.exposure_override_s.unwrap_or(nominal)
    }

    /// Preparing a run (or a resume) whose first trigger needs lamp
    /// `first_lamp`: homing every arm and axis together, then every lamp
    /// and laser switched off in turn (a known state after a crash), then
    /// the first lamp switched on and warmed up (the engine's `prepare`).
    pub fn prepare_s(&self, first_lamp: &str) -> f64 {
        let devices = self.profile.devices.values();
        let homing = devices
            .clone()
            .map(|d| d.homing_time_s())
            .fold(0.0, f64::max);
        let lights_off: f64 = devices
            .filter(|d| matches!(d.kind, DeviceKind::Lamp | DeviceKind::Laser))
            .map(|d| d.switch_s.unwrap_or(0.0))
            .sum();
        homing + lights_off + self.lamp_change_s("", first_lamp)
    }

    /// Exposure plus readout of the slowest camera of a trigger.
    pub fn expose_s(&self, cameras: &[&str]) -> f64 {
        cameras
            .iter()
            .map(|c| self.exposure_s(c) + self.readout_s(c))
            .fold(0.0, f64::max)
    }

    fn readout_s(&self, camera: &str) -> f64 {
        self.profile
            .devices
            .get(camera)
            .and_then(|d| d.timing)
            .map_or(0.0, |t| t.readout_s)
    }

    /// A bracketed step's exposures at its pose: each exposure of the
    /// series read out and transferred (by the slowest camera) before the
    /// next is taken.
    fn bracket_series_s(&self, series: &[f64], cameras: &[&str]) -> f64 {
        let readout = cameras
            .iter()
            .map(|c| self.readout_s(c))
            .fold(0.0, f64::max);
        let transfer = self.transfer_s(cameras);
        series.iter().map(|t| t + readout + transfer).sum()
    }

    /// Transfer time of the slowest camera of a trigger.
    pub fn transfer_s(&self, cameras: &[&str]) -> f64 {
        cameras
            .iter()
            .filter_map(|c| self.profile.devices.get(*c).and_then(|d| d.timing))
            .map(|t| t.transfer_s)
            .fold(0.0, f64::max)
    }

    /// Physical time of a schedule, leaving out the triggers `skip` names:
    /// first the first lamp's warm-up; then per trigger, motion and lamp
    /// changes run in parallel and overlap the previous transfer, while
    /// exposure and readout stand alone; last the final transfer.
    pub fn estimate_s(&self, schedule: &Schedule, skip: impl Fn(usize) -> bool) -> f64 {
        let mut pos = self.home_setpoints();
        let mut pending_transfer = 0.0;
        let mut remaining = schedule
            .triggers
            .iter()
            .filter(|t| !skip(t.index))
            .peekable();
        // Preparing: homing, then the first lamp switched on and warmed up,
        // before anything moves.
        let mut total = match remaining.peek() {
            Some(first) => {
                pos.lamp = first.setpoints.lamp.clone();
                self.prepare_s(&pos.lamp)
            }
            None => 0.0,
        };
        let mut sweep = None;
        for trig in remaining {
            let cams: Vec<&str> = trig
                .images
                .iter()
                .map(|&i| schedule.images[i].camera.as_str())
                .collect();
            if let (Some(s), Some(laser)) = (trig.sweep, &schedule.laser) {
                if sweep == Some(s) {
                    // Inside a sweep the axis runs on and frames follow at video rate.
                    total += 1.0 / laser.plan.frame_hz;
                    pos = trig.setpoints.clone();
                    continue;
                }
            }
            sweep = trig.sweep;
            if trig.setpoints.plate_mm != pos.plate_mm {
                total += PLATE_CHANGE_S;
            }
            let prep = self
                .motion_s(&pos, &trig.setpoints)
                .max(self.lamp_change_s(&pos.lamp, &trig.setpoints.lamp));
            match (&self.brackets_s, trig.sweep) {
                (Some(series), None) => {
                    total += prep.max(pending_transfer) + self.bracket_series_s(series, &cams);
                    pending_transfer = 0.0;
                }
                _ => {
                    total += prep.max(pending_transfer) + self.expose_s(&cams);
                    pending_transfer = self.transfer_s(&cams);
                }
            }
            pos = trig.setpoints.clone();
        }
        total + pending_transfer
    }
}
