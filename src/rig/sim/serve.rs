//! `rigd sim serve`: the simulated firmware of a profile offered the way
//! hardware is, so anything that talks to real devices can talk to it:
//! serial devices on pseudo-terminals, relay modules on Modbus TCP on
//! 127.0.0.1 (and RTU modules also on a pty), cameras as PTP/IP cameras
//! on 127.0.0.1. It answers with a copy of the profile whose
//! transports point at these endpoints.

use std::collections::BTreeMap;
use std::sync::Arc;

use rigd_core::Clock;
use rigd_sim::FaultRule;
use tokio::net::TcpListener;
use tokio_serial::{SerialPort, SerialStream};

use super::{bus_key, firmware};
use crate::kinematics::Solver;
use crate::model::profile::{CameraProtocol, Device, Profile, Transport};
use crate::rig::hal::{DeviceError, ErrorKind};
use crate::rig::{Framing, Link};

/// Where one device of the served rig can be reached.
#[derive(Debug, Clone, PartialEq)]
pub struct Endpoint {
    /// The device's name, or a Modbus bus's key for a relay module.
    pub device: String,
    /// A pty path or `127.0.0.1:PORT`, with what speaks there.
    pub address: String,
    /// What speaks there: `GRBL`, `ACL`, `Modbus RTU`, `Modbus TCP`,
    /// `PTP/IP`.
    pub protocol: String,
}

/// A served rig: the endpoints and the profile that points at them.
#[derive(Debug, Clone)]
pub struct Served {
    /// Every endpoint offered, one per device or Modbus bus (two for an
    /// RTU module: its pty and Modbus TCP).
    pub endpoints: Vec<Endpoint>,
    /// A copy of the profile whose transports point at the endpoints, for
    /// `rigd run --profile`.
    pub profile: Profile,
    /// The pty ends the firmware do not use, kept open: a pty whose last
    /// slave handle closes hangs up its master.
    _keep: Vec<Arc<SerialStream>>,
}

fn io_err(device: &str, what: &str, e: impl std::fmt::Display) -> DeviceError {
    DeviceError::new(device, ErrorKind::Disconnected, format!("{what}: {e}"))
}

/// A pseudo-terminal pair: the master end (for the firmware) and the path
/// of the slave end (for clients), whose handle is kept open.
fn pty(device: &str) -> Result<(SerialStream, String, SerialStream), DeviceError> {
    let (master, slave) =
        SerialStream::pair().map_err(|e| io_err(device, "cannot create a pty", e))?;
    let path = slave
        .name()
        .ok_or_else(|| io_err(device, "pty", "the slave end has no path"))?;
    Ok((master, path, slave))
}

async fn listen(device: &str) -> Result<(TcpListener, u16), DeviceError> {
    let l = TcpListener::bind("127.0.0.1:0")
        .await
        .map_err(|e| io_err(device, "cannot listen on 127.0.0.1", e))?;
    let port = l
        .local_addr()
        .map_err(|e| io_err(device, "listener", e))?
        .port();
    Ok((l, port))
}

/// Starts every device's simulated firmware on its endpoint. The tasks run
/// on the current runtime until it shuts down.
pub async fn serve(
    profile: &Profile,
    faults: Vec<FaultRule>,
    clock: &Clock,
) -> Result<Served, DeviceError> {
    let solver = Solver::new(profile)
        .map_err(|e| DeviceError::new("rig", ErrorKind::NotReady, e.to_string()))?;
    let mut all = super::fault_rules(profile)?;
    all.extend(faults);
    let faults = Arc::new(rigd_sim::FaultInjector::new(all));
    let parts = firmware(profile, Arc::new(solver), None, clock, &faults)?;
    let mut served = profile.clone();
    let mut endpoints = Vec::new();
    let mut keep = Vec::new();
    let mut tcp_of_bus: BTreeMap<String, u16> = BTreeMap::new();

    for (key, m) in &parts.modules {
        let (listener, port) = listen(key).await?;
        let module = m.module.clone();
        tokio::spawn(async move {
            while let Ok((stream, _)) = listener.accept().await {
                let module = module.clone();
                tokio::spawn(async move {
                    if let Err(e) = module.serve_stream(stream, Framing::Tcp).await {
                        tracing::debug!("Modbus TCP client gone: {e}");
                    }
                });
            }
        });
        tcp_of_bus.insert(key.clone(), port);
        if m.framing == Framing::Rtu {
            let (master, path, slave) = pty(key)?;
            let module = m.module.clone();
            tokio::spawn(async move {
                if let Err(e) = module.serve_stream(master, Framing::Rtu).await {
                    tracing::debug!("Modbus RTU pty closed: {e}");
                }
            });
            keep.push(Arc::new(slave));
            endpoints.push(Endpoint {
                device: key.clone(),
                address: path,
                protocol: "Modbus RTU".into(),
            });
        }
        endpoints.push(Endpoint {
            device: key.clone(),
            address: format!("127.0.0.1:{port}"),
            protocol: "Modbus TCP".into(),
        });
    }

    for (name, dev) in served.devices.iter_mut() {
        let Some(link) = parts.links.get(name) else {
            continue;
        };
        match link {
            Link::Line(opener) => {
                let (mut master, path, slave) = pty(name)?;
                let mut fw = opener
                    .open()
                    .await
                    .map_err(|e| io_err(name, "cannot start the firmware", e))?;
                tokio::spawn(async move {
                    // The firmware and the pty exchange bytes until either ends.
                    let _ = tokio::io::copy_bidirectional(&mut fw, &mut master).await;
                });
                keep.push(Arc::new(slave));
                let baud = match dev.transport() {
                    Transport::Serial { baud, .. } => *baud,
                    _ => 115_200,
                };
                *dev.transport_mut() = Transport::Serial {
                    port: path.clone(),
                    baud,
                };
                endpoints.push(Endpoint {
                    device: name.clone(),
                    address: path,
                    protocol: dev.protocol().to_uppercase(),
                });
            }
            Link::Modbus { unit, .. } => {
                let key = bus_key(dev.transport());
                if let Some(&port) = tcp_of_bus.get(&key) {
                    *dev.transport_mut() = Transport::ModbusTcp {
                        host: "127.0.0.1".into(),
                        port,
                        unit: *unit,
                        status_registers: dev.transport().status_registers(),
                    };
                }
            }
            Link::Usb(_) => {
                let Some(cam) = parts.cameras.get(name).cloned() else {
                    continue;
                };
                let (listener, port) = listen(name).await?;
                tokio::spawn(super::ptpip_serve::serve_camera(
                    listener,
                    cam,
                    name.clone(),
                    clock.clone(),
                ));
                *dev.transport_mut() = Transport::PtpIp {
                    host: "127.0.0.1".into(),
                    port,
                };
                // The served camera is a PTP camera whatever the profile
                // reached it by (libgphoto2, Aravis): the printed profile
                // reaches it with rigd's own PTP driver.
                if let Device::Camera(camera) = dev {
                    camera.protocol = CameraProtocol::Ptp;
                    camera.gphoto2 = None;
                    camera.genicam = None;
                }
                endpoints.push(Endpoint {
                    device: name.clone(),
                    address: format!("127.0.0.1:{port}"),
                    protocol: "PTP/IP".into(),
                });
            }
            // The simulator's cameras are PTP cameras; it serves no GenICam.
            Link::Genicam(_) | Link::Gphoto2(_) => {}
        }
    }
    // The faults are the served firmware's business, not the client's.
    served.sim.simulator.remove("faults");
    served.name = format!("{}-sim-served", profile.name);
    served.description = format!(
        "{} (simulated firmware served by `rigd sim serve`)",
        profile.description
    );
    Ok(Served {
        endpoints,
        profile: served,
        _keep: keep,
    })
}
