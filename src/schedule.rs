//! From a plan to the ordered triggers the engine executes: every pair
//! solved into set-points, images that one trigger captures together
//! grouped, and the physical capture time estimated with the same timing
//! model the engine follows.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use crate::geometry::Direction;
use crate::kinematics::{Setpoints, Solver};
use crate::laser::{LaserRig, LaserRun, LaserStep};
use crate::plan::{Plan, RigOffer};
use crate::profile::{DeviceKind, Profile, RigGeometry};

/// One image of the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageStep {
    pub index: usize,
    /// Images taken by one trigger share this index.
    pub trigger: usize,
    pub camera: String,
    /// Commanded directions, in the sample frame.
    pub light: Direction,
    pub view: Direction,
    /// What the set-points really produce.
    pub achieved_light: Direction,
    pub achieved_view: Direction,
    pub feasible: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Laser plans: the source and tilt of this frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<LaserStep>,
}

/// One trigger: set-points, then all its cameras expose together.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Trigger {
    pub index: usize,
    pub setpoints: Setpoints,
    /// Indices into [`Schedule::images`].
    pub images: Vec<usize>,
    /// Triggers of one laser sweep share this index: the engine runs them
    /// as one continuous move while the cameras record at video rate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sweep: Option<usize>,
}

/// A plan solved for a rig, in capture order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    pub plan: String,
    pub profile: String,
    pub images: Vec<ImageStep>,
    pub triggers: Vec<Trigger>,
    /// Laser plans: what the engine needs for the sweeps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<LaserRun>,
}

/// What the rig offers plans: arcs for the grid, fixed lamps for photometric stereo.
pub fn rig_offer(profile: &Profile, solver: &Solver) -> RigOffer {
    let fixed_lamps = match &profile.rig {
        RigGeometry::FixedLamps { camera, lamps, .. } => {
            let dir = |n: &String| profile.devices.get(n).and_then(|d| d.direction);
            let lamp_dirs: Option<Vec<Direction>> = lamps.iter().map(dir).collect();
            lamp_dirs.zip(dir(camera))
        }
        _ => None,
    };
    RigOffer {
        profile: profile.name.clone(),
        arc_elevations: solver.arc_elevations(),
        fixed_lamps,
        laser: LaserRig::of(profile),
    }
}

/// Bit-exact identity of a set-point, for grouping images into triggers.
fn setpoint_key(s: &Setpoints) -> String {
    let mut key = String::new();
    for (name, v) in &s.axes {
        key.push_str(&format!("{name}={:x};", v.to_bits()));
    }
    if let Some(arm) = &s.arm {
        for v in arm {
            key.push_str(&format!("{:x},", v.to_bits()));
        }
    }
    key.push('|');
    key.push_str(&s.lamp);
    if let Some(p) = s.plate_mm {
        key.push_str(&format!("|plate={:x}", p.to_bits()));
    }
    key
}

/// Solves every pair, groups the images of each trigger, and orders the
/// triggers as the plan asks (`ordering`).
pub fn build(profile: &Profile, solver: &Solver, plan: &Plan) -> Schedule {
    let mut schedule = build_in_plan_order(profile, solver, plan);
    let timing = Timing::new(profile, None);
    crate::ordering::apply(profile, &mut schedule, &timing, plan.order, false);
    schedule
}

/// [`build`], and what the order gained: naive, optimised and lower-bound
/// physical times (under the profile's exposures).
pub fn build_with_report(
    profile: &Profile,
    solver: &Solver,
    plan: &Plan,
) -> (Schedule, crate::ordering::OrderReport) {
    let mut schedule = build_in_plan_order(profile, solver, plan);
    let timing = Timing::new(profile, None);
    let report = crate::ordering::apply(profile, &mut schedule, &timing, plan.order, true);
    (schedule, report)
}

/// Solves every pair in the plan's own order.
fn build_in_plan_order(profile: &Profile, solver: &Solver, plan: &Plan) -> Schedule {
    if let (Some(lp), Some(rig)) = (&plan.laser, LaserRig::of(profile)) {
        return crate::laser::schedule(&rig, &plan.name, &profile.name, lp);
    }
    let mut images = Vec::with_capacity(plan.pairs.len());
    let mut triggers: Vec<Trigger> = Vec::new();
    let mut open: HashMap<String, usize> = HashMap::new();
    for pair in &plan.pairs {
        let pose = solver.solve(pair.light, pair.view);
        let key = setpoint_key(&pose.setpoints);
        let existing = open.get(&key).copied().filter(|&t| {
            // One camera takes one image per trigger.
            !triggers[t].images.iter().any(|&i| {
                let img: &ImageStep = &images[i];
                img.camera == pose.camera
            })
        });
        let t = match existing {
            Some(t) => t,
            None => {
                triggers.push(Trigger {
                    index: triggers.len(),
                    setpoints: pose.setpoints.clone(),
                    images: Vec::new(),
                    sweep: None,
                });
                open.insert(key, triggers.len() - 1);
                triggers.len() - 1
            }
        };
        triggers[t].images.push(images.len());
        images.push(ImageStep {
            index: usize::MAX,
            trigger: t,
            camera: pose.camera,
            light: pair.light,
            view: pair.view,
            achieved_light: pose.achieved_light,
            achieved_view: pose.achieved_view,
            feasible: pose.feasible,
            reason: pose.reason,
            laser: None,
        });
    }
    // Number images in capture order: trigger by trigger.
    let mut order: Vec<usize> = (0..images.len()).collect();
    order.sort_by_key(|&i| images[i].trigger);
    let mut sorted: Vec<ImageStep> = order.iter().map(|&i| images[i].clone()).collect();
    for t in triggers.iter_mut() {
        t.images.clear();
    }
    for (i, img) in sorted.iter_mut().enumerate() {
        img.index = i;
        triggers[img.trigger].images.push(i);
    }
    Schedule {
        plan: plan.name.clone(),
        profile: profile.name.clone(),
        images: sorted,
        triggers,
        laser: None,
    }
}

impl Schedule {
    pub fn infeasible(&self) -> impl Iterator<Item = &ImageStep> {
        self.images.iter().filter(|i| !i.feasible)
    }
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
}

impl<'a> Timing<'a> {
    pub fn new(profile: &'a Profile, exposure_override_s: Option<f64>) -> Timing<'a> {
        Timing {
            profile,
            exposure_override_s,
        }
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
                t = t.max(trapezoid(d.motion_or_default()).move_time(target - start));
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
                    t = t.max(trapezoid(j.motion).move_time(qb - qa));
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

    pub fn exposure_s(&self, camera: &str) -> f64 {
        let nominal = self
            .profile
            .devices
            .get(camera)
            .and_then(|d| d.timing)
            .map_or(0.0, |t| t.exposure_s);
        self.exposure_override_s.unwrap_or(nominal)
    }

    /// Exposure plus readout of the slowest camera of a trigger.
    pub fn expose_s(&self, cameras: &[&str]) -> f64 {
        cameras
            .iter()
            .map(|c| {
                let readout = self
                    .profile
                    .devices
                    .get(*c)
                    .and_then(|d| d.timing)
                    .map_or(0.0, |t| t.readout_s);
                self.exposure_s(c) + readout
            })
            .fold(0.0, f64::max)
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
        // Preparing: the first lamp is switched on and warmed up before anything moves.
        let mut total = match remaining.peek() {
            Some(first) => {
                pos.lamp = first.setpoints.lamp.clone();
                self.lamp_change_s("", &pos.lamp)
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
            total += prep.max(pending_transfer) + self.expose_s(&cams);
            pending_transfer = self.transfer_s(&cams);
            pos = trig.setpoints.clone();
        }
        total + pending_transfer
    }
}

fn trapezoid(m: crate::profile::Motion) -> rigd_sim::motion::Trapezoid {
    rigd_sim::motion::Trapezoid {
        max_velocity: m.max_velocity,
        acceleration: m.acceleration,
        settle_s: m.settle_s,
    }
}
