//! Builds a profile's [`Rig`] from the real protocol drivers, over links an
//! opener provides: serial ports, TCP and USB on hardware ([`hardware`]),
//! or in-memory pipes to the simulated firmware ([`sim`]). Either way the
//! same driver code runs; only the wire differs.
//!
//! Every device is wrapped so that a lost link is re-opened (and the
//! driver re-synchronised from what the device reports) on the next call,
//! which is how a run resumes after a disconnect once the operator has
//! fixed the cable.

pub mod camera_file;
pub mod check;
pub mod drivers;
pub mod hal;
pub mod hardware;
pub mod plate;
mod relink;
#[cfg(feature = "sim")]
pub mod sim;

#[cfg(feature = "sim")]
pub use sim::FaultRule;
#[cfg(feature = "sim")]
pub use sim::SimHandle;

/// A fault to inject into the simulated firmware; a build without the
/// simulator has none to inject.
#[cfg(not(feature = "sim"))]
#[derive(Debug, Clone)]
pub enum FaultRule {}

/// The simulated rig of a run; a build without the simulator has none.
#[cfg(not(feature = "sim"))]
#[derive(Debug, Clone)]
pub enum SimHandle {}

/// The simulated rig with `faults` armed, for the command line and the
/// daemon to wire into their runs; None in a build without the simulator
/// (a simulated run is then refused).
pub fn simulated_rig(faults: Vec<FaultRule>) -> Option<Box<dyn Simulator>> {
    #[cfg(feature = "sim")]
    return Some(Box::new(sim::SimulatedRig::new(faults)));
    #[cfg(not(feature = "sim"))]
    {
        let _ = faults;
        None
    }
}

/// The simulated rig as the command line, the daemon and the tests wire it
/// into a run (`sim::SimulatedRig`): the engine connects a simulated run
/// through it and builds no simulator itself.
#[async_trait::async_trait]
pub trait Simulator: Send + Sync {
    /// The scene the simulated cameras render for `profile`, and the
    /// effects its lit frames show, as a new run records them.
    fn scene(&self, profile: &Profile) -> Result<(String, Vec<String>), DeviceError>;
    /// Connects the simulated rig of `profile`, its cameras rendering
    /// frames of `frame_size` (None: the profile's). A run that `starts`
    /// arms the profile's own faults too; a resumed one only the caller's.
    async fn connect(
        &self,
        profile: &Profile,
        solver: Arc<crate::kinematics::Solver>,
        frame_size: Option<[u32; 2]>,
        starts: bool,
        clock: &Clock,
    ) -> Result<(Rig, SimHandle), DeviceError>;
}

use std::collections::BTreeMap;
use std::fmt;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use futures::future::join_all;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio_modbus::client::Context;
use tokio_modbus::Slave;

use crate::model::profile::{Device, DeviceKind, Profile, ProfileError};
use crate::rig::camera_file::DecodeIn;
use crate::rig::drivers::acl::{AclArm, AclConfig, AclJointConfig};
use crate::rig::drivers::genicam::{GenicamCamera, GenicamConfig, GenicamOpener};
use crate::rig::drivers::gphoto2::{Gphoto2Camera, Gphoto2Config, Gphoto2Opener};
use crate::rig::drivers::grbl::{GrblAxis, GrblConfig};
use crate::rig::drivers::modbus::{all_off, ModbusConfig, ModbusLamp, ModbusLaser, SharedBus};
use crate::rig::drivers::ptp::{PtpCamera, PtpConfig};
use crate::rig::drivers::usb::{PtpPipe, UsbError};
use crate::rig::hal::{
    Arm, Axis, Camera, DeviceError, EmergencyStop, ErrorKind, Lamp, LaserLine, Rig,
};
use relink::{lost_link, Line, Linked, OnLine, PtpOnUsb};
use rigd_core::Clock;

pub use rigd_hal::{ByteLink, ByteStream, Opener};

/// A boxed USB pipe: a real camera or the simulated one.
pub type BoxPipe = Box<dyn PtpPipe>;

/// Opens (and re-opens) the USB pipe of one camera.
#[async_trait]
pub trait PipeOpener: Send + Sync {
    /// Where the pipe goes, for error messages.
    fn describe(&self) -> String;
    /// Opens a fresh pipe; called again after the camera is lost.
    async fn open(&self) -> Result<BoxPipe, UsbError>;
    /// Where the camera's files are decoded: in a child, unless the camera
    /// runs in this process.
    fn decode_in(&self) -> DecodeIn {
        DecodeIn::Child
    }
}

/// Modbus framing on a byte stream: the wire codecs' own type.
pub use rigd_proto::modbus::Framing;

/// How one device is reached.
#[derive(Clone)]
pub enum Link {
    /// A line-protocol serial device (GRBL, ACL).
    Line(Arc<dyn Opener>),
    /// A coil on a Modbus module; devices with the same `bus` share it.
    Modbus {
        /// The bus's identity (e.g. `modbus-tcp:HOST:PORT#UNIT`): devices with
        /// the same bus share one connection and one emergency stop.
        bus: String,
        /// Opens the bus's byte stream.
        opener: Arc<dyn Opener>,
        /// RTU (CRC-16 per frame) or TCP (MBAP header) framing on that stream.
        framing: Framing,
        /// The module's Modbus unit (slave) address.
        unit: u8,
        /// Whether the module has the ready and fault input registers.
        status_registers: bool,
    },
    /// A USB camera.
    Usb(Arc<dyn PipeOpener>),
    /// A GenICam camera (Aravis opens it by IP address or device id).
    Genicam(Arc<dyn GenicamOpener>),
    /// A camera through libgphoto2 (by its port and model).
    Gphoto2(Arc<dyn Gphoto2Opener>),
}

/// Deadline for opening a link (physical time).
const OPEN_TIMEOUT: Duration = Duration::from_secs(10);

fn link_error(device: &str, what: &str, e: impl fmt::Display) -> DeviceError {
    DeviceError::new(device, ErrorKind::Disconnected, format!("{what}: {e}"))
}

async fn open_stream(
    clock: &Clock,
    device: &str,
    opener: &dyn Opener,
) -> Result<ByteStream, DeviceError> {
    match clock.deadline(OPEN_TIMEOUT, opener.open()).await {
        Ok(Ok(s)) => Ok(s),
        Ok(Err(e)) => Err(link_error(
            device,
            &format!("cannot open {}", opener.describe()),
            e,
        )),
        Err(_) => Err(DeviceError::new(
            device,
            ErrorKind::Timeout,
            format!("opening {} took over {OPEN_TIMEOUT:?}", opener.describe()),
        )),
    }
}

/// How long a camera that says it is busy is given before it is asked
/// again, within [`OPEN_TIMEOUT`].
const BUSY_RETRY: Duration = Duration::from_millis(250);

/// Opens a camera's link. A camera still held by a session that has just
/// ended (its initiator closed the connection, and the camera has not yet
/// seen it go) answers "busy": it is asked again until [`OPEN_TIMEOUT`].
async fn open_pipe(
    clock: &Clock,
    device: &str,
    opener: &dyn PipeOpener,
) -> Result<BoxPipe, DeviceError> {
    let mut busy = None;
    let opening = async {
        loop {
            match opener.open().await {
                Err(UsbError::Busy(why)) => {
                    busy = Some(why);
                    clock.sleep(BUSY_RETRY).await;
                }
                other => return other,
            }
        }
    };
    let cannot_open = format!("cannot open {}", opener.describe());
    match clock.deadline(OPEN_TIMEOUT, opening).await {
        Ok(Ok(p)) => Ok(p),
        Ok(Err(e)) => Err(link_error(device, &cannot_open, e)),
        Err(_) => Err(match busy {
            Some(why) => link_error(
                device,
                &cannot_open,
                format!("{why}, for over {OPEN_TIMEOUT:?}"),
            ),
            None => DeviceError::new(
                device,
                ErrorKind::Timeout,
                format!("opening {} took over {OPEN_TIMEOUT:?}", opener.describe()),
            ),
        }),
    }
}

fn modbus_context(stream: ByteStream, framing: Framing, unit: u8) -> Context {
    match framing {
        Framing::Tcp => tokio_modbus::client::tcp::attach_slave(stream, Slave(unit)),
        Framing::Rtu => tokio_modbus::client::rtu::attach_slave(stream, Slave(unit)),
    }
}

/// The ACL joint set-up of an arm device.
pub fn acl_joints(dev: &Device) -> Vec<AclJointConfig> {
    dev.as_arm()
        .map(|a| a.joints.as_slice())
        .unwrap_or_default()
        .iter()
        .map(|j| AclJointConfig {
            name: j.name.clone(),
            limits: j.limits,
            motion: j.motion,
            counts_per_deg: j.counts_per_deg,
            home_deg: j.home_deg,
        })
        .collect()
}

/// What a device said of itself at connect, for `rig check`.
pub(crate) struct Identity {
    /// Identity, firmware, settings, position: one line.
    about: String,
    /// Connected, but not usable as it stands: what is wrong, and the fix.
    unusable: Option<(String, String)>,
}

impl Identity {
    fn usable(about: String) -> Identity {
        Identity {
            about,
            unusable: None,
        }
    }
}

/// Loads a profile as the command line and the daemon use it:
/// [`crate::plan::load_profile`], then, with the simulator built in, its
/// `[sim]` table's scene and faults checked by the simulator
/// ([`sim::check_settings`]); without it the table is kept as written.
pub fn load_profile(spec: &str) -> Result<Profile, ProfileError> {
    let profile = crate::plan::load_profile(spec)?;
    #[cfg(feature = "sim")]
    sim::check_settings(&profile).map_err(|(key, message)| ProfileError {
        file: Profile::origin(spec),
        key,
        message,
    })?;
    Ok(profile)
}

/// One line device or camera, connected.
pub(crate) enum Connected {
    Axis(Box<dyn Axis>, Arc<dyn EmergencyStop>),
    Arm(Box<dyn Arm>, Arc<dyn EmergencyStop>),
    Camera(Box<dyn Camera>),
}

/// How a device is reached, checked before anything is opened.
enum Wiring<'a> {
    /// A line device or a camera, connected on its own link.
    Own(&'a Device, Link),
    /// A coil on the Modbus bus of that name.
    Coil(&'a Device, String),
}

/// A Modbus bus to open: its opener, framing, unit, and the first device on
/// it in profile order (its errors are reported under that device's name).
struct BusLink {
    opener: Arc<dyn Opener>,
    framing: Framing,
    unit: u8,
    status_registers: bool,
    first_device: String,
}

/// Connects every device of a profile through its link and returns the rig,
/// with one emergency stop per line device and per Modbus bus.
///
/// Every device and bus connects at once, each under its own deadlines, so
/// bringing up a rig takes its slowest device's time, not the sum (three
/// GRBL boards waiting for their banners, eight cameras opening sessions).
/// When devices fail, the first in profile order is the error returned, and
/// its message names the others (their reasons are logged).
pub async fn build_rig(
    profile: &Profile,
    links: &BTreeMap<String, Link>,
    clock: &Clock,
) -> Result<Rig, DeviceError> {
    let mut wiring: Vec<(&String, Wiring<'_>)> = Vec::new();
    let mut bus_links: BTreeMap<String, BusLink> = BTreeMap::new();
    for (name, dev) in &profile.devices {
        let link = links.get(name).cloned().ok_or_else(|| {
            DeviceError::new(
                name,
                ErrorKind::NotReady,
                "no link configured for this device",
            )
        })?;
        match (dev.kind(), link) {
            (DeviceKind::Axis | DeviceKind::Arm, link @ Link::Line(_))
            | (DeviceKind::Camera, link @ (Link::Usb(_) | Link::Genicam(_) | Link::Gphoto2(_))) => {
                wiring.push((name, Wiring::Own(dev, link)));
            }
            (
                DeviceKind::Lamp | DeviceKind::Laser,
                Link::Modbus {
                    bus,
                    opener,
                    framing,
                    unit,
                    status_registers,
                },
            ) => {
                bus_links.entry(bus.clone()).or_insert_with(|| BusLink {
                    opener,
                    framing,
                    unit,
                    status_registers,
                    first_device: name.clone(),
                });
                wiring.push((name, Wiring::Coil(dev, bus)));
            }
            _ => return Err(wrong_transport(name, dev)),
        }
    }
    let devices = join_all(wiring.iter().filter_map(|(name, w)| match w {
        Wiring::Own(dev, link) => Some(async move {
            (
                name.to_string(),
                connect_device(name, dev, link.clone(), clock)
                    .await
                    .map(|(c, _)| c),
            )
        }),
        Wiring::Coil(..) => None,
    }));
    let streams = join_all(bus_links.iter().map(|(bus, l)| async move {
        let stream = open_stream(clock, &l.first_device, l.opener.as_ref()).await;
        (bus.clone(), stream)
    }));
    let (devices, streams) = tokio::join!(devices, streams);
    let mut devices: BTreeMap<String, Result<Connected, DeviceError>> =
        devices.into_iter().collect();
    let mut buses: BTreeMap<String, Arc<Bus>> = BTreeMap::new();
    let mut bus_failures: BTreeMap<String, DeviceError> = BTreeMap::new();
    for (bus, stream) in streams {
        let Some(l) = bus_links.remove(&bus) else {
            continue;
        };
        match stream {
            Ok(stream) => {
                let shared = Arc::new(Bus {
                    name: bus.clone(),
                    bus: Arc::new(tokio::sync::Mutex::new(modbus_context(
                        stream, l.framing, l.unit,
                    ))),
                    opener: l.opener,
                    framing: l.framing,
                    unit: l.unit,
                    status_registers: l.status_registers,
                    clock: clock.clone(),
                    lost: AtomicBool::new(false),
                    coils: std::sync::atomic::AtomicU16::new(0),
                });
                buses.insert(bus, shared);
            }
            Err(e) => {
                bus_failures.insert(bus, e);
            }
        }
    }
    let mut rig = Rig::default();
    let mut failures = Vec::new();
    for (name, w) in wiring {
        match w {
            Wiring::Own(..) => match devices.remove(name) {
                Some(Ok(Connected::Axis(axis, stop))) => {
                    rig.stops.insert(name.clone(), stop);
                    rig.axes.insert(name.clone(), axis);
                }
                Some(Ok(Connected::Arm(arm, stop))) => {
                    rig.stops.insert(name.clone(), stop);
                    rig.arms.insert(name.clone(), arm);
                }
                Some(Ok(Connected::Camera(cam))) => {
                    rig.cameras.insert(name.clone(), cam);
                }
                Some(Err(e)) => failures.push(e),
                None => {}
            },
            Wiring::Coil(dev, bus) => {
                let Some(shared) = buses.get(&bus) else {
                    // Reported once, under the bus's first device.
                    failures.extend(bus_failures.remove(&bus));
                    continue;
                };
                let coil = dev.coil().unwrap_or(0);
                shared.coils.fetch_max(coil + 1, Ordering::SeqCst);
                let mut cfg = ModbusConfig::new(
                    name,
                    coil,
                    Duration::from_secs_f64(dev.as_lamp().map_or(0.0, |l| l.warm_up_s)),
                    Duration::from_secs_f64(dev.switch_s().unwrap_or(0.0)),
                );
                cfg.status_registers = shared.status_registers;
                if dev.kind() == DeviceKind::Lamp {
                    let lamp = ModbusLamp::new(cfg, clock.clone(), shared.bus.clone());
                    rig.lamps.insert(
                        name.clone(),
                        Box::new(LinkedLamp {
                            lamp,
                            bus: shared.clone(),
                        }),
                    );
                } else {
                    let laser = ModbusLaser::new(cfg, clock.clone(), shared.bus.clone());
                    rig.lasers.insert(
                        name.clone(),
                        Box::new(LinkedLaser {
                            laser,
                            bus: shared.clone(),
                        }),
                    );
                }
            }
        }
    }
    let mut failures = failures.into_iter();
    if let Some(mut first) = failures.next() {
        // One error, naming every device that failed (the log has their
        // reasons), so bring-up sees all that is wrong at once.
        let others: Vec<String> = failures
            .map(|e| {
                tracing::info!("{e}");
                e.device
            })
            .collect();
        if !others.is_empty() {
            first.message = format!("{} (also failed: {})", first.message, others.join(", "));
        }
        return Err(first);
    }
    for (name, bus) in buses {
        rig.stops.insert(name, Arc::new(BusStop(bus)));
    }
    Ok(rig)
}

/// Opens and connects one line device or camera, and says what it found.
/// The PTP driver's settings for camera `name`: the default deadlines, and
/// the sensor layout its profile describes.
fn ptp_config(name: &str, dev: &Device) -> PtpConfig {
    PtpConfig {
        cfa: dev.intrinsics().and_then(|i| i.cfa),
        cfa_key: format!("devices.{name}.intrinsics.cfa"),
        exposure_index: dev
            .as_camera()
            .and_then(|c| c.ptp)
            .and_then(|p| p.exposure_index),
        ..PtpConfig::default()
    }
}

pub(crate) async fn connect_device(
    name: &str,
    dev: &Device,
    link: Link,
    clock: &Clock,
) -> Result<(Connected, Identity), DeviceError> {
    match (dev, link) {
        (Device::Axis(axis_dev), Link::Line(opener)) => {
            let stream = open_stream(clock, name, opener.as_ref()).await?;
            let mut cfg = GrblConfig::new(name, axis_dev.limits, axis_dev.motion);
            cfg.homing = axis_dev.homing;
            cfg.configure = axis_dev.configure;
            cfg.steps_per_deg = axis_dev.steps_per_deg;
            let axis = GrblAxis::connect(stream, cfg, clock.clone()).await?;
            tracing::info!(device = %name, version = ?axis.version(), "GRBL axis connected");
            let identity = grbl_identity(&axis);
            let stop = Arc::new(axis.stopper());
            Ok((
                Connected::Axis(
                    Box::new(Linked::new(OnLine {
                        driver: axis,
                        line: Line {
                            name: name.to_string(),
                            opener,
                            clock: clock.clone(),
                        },
                    })),
                    stop,
                ),
                identity,
            ))
        }
        (Device::Arm(_), Link::Line(opener)) => {
            let stream = open_stream(clock, name, opener.as_ref()).await?;
            let cfg = AclConfig::new(name, acl_joints(dev));
            let arm = AclArm::connect(stream, cfg, clock.clone()).await?;
            tracing::info!(device = %name, "ACL arm connected");
            let joints = arm.last_joints().map_or("unknown".to_string(), |j| {
                j.iter()
                    .map(|x| format!("{x:.3}°"))
                    .collect::<Vec<_>>()
                    .join(", ")
            });
            let identity = Identity::usable(format!("ACL arm; joints at {joints}"));
            let stop = Arc::new(arm.stopper());
            Ok((
                Connected::Arm(
                    Box::new(Linked::new(OnLine {
                        driver: arm,
                        line: Line {
                            name: name.to_string(),
                            opener,
                            clock: clock.clone(),
                        },
                    })),
                    stop,
                ),
                identity,
            ))
        }
        (Device::Camera(_), Link::Usb(opener)) => {
            let pipe = open_pipe(clock, name, opener.as_ref()).await?;
            let config = PtpConfig {
                decode_in: opener.decode_in(),
                ..ptp_config(name, dev)
            };
            let mut cam = PtpCamera::new(name, pipe, clock.clone(), config.clone());
            let info = cam
                .connect()
                .await
                .map_err(|e| DeviceError::new(name, e.kind(), e.to_string()))?;
            tracing::info!(device = %name, model = %info.model, serial = %info.serial_number, "PTP camera connected");
            let identity = Identity::usable(format!(
                "PTP camera {} {}, firmware {}, serial {}",
                info.manufacturer, info.model, info.device_version, info.serial_number
            ));
            Ok((
                Connected::Camera(Box::new(Linked::new(PtpOnUsb {
                    cam,
                    name: name.to_string(),
                    config,
                    opener,
                    clock: clock.clone(),
                    exposure_s: None,
                }))),
                identity,
            ))
        }
        (Device::Camera(_), Link::Genicam(opener)) => {
            let Some(cfg) = GenicamConfig::of(name, dev) else {
                return Err(wrong_transport(name, dev));
            };
            let format = cfg.pixel_format;
            let [w, h] = cfg.size;
            let source = cfg.trigger_source.clone();
            let connect = GenicamCamera::connect(cfg, opener, clock.clone());
            let (cam, id) = match clock.deadline(OPEN_TIMEOUT, connect).await {
                Ok(connected) => connected?,
                Err(_) => {
                    return Err(DeviceError::new(
                        name,
                        ErrorKind::Timeout,
                        format!("opening the GenICam camera took over {OPEN_TIMEOUT:?}"),
                    ))
                }
            };
            tracing::info!(
                device = %name,
                vendor = %id.vendor,
                model = %id.model,
                serial = %id.serial,
                "GenICam camera connected"
            );
            let identity = Identity::usable(format!(
                "GenICam camera {} {}, serial {}, version {}; {format} {w}x{h}, trigger {source}; at {}",
                id.vendor,
                id.model,
                id.serial,
                id.version,
                cam.describe()
            ));
            Ok((Connected::Camera(Box::new(cam)), identity))
        }
        (Device::Camera(_), Link::Gphoto2(opener)) => {
            let Some(cfg) = Gphoto2Config::of(name, dev) else {
                return Err(wrong_transport(name, dev));
            };
            // The driver holds its own deadlines (the open's included), on
            // the clock it is given.
            let (cam, id) = Gphoto2Camera::connect(cfg, opener, clock.clone()).await?;
            let widgets = id
                .widgets
                .iter()
                .map(|(w, v)| format!("{w} {v}"))
                .collect::<Vec<_>>()
                .join(", ");
            let said = [("firmware", &id.version), ("serial", &id.serial)]
                .iter()
                .filter(|(_, v)| !v.is_empty())
                .map(|(k, v)| format!(", {k} {v}"))
                .collect::<String>();
            // A camera that names neither maker nor model is named by
            // libgphoto2's model alone, in the parentheses.
            let named = [id.manufacturer.as_str(), id.model.as_str()]
                .iter()
                .filter(|s| !s.is_empty())
                .map(|s| format!(" {s}"))
                .collect::<String>();
            let identity = Identity::usable(format!(
                "libgphoto2 camera{named}{said} (libgphoto2 model `{}` on `{}`); set {widgets}",
                id.driver_model, id.port
            ));
            Ok((Connected::Camera(Box::new(cam)), identity))
        }
        _ => Err(wrong_transport(name, dev)),
    }
}

/// A GRBL axis's firmware, settings, homing mode and state; an axis
/// without homing must stand Idle, where the operator zeroed it.
fn grbl_identity<S>(axis: &GrblAxis<S>) -> Identity
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let cfg = axis.config();
    let settings = cfg
        .expected_settings()
        .iter()
        .filter_map(|e| {
            let v = axis.settings().get(&e.number)?;
            Some(format!(
                "${}={}",
                e.number,
                rigd_proto::grbl::format_setting(e.number, *v)
            ))
        })
        .collect::<Vec<_>>()
        .join(" ");
    let homing = if cfg.homing {
        "homes with `$H`"
    } else {
        "no homing: zeroed by the operator at its 0° mark"
    };
    let status = axis.last_status();
    let state = status.map(|s| s.state);
    let at = status
        .and_then(|s| s.x())
        .map_or("unknown".to_string(), |x| format!("{x:.3}°"));
    let mut state_text = state.map_or("unknown".to_string(), |s| s.to_string());
    if cfg.homing && state == Some(rigd_proto::grbl::MachineState::Alarm) {
        state_text.push_str(" (until homed)");
    }
    let about = format!(
        "GRBL {}; settings match the profile ({settings}); {homing}; {state_text} at MPos {at}",
        axis.version().unwrap_or("?")
    );
    let unusable = (!cfg.homing && state != Some(rigd_proto::grbl::MachineState::Idle)).then(|| {
        (
            format!("an axis without homing must be Idle, and the controller is {state_text}"),
            "set the axis at its 0° mark, reset the controller there (MPos 0), and unlock it with `$X` if it is in Alarm".to_string(),
        )
    });
    Identity { about, unusable }
}

/// A device kind and link that do not go together (a lamp on a serial line).
fn wrong_transport(name: &str, dev: &Device) -> DeviceError {
    DeviceError::new(
        name,
        ErrorKind::NotReady,
        format!(
            "{} cannot use protocol `{}` over this transport",
            dev.kind().with_article(),
            dev.protocol()
        ),
    )
}

/// One Modbus module's connection, shared by its lamps and laser.
struct Bus {
    name: String,
    bus: SharedBus,
    opener: Arc<dyn Opener>,
    framing: Framing,
    unit: u8,
    /// Whether the module has the ready and fault input registers.
    status_registers: bool,
    clock: Clock,
    lost: AtomicBool,
    /// Coils in use (highest coil + 1), for the all-off stop.
    coils: std::sync::atomic::AtomicU16,
}

impl Bus {
    async fn ready(&self) -> Result<(), DeviceError> {
        if self.lost.load(Ordering::SeqCst) {
            let stream = open_stream(&self.clock, &self.name, self.opener.as_ref()).await?;
            *self.bus.lock().await = modbus_context(stream, self.framing, self.unit);
            self.lost.store(false, Ordering::SeqCst);
            tracing::info!(bus = %self.name, "Modbus link re-opened");
        }
        Ok(())
    }

    fn note<T>(&self, r: Result<T, DeviceError>) -> Result<T, DeviceError> {
        if lost_link(&r) {
            self.lost.store(true, Ordering::SeqCst);
        }
        r
    }
}

struct LinkedLamp {
    lamp: ModbusLamp,
    bus: Arc<Bus>,
}

#[async_trait]
impl Lamp for LinkedLamp {
    async fn set(&mut self, on: bool) -> Result<(), DeviceError> {
        self.bus.ready().await?;
        let r = self.lamp.set(on).await;
        self.bus.note(r)
    }

    async fn wait_ready(&mut self) -> Result<(), DeviceError> {
        self.bus.ready().await?;
        let r = self.lamp.wait_ready().await;
        self.bus.note(r)
    }
}

struct LinkedLaser {
    laser: ModbusLaser,
    bus: Arc<Bus>,
}

#[async_trait]
impl LaserLine for LinkedLaser {
    async fn set(&mut self, on: bool) -> Result<(), DeviceError> {
        self.bus.ready().await?;
        let r = self.laser.set(on).await;
        self.bus.note(r)
    }
}

/// Every coil of a module off in one request.
struct BusStop(Arc<Bus>);

#[async_trait]
impl EmergencyStop for BusStop {
    async fn emergency_stop(&self) -> Result<(), DeviceError> {
        let bus = &self.0;
        let coils = bus.coils.load(Ordering::SeqCst);
        all_off(&bus.clock, &bus.bus, coils, Duration::from_secs(1))
            .await
            .map_err(|e| e.into_device(&bus.name))
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;
    use crate::rig::drivers::usb::memory_pair;

    /// A camera that answers "busy" to its first `busy_for` openings.
    struct BusyCamera {
        busy_for: usize,
        opens: AtomicUsize,
    }

    #[async_trait]
    impl PipeOpener for BusyCamera {
        fn describe(&self) -> String {
            "PTP/IP camera at 127.0.0.1:15740".into()
        }

        async fn open(&self) -> Result<BoxPipe, UsbError> {
            if self.opens.fetch_add(1, Ordering::SeqCst) < self.busy_for {
                return Err(UsbError::Busy(
                    "the camera refused the PTP/IP connection: busy with another initiator".into(),
                ));
            }
            let (host, _device) = memory_pair();
            Ok(Box::new(host))
        }
    }

    #[tokio::test(start_paused = true)]
    async fn a_camera_busy_with_an_ended_session_is_asked_again_until_the_open_timeout() {
        let clock = Clock::virtual_time();
        let soon = BusyCamera {
            busy_for: 3,
            opens: AtomicUsize::new(0),
        };
        let started = clock.now();
        assert!(open_pipe(&clock, "camera", &soon).await.is_ok());
        assert_eq!(soon.opens.load(Ordering::SeqCst), 4);
        assert_eq!(clock.now() - started, 3 * BUSY_RETRY);

        let held = BusyCamera {
            busy_for: usize::MAX,
            opens: AtomicUsize::new(0),
        };
        let started = clock.now();
        let e = open_pipe(&clock, "camera", &held)
            .await
            .err()
            .expect("a camera busy for good is not opened");
        assert_eq!(e.kind, ErrorKind::Disconnected);
        assert!(
            e.message
                .contains("busy with another initiator, for over 10s"),
            "{e}"
        );
        assert!(clock.now() - started <= OPEN_TIMEOUT + BUSY_RETRY);
    }
}
