//! Pose solving: from a requested (light, view) pair in the sample frame to the
//! set-points of one rig, with a feasibility verdict and, when the rig cannot
//! do what was asked, the nearest pose it can do.
//!
//! Every solver reports the directions its set-points really produce, computed
//! by its own forward kinematics, so a substitute is never mistaken for the
//! request downstream (the dataset records both).
//!
//! Conventions shared by the rigs:
//! - requests are sanitised first ([`sanitize`]): non-finite or out-of-hemisphere
//!   input becomes a finite substitute and makes the pose infeasible, φ is wrapped
//!   into [0, 360), and at the pole (θ = 0, where φ is undefined) φ is taken as 0,
//!   so different φ at θ = 0 give the same pose;
//! - φ is handled as an angle, not through a vector round trip, so equal
//!   azimuths give bitwise-equal set-points whatever their θ (the MSRA cameras of
//!   one trigger must share them exactly);
//! - every axis and joint is rotary, so a value may be moved by whole turns to fit
//!   its soft limits ([`fit_to_limits`]).

pub mod arcs;
pub mod camera;
pub mod fixed;
pub mod gonio;

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::model::profile::{Limits, Profile, RigGeometry};
use rigd_core::geometry::{wrap_deg_360, Direction, POLE_EPS};

/// Actuator set-points for one trigger of the cameras.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Setpoints {
    /// Axis device name -> position in degrees (e.g. "rail", "turntable", "light_arc").
    pub axes: BTreeMap<String, f64>,
    /// Arm joint values in degrees, in the profile's joint order (gonioreflectometer only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arm: Option<Vec<f64>>,
    /// The lamp (or laser) that is on during the exposure.
    pub lamp: String,
    /// The laser calibration plate's height over the turntable, when it is
    /// in place (Wang et al., §3.2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plate_mm: Option<f64>,
}

/// The solved pose of one image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseSolution {
    /// What to command the rig's axes, arm and lamps to for this image.
    pub setpoints: Setpoints,
    /// The camera that takes this image.
    pub camera: String,
    /// Light and view directions in the sample frame that the set-points really produce
    /// (computed by forward kinematics from `setpoints`).
    pub achieved_light: Direction,
    /// View direction in the sample frame that the set-points really produce
    /// (forward kinematics for `camera`).
    pub achieved_view: Direction,
    /// Whether the rig can reach the requested pair; when false the set-points
    /// are the nearest substitute and `reason` says why.
    pub feasible: bool,
    /// When infeasible: why, and what was substituted (one human-readable line).
    pub reason: Option<String>,
}

/// Why a solver could not be built or set-points could not be evaluated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum KinematicsError {
    /// The camera is not one of the rig's cameras.
    #[error("unknown camera `{0}`")]
    UnknownCamera(String),
    /// The lamp is not one of the rig's lamps.
    #[error("unknown lamp `{0}`")]
    UnknownLamp(String),
    /// Set-points that do not fit the rig (missing axis, wrong joint count, non-finite value).
    #[error("bad set-points: {0}")]
    BadSetpoints(String),
    /// A profile that passed validation but does not fit the rig model of the solver.
    #[error("profile does not fit the rig model: {0}")]
    BadProfile(String),
}

/// Per-rig solver built from a validated profile.
#[derive(Debug, Clone)]
pub enum Solver {
    /// Gonioreflectometer: fixed lamp, camera on a rail, sample turned by a robot arm.
    Gonio(gonio::GonioSolver),
    /// Turntable under the sample, a rotating light arc and a stationary camera arc.
    Arcs(arcs::ArcsSolver),
    /// Fixed lamps and one fixed camera; only the lamp is chosen.
    Fixed(fixed::FixedSolver),
}

impl Solver {
    /// Builds the solver of the profile's rig kind.
    pub fn new(profile: &Profile) -> Result<Solver, KinematicsError> {
        Ok(match &profile.rig {
            RigGeometry::Gonioreflectometer { .. } => {
                Solver::Gonio(gonio::GonioSolver::new(profile)?)
            }
            RigGeometry::TurntableArcs { .. } => Solver::Arcs(arcs::ArcsSolver::new(profile)?),
            RigGeometry::FixedLamps { .. } => Solver::Fixed(fixed::FixedSolver::new(profile)?),
        })
    }

    /// Solve one (light, view) pair given in the sample frame. Never panics, never returns NaN,
    /// for any finite input (theta outside [0,90] or non-finite input → infeasible with reason,
    /// with some finite substitute).
    pub fn solve(&self, light: Direction, view: Direction) -> PoseSolution {
        match self {
            Solver::Gonio(s) => s.solve(light, view),
            Solver::Arcs(s) => s.solve(light, view),
            Solver::Fixed(s) => s.solve(light, view),
        }
    }

    /// Forward kinematics: the (light, view) directions in the sample frame that these set-points
    /// produce for the named camera. Soft limits are not checked here (that is `solve`'s job);
    /// only whether the set-points make sense for this rig.
    pub fn forward(
        &self,
        setpoints: &Setpoints,
        camera: &str,
    ) -> Result<(Direction, Direction), KinematicsError> {
        match self {
            Solver::Gonio(s) => s.forward(setpoints, camera),
            Solver::Arcs(s) => s.forward(setpoints, camera),
            Solver::Fixed(s) => s.forward(setpoints, camera),
        }
    }

    /// The light-direction and view-direction elevations (theta, degrees) of the rig's arcs, for
    /// the `grid12x8` plan: (lamp elevations in arc order, camera elevations in arc order).
    /// None for rigs without arcs.
    pub fn arc_elevations(&self) -> Option<(Vec<f64>, Vec<f64>)> {
        match self {
            Solver::Arcs(s) => Some(s.arc_elevations()),
            Solver::Gonio(_) | Solver::Fixed(_) => None,
        }
    }
}

/// Slack for comparing angles in degrees, the same as [`Limits::contains`], so a
/// value computed with rounding error on a limit counts as on it.
pub(crate) const ANGLE_TOL_DEG: f64 = 1e-9;

/// The direction with φ in [0, 360), and φ = 0 (θ = 0 exactly) at the pole.
///
/// Works on the angles rather than through a unit vector, so φ is changed only
/// by whole turns and equal inputs give equal outputs whatever θ is.
pub(crate) fn tidy(theta_deg: f64, phi_deg: f64) -> Direction {
    if theta_deg.to_radians().sin().abs() < POLE_EPS {
        Direction::new(0.0, 0.0)
    } else {
        // `+ 0.0` turns -0.0 into 0.0, so set-points and JSON never show "-0".
        Direction::new(theta_deg + 0.0, wrap_deg_360(phi_deg) + 0.0)
    }
}

/// A request made usable: finite, θ in [0, 90], then [`tidy`].
///
/// Returns a note when the request itself was unusable (which makes the pose
/// infeasible); wrapping φ is not worth a note.
pub(crate) fn sanitize(d: Direction, what: &str) -> (Direction, Option<String>) {
    let mut theta = d.theta_deg;
    let mut phi = d.phi_deg;
    let mut note = None;
    if !theta.is_finite() || !phi.is_finite() {
        if !theta.is_finite() {
            theta = 0.0;
        }
        if !phi.is_finite() {
            phi = 0.0;
        }
        note = Some(format!(
            "{what} direction is not finite (θ={}, φ={}); substituted θ={theta}°, φ={phi}°",
            d.theta_deg, d.phi_deg
        ));
    } else if !(0.0..=90.0).contains(&theta) {
        let clamped = theta.clamp(0.0, 90.0);
        note = Some(format!(
            "{what} θ={theta}° lies outside the hemisphere [0°, 90°]; clamped to θ={clamped}°"
        ));
        theta = clamped;
    }
    (tidy(theta, phi), note)
}

/// Moves `x` by whole turns into `limits`, choosing among the turns that fit the one
/// nearest `home` (ties: the lower one, so the choice is deterministic). If no turn
/// fits, the turn nearest the limits is clamped into them.
///
/// Returns the value and whether it fitted without clamping. The value is always
/// clamped into `[min, max]`, so a value on a limit up to rounding is put exactly on it.
pub(crate) fn fit_to_limits(x: f64, limits: Limits, home: f64) -> (f64, bool) {
    let mut best = x;
    let mut best_key = (f64::INFINITY, f64::INFINITY);
    for k in -3..=3 {
        let c = x + 360.0 * f64::from(k);
        let outside = (limits.min - c).max(c - limits.max).max(0.0);
        let key = (outside, (c - home).abs());
        if key < best_key {
            best = c;
            best_key = key;
        }
    }
    let fits = limits.contains(best);
    (best.clamp(limits.min, limits.max) + 0.0, fits)
}

/// Joins the notes of one pose into its reason line; `None` means feasible.
pub(crate) fn reason_from(notes: Vec<String>) -> Option<String> {
    if notes.is_empty() {
        None
    } else {
        Some(notes.join("; "))
    }
}

/// The axis limits and home of a device, for solvers that move it.
pub(crate) fn axis_limits(profile: &Profile, name: &str) -> Result<(Limits, f64), KinematicsError> {
    let dev = profile
        .device(name)
        .ok_or_else(|| KinematicsError::BadProfile(format!("no device `{name}`")))?;
    let axis = dev
        .as_axis()
        .ok_or_else(|| KinematicsError::BadProfile(format!("`{name}` is not an axis")))?;
    Ok((axis.limits, axis.home_deg.unwrap_or(0.0)))
}

/// Reads one axis from set-points, refusing a missing or non-finite value.
pub(crate) fn axis_value(setpoints: &Setpoints, name: &str) -> Result<f64, KinematicsError> {
    match setpoints.axes.get(name) {
        None => Err(KinematicsError::BadSetpoints(format!(
            "missing axis `{name}`"
        ))),
        Some(x) if !x.is_finite() => Err(KinematicsError::BadSetpoints(format!(
            "axis `{name}` is not finite ({x})"
        ))),
        Some(x) => Ok(*x),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sanitize_pole_ignores_phi_and_wraps_phi() {
        let (a, n) = sanitize(Direction::new(0.0, 123.0), "light");
        assert_eq!((a.theta_deg, a.phi_deg, n), (0.0, 0.0, None));
        let (b, _) = sanitize(Direction::new(30.0, 360.0), "light");
        assert_eq!(b.phi_deg, 0.0);
        let (c, _) = sanitize(Direction::new(30.0, -30.0), "light");
        assert_eq!(c.phi_deg, 330.0);
        let (d, _) = sanitize(Direction::new(30.0, -0.0), "light");
        assert!(d.phi_deg.is_sign_positive());
    }

    #[test]
    fn sanitize_flags_bad_input() {
        let (a, n) = sanitize(Direction::new(f64::NAN, f64::INFINITY), "view");
        assert_eq!((a.theta_deg, a.phi_deg), (0.0, 0.0));
        assert!(n.unwrap().contains("not finite"));
        let (b, n) = sanitize(Direction::new(95.0, 10.0), "view");
        assert_eq!(b.theta_deg, 90.0);
        assert!(n.unwrap().contains("outside the hemisphere"));
        let (c, n) = sanitize(Direction::new(-5.0, 10.0), "light");
        assert_eq!(c.theta_deg, 0.0);
        assert!(n.is_some());
    }

    #[test]
    fn fit_to_limits_picks_turn_nearest_home_and_clamps_otherwise() {
        let twist = Limits {
            min: -360.0,
            max: 360.0,
        };
        assert_eq!(fit_to_limits(350.0, twist, 0.0), (-10.0, true));
        assert_eq!(fit_to_limits(-190.0, twist, 0.0), (170.0, true));
        let turntable = Limits {
            min: -5.0,
            max: 365.0,
        };
        assert_eq!(fit_to_limits(-3.0, turntable, 0.0), (-3.0, true));
        assert_eq!(fit_to_limits(-10.0, turntable, 0.0), (350.0, true));
        let pitch = Limits {
            min: -1.0,
            max: 89.0,
        };
        assert_eq!(fit_to_limits(89.5, pitch, 0.0), (89.0, false));
        assert_eq!(fit_to_limits(89.0 + 1e-12, pitch, 0.0), (89.0, true));
        let narrow = Limits {
            min: -90.0,
            max: 90.0,
        };
        assert_eq!(fit_to_limits(150.0, narrow, 0.0), (90.0, false));
        assert_eq!(fit_to_limits(-100.0, narrow, 0.0), (-90.0, false));
    }
}
