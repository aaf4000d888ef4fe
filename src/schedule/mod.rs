//! From a plan to the ordered triggers the engine executes: every pair
//! solved into set-points, images that one trigger captures together
//! grouped, and the physical capture time estimated with the same timing
//! model the engine follows.

pub mod laser;
pub mod order;
pub mod timing;
pub mod volume;

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use crate::kinematics::{Setpoints, Solver};
use crate::model::profile::{Profile, RigGeometry};
use crate::plan::laser::LaserRig;
use crate::plan::{Plan, RigOffer};
use crate::schedule::laser::{LaserRun, LaserStep};
use crate::schedule::timing::Timing;
use rigd_core::geometry::Direction;

/// One image of the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageStep {
    /// The image's number in capture order, from 0; frames are named by it.
    pub index: usize,
    /// Images taken by one trigger share this index.
    pub trigger: usize,
    /// The camera that takes the image.
    pub camera: String,
    /// Commanded directions, in the sample frame.
    pub light: Direction,
    /// Commanded view direction, in the sample frame.
    pub view: Direction,
    /// What the set-points really produce.
    pub achieved_light: Direction,
    /// The view direction the set-points really produce.
    pub achieved_view: Direction,
    /// Whether the rig reaches the commanded pair; an infeasible image is
    /// still taken, at the substitute.
    pub feasible: bool,
    /// When infeasible: why, and what was substituted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Laser plans: the source and tilt of this frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<LaserStep>,
}

/// One trigger: set-points, then all its cameras expose together.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Trigger {
    /// The trigger's number in capture order, from 0.
    pub index: usize,
    /// Where the axes, arm and lamps go before the cameras expose.
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
    /// The plan's name.
    pub plan: String,
    /// The profile's name.
    pub profile: String,
    /// Every image, in capture order (`images[i].index == i`).
    pub images: Vec<ImageStep>,
    /// Every trigger, in capture order.
    pub triggers: Vec<Trigger>,
    /// Laser plans: what the engine needs for the sweeps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub laser: Option<LaserRun>,
}

/// One image of a schedule with its trigger's set-points: the one shape
/// in which `rigd plan show --json` and `GET /api/v1/plans/{name}` list a
/// plan's steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PlanStep<'a> {
    /// The image.
    #[serde(flatten)]
    pub image: &'a ImageStep,
    /// Axes, arm joints and lamp of the image's trigger.
    pub setpoints: &'a Setpoints,
}

impl Schedule {
    /// Every image in capture order, with its trigger's set-points.
    pub fn steps(&self) -> impl Iterator<Item = PlanStep<'_>> {
        self.images.iter().map(|image| PlanStep {
            image,
            setpoints: &self.triggers[image.trigger].setpoints,
        })
    }
}

/// What the rig offers plans: arcs for the grid, fixed lamps for photometric stereo.
pub fn rig_offer(profile: &Profile, solver: &Solver) -> RigOffer {
    let fixed_lamps = match &profile.rig {
        RigGeometry::FixedLamps { camera, lamps, .. } => {
            let dir = |n: &String| profile.devices.get(n).and_then(|d| d.direction());
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
    crate::schedule::order::apply(profile, &mut schedule, &timing, plan.order, false);
    schedule
}

/// [`build`], and what the order gained: naive, optimised and lower-bound
/// physical times (under the profile's exposures).
pub fn build_with_report(
    profile: &Profile,
    solver: &Solver,
    plan: &Plan,
) -> (Schedule, crate::schedule::order::OrderReport) {
    let mut schedule = build_in_plan_order(profile, solver, plan);
    let timing = Timing::new(profile, None);
    let report = crate::schedule::order::apply(profile, &mut schedule, &timing, plan.order, true);
    (schedule, report)
}

/// Solves every pair in the plan's own order.
fn build_in_plan_order(profile: &Profile, solver: &Solver, plan: &Plan) -> Schedule {
    if let (Some(lp), Some(rig)) = (&plan.laser, LaserRig::of(profile)) {
        return crate::schedule::laser::schedule(&rig, &plan.name, &profile.name, lp);
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
    /// The images the rig cannot take as commanded, in capture order.
    pub fn infeasible(&self) -> impl Iterator<Item = &ImageStep> {
        self.images.iter().filter(|i| !i.feasible)
    }
}
