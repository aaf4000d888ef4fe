//! The laser scan of Wang et al., §3.2, as a plan: the calibration captures
//! that fix each laser plane's angle, then for every turntable position and
//! every laser source position (light-arc angle) a sweep of the emitter
//! tilt while every camera records at its video rate.
//!
//! Geometry: the emitter sits on the light arc at polar angle `θ_L` and the
//! arc's radius; its strip on the turntable is orthogonal to the source's
//! horizontal direction (Wang et al., §3.1), and the tilt moves the strip along that
//! direction. At tilt 0 the plane passes through the turntable centre.

use serde::{Deserialize, Serialize};

use crate::model::profile::{Device, Profile, RigGeometry};
use rigd_core::geometry::{Direction, Vec3};

/// The strip lands at most this many emitter radii from the centre; a
/// tilt beyond puts it nowhere a turntable is.
const MAX_STRIP_OFFSET_RADII: f64 = 10.0;

/// Laser source positions of Wang et al. (Figure 4).
pub const MSRA_LASER_SOURCES: usize = 26;

/// What a laser plan captures; `laser:key=value,…` overrides the defaults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaserPlan {
    /// Laser source positions (light-arc angles), evenly spread.
    pub sources: usize,
    /// Turntable positions (views per camera), evenly spread.
    pub turns: usize,
    /// The strip travels ±this far over the turntable, mm.
    pub sweep_mm: f64,
    /// Strip travel between frames, mm.
    pub step_mm: f64,
    /// The cameras' video rate during a sweep (Wang et al.: 7.5 Hz).
    pub frame_hz: f64,
    /// Short exposures keep interreflections dark (Wang et al., §3.2).
    pub exposure_s: f64,
    /// Height of the calibration plate over the turntable, mm.
    pub plate_mm: f64,
    /// Side of the sample's square bounding box on the turntable, mm; the
    /// reference region where the strip is a straight line lies outside it.
    pub box_mm: f64,
    /// Height of the MDF reference plane over the turntable, mm (above the
    /// mesostructure).
    pub reference_mm: f64,
}

impl Default for LaserPlan {
    fn default() -> LaserPlan {
        LaserPlan {
            sources: MSRA_LASER_SOURCES,
            turns: 12,
            sweep_mm: 65.0,
            step_mm: 0.5,
            frame_hz: 7.5,
            exposure_s: 0.002,
            plate_mm: 10.0,
            box_mm: 100.0,
            reference_mm: 10.0,
        }
    }
}

impl LaserPlan {
    /// Parses `laser` or `laser:sources=5,turns=1,step=1` (keys: sources,
    /// turns, sweep, step, hz, exposure, plate, box, reference).
    pub fn parse(spec: &str) -> Result<LaserPlan, String> {
        let mut plan = LaserPlan::default();
        let rest = match spec.strip_prefix("laser") {
            Some("") => return Ok(plan),
            Some(r) => r.strip_prefix(':').ok_or("expected `laser:key=value,…`")?,
            None => return Err("not a laser plan".into()),
        };
        for item in rest.split(',').filter(|s| !s.is_empty()) {
            let (key, value) = item
                .split_once('=')
                .ok_or_else(|| format!("`{item}`: expected key=value"))?;
            let number: f64 = value
                .trim()
                .parse()
                .map_err(|_| format!("`{item}`: `{value}` is not a number"))?;
            let count = || -> Result<usize, String> {
                if number.fract() == 0.0 && (1.0..=10_000.0).contains(&number) {
                    Ok(number as usize)
                } else {
                    Err(format!("`{item}`: expected a whole number from 1"))
                }
            };
            match key.trim() {
                "sources" => plan.sources = count()?,
                "turns" => plan.turns = count()?,
                "sweep" => plan.sweep_mm = number,
                "step" => plan.step_mm = number,
                "hz" => plan.frame_hz = number,
                "exposure" => plan.exposure_s = number,
                "plate" => plan.plate_mm = number,
                "box" => plan.box_mm = number,
                "reference" => plan.reference_mm = number,
                other => {
                    return Err(format!(
                        "unknown key `{other}` (expected sources, turns, sweep, step, hz, exposure, plate, box, reference)"
                    ))
                }
            }
        }
        plan.check()?;
        Ok(plan)
    }

    fn check(&self) -> Result<(), String> {
        let positive = [
            ("sweep", self.sweep_mm),
            ("step", self.step_mm),
            ("hz", self.frame_hz),
            ("exposure", self.exposure_s),
            ("plate", self.plate_mm),
            ("box", self.box_mm),
            ("reference", self.reference_mm),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} = {v}: must be a positive number"));
            }
        }
        if self.frames_per_sweep() > 100_000 {
            return Err(format!(
                "{} frames per sweep: make `step` larger",
                self.frames_per_sweep()
            ));
        }
        if self.exposure_s >= 1.0 / self.frame_hz {
            return Err(format!(
                "exposure {} s does not fit a frame period at {} Hz",
                self.exposure_s, self.frame_hz
            ));
        }
        Ok(())
    }

    /// Frames of one sweep: the strip from +sweep to −sweep in steps.
    pub fn frames_per_sweep(&self) -> usize {
        (2.0 * self.sweep_mm / self.step_mm).ceil() as usize + 1
    }

    /// Light-arc angles of the sources, degrees in (−180, 180): spread
    /// evenly and half a step off 0, where the camera arc stands.
    pub fn source_arc_deg(&self) -> Vec<f64> {
        let n = self.sources as f64;
        (0..self.sources)
            .map(|k| -180.0 + 360.0 * (k as f64 + 0.5) / n)
            .collect()
    }

    /// Turntable angles of the views, degrees in [0, 360).
    pub fn turntable_deg(&self) -> Vec<f64> {
        let n = self.turns as f64;
        (0..self.turns).map(|k| 360.0 * k as f64 / n).collect()
    }
}

/// Where the emitter sits and how its tilt moves the strip.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LaserGeometry {
    /// Polar angle of the emitter, seen from the turntable centre.
    pub theta_deg: f64,
    /// Distance of the emitter from the turntable centre, metres.
    pub radius_m: f64,
}

impl LaserGeometry {
    fn depression_at_zero(&self) -> f64 {
        let t = self.theta_deg.to_radians();
        t.cos().atan2(t.sin())
    }

    /// The emitter's position for a source at `azimuth_deg` (sample frame).
    pub fn emitter(&self, azimuth_deg: f64) -> Vec3 {
        Direction::new(self.theta_deg, azimuth_deg)
            .to_vector()
            .map(|c| c * self.radius_m)
    }

    /// The tilt (degrees) that puts the strip `offset_m` from the centre,
    /// positive towards the source.
    pub fn tilt_for_offset(&self, offset_m: f64) -> f64 {
        let t = self.theta_deg.to_radians();
        let (horizontal, height) = (self.radius_m * t.sin(), self.radius_m * t.cos());
        (height.atan2(horizontal - offset_m) - self.depression_at_zero()).to_degrees()
    }

    /// Where the strip crosses the turntable at `tilt_deg`, metres from the
    /// centre towards the source; `None` once the beam misses the plane.
    pub fn offset_for_tilt(&self, tilt_deg: f64) -> Option<f64> {
        let t = self.theta_deg.to_radians();
        let (horizontal, height) = (self.radius_m * t.sin(), self.radius_m * t.cos());
        let depression = self.depression_at_zero() + tilt_deg.to_radians();
        // A beam this close to the horizon lands far beyond any turntable.
        let offset = horizontal - height / depression.tan();
        (depression > 1e-6
            && depression < std::f64::consts::PI - 1e-6
            && offset.abs() <= MAX_STRIP_OFFSET_RADII * self.radius_m)
            .then_some(offset)
    }

    /// The laser plane for a source at `azimuth_deg` (sample frame) and a
    /// tilt: the emitter's position and the plane's unit normal.
    pub fn plane(&self, azimuth_deg: f64, tilt_deg: f64) -> Option<(Vec3, Vec3)> {
        let offset = self.offset_for_tilt(tilt_deg)?;
        let phi = azimuth_deg.to_radians();
        let along = [phi.cos(), phi.sin(), 0.0];
        let strip = [-phi.sin(), phi.cos(), 0.0];
        let emitter = self.emitter(azimuth_deg);
        let on_plane = along.map(|c| c * offset);
        let to = [
            on_plane[0] - emitter[0],
            on_plane[1] - emitter[1],
            on_plane[2] - emitter[2],
        ];
        let n = rigd_core::geometry::cross(strip, to);
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        (len > 0.0).then(|| (emitter, n.map(|c| c / len)))
    }
}

/// What the rig offers a laser plan.
#[derive(Debug, Clone, PartialEq)]
pub struct LaserRig {
    /// The laser line device, switched on for the sweeps.
    pub laser: String,
    /// The axis that tilts the laser line and so moves its strip.
    pub tilt_axis: String,
    /// The turntable axis, which sets the view.
    pub turntable: String,
    /// The light-arc axis, which sets the laser source's azimuth.
    pub light_arc: String,
    /// Where the emitter sits: polar angle and distance from the centre.
    pub geometry: LaserGeometry,
    /// Cameras with their polar angle on the stationary arc.
    pub cameras: Vec<(String, f64)>,
    /// Soft limits: tilt, light arc, turntable.
    pub tilt_limits: (f64, f64),
    /// The light arc's soft limits (min, max), degrees.
    pub arc_limits: (f64, f64),
    /// The turntable's soft limits (min, max), degrees.
    pub turntable_limits: (f64, f64),
    /// The tilt axis's top speed, degrees/s; a sweep may not need more.
    pub tilt_max_velocity: f64,
    /// Exposure-free part of a frame: slowest readout plus transfer.
    pub frame_overhead_s: f64,
}

impl LaserRig {
    /// The laser rig of a turntable-and-arcs profile with a laser, its tilt
    /// axis and an `elevation_deg` for the laser; `None` otherwise.
    pub fn of(profile: &Profile) -> Option<LaserRig> {
        let RigGeometry::TurntableArcs {
            turntable,
            light_arc,
            cameras,
            laser: Some(laser),
            laser_tilt: Some(tilt),
            arc_radius_m,
            ..
        } = &profile.rig
        else {
            return None;
        };
        let dev = |n: &str| profile.devices.get(n);
        let axis = |n: &str| dev(n).and_then(Device::as_axis);
        let limits = |n: &str| axis(n).map(|a| (a.limits.min, a.limits.max));
        let laser_dev = dev(laser)?;
        let theta = laser_dev.elevation_deg()?;
        let cams = cameras
            .iter()
            .map(|c| {
                dev(c)
                    .and_then(|d| d.direction())
                    .map(|d| (c.clone(), d.theta_deg))
            })
            .collect::<Option<Vec<_>>>()?;
        let frame_overhead_s = cameras
            .iter()
            .filter_map(|c| dev(c).and_then(Device::timing))
            .map(|t| t.readout_s + t.transfer_s)
            .fold(0.0, f64::max);
        Some(LaserRig {
            laser: laser.clone(),
            tilt_axis: tilt.clone(),
            turntable: turntable.clone(),
            light_arc: light_arc.clone(),
            geometry: LaserGeometry {
                theta_deg: theta,
                radius_m: laser_dev.distance_m().unwrap_or(*arc_radius_m),
            },
            cameras: cams,
            tilt_limits: limits(tilt)?,
            arc_limits: limits(light_arc)?,
            turntable_limits: limits(turntable)?,
            tilt_max_velocity: axis(tilt)?.motion.max_velocity,
            frame_overhead_s,
        })
    }

    /// Nominal tilts of one sweep, from the strip at +sweep (towards the
    /// source) to −sweep, evenly spaced in tilt (the axis runs at one
    /// velocity).
    pub fn sweep_tilts(&self, plan: &LaserPlan) -> Vec<f64> {
        let s = plan.sweep_mm * 1e-3;
        let (a, b) = (
            self.geometry.tilt_for_offset(s),
            self.geometry.tilt_for_offset(-s),
        );
        let n = plan.frames_per_sweep();
        (0..n)
            .map(|j| a + (b - a) * j as f64 / (n - 1).max(1) as f64)
            .collect()
    }

    /// The tilt axis's velocity during a sweep, degrees per second.
    pub fn sweep_velocity(&self, plan: &LaserPlan) -> f64 {
        let t = self.sweep_tilts(plan);
        let step = match (t.first(), t.get(1)) {
            (Some(a), Some(b)) => (b - a).abs(),
            _ => 0.0,
        };
        step * plan.frame_hz
    }

    /// Why this rig cannot run the plan, if it cannot.
    pub fn check(&self, plan: &LaserPlan) -> Result<(), String> {
        let tilts = self.sweep_tilts(plan);
        let (lo, hi) = self.tilt_limits;
        for t in [tilts.first(), tilts.last()].into_iter().flatten() {
            if !(t.is_finite() && *t >= lo && *t <= hi) {
                return Err(format!(
                    "a sweep of ±{} mm needs the tilt at {t:.2}°, outside `{}`'s limits [{lo}, {hi}]",
                    plan.sweep_mm, self.tilt_axis
                ));
            }
        }
        let v = self.sweep_velocity(plan);
        if v > self.tilt_max_velocity {
            return Err(format!(
                "steps of {} mm at {} Hz need the tilt at {v:.2}°/s, faster than `{}`'s {}°/s",
                plan.step_mm, plan.frame_hz, self.tilt_axis, self.tilt_max_velocity
            ));
        }
        let images = (2 + plan.turns * plan.frames_per_sweep()) * plan.sources * self.cameras.len();
        if images > crate::plan::MAX_PAIRS {
            return Err(format!(
                "{images} images is more than the {} a plan may hold",
                crate::plan::MAX_PAIRS
            ));
        }
        let period = 1.0 / plan.frame_hz;
        if plan.exposure_s + self.frame_overhead_s > period {
            return Err(format!(
                "a frame takes {:.3} s (exposure, readout, transfer), longer than the {period:.3} s period at {} Hz",
                plan.exposure_s + self.frame_overhead_s,
                plan.frame_hz
            ));
        }
        for a in plan.source_arc_deg() {
            if a < self.arc_limits.0 || a > self.arc_limits.1 {
                return Err(format!(
                    "source at {a:.1}° is outside `{}`'s limits",
                    self.light_arc
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_defaults_and_overrides() {
        assert_eq!(LaserPlan::parse("laser"), Ok(LaserPlan::default()));
        let p = LaserPlan::parse("laser:sources=5,turns=1,step=1").unwrap_or_default();
        assert_eq!((p.sources, p.turns, p.step_mm), (5, 1, 1.0));
        for bad in [
            "laser:sources=0",
            "laser:step=-1",
            "laser:colour=3",
            "laser:step",
            "laser:hz=1000",
        ] {
            assert!(LaserPlan::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn tilt_and_offset_are_inverse_and_the_plane_holds_the_strip() {
        let g = LaserGeometry {
            theta_deg: 45.0,
            radius_m: 0.9,
        };
        assert!(g.tilt_for_offset(0.0).abs() < 1e-12);
        for s in [-0.06, -0.01, 0.0, 0.02, 0.065] {
            let t = g.tilt_for_offset(s);
            let back = g.offset_for_tilt(t).unwrap_or(f64::NAN);
            assert!((back - s).abs() < 1e-12, "{s} → {t} → {back}");
            for az in [0.0, 97.0, 359.0] {
                let (e, n) = g.plane(az, t).unwrap_or_default();
                let phi = f64::to_radians(az);
                let strip_point = [s * phi.cos(), s * phi.sin(), 0.0];
                let d = |p: Vec3| (0..3).map(|i| (p[i] - e[i]) * n[i]).sum::<f64>();
                assert!(d(strip_point).abs() < 1e-12);
                // The strip runs orthogonal to the source's direction.
                let further = [
                    strip_point[0] - 0.01 * phi.sin(),
                    strip_point[1] + 0.01 * phi.cos(),
                    0.0,
                ];
                assert!(d(further).abs() < 1e-12);
            }
        }
        // Beyond the horizon the beam never meets the turntable; just above
        // it, it meets it nowhere near.
        assert_eq!(g.offset_for_tilt(-50.0), None);
        assert_eq!(g.offset_for_tilt(-45.0 + 1e-3), None);
        assert!(g.offset_for_tilt(-40.0).is_some());
    }
}
