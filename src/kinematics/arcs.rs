//! The MSRA turntable-and-arcs rig (Wang et al., §3.1): a turntable turning the
//! sample by τ about world +z, a light arc turned by λ about +z carrying lamps at
//! fixed elevations, and a stationary camera arc at world azimuth 0.
//!
//! Model. Lamp j is at world (θ_j, λ), camera k at world (θ_k, 0); seen from the
//! sample, which the turntable has turned by τ, the light is (θ_j, λ − τ) and the
//! view (θ_k, −τ). So a request (l, v) is met by the camera nearest θ_v, the lamp
//! nearest θ_l, `τ = −φ_v` (in [0, 360)) and `λ = φ_l − φ_v` (in (−180, 180]).
//! τ and λ depend only on the azimuths, so all cameras of one trigger get
//! bitwise-equal set-points. At the pole φ is taken as 0.
//!
//! A lamp closer than `occlusion_deg` to any camera (seen from the sample) is
//! hidden behind it: the whole trigger is dark. This happens whenever the light
//! arc stands over the camera arc (λ ≈ 0), since lamps and cameras share elevations.

use std::collections::BTreeMap;

use crate::model::profile::{Limits, Profile, RigGeometry};
use rigd_core::geometry::{angle_between, wrap_deg_180, wrap_deg_360, Direction};

use super::{
    axis_limits, axis_value, fit_to_limits, reason_from, sanitize, tidy, KinematicsError,
    PoseSolution, Setpoints, ANGLE_TOL_DEG,
};

/// A requested θ further than this from every camera (lamp) is infeasible.
pub const ARC_TOLERANCE_DEG: f64 = 0.5;

/// Solver of the turntable-and-arcs rig.
#[derive(Debug, Clone)]
pub struct ArcsSolver {
    turntable: String,
    turntable_limits: Limits,
    turntable_home: f64,
    light_arc: String,
    light_arc_limits: Limits,
    light_arc_home: f64,
    /// Lamps in arc order with their elevations θ_j.
    lamps: Vec<(String, f64)>,
    /// Cameras in arc order with their elevations θ_k.
    cameras: Vec<(String, f64)>,
    occlusion_deg: f64,
}

impl ArcsSolver {
    /// Builds the solver; every camera must stand on the arc at world azimuth 0.
    pub fn new(profile: &Profile) -> Result<ArcsSolver, KinematicsError> {
        let RigGeometry::TurntableArcs {
            turntable,
            light_arc,
            lamps,
            cameras,
            occlusion_deg,
            ..
        } = &profile.rig
        else {
            return Err(KinematicsError::BadProfile(
                "not a turntable_arcs profile".into(),
            ));
        };
        let (turntable_limits, turntable_home) = axis_limits(profile, turntable)?;
        let (light_arc_limits, light_arc_home) = axis_limits(profile, light_arc)?;
        let lamps = lamps
            .iter()
            .map(|name| {
                profile
                    .device(name)
                    .and_then(|d| d.elevation_deg())
                    .filter(|e| e.is_finite())
                    .map(|e| (name.clone(), e))
                    .ok_or_else(|| {
                        KinematicsError::BadProfile(format!("lamp `{name}` has no elevation_deg"))
                    })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let cameras = cameras
            .iter()
            .map(|name| {
                let d = profile
                    .device(name)
                    .and_then(|d| d.direction())
                    .ok_or_else(|| {
                        KinematicsError::BadProfile(format!("camera `{name}` has no direction"))
                    })?;
                let t = tidy(d.theta_deg, d.phi_deg);
                if t.phi_deg != 0.0 || !t.theta_deg.is_finite() {
                    return Err(KinematicsError::BadProfile(format!(
                        "camera `{name}` must stand on the camera arc at azimuth 0, got φ={}",
                        d.phi_deg
                    )));
                }
                Ok((name.clone(), t.theta_deg))
            })
            .collect::<Result<Vec<_>, _>>()?;
        if lamps.is_empty() || cameras.is_empty() {
            return Err(KinematicsError::BadProfile(
                "needs at least one lamp and one camera".into(),
            ));
        }
        Ok(ArcsSolver {
            turntable: turntable.clone(),
            turntable_limits,
            turntable_home,
            light_arc: light_arc.clone(),
            light_arc_limits,
            light_arc_home,
            lamps,
            cameras,
            occlusion_deg: *occlusion_deg,
        })
    }

    /// (lamp elevations, camera elevations), each in arc order.
    pub fn arc_elevations(&self) -> (Vec<f64>, Vec<f64>) {
        (
            self.lamps.iter().map(|(_, t)| *t).collect(),
            self.cameras.iter().map(|(_, t)| *t).collect(),
        )
    }

    /// See [`super::Solver::solve`].
    pub fn solve(&self, light: Direction, view: Direction) -> PoseSolution {
        let mut notes = Vec::new();
        let (l, note) = sanitize(light, "light");
        notes.extend(note);
        let (v, note) = sanitize(view, "view");
        notes.extend(note);

        let (ci, cam_theta) = nearest(&self.cameras, v.theta_deg);
        let (li, lamp_theta) = nearest(&self.lamps, l.theta_deg);
        let (camera, lamp) = (&self.cameras[ci].0, &self.lamps[li].0);
        if (v.theta_deg - cam_theta).abs() > ARC_TOLERANCE_DEG + ANGLE_TOL_DEG {
            notes.push(format!(
                "no camera at view θ={:.3}° (tolerance {ARC_TOLERANCE_DEG}°); nearest camera {camera} at θ={cam_theta}° substituted",
                v.theta_deg
            ));
        }
        if (l.theta_deg - lamp_theta).abs() > ARC_TOLERANCE_DEG + ANGLE_TOL_DEG {
            notes.push(format!(
                "no lamp at light θ={:.3}° (tolerance {ARC_TOLERANCE_DEG}°); nearest lamp {lamp} at θ={lamp_theta}° substituted",
                l.theta_deg
            ));
        }

        let tau = wrap_deg_360(-v.phi_deg) + 0.0;
        let mut lambda = wrap_deg_180(l.phi_deg - v.phi_deg) + 0.0;
        if let Some((k, angle)) = self.occluder(lamp_theta, lambda) {
            let side = if lambda < 0.0 { -1.0 } else { 1.0 };
            let clear = self.clear_light_arc(lamp_theta);
            let moved = side * clear.unwrap_or(180.0);
            let what = match clear {
                Some(_) => "light arc moved",
                None => "no light-arc angle clears it; light arc moved as far as possible",
            };
            notes.push(format!(
                "camera would stand between lamp and sample (lamp {lamp} hidden behind camera {}: {angle:.1}° apart < occlusion {}°); {what} from {lambda:.3}° to {moved:.3}°",
                self.cameras[k].0, self.occlusion_deg
            ));
            lambda = moved;
        }

        let (tau_fit, ok) = fit_preferring(tau, self.turntable_limits, self.turntable_home);
        if !ok {
            notes.push(out_of_limits(
                &self.turntable,
                tau,
                self.turntable_limits,
                tau_fit,
            ));
        }
        let (lambda_fit, ok) = fit_preferring(lambda, self.light_arc_limits, self.light_arc_home);
        if !ok {
            notes.push(out_of_limits(
                &self.light_arc,
                lambda,
                self.light_arc_limits,
                lambda_fit,
            ));
        }

        let (achieved_light, achieved_view) =
            forward_raw(tau_fit, lambda_fit, lamp_theta, cam_theta);
        let mut axes = BTreeMap::new();
        axes.insert(self.turntable.clone(), tau_fit);
        axes.insert(self.light_arc.clone(), lambda_fit);
        PoseSolution {
            setpoints: Setpoints {
                axes,
                arm: None,
                lamp: lamp.clone(),
                plate_mm: None,
            },
            camera: camera.clone(),
            achieved_light,
            achieved_view,
            feasible: notes.is_empty(),
            reason: reason_from(notes),
        }
    }

    /// See [`super::Solver::forward`].
    pub fn forward(
        &self,
        setpoints: &Setpoints,
        camera: &str,
    ) -> Result<(Direction, Direction), KinematicsError> {
        let cam_theta = self
            .cameras
            .iter()
            .find(|(n, _)| n == camera)
            .map(|(_, t)| *t)
            .ok_or_else(|| KinematicsError::UnknownCamera(camera.to_string()))?;
        let lamp_theta = self
            .lamps
            .iter()
            .find(|(n, _)| *n == setpoints.lamp)
            .map(|(_, t)| *t)
            .ok_or_else(|| KinematicsError::UnknownLamp(setpoints.lamp.clone()))?;
        if setpoints.arm.is_some() {
            return Err(KinematicsError::BadSetpoints(
                "this rig has no arm, but arm joints were given".into(),
            ));
        }
        let tau = axis_value(setpoints, &self.turntable)?;
        let lambda = axis_value(setpoints, &self.light_arc)?;
        Ok(forward_raw(tau, lambda, lamp_theta, cam_theta))
    }

    /// The camera hiding a lamp at elevation `lamp_theta` on the light arc at `lambda`,
    /// and their angle: the nearest camera closer than `occlusion_deg`, if any.
    fn occluder(&self, lamp_theta: f64, lambda: f64) -> Option<(usize, f64)> {
        let lamp = Direction::new(lamp_theta, lambda).to_vector();
        self.cameras
            .iter()
            .enumerate()
            .map(|(k, (_, t))| {
                let cam = Direction::new(*t, 0.0).to_vector();
                (k, angle_between(lamp, cam).to_degrees())
            })
            .filter(|(_, a)| *a < self.occlusion_deg - ANGLE_TOL_DEG)
            .min_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// The smallest |λ| at which a lamp at `lamp_theta` clears every camera, or None
    /// if no λ does.
    ///
    /// From `sin²(γ/2) = sin²((θ_j−θ_k)/2) + sin θ_j sin θ_k sin²(λ/2)` for the angle γ
    /// between lamp and camera k: γ ≥ occlusion needs
    /// `sin²(λ/2) ≥ (sin²(occ/2) − sin²(Δθ/2)) / (sin θ_j sin θ_k)`. The half-angle
    /// form stays accurate for the small angles involved, unlike a cosine.
    fn clear_light_arc(&self, lamp_theta: f64) -> Option<f64> {
        let half_sq = |deg: f64| (deg.to_radians() / 2.0).sin().powi(2);
        let sj = lamp_theta.to_radians().sin();
        let mut need = 0.0_f64;
        for (_, cam_theta) in &self.cameras {
            let numer = half_sq(self.occlusion_deg) - half_sq(lamp_theta - cam_theta);
            if numer <= 0.0 {
                continue;
            }
            let denom = sj * cam_theta.to_radians().sin();
            if denom <= 0.0 || numer > denom {
                return None;
            }
            need = need.max(2.0 * (numer / denom).sqrt().asin().to_degrees());
        }
        Some(need)
    }
}

/// `x` itself when it lies within `limits` (τ in [0, 360) and λ in (−180, 180] are
/// the canonical turns, and the same φ must always give the same turn), otherwise
/// [`fit_to_limits`].
fn fit_preferring(x: f64, limits: Limits, home: f64) -> (f64, bool) {
    if limits.contains(x) {
        (x.clamp(limits.min, limits.max) + 0.0, true)
    } else {
        fit_to_limits(x, limits, home)
    }
}

/// The entry whose θ is nearest `theta` (ties, up to rounding: the first in arc order).
fn nearest(list: &[(String, f64)], theta: f64) -> (usize, f64) {
    let mut best = (0, f64::INFINITY, 0.0);
    for (i, (_, t)) in list.iter().enumerate() {
        let d = (t - theta).abs();
        if d < best.1 - ANGLE_TOL_DEG {
            best = (i, d, *t);
        }
    }
    (best.0, best.2)
}

fn out_of_limits(axis: &str, value: f64, limits: Limits, fitted: f64) -> String {
    format!(
        "axis {axis} = {value:.3}° outside its limits [{}, {}]; clamped to {fitted}°",
        limits.min, limits.max
    )
}

/// Forward kinematics on plain numbers. The turntable is a rotation about the
/// sample normal, so it only shifts azimuths; doing that on the angles keeps grid
/// directions exact (no vector round trip).
fn forward_raw(tau: f64, lambda: f64, lamp_theta: f64, cam_theta: f64) -> (Direction, Direction) {
    (tidy(lamp_theta, lambda - tau), tidy(cam_theta, -tau))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::Solver;

    fn solver() -> ArcsSolver {
        let p = Profile::load("msra-btf-mdf").unwrap();
        match Solver::new(&p).unwrap() {
            Solver::Arcs(s) => s,
            _ => panic!("not an arcs solver"),
        }
    }

    #[test]
    fn grid_pose_is_exact() {
        let s = solver();
        let sol = s.solve(Direction::new(40.0, 120.0), Direction::new(60.0, 30.0));
        assert!(sol.feasible, "{:?}", sol.reason);
        assert_eq!(sol.camera, "cam5");
        assert_eq!(sol.setpoints.lamp, "lamp3");
        assert_eq!(sol.setpoints.axes["turntable"], 330.0);
        assert_eq!(sol.setpoints.axes["light_arc"], 90.0);
        assert_eq!(sol.achieved_light, Direction::new(40.0, 120.0));
        assert_eq!(sol.achieved_view, Direction::new(60.0, 30.0));
    }

    #[test]
    fn clear_angle_is_exactly_on_the_occlusion_boundary() {
        let s = solver();
        for (_, lamp_theta) in &s.lamps {
            let need = s.clear_light_arc(*lamp_theta).unwrap();
            assert!(need > 0.0);
            assert!(s.occluder(*lamp_theta, need).is_none());
            assert!(s.occluder(*lamp_theta, -need).is_none());
            assert!(s.occluder(*lamp_theta, need - 1e-6).is_some());
        }
    }

    #[test]
    fn lamp_far_from_any_camera_elevation_is_substituted() {
        let s = solver();
        let sol = s.solve(Direction::new(44.0, 90.0), Direction::new(50.0, 0.0));
        assert!(!sol.feasible);
        assert_eq!(sol.setpoints.lamp, "lamp3");
        assert!(sol.reason.unwrap().contains("nearest lamp lamp3"));
        assert_eq!(sol.achieved_light.theta_deg, 40.0);
    }

    #[test]
    fn forward_rejects_unknown_names() {
        let s = solver();
        let sol = s.solve(Direction::new(40.0, 120.0), Direction::new(60.0, 30.0));
        assert!(matches!(
            s.forward(&sol.setpoints, "cam9"),
            Err(KinematicsError::UnknownCamera(_))
        ));
        let mut bad = sol.setpoints;
        bad.lamp = "lamp9".into();
        assert!(matches!(
            s.forward(&bad, "cam0"),
            Err(KinematicsError::UnknownLamp(_))
        ));
    }
}
