//! The one model of physical capture time: per trigger, every axis, the
//! arm and the lamp change run in parallel and overlap the previous
//! trigger's transfer; exposure plus readout stand alone; the first lamp's
//! warm-up comes before anything moves. `rigd plan show` estimates with it,
//! the trigger order minimises it, and the engine's pipeline follows it.

use crate::kinematics::Setpoints;
use crate::model::exposure::{AutoExposure, ExposurePolicy};
use crate::model::profile::{Device, DeviceKind, Profile};
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
    /// An `auto` run's settings: what a held step's further exposures take.
    auto: Option<AutoExposure>,
}

impl<'a> Timing<'a> {
    /// The model of `profile`, with every camera's exposure replaced by
    /// `exposure_override_s` (seconds) when given (`--exposure`).
    pub fn new(profile: &'a Profile, exposure_override_s: Option<f64>) -> Timing<'a> {
        Timing {
            profile,
            exposure_override_s,
            brackets_s: None,
            auto: None,
        }
    }

    /// The model of a run under `policy`: a `brackets` run's steps take
    /// their whole series, each exposure read out and transferred before
    /// the next. What an `auto` run retakes depends on the sample:
    /// [`Timing::estimate_s`] counts it as if nothing clipped (a lower
    /// bound), [`Timing::estimate_with_retakes_s`] with what clipped.
    pub fn with_exposure_policy(mut self, policy: &ExposurePolicy) -> Timing<'a> {
        self.brackets_s = match policy {
            ExposurePolicy::Brackets { exposures_s } => Some(exposures_s.clone()),
            _ => None,
        };
        self.auto = policy.auto();
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
            match d {
                Device::Axis(axis) => {
                    s.axes.insert(name.clone(), axis.home_deg.unwrap_or(0.0));
                }
                Device::Arm(arm) => {
                    s.arm = Some(arm.joints.iter().map(|j| j.home_deg).collect());
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
            if let Some(axis) = self.profile.devices.get(name).and_then(Device::as_axis) {
                t = t.max(rigd_core::Trapezoid::from(axis.motion).move_time(target - start));
            }
        }
        if let (Some(a), Some(b)) = (&from.arm, &to.arm) {
            if let Some(arm) = self.profile.devices.values().find_map(Device::as_arm) {
                for ((j, qa), qb) in arm.joints.iter().zip(a).zip(b) {
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
        let off = dev(from).and_then(|d| d.switch_s()).unwrap_or(0.0);
        let on = dev(to)
            .map(|d| d.switch_s().unwrap_or(0.0) + d.as_lamp().map_or(0.0, |l| l.warm_up_s))
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
            .and_then(|d| d.timing())
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
            .filter(|d| matches!(d.kind(), DeviceKind::Lamp | DeviceKind::Laser))
            .map(|d| d.switch_s().unwrap_or(0.0))
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
            .and_then(|d| d.timing())
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
            .filter_map(|c| self.profile.devices.get(*c).and_then(|d| d.timing()))
            .map(|t| t.transfer_s)
            .fold(0.0, f64::max)
    }

    /// Physical time of a schedule, leaving out the triggers `skip` names:
    /// first the first lamp's warm-up; then per trigger, motion and lamp
    /// changes run in parallel and overlap the previous transfer, while
    /// exposure and readout stand alone; last the final transfer. An `auto`
    /// run counts as if nothing clipped (a lower bound).
    pub fn estimate_s(&self, schedule: &Schedule, skip: impl Fn(usize) -> bool) -> f64 {
        self.estimate_with_retakes_s(schedule, skip, |_| 0)
    }

    /// [`Timing::estimate_s`] of an `auto` run whose trigger `t` takes
    /// `retakes(t)` further exposures (0 where its first did not clip), as
    /// the engine takes them: the clipping is seen once the frame is
    /// transferred, while the rig moves on; so the rig exposes the next
    /// trigger, comes back, and takes the further exposures at the held
    /// one's pose, each read out and transferred before the next.
    pub fn estimate_with_retakes_s(
        &self,
        schedule: &Schedule,
        skip: impl Fn(usize) -> bool,
        retakes: impl Fn(usize) -> u32,
    ) -> f64 {
        let mut pos = self.home_setpoints();
        let mut queue: std::collections::VecDeque<usize> = schedule
            .triggers
            .iter()
            .filter(|t| !skip(t.index))
            .map(|t| t.index)
            .collect();
        // Preparing: homing, then the first lamp switched on and warmed up,
        // before anything moves.
        let mut total = match queue.front() {
            Some(&first) => {
                pos.lamp = schedule.triggers[first].setpoints.lamp.clone();
                self.prepare_s(&pos.lamp)
            }
            None => 0.0,
        };
        let cameras = |t: usize| -> Vec<&str> {
            schedule.triggers[t]
                .images
                .iter()
                .map(|&i| schedule.images[i].camera.as_str())
                .collect()
        };
        let auto = self.auto.filter(|_| self.brackets_s.is_none());
        // A laser sweep's frames take one exposure each.
        let retaken =
            |t: usize| auto.is_some() && schedule.triggers[t].sweep.is_none() && retakes(t) > 0;
        // The trigger whose frames are still being transferred (with its
        // transfer time), and the triggers waiting to be taken again at
        // their pose.
        let mut pending: Option<(usize, f64)> = None;
        let mut held: Vec<usize> = Vec::new();
        let mut sweep = None;
        loop {
            let next = queue.front().copied();
            let transfer = pending.map_or(0.0, |(_, t)| t);
            let Some(i) = next else {
                total += transfer;
                match pending.take() {
                    Some((p, _)) if retaken(p) => {
                        held.push(p);
                        queue.push_back(p);
                        continue;
                    }
                    _ => break,
                }
            };
            let trig = &schedule.triggers[i];
            let cams = cameras(i);
            if let (Some(s), Some(laser)) = (trig.sweep, &schedule.laser) {
                if sweep == Some(s) {
                    // Inside a sweep the axis runs on and frames follow at video rate.
                    total += 1.0 / laser.plan.frame_hz;
                    pos = trig.setpoints.clone();
                    queue.pop_front();
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
            // Added with the step's own exposures in one sum, as the
            // trigger order's tour adds them, so both agree to the bit.
            let wait = prep.max(transfer);
            pos = trig.setpoints.clone();
            if let Some((p, _)) = pending.take() {
                if retaken(p) && !queue.contains(&p) {
                    held.push(p);
                    queue.insert(1.min(queue.len()), p);
                }
            }
            queue.pop_front();
            if let Some(at) = held.iter().position(|&h| h == i) {
                held.swap_remove(at);
                let transfer = self.transfer_s(&cams);
                let further: f64 = auto.map_or(0.0, |a| {
                    (1..=retakes(i).min(a.max_extra))
                        .map(|k| {
                            let expose = cams
                                .iter()
                                .map(|c| {
                                    a.extra_exposure_s(self.exposure_s(c), k) + self.readout_s(c)
                                })
                                .fold(0.0, f64::max);
                            expose + transfer
                        })
                        .sum()
                });
                total += wait + further;
                continue;
            }
            match (&self.brackets_s, trig.sweep) {
                (Some(series), None) => total += wait + self.bracket_series_s(series, &cams),
                _ => {
                    total += wait + self.expose_s(&cams);
                    pending = Some((i, self.transfer_s(&cams)));
                }
            }
        }
        total
    }
}
