//! Rig profiles: one TOML file per rig, naming its devices, geometry, limits,
//! motion model, camera timing and default plan.
//!
//! Parsing is strict (unknown keys are errors) and every error names the file,
//! the key and what was expected, on one line, because an operator reads it
//! at the terminal before anything moves.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::exposure::ExposurePolicy;
use rigd_core::holder::HolderSpec;

pub use super::device::{
    ArmDevice, ArmProtocol, AxisDevice, AxisProtocol, CameraDevice, CameraProtocol, CameraTiming,
    Device, DeviceKind, GenicamSettings, Gphoto2Settings, Intrinsics, Joint, LampDevice,
    LaserDevice, Limits, Motion, PtpSettings, RelayProtocol, Transport, DEFAULT_ARM_HOMING_S,
    GPHOTO2_SHUTTER_WIDGET, MAX_BAUD, MAX_SENSOR_PIXELS, MAX_SENSOR_SIDE,
};
pub use super::exposure::{check_exposure_s, MAX_EXPOSURE_S};

/// The profiles of the three rigs of the source documents, embedded so the
/// daemon runs on a fresh machine without any file.
pub const EMBEDDED: &[(&str, &str)] = &[
    (
        "bonn-gonioreflectometer",
        include_str!("../../rig-profiles/bonn-gonioreflectometer.toml"),
    ),
    (
        "msra-btf-mdf",
        include_str!("../../rig-profiles/msra-btf-mdf.toml"),
    ),
    (
        "virtex-photometric-stereo",
        include_str!("../../rig-profiles/virtex-photometric-stereo.toml"),
    ),
];

/// The profile used when none is given: the simulated Bonn gonioreflectometer.
pub const DEFAULT_PROFILE: &str = "bonn-gonioreflectometer";

/// A profile that could not be loaded: where (the file's path as given,
/// or `<embedded NAME>` for an embedded profile), which key, and what was
/// expected; the shape of every configuration file's error.
pub type ProfileError = rigd_core::config::ConfigError;

/// One rig's description.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Profile {
    /// The rig's name (`bonn-gonioreflectometer`), recorded in every run's
    /// manifest and shown by the daemon.
    pub name: String,
    /// One line for people: what the rig is and what it captures.
    #[serde(default)]
    pub description: String,
    /// Plan used when a run names none (`h1`, `h2`, `grid12x8`, `lamps`).
    pub default_plan: String,
    /// Which rig this is and how its devices are arranged.
    pub rig: RigGeometry,
    /// Every device by name.
    pub devices: BTreeMap<String, Device>,
    /// The sample holder plate: its markers, sample window and colour
    /// references. Recorded with every run, so processing registers the
    /// run's frames by the plate they show; the standard plate if left out.
    #[serde(default)]
    pub holder: HolderSpec,
    /// The exposures each step takes (`[exposure_policy]`, `policy =
    /// "single"`, `"brackets"` or `"auto"`); a run's own policy overrides
    /// it. One exposure per step if left out.
    #[serde(default, skip_serializing_if = "ExposurePolicy::is_single")]
    pub exposure_policy: ExposurePolicy,
    /// Settings of the simulated rig.
    #[serde(default)]
    pub sim: SimTable,
}

/// The arrangement of a rig, by kind. The world frame has its origin at the
/// sample centre; see each variant for its axes.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum RigGeometry {
    /// Sattler et al.: a fixed lamp along world +x, a camera on a circular rail in
    /// the world xy plane (rail angle measured from the lamp, counter-clockwise
    /// about +z), and a robot arm orienting the sample at the origin.
    Gonioreflectometer {
        /// The fixed lamp's device (a `lamp`), standing along world +x.
        lamp: String,
        /// The camera's device (a `camera`), carried by the rail.
        camera: String,
        /// The rail's device (an `axis`): the camera's angle on the rail in
        /// degrees, measured from the lamp.
        rail: String,
        /// The arm's device (an `arm`) with the three wrist joints `roll`,
        /// `pitch` and `twist` that orient the sample.
        arm: String,
        /// Distance from the lamp to the sample centre, in metres (unless
        /// the lamp device gives its own `distance_m`).
        lamp_distance_m: f64,
        /// Radius of the camera rail, in metres: the camera's distance from
        /// the sample centre unless the camera gives its own `distance_m`.
        rail_radius_m: f64,
    },
    /// Wang et al.: a turntable (rotation about world +z), a light arc rotating
    /// about +z carrying lamps at fixed elevations, and a stationary camera
    /// arc in the world xz plane at azimuth 0.
    TurntableArcs {
        /// The turntable's device (an `axis`): the sample's rotation about
        /// world +z, in degrees.
        turntable: String,
        /// The light arc's device (an `axis`): the arc's rotation about
        /// world +z, in degrees.
        light_arc: String,
        /// Lamps on the light arc, in arc order; each has an `elevation_deg`.
        lamps: Vec<String>,
        /// Cameras on the stationary arc; each has a `direction` (φ = 0 in the world).
        cameras: Vec<String>,
        /// The laser line unit on the light arc (a `laser`), for MDF scans;
        /// absent on a rig without one.
        #[serde(default)]
        laser: Option<String>,
        /// The axis that tilts the laser line, in degrees (an `axis`);
        /// absent on a rig without one.
        #[serde(default)]
        laser_tilt: Option<String>,
        /// A lamp closer than this to a camera, seen from the sample, is
        /// blocked by that camera.
        occlusion_deg: f64,
        /// Radius of the light arc, in metres: the distance of its lamps and
        /// laser from the sample centre unless a device gives its own
        /// `distance_m`.
        arc_radius_m: f64,
    },
    /// Spence et al.: one fixed camera and lamps at known slant/tilt.
    FixedLamps {
        /// The one camera (a `camera` with a `direction`).
        camera: String,
        /// The lamps in rig order, each a `lamp` with a `direction`.
        lamps: Vec<String>,
        /// A requested light direction further than this from every lamp is infeasible.
        #[serde(default = "default_lamp_tolerance")]
        lamp_tolerance_deg: f64,
    },
}

fn default_lamp_tolerance() -> f64 {
    0.5
}

/// The profile's `[sim]` table: the simulated cameras' frames, which
/// processing models, and the simulator's own keys, which the simulator's
/// settings type reads and checks where the simulator is wired in.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SimTable {
    /// Frame size the simulated cameras render, `[width, height]`; by
    /// default 320×240, small so a full capture is quick (the real sensors
    /// are far larger) and large enough that the holder's markers register
    /// in every view of an H2 ([`MIN_REGISTRABLE_FRAME`]).
    #[serde(default = "default_sim_frame")]
    pub frame_size: [u32; 2],
    /// The simulated cameras' focal length relative to the profile's
    /// intrinsics: a longer lens, so a small simulated frame still
    /// resolves the sample (laser scans need it).
    #[serde(default = "default_zoom")]
    pub zoom: f64,
    /// The table's other keys, as written: the simulator's.
    #[serde(flatten)]
    pub simulator: BTreeMap<String, serde_value::Value>,
}

fn default_zoom() -> f64 {
    1.0
}

/// The smallest simulated frame, measured on the Bonn rig's H2 views, at
/// which `rigd process rectify` finds the holder's markers in every view:
/// at 256×192 about a third of the 75° ring falls back to registration
/// from the pose (`docs/processing.md`, "Registration").
pub const MIN_REGISTRABLE_FRAME: [u32; 2] = [288, 216];

fn default_sim_frame() -> [u32; 2] {
    [320, 240]
}

impl Default for SimTable {
    fn default() -> Self {
        SimTable {
            frame_size: default_sim_frame(),
            zoom: default_zoom(),
            simulator: BTreeMap::new(),
        }
    }
}

impl Profile {
    /// Loads a profile from a path, or, if no such file exists, from the
    /// embedded profile of that name (`bonn-gonioreflectometer`, ...).
    pub fn load(spec: &str) -> Result<Profile, ProfileError> {
        let path = Path::new(spec);
        if path.exists() {
            return Profile::from_file(path);
        }
        if let Some((_, text)) = EMBEDDED.iter().find(|(n, _)| *n == spec) {
            return Profile::parse(text, &Profile::origin(spec));
        }
        let names: Vec<&str> = EMBEDDED.iter().map(|(n, _)| *n).collect();
        Err(ProfileError {
            file: spec.to_string(),
            key: String::new(),
            message: format!(
                "no such file, and not an embedded profile (expected a path or one of: {})",
                names.join(", ")
            ),
        })
    }

    /// How errors and a run's record name the profile that
    /// [`Profile::load`] loads for `spec`: its path, or `<embedded NAME>`.
    pub fn origin(spec: &str) -> String {
        if Path::new(spec).exists() {
            spec.to_string()
        } else {
            format!("<embedded {spec}>")
        }
    }

    /// Reads, parses and validates the profile file at `path`; errors name
    /// that path.
    pub fn from_file(path: &Path) -> Result<Profile, ProfileError> {
        let profile = rigd_core::config::load(
            path,
            rigd_core::read::TEXT_LIMIT,
            rigd_core::config::Format::Toml,
        )?;
        Profile::checked(profile, &path.display().to_string())
    }

    /// Parses and validates profile text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Profile, ProfileError> {
        let profile = rigd_core::config::parse(text, file, rigd_core::config::Format::Toml)?;
        Profile::checked(profile, file)
    }

    /// A parsed profile, validated and with its azimuths normalised.
    fn checked(mut profile: Profile, file: &str) -> Result<Profile, ProfileError> {
        profile.validate().map_err(|(key, message)| ProfileError {
            file: file.to_string(),
            key,
            message,
        })?;
        // One azimuth for every later step, as a plan's directions have.
        for dev in profile.devices.values_mut() {
            if let Some(d) = dev.direction_mut() {
                d.phi_deg = crate::model::text::normalise_phi(d.phi_deg).unwrap_or(d.phi_deg);
            }
        }
        Ok(profile)
    }

    /// The device of that name, if it has the expected kind.
    pub fn device(&self, name: &str) -> Option<&Device> {
        self.devices.get(name)
    }

    /// Names of all cameras the rig triggers, in trigger order.
    pub fn camera_names(&self) -> Vec<String> {
        match &self.rig {
            RigGeometry::Gonioreflectometer { camera, .. } => vec![camera.clone()],
            RigGeometry::TurntableArcs { cameras, .. } => cameras.clone(),
            RigGeometry::FixedLamps { camera, .. } => vec![camera.clone()],
        }
    }

    /// Whether every camera of the rig can expose for `exposure_s`
    /// seconds (a run's `--exposure`, the API's `exposure_s`); the error
    /// names the first camera that cannot and its range.
    pub fn check_exposure_override(&self, exposure_s: f64) -> Result<(), String> {
        check_exposure_s(exposure_s)?;
        for name in self.camera_names() {
            self.check_camera_exposure(&name, exposure_s)?;
        }
        Ok(())
    }

    /// Whether every camera can take the exposures of `policy`, its base
    /// exposure being `exposure_override` if given, else the camera's own:
    /// the policy's own rules ([`ExposurePolicy::check`]), then each
    /// bracket, and `auto`'s shortest exposure, within every camera's
    /// `timing.exposure_range_s`. `Err` names the policy's key and why.
    pub fn check_exposure_policy(
        &self,
        policy: &ExposurePolicy,
        exposure_override: Option<f64>,
    ) -> Result<(), (String, String)> {
        policy.check().map_err(|e| (e.key.to_string(), e.message))?;
        for name in self.camera_names() {
            match policy {
                ExposurePolicy::Single {} => {}
                ExposurePolicy::Brackets { exposures_s } => {
                    for &t in exposures_s {
                        self.check_camera_exposure(&name, t)
                            .map_err(|why| ("exposures_s".to_string(), why))?;
                    }
                }
                ExposurePolicy::Auto { .. } => {
                    let Some(a) = policy.auto() else { continue };
                    let base = exposure_override.unwrap_or_else(|| {
                        self.devices
                            .get(&name)
                            .and_then(Device::as_camera)
                            .map_or(0.0, |c| c.timing.exposure_s)
                    });
                    if base > 0.0 {
                        self.check_camera_exposure(&name, a.shortest_s(base))
                            .map_err(|why| {
                                (
                                    "max_extra".to_string(),
                                    format!(
                                        "{} further exposures {} times shorter than {} s reach {why}",
                                        a.max_extra,
                                        crate::model::text::short_number(a.factor),
                                        crate::model::text::short_number(base)
                                    ),
                                )
                            })?;
                    }
                }
            }
        }
        Ok(())
    }

    /// Whether camera `name` can expose for `exposure_s` seconds: within
    /// [`check_exposure_s`] and its `timing.exposure_range_s`.
    pub fn check_camera_exposure(&self, name: &str, exposure_s: f64) -> Result<(), String> {
        check_exposure_s(exposure_s)?;
        let Some([low, high]) = self
            .devices
            .get(name)
            .and_then(Device::as_camera)
            .and_then(|c| c.timing.exposure_range_s)
        else {
            return Ok(());
        };
        if (low..=high).contains(&exposure_s) {
            Ok(())
        } else {
            Err(format!(
                "{} s: camera `{name}` exposes {low} … {high} s (devices.{name}.timing.exposure_range_s)",
                crate::model::text::short_number(exposure_s)
            ))
        }
    }

    /// Names of all lamps, in rig order.
    pub fn lamp_names(&self) -> Vec<String> {
        match &self.rig {
            RigGeometry::Gonioreflectometer { lamp, .. } => vec![lamp.clone()],
            RigGeometry::TurntableArcs { lamps, .. } | RigGeometry::FixedLamps { lamps, .. } => {
                lamps.clone()
            }
        }
    }

    fn validate(&self) -> Result<(), (String, String)> {
        crate::model::text::check_name(&self.name)
            .map_err(|why| ("name".to_string(), format!("the rig's name {why}")))?;
        self.holder.check().map_err(|e| (e.key, e.message))?;
        self.check_exposure_policy(&self.exposure_policy, None)
            .map_err(|(key, why)| (format!("exposure_policy.{key}"), why))?;
        for (name, dev) in &self.devices {
            check_device_name(name)?;
            dev.validate(&format!("devices.{name}"))?;
        }
        // The [sim] section's scene and faults are the simulator's to
        // check (`rig::load_profile`); its values are checked here.
        let want = |key: &str, name: &str, kind: DeviceKind| -> Result<(), (String, String)> {
            match self.devices.get(name) {
                None => Err((
                    key.to_string(),
                    format!(
                        "names device `{name}`, but there is no [devices.{name}] (expected {})",
                        kind.with_article()
                    ),
                )),
                Some(d) if d.kind() != kind => Err((
                    key.to_string(),
                    format!(
                        "device `{name}` is {}, expected {}",
                        d.kind().with_article(),
                        kind.with_article()
                    ),
                )),
                Some(_) => Ok(()),
            }
        };
        let positive = |key: &str, v: f64| -> Result<(), (String, String)> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err((
                    key.to_string(),
                    format!("expected a positive number, got {v}"),
                ))
            }
        };
        match &self.rig {
            RigGeometry::Gonioreflectometer {
                lamp,
                camera,
                rail,
                arm,
                lamp_distance_m,
                rail_radius_m,
            } => {
                want("rig.lamp", lamp, DeviceKind::Lamp)?;
                want("rig.camera", camera, DeviceKind::Camera)?;
                want("rig.rail", rail, DeviceKind::Axis)?;
                want("rig.arm", arm, DeviceKind::Arm)?;
                positive("rig.lamp_distance_m", *lamp_distance_m)?;
                positive("rig.rail_radius_m", *rail_radius_m)?;
                let joints = self.devices[arm].as_arm().map_or(0, |a| a.joints.len());
                if joints != 3 {
                    return Err((
                        format!("devices.{arm}.joints"),
                        format!("the gonioreflectometer arm needs 3 wrist joints (roll, pitch, roll), got {joints}"),
                    ));
                }
            }
            RigGeometry::TurntableArcs {
                turntable,
                light_arc,
                lamps,
                cameras,
                laser,
                laser_tilt,
                occlusion_deg,
                arc_radius_m,
            } => {
                want("rig.turntable", turntable, DeviceKind::Axis)?;
                want("rig.light_arc", light_arc, DeviceKind::Axis)?;
                if lamps.is_empty() {
                    return Err(("rig.lamps".into(), "expected at least one lamp".into()));
                }
                if cameras.is_empty() {
                    return Err(("rig.cameras".into(), "expected at least one camera".into()));
                }
                listed_once("rig.lamps", lamps)?;
                listed_once("rig.cameras", cameras)?;
                for (i, l) in lamps.iter().enumerate() {
                    want(&format!("rig.lamps[{i}]"), l, DeviceKind::Lamp)?;
                    if self.devices[l].elevation_deg().is_none() {
                        return Err((
                            format!("devices.{l}.elevation_deg"),
                            "a lamp on a light arc needs its elevation in degrees".into(),
                        ));
                    }
                }
                for (i, c) in cameras.iter().enumerate() {
                    want(&format!("rig.cameras[{i}]"), c, DeviceKind::Camera)?;
                    self.need_direction(c)?;
                }
                if let Some(l) = laser {
                    want("rig.laser", l, DeviceKind::Laser)?;
                }
                if let Some(t) = laser_tilt {
                    want("rig.laser_tilt", t, DeviceKind::Axis)?;
                }
                positive("rig.occlusion_deg", *occlusion_deg)?;
                positive("rig.arc_radius_m", *arc_radius_m)?;
            }
            RigGeometry::FixedLamps {
                camera,
                lamps,
                lamp_tolerance_deg,
            } => {
                want("rig.camera", camera, DeviceKind::Camera)?;
                self.need_direction(camera)?;
                if lamps.is_empty() {
                    return Err(("rig.lamps".into(), "expected at least one lamp".into()));
                }
                listed_once("rig.lamps", lamps)?;
                for (i, l) in lamps.iter().enumerate() {
                    want(&format!("rig.lamps[{i}]"), l, DeviceKind::Lamp)?;
                    self.need_direction(l)?;
                }
                positive("rig.lamp_tolerance_deg", *lamp_tolerance_deg)?;
            }
        }
        self.validate_modules()?;
        let [w, h] = self.sim.frame_size;
        if w == 0 || h == 0 || w > 8192 || h > 8192 {
            return Err((
                "sim.frame_size".into(),
                format!("expected [width, height] between 1 and 8192, got [{w}, {h}]"),
            ));
        }
        let zoom = self.sim.zoom;
        if !(zoom.is_finite() && (0.1..=100.0).contains(&zoom)) {
            return Err((
                "sim.zoom".into(),
                format!("expected 0.1 ..= 100, got {zoom}"),
            ));
        }
        Ok(())
    }

    /// The axes without homing (`homing = false`): their zero is the
    /// operator's, so resuming a run on them needs the operator's word.
    pub fn axes_without_homing(&self) -> Vec<&str> {
        self.devices
            .iter()
            .filter(|(_, d)| !d.homes())
            .map(|(name, _)| name.as_str())
            .collect()
    }

    /// Every lamp and laser on one relay module says the same about the
    /// module's status registers: the module has them or it has not.
    fn validate_modules(&self) -> Result<(), (String, String)> {
        let mut seen: BTreeMap<String, (&str, bool)> = BTreeMap::new();
        let mut coils: BTreeMap<(String, u16), &str> = BTreeMap::new();
        for (name, dev) in &self.devices {
            let Some(coil) = dev.coil() else {
                continue;
            };
            let Some(module) = dev.transport().modbus_module() else {
                continue;
            };
            // Two devices on one relay would switch together: the light
            // of one image would be both.
            if let Some(other) = coils.insert((module.clone(), coil), name) {
                return Err((
                    format!("devices.{name}.coil"),
                    format!(
                        "coil {coil} of {module} is also `{other}`'s (a missing `coil` is 0); each lamp and laser needs its own relay"
                    ),
                ));
            }
            let has = dev.transport().status_registers();
            match seen.get(&module) {
                Some(&(other, other_has)) if other_has != has => {
                    return Err((
                        format!("devices.{name}.transport.status_registers"),
                        format!(
                            "is {has} here but {other_has} on `{other}`, which is on the same module ({module}); every device on one module must agree"
                        ),
                    ));
                }
                Some(_) => {}
                None => {
                    seen.insert(module, (name, has));
                }
            }
        }
        Ok(())
    }

    fn need_direction(&self, name: &str) -> Result<(), (String, String)> {
        match self.devices[name].direction() {
            Some(d) if d.theta_deg.is_finite() && d.phi_deg.is_finite() => Ok(()),
            _ => Err((
                format!("devices.{name}.direction"),
                "expected {theta_deg, phi_deg}: where the device stands, seen from the sample"
                    .into(),
            )),
        }
    }
}

/// A device's name is part of file names (a laser run's MDF per camera)
/// and of every message about it: letters, digits, `-` and `_` only.
fn check_device_name(name: &str) -> Result<(), (String, String)> {
    let usable = (1..=64).contains(&name.chars().count())
        && name.chars().all(crate::model::text::is_file_name_char);
    if usable {
        Ok(())
    } else {
        Err((
            format!("devices.{}", name.escape_debug()),
            "a device's name has 1 to 64 letters, digits, `-` or `_`".into(),
        ))
    }
}

/// Each name appears once in a list of the rig's devices (`rig.lamps`,
/// `rig.cameras`): a lamp listed twice would be planned twice.
fn listed_once(key: &str, names: &[String]) -> Result<(), (String, String)> {
    for (i, name) in names.iter().enumerate() {
        if let Some(first) = names[..i].iter().position(|n| n == name) {
            return Err((
                format!("{key}[{i}]"),
                format!("`{name}` is listed twice (also {key}[{first}])"),
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One relay module has its status registers or has not: devices on
    /// it that disagree are refused, naming both; another module may differ.
    #[test]
    fn devices_on_one_module_agree_about_its_status_registers() {
        let text = virtex_text();
        let rtu = "transport = { type = \"modbus_rtu\", port = \"/dev/ttyUSB1\", baud = 19200, unit = 1 }";
        assert_eq!(text.matches(rtu).count(), 3, "fixture drifted");
        let coil_only = rtu.replace(" }", ", status_registers = false }");
        let all = text.replace(rtu, &coil_only);
        let p = Profile::parse(&all, "all.toml").expect("all three coil-only");
        assert!(p
            .devices
            .values()
            .filter(|d| d.kind() == DeviceKind::Lamp)
            .all(|d| !d.transport().status_registers()));

        let one = text.replacen(rtu, &coil_only, 1);
        let e = Profile::parse(&one, "one.toml").expect_err("disagreement");
        assert_eq!(e.key, "devices.lamp1.transport.status_registers");
        assert!(
            e.message.contains("is true here but false on `lamp0`"),
            "{e}"
        );
        assert!(e.message.contains("modbus-rtu:/dev/ttyUSB1#1"), "{e}");

        // On another unit it is another module.
        let other = one.replacen("unit = 1 }", "unit = 2 }", 2);
        Profile::parse(&other, "other.toml").expect("two modules");
    }

    /// The embedded VirTex profile's text.
    fn virtex_text() -> &'static str {
        EMBEDDED
            .iter()
            .find(|(n, _)| *n == "virtex-photometric-stereo")
            .map(|(_, t)| *t)
            .unwrap_or_default()
    }

    /// The VirTex camera moved to a GenICam transport, with `extra` lines
    /// in its table and the protocol and bit depth given.
    fn genicam_virtex(protocol: &str, bit_depth: u8, extra: &str) -> Result<Profile, ProfileError> {
        let text = genicam_virtex_text(protocol, extra)
            .replace("bit_depth = 12", &format!("bit_depth = {bit_depth}"));
        Profile::parse(&text, "genicam.toml")
    }

    /// The VirTex profile's text with its camera moved to a GenICam transport.
    fn genicam_virtex_text(protocol: &str, extra: &str) -> String {
        let text = virtex_text();
        let usb = "protocol = \"ptp\"\ntransport = { type = \"usb\", vendor_id = 0x04a9, product_id = 0x3200 }";
        assert!(text.contains(usb), "fixture drifted");
        let genicam = format!(
            "protocol = \"{protocol}\"\ntransport = {{ type = \"genicam\", id = \"192.168.1.20\" }}\n{extra}"
        );
        text.replace(usb, &genicam)
    }

    /// The VirTex profile's text with its camera on libgphoto2: `transport`
    /// and `protocol` as given, `extra` lines in its table.
    fn gphoto2_virtex(
        transport: &str,
        protocol: &str,
        extra: &str,
    ) -> Result<Profile, ProfileError> {
        let usb = "protocol = \"ptp\"\ntransport = { type = \"usb\", vendor_id = 0x04a9, product_id = 0x3200 }";
        assert!(virtex_text().contains(usb), "fixture drifted");
        let text = virtex_text().replace(
            usb,
            &format!("protocol = \"{protocol}\"\ntransport = {transport}\n{extra}"),
        );
        Profile::parse(&text, "gphoto2.toml")
    }

    #[test]
    fn a_gphoto2_camera_names_port_and_model_or_neither_and_its_widgets() {
        let p = gphoto2_virtex(
            r#"{ type = "gphoto2", port = "ptpip:127.0.0.1:15740:15740", model = "PTP/IP Camera" }"#,
            "gphoto2",
            r#"gphoto2 = { settings = { iso = "100", imageformat = "RAW" } }"#,
        )
        .expect("port, model and widgets");
        let cam = p.devices["camera"].as_camera().expect("a camera");
        assert_eq!(
            cam.transport,
            Transport::Gphoto2 {
                port: Some("ptpip:127.0.0.1:15740:15740".into()),
                model: Some("PTP/IP Camera".into()),
            }
        );
        let widgets = &cam.gphoto2.as_ref().expect("table").settings;
        assert_eq!(widgets.get("iso").map(String::as_str), Some("100"));
        gphoto2_virtex(r#"{ type = "gphoto2" }"#, "gphoto2", "").expect("autodetect");
        for (transport, protocol, extra, key, says) in [
            (
                r#"{ type = "gphoto2" }"#,
                "ptp",
                "",
                "devices.camera.protocol",
                "speaks `protocol = \"gphoto2\"`",
            ),
            (
                r#"{ type = "usb", vendor_id = 1, product_id = 2 }"#,
                "gphoto2",
                "",
                "devices.camera.protocol",
                "speaks `protocol = \"ptp\"`",
            ),
            (
                r#"{ type = "gphoto2", port = " " }"#,
                "gphoto2",
                "",
                "devices.camera.transport.port",
                "libgphoto2's port",
            ),
            (
                r#"{ type = "gphoto2", model = "" }"#,
                "gphoto2",
                "",
                "devices.camera.transport.model",
                "model name",
            ),
            (
                r#"{ type = "gphoto2" }"#,
                "gphoto2",
                r#"gphoto2 = { settings = { shutterspeed = "1/100" } }"#,
                "devices.camera.gphoto2.settings.shutterspeed",
                "timing.exposure_s",
            ),
            (
                r#"{ type = "gphoto2" }"#,
                "gphoto2",
                r#"gphoto2 = { settings = { "/main/iso" = "100" } }"#,
                "devices.camera.gphoto2.settings",
                "without its path",
            ),
            (
                r#"{ type = "gphoto2" }"#,
                "gphoto2",
                "ptp = { exposure_index = 100 }",
                "devices.camera.ptp",
                "protocol = \"ptp\"",
            ),
        ] {
            let e = gphoto2_virtex(transport, protocol, extra).expect_err(extra);
            assert_eq!(e.key, key, "{e}");
            assert!(e.message.contains(says), "{e}");
        }
        let e = Profile::parse(
            &virtex_text().replace(
                "protocol = \"ptp\"\n",
                "protocol = \"ptp\"\ngphoto2 = { settings = { iso = \"100\" } }\n",
            ),
            "x.toml",
        )
        .expect_err("a gphoto2 table on USB");
        assert_eq!(e.key, "devices.camera.gphoto2", "{e}");
    }

    #[test]
    fn a_ptp_camera_s_iso_is_positive_and_only_for_ptp() {
        let with = |text: String| Profile::parse(&text, "ptp.toml");
        let ptp = |extra: &str| {
            virtex_text().replace(
                "protocol = \"ptp\"\n",
                &format!("protocol = \"ptp\"\n{extra}\n"),
            )
        };
        let p = with(ptp("ptp = { exposure_index = 200 }")).expect("ISO 200");
        assert_eq!(
            p.devices["camera"]
                .as_camera()
                .and_then(|c| c.ptp)
                .and_then(|p| p.exposure_index),
            Some(200)
        );
        let e = with(ptp("ptp = { exposure_index = 0 }")).expect_err("ISO 0");
        assert_eq!(e.key, "devices.camera.ptp.exposure_index", "{e}");
        let e = with(genicam_virtex_text(
            "genicam",
            "ptp = { exposure_index = 100 }",
        ))
        .expect_err("not PTP");
        assert_eq!(e.key, "devices.camera.ptp", "{e}");
    }

    #[test]
    fn a_genicam_pixel_format_agrees_with_the_named_filter_array() {
        let with_cfa = |cfa: &str, format: &str| {
            let text = genicam_virtex_text(
                "genicam",
                &format!("genicam = {{ pixel_format = \"{format}\" }}"),
            )
            .replace("bit_depth = 12", &format!("bit_depth = 8, cfa = \"{cfa}\""));
            Profile::parse(&text, "genicam.toml")
        };
        let p = with_cfa("RGGB", "BayerRG8").expect("the same tile");
        assert_eq!(
            p.devices["camera"].intrinsics().and_then(|i| i.cfa),
            Some(rigd_core::Cfa::Rggb)
        );
        for format in ["BayerBG8", "Mono8"] {
            let e = with_cfa("RGGB", format).expect_err(format);
            assert_eq!(e.key, "devices.camera.genicam.pixel_format", "{e}");
            assert!(e.message.contains("RGGB filter array"), "{e}");
        }
    }

    #[test]
    fn a_genicam_camera_names_a_pixel_format_of_its_depth_and_a_trigger() {
        let p = genicam_virtex("genicam", 12, "").expect("Mono12 by default");
        let cam = p.devices["camera"].as_camera().expect("a camera");
        assert_eq!(
            GenicamSettings::pixel_format_for(cam.genicam.as_ref(), 12).map(|f| f.to_string()),
            Ok("Mono12".into())
        );
        genicam_virtex(
            "genicam",
            8,
            "genicam = { pixel_format = \"BayerRG8\", gain_db = 3.0, trigger_source = \"Line0\" }",
        )
        .expect("Bayer on a line trigger");
        for (protocol, depth, extra, key, says) in [
            (
                "ptp",
                12,
                "",
                "devices.camera.protocol",
                "speaks `protocol = \"genicam\"`",
            ),
            (
                "genicam",
                12,
                "genicam = { pixel_format = \"Mono8\" }",
                "devices.camera.genicam.pixel_format",
                "Mono8 has 8 bits, but intrinsics.bit_depth is 12",
            ),
            (
                "genicam",
                12,
                "genicam = { pixel_format = \"Mono12p\" }",
                "devices.camera.genicam.pixel_format",
                "packed formats",
            ),
            (
                "genicam",
                9,
                "",
                "devices.camera.genicam.pixel_format",
                "Mono10 has 10 bits",
            ),
            (
                "genicam",
                12,
                "genicam = { trigger_source = \"Soft\" }",
                "devices.camera.genicam.trigger_source",
                "`Software` or a line",
            ),
            (
                "genicam",
                12,
                "genicam = { gain_db = nan }",
                "devices.camera.genicam.gain_db",
                "finite gain",
            ),
        ] {
            let e = genicam_virtex(protocol, depth, extra).expect_err(extra);
            assert_eq!(e.key, key, "{e}");
            assert!(e.message.contains(says), "{says}: {e}");
        }
    }
}
