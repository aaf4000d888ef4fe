//! The laser plan's schedule (Wang et al., §3.2): calibration captures
//! with and without the plate, then the sweeps; and what each image and the
//! engine's sweeps record of the laser.

use serde::{Deserialize, Serialize};

use crate::kinematics::Setpoints;
use crate::plan::laser::{LaserGeometry, LaserPlan, LaserRig};
use crate::schedule::{ImageStep, Schedule, Trigger};
use rigd_core::geometry::Direction;

/// Why an image of a laser plan exists.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LaserRole {
    /// A strip on a plane of known height, to fix the plane's angle.
    Calibration,
    /// A frame of a sweep over the sample.
    Scan,
}

/// The laser side of an image: which source, which tilt.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LaserStep {
    /// Whether the image calibrates a plane or belongs to a sweep.
    pub role: LaserRole,
    /// Index of the source position.
    pub source: usize,
    /// The emitter's direction in the sample frame.
    pub source_direction: Direction,
    /// The sweep this frame belongs to, and its place in it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sweep: Option<usize>,
    /// The frame's place in its sweep, from 0 (0 for calibration frames).
    #[serde(default)]
    pub frame: usize,
    /// Emitter tilt, degrees: nominal in the schedule; in a frame's record,
    /// as measured around the exposure.
    pub tilt_deg: f64,
    /// Height of the plane the strip falls on (the plate, or 0), mm;
    /// calibration frames only.
    #[serde(default)]
    pub plane_mm: f64,
}

/// What the engine needs to run the sweeps of a laser schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LaserRun {
    /// The laser plan being run.
    pub plan: LaserPlan,
    /// The axis that tilts the laser line during a sweep.
    pub tilt_axis: String,
    /// The tilt axis's constant velocity during a sweep, degrees/s.
    pub velocity_deg_s: f64,
    /// Where the emitter sits: polar angle and distance from the centre.
    pub geometry: LaserGeometry,
}

/// The laser plan's schedule: the calibrations with the plate (one plate
/// placement for all sources), the same without it, then the sweeps.
pub fn schedule(rig: &LaserRig, plan_name: &str, profile: &str, plan: &LaserPlan) -> Schedule {
    let mut images = Vec::new();
    let mut triggers = Vec::new();
    let sources = plan.source_arc_deg();
    let mut add = |turn: f64,
                   arc: f64,
                   tilt: f64,
                   plate: Option<f64>,
                   step: LaserStep,
                   sweep: Option<usize>| {
        let t = triggers.len();
        let mut axes = std::collections::BTreeMap::new();
        axes.insert(rig.turntable.clone(), turn);
        axes.insert(rig.light_arc.clone(), arc);
        axes.insert(rig.tilt_axis.clone(), tilt);
        let mut members = Vec::new();
        for (camera, theta) in &rig.cameras {
            let view = crate::kinematics::tidy(*theta, -turn);
            members.push(images.len());
            images.push(ImageStep {
                index: images.len(),
                trigger: t,
                camera: camera.clone(),
                light: step.source_direction,
                view,
                achieved_light: step.source_direction,
                achieved_view: view,
                feasible: true,
                reason: None,
                laser: Some(step),
            });
        }
        triggers.push(Trigger {
            index: t,
            setpoints: Setpoints {
                axes,
                arm: None,
                lamp: rig.laser.clone(),
                plate_mm: plate,
            },
            images: members,
            sweep,
        });
    };
    for plate in [Some(plan.plate_mm), None] {
        for (k, &arc) in sources.iter().enumerate() {
            let step = LaserStep {
                role: LaserRole::Calibration,
                source: k,
                source_direction: crate::kinematics::tidy(rig.geometry.theta_deg, arc),
                sweep: None,
                frame: 0,
                tilt_deg: 0.0,
                plane_mm: plate.unwrap_or(0.0),
            };
            add(0.0, arc, 0.0, plate, step, None);
        }
    }
    let tilts = rig.sweep_tilts(plan);
    let mut sweep = 0;
    for turn in plan.turntable_deg() {
        for (k, &arc) in sources.iter().enumerate() {
            let direction = crate::kinematics::tidy(rig.geometry.theta_deg, arc - turn);
            for (j, &tilt) in tilts.iter().enumerate() {
                let step = LaserStep {
                    role: LaserRole::Scan,
                    source: k,
                    source_direction: direction,
                    sweep: Some(sweep),
                    frame: j,
                    tilt_deg: tilt,
                    plane_mm: 0.0,
                };
                add(turn, arc, tilt, None, step, Some(sweep));
            }
            sweep += 1;
        }
    }
    Schedule {
        plan: plan_name.to_string(),
        profile: profile.to_string(),
        images,
        triggers,
        laser: Some(LaserRun {
            plan: plan.clone(),
            tilt_axis: rig.tilt_axis.clone(),
            velocity_deg_s: rig.sweep_velocity(plan),
            geometry: rig.geometry,
        }),
    }
}
