//! The VirTex photometric-stereo rig (Spence et al., §2): one fixed camera and lamps
//! at fixed directions; world frame = sample frame, nothing moves.
//!
//! Solving is choosing: the lamp nearest the requested light, and the one camera.
//! A request further than `lamp_tolerance_deg` from what the rig has is infeasible,
//! and the rig's own direction is substituted.

use std::collections::BTreeMap;

use crate::model::profile::{Profile, RigGeometry};
use rigd_core::geometry::{angle_between, Direction};

use super::{reason_from, sanitize, tidy, KinematicsError, PoseSolution, Setpoints, ANGLE_TOL_DEG};

/// Solver of the fixed-lamps rig.
#[derive(Debug, Clone)]
pub struct FixedSolver {
    camera: String,
    camera_dir: Direction,
    /// Lamps in rig order with their directions.
    lamps: Vec<(String, Direction)>,
    tolerance_deg: f64,
}

impl FixedSolver {
    /// Builds the solver from the camera's and lamps' `direction`s.
    pub fn new(profile: &Profile) -> Result<FixedSolver, KinematicsError> {
        let RigGeometry::FixedLamps {
            camera,
            lamps,
            lamp_tolerance_deg,
        } = &profile.rig
        else {
            return Err(KinematicsError::BadProfile(
                "not a fixed_lamps profile".into(),
            ));
        };
        let direction = |name: &str| {
            profile
                .device(name)
                .and_then(|d| d.direction())
                .filter(|d| d.theta_deg.is_finite() && d.phi_deg.is_finite())
                .map(|d| tidy(d.theta_deg, d.phi_deg))
                .ok_or_else(|| {
                    KinematicsError::BadProfile(format!("device `{name}` has no direction"))
                })
        };
        let lamps = lamps
            .iter()
            .map(|n| direction(n).map(|d| (n.clone(), d)))
            .collect::<Result<Vec<_>, _>>()?;
        if lamps.is_empty() {
            return Err(KinematicsError::BadProfile(
                "needs at least one lamp".into(),
            ));
        }
        Ok(FixedSolver {
            camera: camera.clone(),
            camera_dir: direction(camera)?,
            lamps,
            tolerance_deg: *lamp_tolerance_deg,
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
        let mut best = (0, f64::INFINITY);
        for (i, (_, d)) in self.lamps.iter().enumerate() {
            let a = angle_between(lv, d.to_vector()).to_degrees();
            // Ties (up to rounding) go to the first lamp, so equidistant lamps do
            // not pick one by the last bit of a cosine.
            if a < best.1 - ANGLE_TOL_DEG {
                best = (i, a);
            }
        }
        let (lamp, lamp_dir) = &self.lamps[best.0];
        if best.1 > self.tolerance_deg + ANGLE_TOL_DEG {
            notes.push(format!(
                "no lamp at light θ={:.3}°, φ={:.3}° (nearest is {lamp}, {:.1}° away > tolerance {}°); {lamp} substituted",
                l.theta_deg, l.phi_deg, best.1, self.tolerance_deg
            ));
        }
        let view_off = angle_between(v.to_vector(), self.camera_dir.to_vector()).to_degrees();
        if view_off > self.tolerance_deg + ANGLE_TOL_DEG {
            notes.push(format!(
                "the camera is fixed at θ={}°, φ={}° ({view_off:.1}° from the requested view > tolerance {}°); its direction substituted",
                self.camera_dir.theta_deg, self.camera_dir.phi_deg, self.tolerance_deg
            ));
        }
        PoseSolution {
            setpoints: Setpoints {
                axes: BTreeMap::new(),
                arm: None,
                lamp: lamp.clone(),
                plate_mm: None,
            },
            camera: self.camera.clone(),
            achieved_light: *lamp_dir,
            achieved_view: self.camera_dir,
            feasible: notes.is_empty(),
            reason: reason_from(notes),
        }
    }

    /// See [`super::Solver::forward`]: the lamp's and the camera's fixed directions.
    pub fn forward(
        &self,
        setpoints: &Setpoints,
        camera: &str,
    ) -> Result<(Direction, Direction), KinematicsError> {
        if camera != self.camera {
            return Err(KinematicsError::UnknownCamera(camera.to_string()));
        }
        if !setpoints.axes.is_empty() || setpoints.arm.is_some() {
            return Err(KinematicsError::BadSetpoints(
                "this rig has no axes and no arm".into(),
            ));
        }
        let (_, d) = self
            .lamps
            .iter()
            .find(|(n, _)| *n == setpoints.lamp)
            .ok_or_else(|| KinematicsError::UnknownLamp(setpoints.lamp.clone()))?;
        Ok((*d, self.camera_dir))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::Solver;

    fn solver() -> Solver {
        Solver::new(&Profile::load("virtex-photometric-stereo").unwrap()).unwrap()
    }

    #[test]
    fn lamp_directions_are_feasible_and_pick_their_lamp() {
        let s = solver();
        for (i, phi) in [0.0, 120.0, 240.0].into_iter().enumerate() {
            let sol = s.solve(Direction::new(45.0, phi), Direction::new(0.0, 17.0));
            assert!(sol.feasible, "{:?}", sol.reason);
            assert_eq!(sol.setpoints.lamp, format!("lamp{i}"));
            assert!(sol.setpoints.axes.is_empty() && sol.setpoints.arm.is_none());
            assert_eq!(
                s.forward(&sol.setpoints, "camera").unwrap(),
                (sol.achieved_light, sol.achieved_view)
            );
        }
    }

    #[test]
    fn off_lamp_request_is_infeasible_with_nearest_lamp() {
        let s = solver();
        let sol = s.solve(Direction::new(45.0, 100.0), Direction::new(0.0, 0.0));
        assert!(!sol.feasible);
        assert_eq!(sol.setpoints.lamp, "lamp1");
        assert_eq!(sol.achieved_light, Direction::new(45.0, 120.0));
        let sol = s.solve(Direction::new(45.0, 0.0), Direction::new(30.0, 0.0));
        assert!(!sol.feasible);
        assert!(sol.reason.unwrap().contains("camera is fixed"));
        assert_eq!(sol.achieved_view, Direction::new(0.0, 0.0));
    }
}
