//! A rig profile's devices: one table per device, its type chosen by its
//! `kind`, with the link that reaches it and the settings of that kind,
//! and the checks of values that the types cannot express.

use std::collections::BTreeMap;
use std::fmt;

use serde::{Deserialize, Serialize};

use super::exposure::{check_exposure_s, MAX_EXPOSURE_S};
use rigd_core::geometry::Direction;

/// What a device is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeviceKind {
    /// One rotary axis in degrees (rail, turntable, arc, tilt); needs
    /// `limits` and `motion`.
    Axis,
    /// A robot arm; needs `joints`.
    Arm,
    /// A lamp switched by a relay coil; needs `warm_up_s`.
    Lamp,
    /// A camera; needs `intrinsics` and `timing`.
    Camera,
    /// A laser line unit switched by a relay coil.
    Laser,
}

impl DeviceKind {
    /// "an axis", "a lamp": for messages.
    pub fn with_article(self) -> String {
        let article = if self == DeviceKind::Axis || self == DeviceKind::Arm {
            "an"
        } else {
            "a"
        };
        format!("{article} {self}")
    }
}

impl fmt::Display for DeviceKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self {
            DeviceKind::Axis => "axis",
            DeviceKind::Arm => "arm",
            DeviceKind::Lamp => "lamp",
            DeviceKind::Camera => "camera",
            DeviceKind::Laser => "laser",
        };
        f.write_str(s)
    }
}

/// One device, a table tagged by its `kind`: each kind has its own keys,
/// and a key another kind has is refused naming that kind. A device's
/// errors name the key inside its table (`devices.rail.limits.min`).
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Device {
    /// A rotary axis.
    Axis(AxisDevice),
    /// A robot arm.
    Arm(ArmDevice),
    /// A lamp on a relay.
    Lamp(LampDevice),
    /// A camera.
    Camera(CameraDevice),
    /// A laser line unit on a relay.
    Laser(LaserDevice),
}

/// The wire protocol of an axis controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AxisProtocol {
    /// GRBL 1.1's line protocol.
    Grbl,
}

/// The wire protocol of an arm controller.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ArmProtocol {
    /// The ACL command language of Eshed/Intelitek controllers.
    Acl,
}

/// The wire protocol of the relay module that switches a lamp or laser.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RelayProtocol {
    /// Modbus coils (RTU on a serial line, or TCP).
    Modbus,
}

/// How rigd speaks to a camera; it must agree with the camera's transport.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CameraProtocol {
    /// PTP (ISO 15740), on `usb` or `ptpip`.
    Ptp,
    /// GenICam through Aravis, on `genicam`.
    Genicam,
    /// Whatever libgphoto2 speaks to the camera, on `gphoto2`.
    Gphoto2,
}

impl CameraProtocol {
    /// The protocol's name, as the profile writes it.
    pub fn name(self) -> &'static str {
        match self {
            CameraProtocol::Ptp => "ptp",
            CameraProtocol::Genicam => "genicam",
            CameraProtocol::Gphoto2 => "gphoto2",
        }
    }
}

/// An axis: `kind = "axis"`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisDevice {
    /// How the daemon reaches the controller.
    pub transport: Transport,
    /// The controller's protocol: `grbl`.
    pub protocol: AxisProtocol,
    /// Soft limits, in degrees.
    pub limits: Limits,
    /// Motion model.
    pub motion: Motion,
    /// Where the axis stands after homing, in degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub home_deg: Option<f64>,
    /// Whether the controller homes it (GRBL `$H`, which needs `$22=1`
    /// and a home switch). With `false` rigd never homes it: the operator
    /// sets the axis at its 0° mark and zeroes the controller there, and
    /// rigd takes the machine position as it is. Default `true`.
    #[serde(default = "default_true")]
    pub homing: bool,
    /// Write the controller settings the profile implies at connect
    /// (GRBL `$22`, `$20`, `$110`, `$120`, `$130`, `$100`), then read them
    /// back. Without it, a controller whose settings differ is refused
    /// with the lines that would fix it. Default `false`.
    #[serde(default)]
    pub configure: bool,
    /// Motor steps per degree (GRBL `$100`), compared with the controller
    /// (and written with `configure`) when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps_per_deg: Option<f64>,
}

/// A robot arm: `kind = "arm"`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArmDevice {
    /// How the daemon reaches the controller.
    pub transport: Transport,
    /// The controller's protocol: `acl`.
    pub protocol: ArmProtocol,
    /// The joints, in the order the arm's protocol expects them.
    pub joints: Vec<Joint>,
    /// How long its homing cycle (the controller's `HOME`) takes, in
    /// seconds. Every run starts by homing, so the estimate counts it, and
    /// the simulated controller takes exactly this long. Default
    /// [`DEFAULT_ARM_HOMING_S`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub homing_s: Option<f64>,
}

/// A lamp switched by a relay coil: `kind = "lamp"`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LampDevice {
    /// How the daemon reaches the relay module.
    pub transport: Transport,
    /// The relay module's protocol: `modbus`.
    pub protocol: RelayProtocol,
    /// The Modbus coil of its relay (default 0).
    #[serde(default)]
    pub coil: u16,
    /// Time from switch-on to stable output, seconds.
    pub warm_up_s: f64,
    /// Time a switch takes to settle (relay plus filament), seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub switch_s: Option<f64>,
    /// Fixed direction, seen from the sample centre, in the world frame
    /// (a fixed-lamp rig's lamps).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction: Option<Direction>,
    /// Elevation (θ) on a light arc, degrees (a turntable rig's lamps).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevation_deg: Option<f64>,
    /// Distance from the sample centre, metres; absent: the rig's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distance_m: Option<f64>,
}

/// A camera: `kind = "camera"`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraDevice {
    /// How the daemon reaches the camera.
    pub transport: Transport,
    /// How rigd speaks to it: `ptp`, `genicam` or `gphoto2`, as its
    /// transport implies.
    pub protocol: CameraProtocol,
    /// Sensor resolution, focal length and bit depth.
    pub intrinsics: Intrinsics,
    /// Exposure, readout and transfer time per frame.
    pub timing: CameraTiming,
    /// Fixed direction, seen from the sample centre, in the world frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction: Option<Direction>,
    /// Distance from the sample centre, metres; absent: the rig's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distance_m: Option<f64>,
    /// GenICam camera: the features rigd sets at connect.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub genicam: Option<GenicamSettings>,
    /// PTP camera: the device properties rigd sets at connect.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ptp: Option<PtpSettings>,
    /// Camera through libgphoto2: the configuration widgets rigd sets at
    /// connect.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gphoto2: Option<Gphoto2Settings>,
}

/// A laser line unit switched by a relay coil: `kind = "laser"`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LaserDevice {
    /// How the daemon reaches the relay module.
    pub transport: Transport,
    /// The relay module's protocol: `modbus`.
    pub protocol: RelayProtocol,
    /// The Modbus coil of its relay (default 0).
    #[serde(default)]
    pub coil: u16,
    /// Time a switch takes to settle, seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub switch_s: Option<f64>,
    /// Elevation (θ) on the light arc, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevation_deg: Option<f64>,
    /// Distance from the sample centre, metres; absent: the light arc's
    /// radius.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distance_m: Option<f64>,
}

impl DeviceKind {
    /// The keys a device of this kind may have, besides `kind`.
    fn keys(self) -> &'static [&'static str] {
        match self {
            DeviceKind::Axis => &[
                "transport",
                "protocol",
                "limits",
                "motion",
                "home_deg",
                "homing",
                "configure",
                "steps_per_deg",
            ],
            DeviceKind::Arm => &["transport", "protocol", "joints", "homing_s"],
            DeviceKind::Lamp => &[
                "transport",
                "protocol",
                "coil",
                "warm_up_s",
                "switch_s",
                "direction",
                "elevation_deg",
                "distance_m",
            ],
            DeviceKind::Camera => &[
                "transport",
                "protocol",
                "intrinsics",
                "timing",
                "direction",
                "distance_m",
                "genicam",
                "ptp",
                "gphoto2",
            ],
            DeviceKind::Laser => &[
                "transport",
                "protocol",
                "coil",
                "switch_s",
                "elevation_deg",
                "distance_m",
            ],
        }
    }

    /// Every kind, in the order messages list them.
    const ALL: [DeviceKind; 5] = [
        DeviceKind::Axis,
        DeviceKind::Arm,
        DeviceKind::Lamp,
        DeviceKind::Camera,
        DeviceKind::Laser,
    ];

    /// "axes", "lamps": for messages.
    fn plural(self) -> &'static str {
        match self {
            DeviceKind::Axis => "axes",
            DeviceKind::Arm => "arms",
            DeviceKind::Lamp => "lamps",
            DeviceKind::Camera => "cameras",
            DeviceKind::Laser => "lasers",
        }
    }
}

/// A device's table is read whole first, since its `kind` (which may come
/// anywhere in it) decides its type; then it is read as that kind's struct
/// with its errors' keys kept. An absent key and a null one are the same,
/// as a run's snapshot of an older profile writes them.
impl<'de> Deserialize<'de> for Device {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Device, D::Error> {
        use serde::de::Error;
        use serde_value::{Value, ValueDeserializer};
        let table = BTreeMap::<String, Value>::deserialize(deserializer)?;
        let mut table: BTreeMap<String, Value> = table
            .into_iter()
            .filter(|(_, v)| !matches!(v, Value::Unit | Value::Option(None)))
            .collect();
        let Some(kind) = table.remove("kind") else {
            return Err(D::Error::custom(
                "missing field `kind` (expected `axis`, `arm`, `lamp`, `camera` or `laser`)",
            ));
        };
        let kind = DeviceKind::deserialize(ValueDeserializer::<D::Error>::new(kind))
            .map_err(|e| nested_error("kind", e))?;
        for key in table.keys() {
            if kind.keys().contains(&key.as_str()) {
                continue;
            }
            let owners: Vec<&str> = DeviceKind::ALL
                .iter()
                .filter(|k| k.keys().contains(&key.as_str()))
                .map(|k| k.plural())
                .collect();
            let message = if owners.is_empty() {
                format!(
                    "unknown key; {} has `kind`, `{}`",
                    kind.with_article(),
                    kind.keys().join("`, `")
                )
            } else {
                format!(
                    "`{key}` is for {}, not {}",
                    owners.join(" and "),
                    kind.with_article()
                )
            };
            return Err(nested_error(key, message));
        }
        let fields = Value::Map(
            table
                .into_iter()
                .map(|(k, v)| (Value::String(k), v))
                .collect(),
        );
        fn typed<T: serde::de::DeserializeOwned + Serialize, E: serde::de::Error>(
            kind: DeviceKind,
            fields: Value,
        ) -> Result<T, E> {
            super::whole_value::typed(fields).map_err(|(path, message): (String, E)| {
                if path == "." {
                    E::custom(format_args!("{}: {message}", kind.with_article()))
                } else {
                    nested_error(&path, message)
                }
            })
        }
        Ok(match kind {
            DeviceKind::Axis => Device::Axis(typed(kind, fields)?),
            DeviceKind::Arm => Device::Arm(typed(kind, fields)?),
            DeviceKind::Lamp => Device::Lamp(typed(kind, fields)?),
            DeviceKind::Camera => Device::Camera(typed(kind, fields)?),
            DeviceKind::Laser => Device::Laser(typed(kind, fields)?),
        })
    }
}

fn default_true() -> bool {
    true
}

/// The libgphoto2 configuration of a camera on `transport = { type =
/// "gphoto2" }`, set at every connect. The exposure time is the
/// `shutterspeed` widget, from `timing.exposure_s` (or the run's
/// exposure), so it is not among these.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gphoto2Settings {
    /// Widget name → value, as `gphoto2 --get-config NAME` lists them
    /// (`iso = "100"`, `imageformat = "RAW"`). A value the camera does not
    /// offer is refused at connect, naming what it offers.
    #[serde(default)]
    pub settings: std::collections::BTreeMap<String, String>,
}

/// The libgphoto2 widget that holds the exposure time.
pub const GPHOTO2_SHUTTER_WIDGET: &str = "shutterspeed";

/// The PTP device properties of a camera on `protocol = "ptp"`, set at
/// every connect (ExposureTime comes from `timing.exposure_s` or the run's
/// exposure, at every exposure).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PtpSettings {
    /// ExposureIndex, the ISO sensitivity (1 to 65535); absent: the
    /// camera's own. A measurement keeps it fixed, so set it.
    #[serde(default)]
    pub exposure_index: Option<u16>,
}

/// The GenICam features of a camera on `transport = { type = "genicam" }`,
/// set by their SFNC names at every connect. `Width` and `Height` come from
/// `intrinsics.resolution`, `ExposureTime` from `timing.exposure_s` (or the
/// run's exposure).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GenicamSettings {
    /// `PixelFormat`, unpacked: `Mono8` … `Mono16`, `BayerRG8` …
    /// `BayerBG16`. Its bit depth must be `intrinsics.bit_depth`. Default:
    /// the monochrome format of that depth.
    #[serde(default)]
    pub pixel_format: Option<String>,
    /// `Gain` in dB; absent: the camera's own.
    #[serde(default)]
    pub gain_db: Option<f64>,
    /// `TriggerSource` of the frame-start trigger: `Software` (default,
    /// rigd fires it for each exposure) or a line (`Line0`, …) that an
    /// external trigger drives.
    #[serde(default)]
    pub trigger_source: Option<String>,
}

impl GenicamSettings {
    /// The pixel format asked of a camera of `bit_depth` bits.
    pub fn pixel_format_for(
        settings: Option<&GenicamSettings>,
        bit_depth: u8,
    ) -> Result<rigd_core::PixelFormat, rigd_core::pixel_format::UnknownPixelFormat> {
        match settings.and_then(|g| g.pixel_format.as_deref()) {
            Some(name) => name.parse(),
            None => Ok(rigd_core::PixelFormat::mono_for_depth(bit_depth)),
        }
    }

    /// The trigger source, `Software` unless set.
    pub fn trigger_source_of(settings: Option<&GenicamSettings>) -> String {
        settings
            .and_then(|g| g.trigger_source.clone())
            .unwrap_or_else(|| "Software".into())
    }
}

/// Soft limits of an axis or joint.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Limits {
    /// Lowest allowed position, in degrees.
    pub min: f64,
    /// Highest allowed position, in degrees; must exceed `min`.
    pub max: f64,
}

impl Limits {
    /// Whether `x` (degrees) lies within the limits, with 1e-9° of slack so
    /// a value on a limit up to rounding counts as inside.
    pub fn contains(&self, x: f64) -> bool {
        x >= self.min - 1e-9 && x <= self.max + 1e-9
    }
}

/// Trapezoidal motion model of one axis (units: degrees, seconds).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Motion {
    /// Top speed, in degrees/s.
    pub max_velocity: f64,
    /// Acceleration and deceleration, in degrees/s².
    pub acceleration: f64,
    /// Time the axis needs to settle after a move before a frame may be
    /// exposed, in seconds.
    pub settle_s: f64,
}

impl From<Motion> for rigd_core::Trapezoid {
    fn from(m: Motion) -> rigd_core::Trapezoid {
        rigd_core::Trapezoid {
            max_velocity: m.max_velocity,
            acceleration: m.acceleration,
            settle_s: m.settle_s,
        }
    }
}

/// One joint of an arm.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Joint {
    /// The joint's name; the gonioreflectometer's solver finds its wrist
    /// joints by the names `roll`, `pitch` and `twist`.
    pub name: String,
    /// Soft limits of the joint, in degrees.
    pub limits: Limits,
    /// Trapezoidal motion model of the joint (degrees, seconds).
    pub motion: Motion,
    /// Where the joint stands after homing, in degrees (0 if absent).
    #[serde(default)]
    pub home_deg: f64,
    /// Encoder counts per degree, as the arm's controller counts.
    #[serde(default = "default_counts_per_deg")]
    pub counts_per_deg: f64,
}

fn default_counts_per_deg() -> f64 {
    100.0
}

/// Camera intrinsics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Intrinsics {
    /// Sensor size in pixels, `[width, height]`.
    pub resolution: [u32; 2],
    /// Focal length in pixels of the full-resolution sensor.
    pub focal_px: f64,
    /// Bits per pixel sample of the raw frames, 8 to 16.
    pub bit_depth: u8,
    /// The sensor's colour filter array, `"RGGB"`, `"GRBG"`, `"GBRG"` or
    /// `"BGGR"`, read from the frame's first pixel; absent for a
    /// monochrome sensor. A raw frame with another layout is refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cfa: Option<rigd_core::Cfa>,
}

/// The largest sensor side a camera may have, pixels.
pub const MAX_SENSOR_SIDE: u32 = 65_535;
/// The most pixels a camera's sensor may have: 2²⁸, 512 MiB a frame at
/// 16 bits, twice the largest sensors sold.
pub const MAX_SENSOR_PIXELS: u64 = 1 << 28;
/// The fastest serial line a profile may name, baud.
pub const MAX_BAUD: u32 = 12_000_000;

/// What one frame costs the camera, in seconds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraTiming {
    /// Exposure time, in seconds (positive, within `exposure_range_s`);
    /// `--exposure` overrides it.
    pub exposure_s: f64,
    /// The shortest and longest exposure the camera can set, seconds
    /// (its data sheet); absent: anything above 0 up to
    /// [`MAX_EXPOSURE_S`]. `exposure_s` and every run's `--exposure` must
    /// lie within it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exposure_range_s: Option<[f64; 2]>,
    /// Sensor readout after the exposure, in seconds; the rig does not move
    /// meanwhile.
    pub readout_s: f64,
    /// Moving the frame to the host, in seconds; it overlaps the next
    /// trigger's moves.
    pub transfer_s: f64,
}

/// How the daemon reaches a device.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Transport {
    /// A serial line: GRBL axes and ACL arms speak their text protocol on it;
    /// a lamp or laser on it speaks Modbus RTU.
    Serial {
        /// The serial device, e.g. `/dev/ttyUSB0`.
        port: String,
        /// Line speed in baud (GRBL: 115200).
        baud: u32,
    },
    /// A relay module speaking Modbus RTU on a serial line (RS-485).
    ModbusRtu {
        /// The serial device, e.g. `/dev/ttyUSB2`.
        port: String,
        /// Line speed in baud.
        baud: u32,
        /// The relay module's Modbus unit (slave) address, 1 if absent.
        #[serde(default = "default_unit")]
        unit: u8,
        /// Whether the module has rigd's status input registers (IR 0 ready
        /// bits, IR 1 fault bits). `false` for a coil-only relay module as
        /// sold: lamp readiness is then timed by rigd from `warm_up_s`, and
        /// only FC01, FC05 and FC0F go on the wire. Every device on one
        /// module must agree. Default `true`.
        #[serde(default = "default_true")]
        status_registers: bool,
    },
    /// A relay module speaking Modbus TCP.
    ModbusTcp {
        /// The module's (or gateway's) host name or IP address.
        host: String,
        /// TCP port, usually 502.
        port: u16,
        /// The Modbus unit identifier of the requests, 1 if absent.
        #[serde(default = "default_unit")]
        unit: u8,
        /// Whether the module has rigd's status input registers (IR 0 ready
        /// bits, IR 1 fault bits). `false` for a coil-only relay module as
        /// sold: lamp readiness is then timed by rigd from `warm_up_s`, and
        /// only FC01, FC05 and FC0F go on the wire. Every device on one
        /// module must agree. Default `true`.
        #[serde(default = "default_true")]
        status_registers: bool,
    },
    /// A PTP (USB Still Image) camera on USB.
    Usb {
        /// The camera's USB vendor id (`0x040a`).
        vendor_id: u16,
        /// The camera's USB product id.
        product_id: u16,
        /// The USB serial number that picks one of several identical
        /// cameras; absent: the first that matches the ids.
        #[serde(default)]
        serial: Option<String>,
    },
    /// A PTP camera on the network, over PTP/IP (CIPA DC-005): its command
    /// and event connections on one port (how `rigd sim serve` offers its
    /// simulated cameras, too).
    #[serde(rename = "ptpip")]
    PtpIp {
        /// The camera's host name or IP address.
        host: String,
        /// TCP port, 15740 (PTP/IP's own) if absent.
        #[serde(default = "default_ptpip_port")]
        port: u16,
    },
    /// A GenICam camera (GigE Vision or USB3 Vision) reached through
    /// Aravis; needs a rigd built with the `genicam` feature.
    Genicam {
        /// What Aravis opens: the camera's IP address, or its device id
        /// (`Vendor-Model-Serial`, as `arv-tool-0.8` lists it).
        id: String,
    },
    /// A camera reached through libgphoto2 (USB or PTP/IP, any make
    /// libgphoto2 drives); needs a rigd built with the `gphoto2` feature.
    /// With neither field, libgphoto2 autodetects and exactly one camera
    /// must be found.
    Gphoto2 {
        /// libgphoto2's port: `usb:BUS,DEV`, or `ptpip:HOST:CMDPORT:EVENTPORT`
        /// for a network camera (`gphoto2 --auto-detect` lists them);
        /// absent: the one camera autodetected (with `model`, the one of
        /// that model).
        #[serde(default)]
        port: Option<String>,
        /// libgphoto2's model name (`gphoto2 --list-cameras`), which picks
        /// its driver; `PTP/IP Camera` for a generic PTP/IP camera. Absent:
        /// the model autodetected on the port.
        #[serde(default)]
        model: Option<String>,
    },
}

fn default_unit() -> u8 {
    1
}

fn default_ptpip_port() -> u16 {
    rigd_proto::ptp::ip::DEFAULT_PORT
}

impl Transport {
    /// The relay module a lamp or laser on this transport is wired to, as
    /// `modbus-rtu:PORT#UNIT` or `modbus-tcp:HOST:PORT#UNIT` (a module on a
    /// plain serial line speaks RTU as unit 1); None for other transports.
    /// Devices with the same module share its bus and its emergency stop.
    pub fn modbus_module(&self) -> Option<String> {
        match self {
            Transport::ModbusRtu { port, unit, .. } => Some(format!("modbus-rtu:{port}#{unit}")),
            Transport::ModbusTcp {
                host, port, unit, ..
            } => Some(format!("modbus-tcp:{host}:{port}#{unit}")),
            Transport::Serial { port, .. } => Some(format!("modbus-rtu:{port}#1")),
            Transport::Usb { .. }
            | Transport::PtpIp { .. }
            | Transport::Genicam { .. }
            | Transport::Gphoto2 { .. } => None,
        }
    }

    /// Whether a relay module on this transport has the ready and fault
    /// input registers (always true for a transport that is no module).
    pub fn status_registers(&self) -> bool {
        match self {
            Transport::ModbusRtu {
                status_registers, ..
            }
            | Transport::ModbusTcp {
                status_registers, ..
            } => *status_registers,
            _ => true,
        }
    }
}

/// How long an arm's homing cycle takes when its profile does not say.
pub const DEFAULT_ARM_HOMING_S: f64 = 12.0;

/// The longest homing cycle a profile may state, seconds.
const MAX_HOMING_S: f64 = 3600.0;

/// An error at `path` inside a device's table, as the configuration
/// loader reads it (see [`rigd_core::config::nested_error`]).
fn nested_error<E: serde::de::Error>(path: &str, message: impl fmt::Display) -> E {
    rigd_core::config::nested_error(path, message)
}

impl Device {
    /// What the device is.
    pub fn kind(&self) -> DeviceKind {
        match self {
            Device::Axis(_) => DeviceKind::Axis,
            Device::Arm(_) => DeviceKind::Arm,
            Device::Lamp(_) => DeviceKind::Lamp,
            Device::Camera(_) => DeviceKind::Camera,
            Device::Laser(_) => DeviceKind::Laser,
        }
    }

    /// How the daemon reaches it.
    pub fn transport(&self) -> &Transport {
        match self {
            Device::Axis(d) => &d.transport,
            Device::Arm(d) => &d.transport,
            Device::Lamp(d) => &d.transport,
            Device::Camera(d) => &d.transport,
            Device::Laser(d) => &d.transport,
        }
    }

    /// The transport, to change (the simulator serves a profile's devices
    /// on links of its own).
    pub fn transport_mut(&mut self) -> &mut Transport {
        match self {
            Device::Axis(d) => &mut d.transport,
            Device::Arm(d) => &mut d.transport,
            Device::Lamp(d) => &mut d.transport,
            Device::Camera(d) => &mut d.transport,
            Device::Laser(d) => &mut d.transport,
        }
    }

    /// The wire protocol's name, as the profile writes it (`grbl`, `acl`,
    /// `modbus`, `ptp`, `genicam`, `gphoto2`).
    pub fn protocol(&self) -> &'static str {
        match self {
            Device::Axis(_) => "grbl",
            Device::Arm(_) => "acl",
            Device::Lamp(_) | Device::Laser(_) => "modbus",
            Device::Camera(c) => c.protocol.name(),
        }
    }

    /// The axis, if this is one.
    pub fn as_axis(&self) -> Option<&AxisDevice> {
        match self {
            Device::Axis(d) => Some(d),
            _ => None,
        }
    }

    /// The arm, if this is one.
    pub fn as_arm(&self) -> Option<&ArmDevice> {
        match self {
            Device::Arm(d) => Some(d),
            _ => None,
        }
    }

    /// The lamp, if this is one.
    pub fn as_lamp(&self) -> Option<&LampDevice> {
        match self {
            Device::Lamp(d) => Some(d),
            _ => None,
        }
    }

    /// The camera, if this is one.
    pub fn as_camera(&self) -> Option<&CameraDevice> {
        match self {
            Device::Camera(d) => Some(d),
            _ => None,
        }
    }

    /// A camera's intrinsics.
    pub fn intrinsics(&self) -> Option<Intrinsics> {
        self.as_camera().map(|c| c.intrinsics)
    }

    /// A camera's timing.
    pub fn timing(&self) -> Option<CameraTiming> {
        self.as_camera().map(|c| c.timing)
    }

    /// A lamp's or camera's fixed direction, seen from the sample centre.
    pub fn direction(&self) -> Option<Direction> {
        match self {
            Device::Lamp(d) => d.direction,
            Device::Camera(d) => d.direction,
            _ => None,
        }
    }

    /// A lamp's, camera's or laser's own distance from the sample centre,
    /// metres.
    pub fn distance_m(&self) -> Option<f64> {
        match self {
            Device::Lamp(d) => d.distance_m,
            Device::Camera(d) => d.distance_m,
            Device::Laser(d) => d.distance_m,
            _ => None,
        }
    }

    /// A lamp's or laser's elevation on a light arc, degrees.
    pub fn elevation_deg(&self) -> Option<f64> {
        match self {
            Device::Lamp(d) => d.elevation_deg,
            Device::Laser(d) => d.elevation_deg,
            _ => None,
        }
    }

    /// A lamp's or laser's relay coil.
    pub fn coil(&self) -> Option<u16> {
        match self {
            Device::Lamp(d) => Some(d.coil),
            Device::Laser(d) => Some(d.coil),
            _ => None,
        }
    }

    /// A lamp's or laser's switch settling time, seconds, where given.
    pub fn switch_s(&self) -> Option<f64> {
        match self {
            Device::Lamp(d) => d.switch_s,
            Device::Laser(d) => d.switch_s,
            _ => None,
        }
    }

    /// Whether rigd homes this device at a run's start: every device but an
    /// axis with `homing = false`.
    pub fn homes(&self) -> bool {
        self.as_axis().is_none_or(|a| a.homing)
    }

    /// How long homing this device takes, seconds: an arm's `homing_s`;
    /// 0 for every other kind (an axis's GRBL homing cycle lasts as long as
    /// its travel back from where it stands, and a simulated controller
    /// powers up at its home).
    pub fn homing_time_s(&self) -> f64 {
        match self {
            Device::Arm(a) => a.homing_s.unwrap_or(DEFAULT_ARM_HOMING_S),
            _ => 0.0,
        }
    }

    /// The fixed direction, to normalise its azimuth.
    pub(crate) fn direction_mut(&mut self) -> Option<&mut Direction> {
        match self {
            Device::Lamp(d) => d.direction.as_mut(),
            Device::Camera(d) => d.direction.as_mut(),
            _ => None,
        }
    }

    /// Checks what the types cannot: values and their combinations. `key`
    /// is the device's table (`devices.rail`).
    pub(crate) fn validate(&self, key: &str) -> Result<(), (String, String)> {
        check_transport(&format!("{key}.transport"), self.transport())?;
        match self {
            Device::Axis(a) => a.validate(key)?,
            Device::Arm(a) => a.validate(key)?,
            Device::Lamp(l) => {
                non_negative(&format!("{key}.warm_up_s"), Some(l.warm_up_s))?;
                non_negative(&format!("{key}.switch_s"), l.switch_s)?;
            }
            Device::Camera(c) => c.validate(key)?,
            Device::Laser(l) => non_negative(&format!("{key}.switch_s"), l.switch_s)?,
        }
        if let Some(d) = self.direction() {
            if !(0.0..=90.0).contains(&d.theta_deg) {
                return Err((
                    format!("{key}.direction.theta_deg"),
                    format!("expected 0 to 90 degrees, got {}", d.theta_deg),
                ));
            }
            crate::model::text::normalise_phi(d.phi_deg)
                .map_err(|why| (format!("{key}.direction.phi_deg"), why))?;
        }
        Ok(())
    }
}

impl AxisDevice {
    fn validate(&self, key: &str) -> Result<(), (String, String)> {
        let limits = self.limits;
        check_limits(&format!("{key}.limits"), limits)?;
        let motion = self.motion;
        check_motion(&format!("{key}.motion"), motion)?;
        if let Some(steps) = self.steps_per_deg {
            if !(steps.is_finite() && steps > 0.0) {
                return Err((
                    format!("{key}.steps_per_deg"),
                    format!("expected a positive number, got {steps}"),
                ));
            }
            let rate = steps * motion.max_velocity;
            if rate > rigd_proto::grbl::MAX_STEP_RATE_HZ {
                return Err((
                    format!("{key}.steps_per_deg"),
                    format!(
                        "{steps} steps/deg at motion.max_velocity {} deg/s is {rate:.0} steps/s; GRBL steps at most {:.0}/s (it refuses such settings with error:12)",
                        motion.max_velocity,
                        rigd_proto::grbl::MAX_STEP_RATE_HZ
                    ),
                ));
            }
        }
        if !self.homing && self.home_deg.is_some_and(|h| h != 0.0) {
            return Err((
                format!("{key}.home_deg"),
                "an axis without homing (`homing = false`) is zeroed at its 0° mark; leave `home_deg` out".into(),
            ));
        }
        if let Some(h) = self.home_deg {
            if !limits.contains(h) {
                return Err((
                    format!("{key}.home_deg"),
                    format!(
                        "home {h} lies outside the limits [{}, {}]",
                        limits.min, limits.max
                    ),
                ));
            }
        }
        Ok(())
    }
}

impl ArmDevice {
    fn validate(&self, key: &str) -> Result<(), (String, String)> {
        if let Some(h) = self.homing_s {
            if !(h.is_finite() && (0.0..=MAX_HOMING_S).contains(&h)) {
                return Err((
                    format!("{key}.homing_s"),
                    format!("expected 0 to {MAX_HOMING_S} seconds, got {h}"),
                ));
            }
        }
        let joints = &self.joints;
        for (i, j) in joints.iter().enumerate() {
            if let Err(why) = crate::model::text::check_name(&j.name) {
                return Err((format!("{key}.joints[{i}].name"), format!("the name {why}")));
            }
            if let Some(first) = joints[..i].iter().position(|o| o.name == j.name) {
                return Err((
                    format!("{key}.joints[{i}].name"),
                    format!(
                        "`{}` is also joints[{first}]'s name; each joint needs its own",
                        j.name
                    ),
                ));
            }
            check_limits(&format!("{key}.joints[{i}].limits"), j.limits)?;
            check_motion(&format!("{key}.joints[{i}].motion"), j.motion)?;
            if !(j.counts_per_deg.is_finite() && j.counts_per_deg > 0.0) {
                return Err((
                    format!("{key}.joints[{i}].counts_per_deg"),
                    format!("expected a positive number, got {}", j.counts_per_deg),
                ));
            }
            if !j.limits.contains(j.home_deg) {
                return Err((
                    format!("{key}.joints[{i}].home_deg"),
                    format!("home {} lies outside the limits", j.home_deg),
                ));
            }
        }
        Ok(())
    }
}

impl CameraDevice {
    /// The exposures this camera can set, `[shortest, longest]` seconds:
    /// its profile's `timing.exposure_range_s`, else anything up to
    /// [`MAX_EXPOSURE_S`] (the shortest then is the smallest positive
    /// number, since 0 itself is refused).
    pub fn exposure_range_s(&self) -> [f64; 2] {
        self.timing
            .exposure_range_s
            .unwrap_or([f64::MIN_POSITIVE, MAX_EXPOSURE_S])
    }

    fn validate(&self, key: &str) -> Result<(), (String, String)> {
        let intr = self.intrinsics;
        if !(8..=16).contains(&intr.bit_depth) {
            return Err((
                format!("{key}.intrinsics.bit_depth"),
                format!("expected 8 to 16 bits, got {}", intr.bit_depth),
            ));
        }
        let [w, h] = intr.resolution;
        let side = 1..=MAX_SENSOR_SIDE;
        if !(side.contains(&w) && side.contains(&h))
            || u64::from(w) * u64::from(h) > MAX_SENSOR_PIXELS
        {
            return Err((
                format!("{key}.intrinsics.resolution"),
                format!(
                    "{w}×{h}: expected [width, height] each 1 … {MAX_SENSOR_SIDE} pixels and at most {MAX_SENSOR_PIXELS} pixels in all"
                ),
            ));
        }
        if !(intr.focal_px.is_finite() && intr.focal_px > 0.0) {
            return Err((
                format!("{key}.intrinsics.focal_px"),
                format!(
                    "expected a positive focal length in pixels, got {}",
                    intr.focal_px
                ),
            ));
        }
        let t = self.timing;
        if let Some([low, high]) = t.exposure_range_s {
            let usable = low.is_finite() && low > 0.0 && low < high;
            if !(usable && high <= MAX_EXPOSURE_S) {
                return Err((
                    format!("{key}.timing.exposure_range_s"),
                    format!(
                        "expected [shortest, longest] seconds with 0 < shortest < longest ≤ {MAX_EXPOSURE_S}, got [{}, {}]",
                        crate::model::text::short_number(low),
                        crate::model::text::short_number(high)
                    ),
                ));
            }
        }
        check_exposure_s(t.exposure_s).map_err(|why| (format!("{key}.timing.exposure_s"), why))?;
        let [low, high] = self.exposure_range_s();
        if !(low..=high).contains(&t.exposure_s) {
            return Err((
                format!("{key}.timing.exposure_s"),
                format!(
                    "{} s lies outside the camera's exposure_range_s [{low}, {high}]",
                    t.exposure_s
                ),
            ));
        }
        non_negative(&format!("{key}.timing.readout_s"), Some(t.readout_s))?;
        non_negative(&format!("{key}.timing.transfer_s"), Some(t.transfer_s))?;
        self.validate_link(key)?;
        self.validate_genicam(key, intr.bit_depth)?;
        self.validate_gphoto2(key)
    }

    /// The protocol is the one the transport carries, and each protocol's
    /// settings table is only on a camera that speaks it.
    fn validate_link(&self, key: &str) -> Result<(), (String, String)> {
        let carried = match self.transport {
            Transport::Genicam { .. } => CameraProtocol::Genicam,
            Transport::Gphoto2 { .. } => CameraProtocol::Gphoto2,
            _ => CameraProtocol::Ptp,
        };
        if self.protocol != carried {
            let transport = match carried {
                CameraProtocol::Genicam => "genicam",
                CameraProtocol::Gphoto2 => "gphoto2",
                CameraProtocol::Ptp => "usb\" or \"ptpip",
            };
            let protocol = carried.name();
            return Err((
                format!("{key}.protocol"),
                format!(
                    "a camera on `transport = {{ type = \"{transport}\" }}` speaks `protocol = \"{protocol}\"`"
                ),
            ));
        }
        for (set, table, protocol) in [
            (self.genicam.is_some(), "genicam", CameraProtocol::Genicam),
            (self.ptp.is_some(), "ptp", CameraProtocol::Ptp),
            (self.gphoto2.is_some(), "gphoto2", CameraProtocol::Gphoto2),
        ] {
            if set && self.protocol != protocol {
                return Err((
                    format!("{key}.{table}"),
                    format!("is for cameras on `protocol = \"{table}\"`"),
                ));
            }
        }
        if self.ptp.is_some_and(|p| p.exposure_index == Some(0)) {
            return Err((
                format!("{key}.ptp.exposure_index"),
                "expected an ISO sensitivity of 1 or more".into(),
            ));
        }
        Ok(())
    }

    /// A GenICam camera names its device, and its pixel format is one rigd
    /// takes, of the sensor's bit depth and filter array.
    fn validate_genicam(&self, key: &str, bit_depth: u8) -> Result<(), (String, String)> {
        let on_genicam = self.protocol == CameraProtocol::Genicam;
        if let Transport::Genicam { id } = &self.transport {
            if id.trim().is_empty() {
                return Err((
                    format!("{key}.transport.id"),
                    "expected the camera's IP address or Aravis device id".into(),
                ));
            }
        }
        let settings = self.genicam.as_ref();
        let format = GenicamSettings::pixel_format_for(settings, bit_depth)
            .map_err(|e| (format!("{key}.genicam.pixel_format"), e.to_string()))?;
        if format.bit_depth() != bit_depth && on_genicam {
            return Err((
                format!("{key}.genicam.pixel_format"),
                format!(
                    "{format} has {} bits, but intrinsics.bit_depth is {bit_depth}",
                    format.bit_depth()
                ),
            ));
        }
        // The pixel format decides a GenICam camera's filter array; the
        // profile's `intrinsics.cfa`, where given, must say the same.
        if let (true, Some(cfa)) = (on_genicam, self.intrinsics.cfa) {
            if format.cfa() != Some(cfa) {
                return Err((
                    format!("{key}.genicam.pixel_format"),
                    format!("{format} is not behind the {cfa} filter array `intrinsics.cfa` names"),
                ));
            }
        }
        if let Some(g) = settings.and_then(|g| g.gain_db) {
            if !g.is_finite() {
                return Err((
                    format!("{key}.genicam.gain_db"),
                    format!("expected a finite gain in dB, got {g}"),
                ));
            }
        }
        let source = GenicamSettings::trigger_source_of(settings);
        if source != "Software" && !source.starts_with("Line") {
            return Err((
                format!("{key}.genicam.trigger_source"),
                format!("expected `Software` or a line (`Line0`, …), got `{source}`"),
            ));
        }
        Ok(())
    }

    /// A libgphoto2 camera's widgets are named and valued, and leave the
    /// exposure to `timing.exposure_s`.
    fn validate_gphoto2(&self, key: &str) -> Result<(), (String, String)> {
        let Some(g) = &self.gphoto2 else {
            return Ok(());
        };
        for (name, value) in &g.settings {
            let widget = format!("{key}.gphoto2.settings.{name}");
            if name == GPHOTO2_SHUTTER_WIDGET {
                return Err((
                    widget,
                    "the exposure time comes from `timing.exposure_s` (or the run's `--exposure`): remove it here".into(),
                ));
            }
            if name.trim().is_empty() || name.contains('/') || name.chars().any(char::is_control) {
                return Err((
                    format!("{key}.gphoto2.settings"),
                    "a widget's name, as `gphoto2 --list-config` lists it (without its path)"
                        .into(),
                ));
            }
            if value.chars().any(char::is_control) {
                return Err((widget, "expected a value without control characters".into()));
            }
        }
        Ok(())
    }
}

/// A transport that can be reached at all: a line speed above 0 on a
/// serial line, a port and host on TCP.
fn check_transport(key: &str, transport: &Transport) -> Result<(), (String, String)> {
    match transport {
        Transport::Serial { port, baud } | Transport::ModbusRtu { port, baud, .. } => {
            if port.trim().is_empty() {
                return Err((
                    format!("{key}.port"),
                    "expected the serial device, e.g. /dev/ttyUSB0".into(),
                ));
            }
            if !(1..=MAX_BAUD).contains(baud) {
                return Err((
                    format!("{key}.baud"),
                    format!("{baud}: expected a line speed of 1 … {MAX_BAUD} baud, e.g. 115200"),
                ));
            }
        }
        Transport::ModbusTcp { host, port, .. } | Transport::PtpIp { host, port } => {
            if host.trim().is_empty() {
                return Err((
                    format!("{key}.host"),
                    "expected a host name or IP address".into(),
                ));
            }
            if *port == 0 {
                return Err((
                    format!("{key}.port"),
                    "0: expected a TCP port of 1 … 65535".into(),
                ));
            }
        }
        Transport::Gphoto2 { port, model } => {
            for (field, value, expected) in [
                (
                    "port",
                    port,
                    "libgphoto2's port, e.g. `usb:001,004` or `ptpip:192.168.1.20:15740:15740`",
                ),
                (
                    "model",
                    model,
                    "libgphoto2's model name, e.g. `PTP/IP Camera`",
                ),
            ] {
                if value.as_ref().is_some_and(|v| v.trim().is_empty()) {
                    return Err((
                        format!("{key}.{field}"),
                        format!("expected {expected}, or no `{field}` to autodetect"),
                    ));
                }
            }
        }
        Transport::Usb { .. } | Transport::Genicam { .. } => {}
    }
    Ok(())
}

fn check_limits(key: &str, l: Limits) -> Result<(), (String, String)> {
    if !(l.min.is_finite() && l.max.is_finite()) || l.min >= l.max {
        return Err((
            key.to_string(),
            format!(
                "expected min < max, got min = {}, max = {} (inverted or empty)",
                l.min, l.max
            ),
        ));
    }
    Ok(())
}

fn check_motion(key: &str, m: Motion) -> Result<(), (String, String)> {
    if !(m.max_velocity > 0.0 && m.acceleration > 0.0 && m.settle_s >= 0.0) {
        return Err((
            key.to_string(),
            "expected max_velocity > 0, acceleration > 0 and settle_s >= 0".into(),
        ));
    }
    Ok(())
}

fn non_negative(key: &str, v: Option<f64>) -> Result<(), (String, String)> {
    match v {
        Some(x) if !(x >= 0.0 && x.is_finite()) => Err((
            key.to_string(),
            format!("expected a non-negative number of seconds, got {x}"),
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_core::config::{parse, ConfigError, Format};

    #[derive(Debug, Deserialize)]
    struct Devices {
        devices: BTreeMap<String, Device>,
    }

    fn devices(text: &str) -> Result<BTreeMap<String, Device>, ConfigError> {
        parse::<Devices>(text, "t.toml", Format::Toml).map(|d| d.devices)
    }

    const SERIAL: &str = r#"transport = { type = "serial", port = "/dev/ttyUSB0", baud = 115200 }"#;

    fn lamp(extra: &str) -> String {
        format!(
            "[devices.hmi]\nkind = \"lamp\"\n{SERIAL}\nprotocol = \"modbus\"\nwarm_up_s = 1.0\n{extra}"
        )
    }

    fn rail(extra: &str) -> String {
        format!(
            "[devices.rail]\nkind = \"axis\"\n{SERIAL}\nprotocol = \"grbl\"\n\
             limits = {{ min = 0.0, max = 180.0 }}\n\
             motion = {{ max_velocity = 10.0, acceleration = 20.0, settle_s = 0.1 }}\n{extra}"
        )
    }

    /// Every kind's struct, with every optional key set: serialised, its
    /// keys are the kind's table of keys, so the table that names another
    /// kind's keys in errors cannot drift from the structs.
    #[test]
    fn each_kind_s_keys_are_its_struct_s_fields() {
        let transport = Transport::Serial {
            port: "/dev/ttyUSB0".into(),
            baud: 115_200,
        };
        let limits = Limits { min: 0.0, max: 1.0 };
        let motion = Motion {
            max_velocity: 1.0,
            acceleration: 1.0,
            settle_s: 0.0,
        };
        let direction = Some(Direction {
            theta_deg: 10.0,
            phi_deg: 0.0,
        });
        let every = [
            Device::Axis(AxisDevice {
                transport: transport.clone(),
                protocol: AxisProtocol::Grbl,
                limits,
                motion,
                home_deg: Some(0.0),
                homing: true,
                configure: false,
                steps_per_deg: Some(80.0),
            }),
            Device::Arm(ArmDevice {
                transport: transport.clone(),
                protocol: ArmProtocol::Acl,
                joints: Vec::new(),
                homing_s: Some(1.0),
            }),
            Device::Lamp(LampDevice {
                transport: transport.clone(),
                protocol: RelayProtocol::Modbus,
                coil: 1,
                warm_up_s: 1.0,
                switch_s: Some(0.1),
                direction,
                elevation_deg: Some(30.0),
                distance_m: Some(1.0),
            }),
            Device::Camera(CameraDevice {
                transport: transport.clone(),
                protocol: CameraProtocol::Ptp,
                intrinsics: Intrinsics {
                    resolution: [8, 8],
                    focal_px: 10.0,
                    bit_depth: 12,
                    cfa: None,
                },
                timing: CameraTiming {
                    exposure_s: 0.1,
                    exposure_range_s: None,
                    readout_s: 0.0,
                    transfer_s: 0.0,
                },
                direction,
                distance_m: Some(1.0),
                genicam: Some(GenicamSettings {
                    pixel_format: None,
                    gain_db: None,
                    trigger_source: None,
                }),
                ptp: Some(PtpSettings {
                    exposure_index: None,
                }),
                gphoto2: Some(Gphoto2Settings::default()),
            }),
            Device::Laser(LaserDevice {
                transport,
                protocol: RelayProtocol::Modbus,
                coil: 2,
                switch_s: Some(0.1),
                elevation_deg: Some(45.0),
                distance_m: Some(1.0),
            }),
        ];
        for device in every {
            let value = serde_json::to_value(&device).expect("serialise");
            let mut keys: Vec<&str> = value
                .as_object()
                .expect("a table")
                .keys()
                .map(String::as_str)
                .filter(|k| *k != "kind")
                .collect();
            let mut table = device.kind().keys().to_vec();
            keys.sort_unstable();
            table.sort_unstable();
            assert_eq!(keys, table, "{}", device.kind());
            let back: Device = serde_json::from_value(value).expect("read back");
            assert_eq!(back.kind(), device.kind());
        }
    }

    /// An error inside a device's table names the key inside it, though the
    /// table is read whole before its kind types it; `kind` may stand
    /// anywhere in the table.
    #[test]
    fn a_device_s_errors_name_the_key_inside_its_table() {
        let e = devices(&rail("").replace("min = 0.0", "min = \"low\"")).expect_err("a string");
        assert_eq!(e.key, "devices.rail.limits.min", "{e}");
        assert!(e.message.contains("invalid type"), "{e}");

        let e = devices(&lamp("homing = false\n")).expect_err("homing on a lamp");
        assert_eq!(e.key, "devices.hmi.homing", "{e}");
        assert!(
            e.message.contains("`homing` is for axes, not a lamp"),
            "{e}"
        );

        let e = devices(&lamp("elevation = 30.0\n")).expect_err("a misspelt key");
        assert_eq!(e.key, "devices.hmi.elevation", "{e}");
        assert!(e.message.contains("a lamp has `kind`, `transport`"), "{e}");
        assert!(e.message.contains("`elevation_deg`"), "{e}");

        let e = devices(&lamp("").replace("warm_up_s = 1.0\n", "")).expect_err("no warm-up");
        assert_eq!(e.key, "devices.hmi", "{e}");
        assert!(
            e.message.contains("a lamp: missing field `warm_up_s`"),
            "{e}"
        );

        let e = devices(&lamp("").replace("\"lamp\"", "\"lmap\"")).expect_err("no such kind");
        assert_eq!(e.key, "devices.hmi.kind", "{e}");
        assert!(e.message.contains("unknown variant `lmap`"), "{e}");

        let e = devices(&lamp("").replace("kind = \"lamp\"\n", "")).expect_err("no kind");
        assert_eq!(e.key, "devices.hmi", "{e}");
        assert!(e.message.contains("missing field `kind`"), "{e}");

        let e = devices(&lamp("").replace("\"modbus\"", "\"grbl\"")).expect_err("a lamp on GRBL");
        assert_eq!(e.key, "devices.hmi.protocol", "{e}");
        assert!(e.message.contains("expected `modbus`"), "{e}");

        let last = lamp("").replace("kind = \"lamp\"\n", "") + "kind = \"lamp\"\n";
        let d = devices(&last).expect("kind last");
        assert_eq!(d["hmi"].kind(), DeviceKind::Lamp);
    }

    /// A value TOML can write but JSON cannot reaches the checks: the table
    /// is held in a form that keeps NaN, so a NaN home is refused, not lost.
    #[test]
    fn a_nan_in_a_device_s_table_is_kept_for_the_checks() {
        let d = devices(&rail("home_deg = nan\n")).expect("parses");
        let axis = d["rail"].as_axis().expect("an axis");
        assert!(axis.home_deg.is_some_and(f64::is_nan));
        let e = d["rail"].validate("devices.rail").expect_err("NaN home");
        assert_eq!(e.0, "devices.rail.home_deg");
    }

    /// A run's snapshot of a profile written before devices were typed holds
    /// every other kind's keys as nulls: they read as absent.
    #[test]
    fn an_older_snapshot_s_null_keys_read_as_absent() {
        let old = serde_json::json!({
            "kind": "lamp",
            "transport": { "type": "serial", "port": "/dev/ttyUSB0", "baud": 115200 },
            "protocol": "modbus",
            "limits": null, "motion": null, "home_deg": null, "homing": null,
            "configure": null, "steps_per_deg": null, "joints": null,
            "direction": { "theta_deg": 20.0, "phi_deg": 0.0 },
            "elevation_deg": null, "distance_m": null, "warm_up_s": 2.0,
            "switch_s": null, "coil": 3, "intrinsics": null, "timing": null,
            "genicam": null
        });
        let d: Device = serde_json::from_value(old).expect("an older snapshot");
        let lamp = d.as_lamp().expect("a lamp");
        assert_eq!((lamp.coil, lamp.warm_up_s), (3, 2.0));
        assert!(lamp.switch_s.is_none() && lamp.direction.is_some());
    }
}
