//! The simulated rig: each device of a profile gets its simulated firmware
//! (`rigd_sim::firmware`) on the far end of an in-memory pipe, and the real
//! driver on the near end. Pipes, not sockets: under paused (virtual) time
//! tokio advances the clock whenever every task waits, which is only sound
//! when no byte is in flight outside the runtime.
//!
//! All firmware of a rig share one [`SharedWorld`] (axis positions, arm
//! joints) and one [`FaultInjector`]; the cameras render what the world
//! holds when they expose, by forward kinematics of where the devices
//! physically are.
//!
//! This module is where the rest of rigd reaches the simulator: the
//! simulated rig here, its firmware served on ptys and sockets (`serve`,
//! `ptpip_serve`), one frame rendered on demand (`shot`), and the
//! simulator's types the command line and the daemon name.

use std::collections::BTreeMap;
use std::sync::Arc;

use async_trait::async_trait;
use rigd_core::Clock;
use rigd_core::Trapezoid;
use rigd_sim::devices::{CameraTimes, SimContext};
use rigd_sim::firmware::acl::{AclJoint, AclParams};
use rigd_sim::firmware::grbl::{Eeprom, GrblParams};
use rigd_sim::firmware::modbus::{LampSpec, ModbusModule, ModuleConfig};
use rigd_sim::firmware::ptp::{PtpCameraSpec, PtpFirmware};
use rigd_sim::links::{LineOpener, ModbusOpener};
use rigd_sim::scene::{LaserSheet, Scene as SceneModel, Shot};
use rigd_sim::{FaultInjector, SharedWorld};

pub use rigd_sim::scene::{Scene, SceneError};
pub use rigd_sim::settings::{SimGrblSettings, SimSettings};
pub use rigd_sim::{FaultRule, World};

pub mod ptpip_serve;
pub mod serve;
pub mod shot;

use crate::kinematics::camera::{camera_geometry, lamp_distances, CameraGeometry};
use crate::kinematics::{Setpoints, Solver};
use crate::model::profile::{Device, DeviceKind, Profile, SimTable, Transport};
use crate::rig::camera_file::DecodeIn;
use crate::rig::drivers::usb::{memory_pair, MemoryDevice, UsbError};
use crate::rig::hal::{DeviceError, ErrorKind, Fixture, Rig};
use crate::rig::{build_rig, BoxPipe, Framing, Link, PipeOpener};

/// Width (FWHM) and peak of the simulated laser strip.
const SIM_LASER_WIDTH_M: f64 = 1.0e-3;
const SIM_LASER_POWER: f64 = 12.0;

/// What a test or the command line may set on the simulated rig.
#[derive(Debug, Clone, Default)]
pub struct SimOptions {
    /// Frame size the cameras render; the profile's `[sim] frame_size` if None.
    pub frame_size: Option<[u32; 2]>,
    /// Faults the simulated firmware inject (`--sim-fault`), armed from the
    /// start.
    pub faults: Vec<FaultRule>,
}

/// The simulator's keys of a `[sim]` table, read and checked; `Err` names
/// the key (`sim.…`) and what was expected.
pub fn settings(table: &SimTable) -> Result<SimSettings, (String, String)> {
    use serde_value::{DeserializerError, Value};
    let keys = Value::Map(
        table
            .simulator
            .iter()
            .map(|(k, v)| (Value::String(k.clone()), v.clone()))
            .collect(),
    );
    let settings: SimSettings = crate::model::whole_value::typed(keys).map_err(
        |(path, e): (String, DeserializerError)| {
            let key = if path == "." {
                "sim".to_string()
            } else {
                format!("sim.{path}")
            };
            let message = match e {
                DeserializerError::UnknownField(field, keys) => format!(
                    "unknown field `{field}`, expected one of `frame_size`, `zoom`, `{}`",
                    keys.join("`, `")
                ),
                e => e.to_string(),
            };
            (key, message)
        },
    )?;
    settings.check()?;
    Ok(settings)
}

/// [`settings`] for a device's start: an error is the profile's.
fn settings_for_rig(profile: &Profile) -> Result<SimSettings, DeviceError> {
    settings(&profile.sim)
        .map_err(|(key, message)| DeviceError::new(&key, ErrorKind::NotReady, message))
}

/// The simulated rig wired into a run ([`crate::rig::Simulator`]), with the
/// faults its caller arms from the start (`--sim-fault`, the daemon's).
#[derive(Debug, Clone, Default)]
pub struct SimulatedRig {
    /// Faults armed from the start, after the profile's own.
    pub faults: Vec<FaultRule>,
}

impl SimulatedRig {
    /// The simulated rig with `faults` armed.
    pub fn new(faults: Vec<FaultRule>) -> SimulatedRig {
        SimulatedRig { faults }
    }
}

#[async_trait]
impl crate::rig::Simulator for SimulatedRig {
    fn scene(&self, profile: &Profile) -> Result<(String, Vec<String>), DeviceError> {
        lit_effects(profile)
    }

    async fn connect(
        &self,
        profile: &Profile,
        solver: Arc<Solver>,
        frame_size: Option<[u32; 2]>,
        starts: bool,
        clock: &Clock,
    ) -> Result<(Rig, SimHandle), DeviceError> {
        let mut faults = if starts {
            fault_rules(profile)?
        } else {
            Vec::new()
        };
        faults.extend(self.faults.iter().cloned());
        connect(profile, solver, SimOptions { frame_size, faults }, clock).await
    }
}

/// The `[sim]` table's fault rules, parsed ([`check_settings`] refuses a
/// profile with one that does not parse).
pub fn fault_rules(profile: &Profile) -> Result<Vec<FaultRule>, DeviceError> {
    Ok(settings_for_rig(profile)?
        .faults
        .iter()
        .filter_map(|f| f.parse().ok())
        .collect())
}

/// The scene the simulated cameras render: the `[sim]` table's, else the
/// simulator's default.
pub fn scene_name(settings: &SimSettings) -> &str {
    settings
        .scene
        .as_deref()
        .unwrap_or(rigd_sim::scene::DEFAULT_SCENE)
}

/// [`scene_name`] of a profile's `[sim]` table; `Err` when the table does
/// not read.
pub fn profile_scene(profile: &Profile) -> Result<String, DeviceError> {
    settings_for_rig(profile).map(|s| scene_name(&s).to_string())
}

/// Sets the scene a profile's simulated cameras render (recorded with the
/// run's profile, so a resume renders the same).
pub fn set_scene(profile: &mut Profile, scene: &str) {
    profile.sim.simulator.insert(
        "scene".into(),
        serde_value::Value::String(scene.to_string()),
    );
}

/// What only the simulator can check of a profile's `[sim]` table: its
/// keys and their values, its scene is a built-in one or a scene file, and
/// each fault parses and names a device of the profile (or a Modbus
/// module). `Err` names the key.
pub fn check_settings(profile: &Profile) -> Result<(), (String, String)> {
    let settings = settings(&profile.sim)?;
    if let Some(scene) = &settings.scene {
        let builtin = SceneModel::builtin_names();
        if !builtin.contains(&scene.as_str()) && !std::path::Path::new(scene).is_file() {
            return Err((
                "sim.scene".into(),
                format!(
                    "no built-in scene or scene file `{scene}` (built in: {})",
                    builtin.join(", ")
                ),
            ));
        }
    }
    for (i, f) in settings.faults.iter().enumerate() {
        let rule: FaultRule = f.parse().map_err(|e| (format!("sim.faults[{i}]"), e))?;
        if !profile.devices.contains_key(&rule.device) && !rule.device.starts_with("modbus-") {
            return Err((
                format!("sim.faults[{i}]"),
                format!(
                    "names device `{}`, but there is no [devices.{}]",
                    rule.device, rule.device
                ),
            ));
        }
    }
    Ok(())
}

/// The scene a profile's simulated cameras render, loaded once.
pub fn load_scene(profile: &Profile) -> Result<Arc<SceneModel>, DeviceError> {
    SceneModel::load_on(&profile_scene(profile)?, &profile.holder)
        .map_err(|e| DeviceError::new("sim.scene", ErrorKind::NotReady, e.to_string()))
}

/// The scene a profile's simulated cameras render, by name, and the
/// effects live in a frame it renders lit by a lamp (no laser).
pub fn lit_effects(profile: &Profile) -> Result<(String, Vec<String>), DeviceError> {
    let scene = load_scene(profile)?;
    let effects = scene
        .plan(&Shot::default())
        .live
        .names()
        .into_iter()
        .map(String::from)
        .collect();
    Ok((scene.name.clone(), effects))
}

/// Handles into a running simulated rig: its faults and its world.
#[derive(Clone)]
pub struct SimHandle {
    /// The rig's fault injector, shared by all its simulated devices: arm
    /// more faults while it runs, or clear a device's sticky ones.
    pub faults: Arc<FaultInjector>,
    world: SimWorld,
}

impl std::fmt::Debug for SimHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimHandle")
            .field("world", &self.world())
            .finish()
    }
}

impl SimHandle {
    /// Where every simulated device physically is, and which lamps are lit.
    pub fn world(&self) -> World {
        self.world.snapshot()
    }
}

/// One simulated relay module and how its bus is framed.
#[derive(Clone)]
pub(crate) struct SimModule {
    pub module: ModbusModule,
    /// The lamp on each coil (None: a coil no lamp of the profile uses).
    lamp_names: Vec<Option<String>>,
    pub framing: Framing,
    unit: u8,
}

/// The world the firmware publish, plus the lamp relays read from the
/// Modbus modules themselves.
#[derive(Clone)]
struct SimWorld {
    shared: SharedWorld,
    modules: Vec<SimModule>,
    /// Per arm joint, the angle at zero encoder counts.
    arm_home_deg: Vec<f64>,
}

impl SimWorld {
    fn snapshot(&self) -> World {
        let mut w = self.shared.snapshot();
        if let Some(q) = &mut w.arm {
            for (v, h) in q.iter_mut().zip(&self.arm_home_deg) {
                *v += h;
            }
        }
        for m in &self.modules {
            // Lamps, then the laser, in coil order.
            for (on, name) in m.module.coils().into_iter().zip(&m.lamp_names) {
                if let Some(n) = name {
                    w.lamps_on.insert(n.clone(), on);
                }
            }
        }
        w
    }
}

/// A bus key for devices that share one Modbus module.
pub(crate) fn bus_key(t: &Transport) -> String {
    t.modbus_module().unwrap_or_else(|| "usb".into())
}

/// Builds the simulated rig of a profile: firmware behind every device,
/// real drivers in front.
pub async fn connect(
    profile: &Profile,
    solver: Arc<Solver>,
    opts: SimOptions,
    clock: &Clock,
) -> Result<(Rig, SimHandle), DeviceError> {
    let faults = Arc::new(FaultInjector::new(opts.faults));
    let parts = firmware(profile, solver, opts.frame_size, clock, &faults)?;
    let mut rig = build_rig(profile, &parts.links, clock).await?;
    if crate::plan::laser::LaserRig::of(profile).is_some() {
        rig.fixture = Some(Box::new(SimPlate {
            world: parts.world.shared.clone(),
            clock: clock.clone(),
        }));
    }
    Ok((
        rig,
        SimHandle {
            faults,
            world: parts.world,
        },
    ))
}

/// `rig check` on the simulated rig: its firmware, as it powers up, checked
/// through the real drivers.
pub async fn check(
    profile: &Profile,
    solver: Arc<Solver>,
    clock: &Clock,
) -> Result<crate::rig::check::RigCheck, DeviceError> {
    let faults = Arc::new(FaultInjector::new(fault_rules(profile)?));
    let parts = firmware(profile, solver, Some([1, 1]), clock, &faults)?;
    Ok(crate::rig::check::check_rig(profile, &parts.links, clock).await)
}

/// The simulated firmware of a profile, ready to be connected: a link per
/// device, and what `rigd sim serve` needs to offer the same firmware on
/// ptys and sockets.
pub(crate) struct SimParts {
    pub links: BTreeMap<String, Link>,
    world: SimWorld,
    /// The relay modules, by bus key.
    pub modules: BTreeMap<String, SimModule>,
    /// The cameras' firmware starters, by device name.
    pub cameras: BTreeMap<String, Arc<PtpOpener>>,
}

/// Starts nothing yet: returns an opener per device that starts the
/// device's firmware on a fresh pipe each time the driver opens its link.
pub(crate) fn firmware(
    profile: &Profile,
    solver: Arc<Solver>,
    frame_size: Option<[u32; 2]>,
    clock: &Clock,
    faults: &Arc<FaultInjector>,
) -> Result<SimParts, DeviceError> {
    let mut cameras = BTreeMap::new();
    let shared = SharedWorld::new();
    let mut links = BTreeMap::new();
    let mut modules: BTreeMap<String, SimModule> = BTreeMap::new();
    let mut arm_home_deg = Vec::new();

    // Modbus modules first: cameras read their coils.
    let mut by_bus: BTreeMap<String, Vec<(&String, &Device)>> = BTreeMap::new();
    for (name, dev) in &profile.devices {
        if matches!(dev.kind(), DeviceKind::Lamp | DeviceKind::Laser) {
            by_bus
                .entry(bus_key(dev.transport()))
                .or_default()
                .push((name, dev));
        }
    }
    for (key, devs) in by_bus {
        let lamps: Vec<_> = devs
            .iter()
            .filter(|(_, d)| d.kind() == DeviceKind::Lamp)
            .collect();
        let n = lamps
            .iter()
            .map(|(_, d)| usize::from(d.coil().unwrap_or(0)) + 1)
            .max()
            .unwrap_or(0);
        let mut specs: Vec<LampSpec> = (0..n)
            .map(|k| LampSpec {
                name: format!("{key}/coil{k}"),
                warm_up_s: 0.0,
                switch_s: 0.0,
            })
            .collect();
        let mut names = vec![None; n];
        for (name, d) in &lamps {
            let k = usize::from(d.coil().unwrap_or(0));
            specs[k] = LampSpec {
                name: (*name).clone(),
                warm_up_s: d.as_lamp().map_or(0.0, |l| l.warm_up_s),
                switch_s: d.switch_s().unwrap_or(0.0),
            };
            names[k] = Some((*name).clone());
        }
        let laser = devs.iter().find(|(_, d)| d.kind() == DeviceKind::Laser);
        if let Some((lname, ld)) = laser {
            // The world reports the laser's relay beside the lamps'.
            names.push(Some((*lname).clone()));
            let coil = usize::from(ld.coil().unwrap_or(0));
            if coil != n {
                return Err(DeviceError::new(
                    lname,
                    ErrorKind::NotReady,
                    format!("the simulated module wires the laser on the coil after the lamps ({n}), not on coil {coil}"),
                ));
            }
        }
        let (framing, unit) = match devs[0].1.transport() {
            Transport::ModbusTcp { unit, .. } => (Framing::Tcp, *unit),
            Transport::ModbusRtu { unit, .. } => (Framing::Rtu, *unit),
            _ => (Framing::Tcp, 1),
        };
        let module = ModbusModule::new(
            ModuleConfig {
                unit,
                lamps: specs,
                laser: laser.map(|(n, _)| (*n).clone()),
                laser_switch_s: laser.and_then(|(_, d)| d.switch_s()).unwrap_or(0.0),
                status_registers: devs[0].1.transport().status_registers(),
                write_multiple_coils: true,
            },
            clock.clone(),
            faults.clone(),
        );
        modules.insert(
            key,
            SimModule {
                module,
                lamp_names: names,
                framing,
                unit,
            },
        );
    }

    for dev in profile.devices.values() {
        if let Some(arm) = dev.as_arm() {
            arm_home_deg = arm.joints.iter().map(|j| j.home_deg).collect();
        }
    }
    let world = SimWorld {
        shared: shared.clone(),
        modules: modules.values().cloned().collect(),
        arm_home_deg,
    };
    let size = frame_size.unwrap_or(profile.sim.frame_size);
    let sim = settings_for_rig(profile)?;
    let scene = load_scene(profile)?;
    tracing::info!("{}", scene.describe_effects());

    for (name, dev) in &profile.devices {
        let link = match dev {
            Device::Axis(axis) => {
                let home = axis.home_deg.unwrap_or(0.0);
                let motion = Trapezoid::from(axis.motion);
                let settings = match sim.grbl_settings {
                    SimGrblSettings::Factory => Eeprom::factory(),
                    SimGrblSettings::Configured => {
                        let travel = axis.limits.max - axis.limits.min;
                        // A board set up for its axis: its rates, its
                        // travel, and homing if the axis homes.
                        let e = Eeprom::configured(motion, axis.homing, travel);
                        if let Some(steps) = axis.steps_per_deg {
                            e.set(100, steps);
                        }
                        e
                    }
                };
                let params = GrblParams {
                    name: name.clone(),
                    motion,
                    home_position: home,
                    physical_start: home,
                    start_homed: false,
                    settings,
                    reset_on_open: sim.grbl_reset_on_open,
                    world: Some(shared.clone()),
                    answer_delay_s: sim.grbl_answer_delay_s,
                };
                let (clock, faults, world) = (clock.clone(), faults.clone(), shared.clone());
                Link::Line(Arc::new(LineOpener::new(params, clock, faults, world)))
            }
            Device::Arm(arm) => {
                let joints: Vec<AclJoint> = arm
                    .joints
                    .iter()
                    .map(|j| AclJoint {
                        counts_per_deg: j.counts_per_deg,
                        min_deg: j.limits.min - j.home_deg,
                        max_deg: j.limits.max - j.home_deg,
                        motion: Trapezoid::from(j.motion),
                    })
                    .collect();
                let n = joints.len();
                let params = AclParams {
                    name: name.clone(),
                    joints,
                    home_s: dev.homing_time_s(),
                    power_up_counts: vec![0; n],
                    start_homed: false,
                    world: Some(shared.clone()),
                };
                let (clock, faults, world) = (clock.clone(), faults.clone(), shared.clone());
                Link::Line(Arc::new(LineOpener::new(params, clock, faults, world)))
            }
            Device::Lamp(_) | Device::Laser(_) => {
                let key = bus_key(dev.transport());
                let Some(m) = modules.get(&key) else {
                    continue;
                };
                Link::Modbus {
                    bus: key.clone(),
                    opener: Arc::new(ModbusOpener::new(m.module.clone(), m.framing, key.clone())),
                    framing: m.framing,
                    unit: m.unit,
                    status_registers: dev.transport().status_registers(),
                }
            }
            Device::Camera(camera) => {
                let t = camera.timing;
                let Some(geometry) = camera_geometry(profile, name, size) else {
                    return Err(DeviceError::new(
                        name,
                        ErrorKind::NotReady,
                        "a camera needs intrinsics",
                    ));
                };
                let opener = Arc::new(PtpOpener {
                    spec: PtpCameraSpec {
                        name: name.clone(),
                        manufacturer: "rigd".into(),
                        model: "simulated PTP camera".into(),
                        version: env!("CARGO_PKG_VERSION").into(),
                        serial: name.clone(),
                        times: CameraTimes {
                            exposure_s: t.exposure_s,
                            readout_s: t.readout_s,
                            transfer_s: t.transfer_s,
                        },
                        cfa: camera.intrinsics.cfa,
                    },
                    ctx: SimContext::new(clock.clone(), faults.clone()),
                    view: CameraView {
                        camera: name.clone(),
                        solver: solver.clone(),
                        world: world.clone(),
                        size,
                        geometry,
                        lamp_distance_m: lamp_distances(profile),
                        laser: crate::plan::laser::LaserRig::of(profile),
                        holder_offset_m: sim.holder_offset_mm.map(|v| v * 1e-3),
                        cfa: camera.intrinsics.cfa,
                        lamp_drift: sim.lamp_drift,
                        clock: clock.clone(),
                    },
                    scene: scene.clone(),
                });
                cameras.insert(name.clone(), opener.clone());
                Link::Usb(opener)
            }
        };
        links.insert(name.clone(), link);
    }
    Ok(SimParts {
        links,
        world,
        modules,
        cameras,
    })
}

/// What a simulated camera sees: where it is and what the lamps do.
#[derive(Clone)]
struct CameraView {
    camera: String,
    solver: Arc<Solver>,
    world: SimWorld,
    size: [u32; 2],
    geometry: CameraGeometry,
    /// Per lamp: the geometry's own lamp distance is only the first lamp's.
    lamp_distance_m: BTreeMap<String, f64>,
    /// The laser unit, on rigs that have one.
    laser: Option<crate::plan::laser::LaserRig>,
    /// `[sim] holder_offset_mm`, metres.
    holder_offset_m: [f64; 2],
    /// The sensor's colour filter array (`intrinsics.cfa`); `None`: mono.
    cfa: Option<rigd_core::Cfa>,
    /// `[sim] lamp_drift`: the lamps' level over physical time.
    lamp_drift: Option<rigd_core::lamp_drift::LampDrift>,
    /// The rig's clock, whose time the lamps drift over.
    clock: Clock,
}

impl CameraView {
    /// Light and view in the sample frame, from where the devices really are.
    fn shot(&self) -> Shot {
        let world = self.world.snapshot();
        let laser_name = self.laser.as_ref().map(|l| l.laser.as_str());
        let lamp = world
            .lamps_on
            .iter()
            .find(|(n, on)| **on && Some(n.as_str()) != laser_name)
            .map(|(n, _)| n.clone());
        let laser = self.laser.as_ref().and_then(|rig| {
            if world.lamps_on.get(&rig.laser) != Some(&true) {
                return None;
            }
            let axis = |n: &str| world.axes.get(n).copied().unwrap_or(0.0);
            // The source's azimuth in the sample frame, as for a lamp on the arc.
            let azimuth = axis(&rig.light_arc) - axis(&rig.turntable);
            let (emitter, normal) = rig.geometry.plane(azimuth, axis(&rig.tilt_axis))?;
            // The emitter stands where the rig put it; the plate is offset.
            let [dx, dy] = self.holder_offset_m;
            Some(LaserSheet {
                emitter: [emitter[0] - dx, emitter[1] - dy, emitter[2]],
                normal,
                width_m: SIM_LASER_WIDTH_M,
                power: SIM_LASER_POWER,
            })
        });
        // The view does not depend on the lamp, but forward kinematics
        // needs one: with every lamp dark (laser frames), any lamp will do.
        let any_lamp = world
            .lamps_on
            .keys()
            .find(|n| Some(n.as_str()) != laser_name)
            .cloned();
        let setpoints = Setpoints {
            axes: world.axes,
            arm: world.arm,
            lamp: lamp.clone().or(any_lamp).unwrap_or_default(),
            plate_mm: None,
        };
        let dark = [0.0, 0.0, -1.0];
        let (light, view) = match self.solver.forward(&setpoints, &self.camera) {
            Ok((l, v)) => (l.to_vector(), v.to_vector()),
            // Devices not yet where forward kinematics needs them: render the
            // holder unlit rather than invent a pose.
            Err(_) => (dark, [0.0, 0.0, 1.0]),
        };
        Shot {
            light: if lamp.is_some() { light } else { dark },
            view,
            width: self.size[0],
            height: self.size[1],
            bit_depth: self.geometry.bit_depth,
            focal_px: Some(self.geometry.focal_px),
            camera_distance_m: self.geometry.distance_m,
            lamp_distance_m: lamp.and_then(|l| self.lamp_distance_m.get(&l).copied()),
            laser,
            plate_height_m: world.plate_mm.map(|h| h * 1e-3),
            holder_offset_m: self.holder_offset_m,
            cfa: self.cfa,
            lamp_level: self.lamp_drift.map_or(1.0, |d| d.level(self.clock.now_s())),
            ..Shot::default()
        }
    }
}

/// Starts the camera's PTP firmware on a fresh in-memory USB link per open.
pub(crate) struct PtpOpener {
    spec: PtpCameraSpec,
    ctx: SimContext,
    view: CameraView,
    scene: Arc<SceneModel>,
}

impl PtpOpener {
    /// The camera's model, as its DeviceInfo names it.
    pub(crate) fn model(&self) -> &str {
        &self.spec.model
    }

    /// Starts the camera's firmware on the device end of a link.
    pub(crate) fn start(&self, dev: MemoryDevice) {
        let view = self.view.clone();
        let fw = PtpFirmware::new(
            self.spec.clone(),
            self.ctx.clone(),
            Box::new(move || view.shot()),
        )
        .with_scene(self.scene.clone());
        fw.spawn(dev);
    }
}

#[async_trait]
impl PipeOpener for PtpOpener {
    fn describe(&self) -> String {
        format!("simulated PTP camera `{}`", self.spec.name)
    }

    async fn open(&self) -> Result<BoxPipe, UsbError> {
        let (host, dev) = memory_pair();
        self.start(dev);
        Ok(Box::new(host))
    }

    fn decode_in(&self) -> DecodeIn {
        DecodeIn::ThisProcess
    }
}

/// The simulated operator: moves the plate in the simulated world.
pub struct SimPlate {
    /// The world the plate is placed in.
    pub world: SharedWorld,
    /// The clock the operator's time passes on.
    pub clock: Clock,
}

#[async_trait]
impl Fixture for SimPlate {
    async fn place(&mut self, height_mm: Option<f64>) -> Result<(), DeviceError> {
        if self.world.snapshot().plate_mm == height_mm {
            return Ok(());
        }
        // The operator takes the time the estimate allows.
        self.clock
            .sleep_s(crate::schedule::timing::PLATE_CHANGE_S)
            .await;
        self.world.set_plate(height_mm);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{ByteStream, Opener};
    use std::time::Duration;

    /// A link that takes `delay` to open, like a board that resets when its
    /// port opens and boots before it answers.
    struct SlowLine(Arc<dyn Opener>, Clock, Duration);

    #[async_trait]
    impl Opener for SlowLine {
        fn describe(&self) -> String {
            self.0.describe()
        }
        async fn open(&self) -> std::io::Result<ByteStream> {
            self.1.sleep(self.2).await;
            self.0.open().await
        }
    }

    /// A camera that takes `delay` to enumerate.
    struct SlowPipe(Arc<dyn PipeOpener>, Clock, Duration);

    #[async_trait]
    impl PipeOpener for SlowPipe {
        fn describe(&self) -> String {
            self.0.describe()
        }
        async fn open(&self) -> Result<BoxPipe, UsbError> {
            self.1.sleep(self.2).await;
            self.0.open().await
        }
        fn decode_in(&self) -> DecodeIn {
            self.0.decode_in()
        }
    }

    fn slow(link: Link, clock: &Clock, delay: Duration) -> Link {
        let c = clock.clone();
        match link {
            Link::Line(o) => Link::Line(Arc::new(SlowLine(o, c, delay))),
            Link::Modbus {
                bus,
                opener,
                framing,
                unit,
                status_registers,
            } => Link::Modbus {
                bus,
                opener: Arc::new(SlowLine(opener, c, delay)),
                framing,
                unit,
                status_registers,
            },
            Link::Usb(o) => Link::Usb(Arc::new(SlowPipe(o, c, delay))),
            own @ (Link::Genicam(_) | Link::Gphoto2(_)) => own,
        }
    }

    /// Physical seconds `build_rig` takes on the MSRA rig when every link
    /// takes `delay` to open.
    async fn msra_connect_time(delay: Duration) -> f64 {
        let profile = Profile::load("msra-btf-mdf").expect("profile");
        let solver = Arc::new(Solver::new(&profile).expect("solver"));
        let clock = Clock::virtual_time();
        let faults = Arc::new(FaultInjector::new(vec![]));
        let parts = firmware(&profile, solver, Some([1, 1]), &clock, &faults).expect("firmware");
        let links = parts
            .links
            .into_iter()
            .map(|(name, link)| (name, slow(link, &clock, delay)))
            .collect();
        let t0 = clock.now_s();
        let rig = build_rig(&profile, &links, &clock).await.expect("connect");
        assert_eq!((rig.axes.len(), rig.cameras.len()), (3, 8));
        assert_eq!((rig.lamps.len(), rig.lasers.len()), (8, 1));
        clock.now_s() - t0
    }

    #[tokio::test(start_paused = true)]
    async fn a_rig_connects_in_its_slowest_devices_time_not_the_sum() {
        let at_once = msra_connect_time(Duration::ZERO).await;
        let slow = msra_connect_time(Duration::from_secs(1)).await;
        // Three axes, eight cameras and one relay module one after another
        // would add 12 s; at once they add the one second.
        let added = slow - at_once;
        assert!((1.0..1.5).contains(&added), "1 s per link added {added} s");
    }
}
