//! Links to real hardware: serial ports (tokio-serial), Modbus TCP sockets,
//! USB cameras (nusb), PTP/IP cameras, GenICam cameras (Aravis) and
//! cameras through libgphoto2, as the profile's `transport` of each device
//! says.

use std::collections::BTreeMap;
use std::sync::Arc;

use async_trait::async_trait;

use super::{build_rig, BoxPipe, ByteStream, Framing, Link, Opener, PipeOpener};
use crate::model::profile::{DeviceKind, Profile, Transport};
use crate::rig::drivers::genicam::{GenicamConfig, GenicamOpener, GenicamSession, SessionError};
use crate::rig::drivers::gphoto2::{Gphoto2Error, Gphoto2Opener, Gphoto2Session};
use crate::rig::drivers::ptpip::PtpIpPipe;
use crate::rig::drivers::usb::{NusbPipe, UsbError};
use crate::rig::hal::{DeviceError, ErrorKind, Rig};
use rigd_core::Clock;
use rigd_proto::ptp::ip::{FailReason, IpError};

/// A serial port (a USB-serial adapter, an RS-485 dongle, a pty).
pub struct SerialOpener {
    /// The serial device path, e.g. `/dev/ttyUSB0`.
    pub port: String,
    /// Line speed in baud.
    pub baud: u32,
}

#[async_trait]
impl Opener for SerialOpener {
    fn describe(&self) -> String {
        format!("serial port {} at {} baud", self.port, self.baud)
    }

    async fn open(&self) -> std::io::Result<ByteStream> {
        let builder = tokio_serial::new(&self.port, self.baud);
        let stream = tokio_serial::SerialStream::open(&builder)?;
        Ok(Box::new(stream))
    }
}

/// A TCP connection (Modbus TCP, or an RS-485 gateway).
pub struct TcpOpener {
    /// Host name or IP address to connect to.
    pub host: String,
    /// TCP port (502 for Modbus TCP).
    pub port: u16,
}

#[async_trait]
impl Opener for TcpOpener {
    fn describe(&self) -> String {
        format!("TCP {}:{}", self.host, self.port)
    }

    async fn open(&self) -> std::io::Result<ByteStream> {
        let stream = tokio::net::TcpStream::connect((self.host.as_str(), self.port)).await?;
        stream.set_nodelay(true)?;
        Ok(Box::new(stream))
    }
}

/// A USB Still Image camera by vendor, product and (optionally) serial.
pub struct UsbOpener {
    /// USB vendor id of the camera.
    pub vendor_id: u16,
    /// USB product id of the camera.
    pub product_id: u16,
    /// USB serial number that picks one of several identical cameras;
    /// None: the first with these ids.
    pub serial: Option<String>,
}

#[async_trait]
impl PipeOpener for UsbOpener {
    fn describe(&self) -> String {
        match &self.serial {
            Some(s) => format!(
                "USB camera {:04x}:{:04x} serial {s}",
                self.vendor_id, self.product_id
            ),
            None => format!("USB camera {:04x}:{:04x}", self.vendor_id, self.product_id),
        }
    }

    async fn open(&self) -> Result<BoxPipe, UsbError> {
        let pipe = NusbPipe::open_serial(self.vendor_id, self.product_id, self.serial.as_deref())?;
        Ok(Box::new(pipe))
    }
}

/// A PTP/IP camera (CIPA DC-005) on the network.
pub struct PtpIpOpener {
    /// The camera's host name or IP address.
    pub host: String,
    /// Its TCP port (15740 as a rule).
    pub port: u16,
}

#[async_trait]
impl PipeOpener for PtpIpOpener {
    fn describe(&self) -> String {
        format!("PTP/IP camera at {}:{}", self.host, self.port)
    }

    async fn open(&self) -> Result<BoxPipe, UsbError> {
        let pipe = PtpIpPipe::connect(&self.host, self.port)
            .await
            .map_err(|e| match e {
                IpError::Refused(FailReason::Busy) => UsbError::Busy(e.to_string()),
                e => UsbError::Io(e.to_string()),
            })?;
        tracing::info!(camera = %pipe.camera().name, "PTP/IP session open");
        Ok(Box::new(pipe))
    }
}

/// The link of every device, from its transport.
pub fn links(profile: &Profile) -> BTreeMap<String, Link> {
    profile
        .devices
        .iter()
        .map(|(name, dev)| {
            let link = match (dev.transport(), dev.kind()) {
                (
                    Transport::Usb {
                        vendor_id,
                        product_id,
                        serial,
                    },
                    _,
                ) => Link::Usb(Arc::new(UsbOpener {
                    vendor_id: *vendor_id,
                    product_id: *product_id,
                    serial: serial.clone(),
                })),
                (Transport::ModbusRtu { port, baud, .. }, _)
                | (Transport::Serial { port, baud }, DeviceKind::Lamp | DeviceKind::Laser) => {
                    // A relay module on a plain serial line speaks RTU.
                    modbus_link(
                        dev.transport(),
                        Arc::new(SerialOpener {
                            port: port.clone(),
                            baud: *baud,
                        }),
                        Framing::Rtu,
                    )
                }
                (Transport::ModbusTcp { host, port, .. }, _) => modbus_link(
                    dev.transport(),
                    Arc::new(TcpOpener {
                        host: host.clone(),
                        port: *port,
                    }),
                    Framing::Tcp,
                ),
                (Transport::PtpIp { host, port }, _) => Link::Usb(Arc::new(PtpIpOpener {
                    host: host.clone(),
                    port: *port,
                })),
                (Transport::Genicam { id }, _) => Link::Genicam(genicam_opener(id)),
                (Transport::Gphoto2 { port, model }, _) => {
                    Link::Gphoto2(gphoto2_opener(port.clone(), model.clone()))
                }
                (Transport::Serial { port, baud }, _) => Link::Line(Arc::new(SerialOpener {
                    port: port.clone(),
                    baud: *baud,
                })),
            };
            (name.clone(), link)
        })
        .collect()
}

/// The link to the relay module a transport names.
fn modbus_link(transport: &Transport, opener: Arc<dyn Opener>, framing: Framing) -> Link {
    let unit = match transport {
        Transport::ModbusRtu { unit, .. } | Transport::ModbusTcp { unit, .. } => *unit,
        _ => 1,
    };
    Link::Modbus {
        bus: transport.modbus_module().unwrap_or_default(),
        opener,
        framing,
        unit,
        status_registers: transport.status_registers(),
    }
}

/// `rig check` on real hardware: every device connected and reported.
pub async fn check(profile: &Profile, clock: &Clock) -> super::check::RigCheck {
    super::check::check_rig(profile, &links(profile), clock).await
}

/// Opens every device of a profile on real hardware.
pub async fn connect(profile: &Profile, clock: &Clock) -> Result<Rig, DeviceError> {
    let mut rig = build_rig(profile, &links(profile), clock).await?;
    if crate::plan::laser::LaserRig::of(profile).is_some() {
        rig.fixture = Some(Box::new(super::plate::OperatorPlate::default()));
    }
    Ok(rig)
}

/// Stands in for Aravis in a rigd built without the `genicam` feature:
/// every open says how to get a build that has it.
pub struct NoGenicam {
    /// The camera's id, for messages.
    pub id: String,
}

impl GenicamOpener for NoGenicam {
    fn describe(&self) -> String {
        format!("GenICam camera `{}`", self.id)
    }

    fn open(&self, _cfg: &GenicamConfig) -> Result<Box<dyn GenicamSession>, SessionError> {
        Err(SessionError::new(
            ErrorKind::NotReady,
            "this rigd was built without GenICam support: install Debian's libaravis-dev (Aravis 0.8) and build with `cargo build --release --features genicam`",
        ))
    }
}

/// The opener of a camera on `transport = { type = "genicam", id }`: Aravis
/// when built in, else [`NoGenicam`].
pub fn genicam_opener(id: &str) -> Arc<dyn GenicamOpener> {
    #[cfg(feature = "genicam")]
    {
        Arc::new(crate::rig::drivers::aravis::AravisOpener { id: id.to_string() })
    }
    #[cfg(not(feature = "genicam"))]
    {
        Arc::new(NoGenicam { id: id.to_string() })
    }
}

/// Stands in for libgphoto2 in a rigd built without the `gphoto2`
/// feature: every open says how to get a build that has it.
pub struct NoGphoto2 {
    /// The transport's port, for messages.
    pub port: Option<String>,
}

impl Gphoto2Opener for NoGphoto2 {
    fn describe(&self) -> String {
        match &self.port {
            Some(p) => format!("libgphoto2 camera on `{p}`"),
            None => "libgphoto2 camera".into(),
        }
    }

    fn open(&self) -> Result<Box<dyn Gphoto2Session>, Gphoto2Error> {
        Err(Gphoto2Error::new(
            ErrorKind::NotReady,
            "this rigd was built without libgphoto2 support: install Debian's libgphoto2-dev and libclang-dev and build with `cargo build --release --features gphoto2`",
        ))
    }
}

/// The opener of a camera on `transport = { type = "gphoto2" }`:
/// libgphoto2 when built in, else [`NoGphoto2`].
pub fn gphoto2_opener(port: Option<String>, model: Option<String>) -> Arc<dyn Gphoto2Opener> {
    #[cfg(feature = "gphoto2")]
    {
        Arc::new(crate::rig::drivers::libgphoto2::LibGphoto2Opener { port, model })
    }
    #[cfg(not(feature = "gphoto2"))]
    {
        let _ = model;
        Arc::new(NoGphoto2 { port })
    }
}
