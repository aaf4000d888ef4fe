//! The Bonn gonioreflectometer (Sattler et al., §3): a fixed lamp along world +x, a
//! camera on a circular rail in the world xy plane, and a robot arm whose
//! spherical wrist orients the sample at the origin.
//!
//! Model. The arm turns the sample frame into the world frame by
//! `R = Rx(roll) · Ry(pitch) · Rx(twist) · R0`, with the fixed mount rotation
//! `R0 = Ry(90°) · Rz(180°)` (rows `[0,0,1], [0,-1,0], [1,0,0]`), which takes the
//! sample normal +z to the lamp direction +x. Working through `Rᵀ·x̂ = l` gives
//! `l = (sin p cos t, −sin p sin t, cos p)`, so
//! - `pitch = θ_l` (the angle between normal and lamp),
//! - `twist = −φ_l` (this R0 rather than plain `Ry(90°)` puts twist's ±180° branch
//!   cut at φ_l = 180° instead of at φ_l = 0°, where every plan ring starts),
//! - `roll` turns about the lamp axis, so it moves the view without moving the
//!   light: it brings `R·v` into the rail plane at the rail angle
//!   `α = angle(l, v)`, camera direction `C(α) = (cos α, sin α, 0)`.
//!
//! At pitch = 0 roll and twist turn about the same axis (the wrist
//! singularity, every θ_l = 0 pose). There the whole rotation goes into twist
//! and roll = 0, which is deterministic and exact because `Ry(0)` is the identity.
//! Near the singularity the joint values come straight from the requested angles
//! and one atan2, with no division by sin θ_l, so they stay finite and round-trip.

use std::collections::BTreeMap;

use crate::model::profile::{Limits, Profile, RigGeometry};
use rigd_core::geometry::{
    angle_between, cross, mat_mul, mat_vec, norm, normalize, rot_x, rot_y, rotate_about, transpose,
    Direction, Mat3, Vec3, POLE_EPS,
};

use super::{
    axis_limits, axis_value, fit_to_limits, reason_from, sanitize, KinematicsError, PoseSolution,
    Setpoints, ANGLE_TOL_DEG,
};

/// The fixed mount rotation: sample normal +z → world +x (lamp), sample +x → world +z.
const R0: Mat3 = [[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]];

/// Below this |l × v| the plane of light and view is taken as undefined (l = v or l = −v).
const PLANE_EPS: f64 = 1e-9;

/// One arm joint: its name, soft limits and home.
#[derive(Debug, Clone)]
struct JointSpec {
    name: String,
    limits: Limits,
    home: f64,
}

/// Solver of the gonioreflectometer.
#[derive(Debug, Clone)]
pub struct GonioSolver {
    lamp: String,
    camera: String,
    rail: String,
    rail_limits: Limits,
    rail_home: f64,
    /// The arm's joints in profile order.
    joints: Vec<JointSpec>,
    /// Positions of roll, pitch and twist in `joints`.
    roll: usize,
    pitch: usize,
    twist: usize,
}

impl GonioSolver {
    /// Builds the solver; the arm must have joints named `roll`, `pitch` and `twist`.
    pub fn new(profile: &Profile) -> Result<GonioSolver, KinematicsError> {
        let RigGeometry::Gonioreflectometer {
            lamp,
            camera,
            rail,
            arm,
            ..
        } = &profile.rig
        else {
            return Err(KinematicsError::BadProfile(
                "not a gonioreflectometer profile".into(),
            ));
        };
        let (rail_limits, rail_home) = axis_limits(profile, rail)?;
        let arm_dev = profile
            .device(arm)
            .ok_or_else(|| KinematicsError::BadProfile(format!("no device `{arm}`")))?;
        let joints: Vec<JointSpec> = arm_dev
            .as_arm()
            .ok_or_else(|| KinematicsError::BadProfile(format!("`{arm}` is not an arm")))?
            .joints
            .iter()
            .map(|j| JointSpec {
                name: j.name.clone(),
                limits: j.limits,
                home: j.home_deg,
            })
            .collect();
        let find = |name: &str| {
            joints.iter().position(|j| j.name == name).ok_or_else(|| {
                KinematicsError::BadProfile(format!(
                    "arm `{arm}` needs joints named roll, pitch and twist; there is no `{name}`"
                ))
            })
        };
        let (roll, pitch, twist) = (find("roll")?, find("pitch")?, find("twist")?);
        if joints.len() != 3 {
            return Err(KinematicsError::BadProfile(format!(
                "arm `{arm}` needs exactly 3 joints, got {}",
                joints.len()
            )));
        }
        Ok(GonioSolver {
            lamp: lamp.clone(),
            camera: camera.clone(),
            rail: rail.clone(),
            rail_limits,
            rail_home,
            joints,
            roll,
            pitch,
            twist,
        })
    }

    /// See [`super::Solver::solve`].
    pub fn solve(&self, light: Direction, view: Direction) -> PoseSolution {
        let mut notes = Vec::new();
        let (l, note) = sanitize(light, "light");
        notes.extend(note);
        let (v, note) = sanitize(view, "view");
        notes.extend(note);

        let lv = l.to_vector();
        let mut vv = v.to_vector();
        let mut alpha = angle_between(lv, vv).to_degrees();
        let (min, max) = (self.rail_limits.min, self.rail_limits.max);
        let target = if alpha < min - ANGLE_TOL_DEG {
            Some((
                min,
                format!(
                    "camera would stand between lamp and sample (lamp-camera angle {alpha:.1}° < rail minimum {min}°)"
                ),
            ))
        } else if alpha > max + ANGLE_TOL_DEG {
            Some((
                max,
                format!(
                    "camera would see the lamp housing (lamp-camera angle {alpha:.1}° > rail maximum {max}°)"
                ),
            ))
        } else {
            None
        };
        if let Some((to, why)) = target {
            // Keep the light, put the view on the great circle through l and v
            // (or l's meridian when that circle is undefined) at exactly the limit.
            vv = rotate_about(lv, plane_axis(lv, vv), to.to_radians());
            alpha = to;
            let nv = Direction::from_vector(vv);
            notes.push(format!(
                "{why}; view moved to θ={:.3}°, φ={:.3}°",
                nv.theta_deg, nv.phi_deg
            ));
        }

        let pitch = l.theta_deg;
        let twist0 = -l.phi_deg;
        let n = mat_mul(
            &rot_y(pitch.to_radians()),
            &mat_mul(&rot_x(twist0.to_radians()), &R0),
        );
        let w = mat_vec(&n, vv);
        let mut roll = -w[2].atan2(w[1]).to_degrees();
        let mut twist = twist0;
        if pitch == 0.0 {
            // Wrist singularity: roll and twist share an axis; give it all to twist.
            twist += roll;
            roll = 0.0;
        }

        let (rail, rail_ok) = fit_to_limits(alpha, self.rail_limits, self.rail_home);
        if !rail_ok {
            notes.push(format!(
                "axis {} = {alpha:.3}° outside its limits [{min}, {max}]; clamped to {rail}°",
                self.rail
            ));
        }
        let mut arm = vec![0.0; self.joints.len()];
        let mut clamped_ok = rail_ok;
        for (idx, value) in [(self.roll, roll), (self.pitch, pitch), (self.twist, twist)] {
            let j = &self.joints[idx];
            let (fitted, ok) = fit_to_limits(value, j.limits, j.home);
            if !ok {
                notes.push(format!(
                    "arm joint {} = {value:.3}° outside its limits [{}, {}]; clamped to {fitted}°",
                    j.name, j.limits.min, j.limits.max
                ));
            }
            clamped_ok = clamped_ok && ok;
            arm[idx] = fitted;
        }

        let (achieved_light, achieved_view) =
            forward_raw(rail, arm[self.roll], arm[self.pitch], arm[self.twist]);
        if !clamped_ok {
            // A clamp moves light and view in ways the request does not show; say where.
            notes.push(format!(
                "achieved light θ={:.3}°, φ={:.3}°, view θ={:.3}°, φ={:.3}°",
                achieved_light.theta_deg,
                achieved_light.phi_deg,
                achieved_view.theta_deg,
                achieved_view.phi_deg
            ));
        }
        let mut axes = BTreeMap::new();
        axes.insert(self.rail.clone(), rail);
        PoseSolution {
            setpoints: Setpoints {
                axes,
                arm: Some(arm),
                lamp: self.lamp.clone(),
                plate_mm: None,
            },
            camera: self.camera.clone(),
            achieved_light,
            achieved_view,
            feasible: notes.is_empty(),
            reason: reason_from(notes),
        }
    }

    /// See [`super::Solver::forward`]: `l = Rᵀ·x̂`, `v = Rᵀ·C(α_rail)`.
    pub fn forward(
        &self,
        setpoints: &Setpoints,
        camera: &str,
    ) -> Result<(Direction, Direction), KinematicsError> {
        if camera != self.camera {
            return Err(KinematicsError::UnknownCamera(camera.to_string()));
        }
        if setpoints.lamp != self.lamp {
            return Err(KinematicsError::UnknownLamp(setpoints.lamp.clone()));
        }
        let rail = axis_value(setpoints, &self.rail)?;
        let arm = setpoints
            .arm
            .as_ref()
            .ok_or_else(|| KinematicsError::BadSetpoints("missing arm joints".into()))?;
        if arm.len() != self.joints.len() {
            return Err(KinematicsError::BadSetpoints(format!(
                "expected {} arm joints, got {}",
                self.joints.len(),
                arm.len()
            )));
        }
        if let Some((j, x)) = self.joints.iter().zip(arm).find(|(_, x)| !x.is_finite()) {
            return Err(KinematicsError::BadSetpoints(format!(
                "arm joint {} is not finite ({x})",
                j.name
            )));
        }
        Ok(forward_raw(
            rail,
            arm[self.roll],
            arm[self.pitch],
            arm[self.twist],
        ))
    }
}

/// The wrist rotation (sample frame → world) for joint values in degrees.
fn wrist(roll: f64, pitch: f64, twist: f64) -> Mat3 {
    mat_mul(
        &rot_x(roll.to_radians()),
        &mat_mul(
            &rot_y(pitch.to_radians()),
            &mat_mul(&rot_x(twist.to_radians()), &R0),
        ),
    )
}

/// Forward kinematics on plain numbers: (light, view) in the sample frame.
fn forward_raw(rail: f64, roll: f64, pitch: f64, twist: f64) -> (Direction, Direction) {
    let rt = transpose(&wrist(roll, pitch, twist));
    let a = rail.to_radians();
    let l = mat_vec(&rt, [1.0, 0.0, 0.0]);
    let v = mat_vec(&rt, [a.cos(), a.sin(), 0.0]);
    (Direction::from_vector(l), Direction::from_vector(v))
}

/// The axis about which l turns towards v. When l and v are (anti)parallel, the
/// plane is undefined: turn l towards the pole along its meridian, or, with l at
/// the pole, towards φ = 0 (about +y).
fn plane_axis(l: Vec3, v: Vec3) -> Vec3 {
    let c = cross(l, v);
    if norm(c) > PLANE_EPS {
        return normalize(c);
    }
    let m = cross(l, [0.0, 0.0, 1.0]);
    if norm(m) > POLE_EPS {
        normalize(m)
    } else {
        [0.0, 1.0, 0.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::Solver;

    fn solver() -> GonioSolver {
        let p = Profile::load("bonn-gonioreflectometer").unwrap();
        match Solver::new(&p).unwrap() {
            Solver::Gonio(s) => s,
            _ => panic!("not a gonio solver"),
        }
    }

    fn close(a: Direction, b: Direction) -> f64 {
        angle_between(a.to_vector(), b.to_vector())
    }

    #[test]
    fn r0_takes_normal_to_lamp() {
        assert_eq!(mat_vec(&R0, [0.0, 0.0, 1.0]), [1.0, 0.0, 0.0]);
        // R0 is a proper rotation.
        let i = mat_mul(&R0, &transpose(&R0));
        assert_eq!(i, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        let det = rigd_core::geometry::dot(R0[0], cross(R0[1], R0[2]));
        assert_eq!(det, 1.0);
    }

    #[test]
    fn pitch_is_theta_l_and_twist_is_minus_phi_l() {
        let s = solver();
        let sol = s.solve(Direction::new(34.0, 60.0), Direction::new(51.0, 200.0));
        assert!(sol.feasible, "{:?}", sol.reason);
        let arm = sol.setpoints.arm.unwrap();
        assert_eq!(arm[s.pitch], 34.0);
        assert_eq!(arm[s.twist], -60.0);
        let want = Direction::new(34.0, 60.0).angle_to_deg(Direction::new(51.0, 200.0));
        assert!((sol.setpoints.axes["rail"] - want).abs() < 1e-12);
    }

    #[test]
    fn solve_forward_round_trip() {
        let s = solver();
        let (l, v) = (Direction::new(68.0, 342.0), Direction::new(17.0, 120.0));
        let sol = s.solve(l, v);
        assert!(sol.feasible);
        assert!(close(sol.achieved_light, l) < 1e-12);
        assert!(close(sol.achieved_view, v) < 1e-12);
    }

    #[test]
    fn singular_pose_has_zero_roll() {
        let s = solver();
        let sol = s.solve(Direction::new(0.0, 77.0), Direction::new(40.0, 250.0));
        let arm = sol.setpoints.arm.unwrap();
        assert_eq!(arm[s.roll], 0.0);
        assert_eq!(arm[s.pitch], 0.0);
        assert!(close(sol.achieved_view, Direction::new(40.0, 250.0)) < 1e-12);
    }

    #[test]
    fn grazing_light_beyond_pitch_limit_is_clamped() {
        let s = solver();
        let sol = s.solve(Direction::new(89.5, 0.0), Direction::new(30.0, 180.0));
        assert!(!sol.feasible);
        assert!(sol.reason.unwrap().contains("arm joint pitch"));
        assert!((sol.achieved_light.theta_deg - 89.0).abs() < 1e-9);
    }

    #[test]
    fn antiparallel_pair_is_moved_to_rail_maximum() {
        let s = solver();
        let sol = s.solve(Direction::new(90.0, 0.0), Direction::new(90.0, 180.0));
        assert!(!sol.feasible);
        assert_eq!(sol.setpoints.axes["rail"], 172.0);
        assert!(sol.reason.unwrap().contains("rail maximum"));
        let a = sol.achieved_light.angle_to_deg(sol.achieved_view);
        assert!((a - 172.0).abs() < 1e-9);
        // Turned over the pole, so the substitute stays above the horizon.
        assert!(sol.achieved_view.theta_deg < 90.0);
    }

    #[test]
    fn forward_rejects_wrong_setpoints() {
        let s = solver();
        let sol = s.solve(Direction::new(30.0, 0.0), Direction::new(30.0, 90.0));
        assert!(matches!(
            s.forward(&sol.setpoints, "nope"),
            Err(KinematicsError::UnknownCamera(_))
        ));
        let mut bad = sol.setpoints.clone();
        bad.arm = Some(vec![0.0; 2]);
        assert!(matches!(
            s.forward(&bad, "camera"),
            Err(KinematicsError::BadSetpoints(_))
        ));
        let mut bad = sol.setpoints.clone();
        bad.axes.clear();
        assert!(matches!(
            s.forward(&bad, "camera"),
            Err(KinematicsError::BadSetpoints(_))
        ));
        let mut bad = sol.setpoints;
        bad.arm = Some(vec![0.0, f64::NAN, 0.0]);
        assert!(matches!(
            s.forward(&bad, "camera"),
            Err(KinematicsError::BadSetpoints(_))
        ));
    }
}
