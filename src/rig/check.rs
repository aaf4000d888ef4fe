//! `rigd rig check`: bring-up without moving anything. Every device is
//! connected through the same drivers and deadlines as a run (all at once,
//! like [`super::build_rig`]), asked who it is and how it is set up, and
//! reported on one line: usable, or what is wrong and the fix. Nothing is
//! homed, moved or switched; `configure = true` may write GRBL settings,
//! which is what it asks for.

use std::collections::BTreeMap;
use std::time::Duration;

use futures::future::join_all;
use serde::Serialize;

use super::drivers::modbus::{probe_coil, ModbusConfig};
use super::{connect_device, modbus_context, open_stream, Link};
use crate::model::profile::{Device, DeviceKind, Profile};
use crate::rig::hal::{DeviceError, ErrorKind};
use rigd_core::Clock;

/// One device's verdict.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct DeviceCheck {
    /// The device's name in the profile.
    pub device: String,
    /// `axis`, `arm`, `lamp`, `camera` or `laser`.
    pub kind: String,
    /// Whether a run could use it as it stands.
    pub usable: bool,
    /// What it said of itself (identity, firmware, settings, homing mode,
    /// position or state), or what went wrong.
    pub detail: String,
    /// The fix, when it is not usable and the detail does not already say.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fix: Option<String>,
    /// Seconds from opening its link to its verdict (for a lamp or laser:
    /// its module's connection and its own reads).
    pub connect_s: f64,
}

/// The whole rig's verdict.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct RigCheck {
    /// The profile's name.
    pub profile: String,
    /// True when every device is usable.
    pub usable: bool,
    /// One entry per device, in profile order.
    pub devices: Vec<DeviceCheck>,
    /// Seconds the whole check took: about the slowest device's
    /// `connect_s`, since every device connects at once.
    pub took_s: f64,
}

impl RigCheck {
    /// The report as text: one line per device, then a summary line.
    pub fn lines(&self) -> Vec<String> {
        let width = self
            .devices
            .iter()
            .map(|d| d.device.len())
            .max()
            .unwrap_or(0);
        let mut out: Vec<String> = self
            .devices
            .iter()
            .map(|d| {
                let verdict = if d.usable { "OK  " } else { "FAIL" };
                let fix = d
                    .fix
                    .as_deref()
                    .map(|f| format!("; fix: {f}"))
                    .unwrap_or_default();
                format!(
                    "{verdict} {:<width$} {:<6} {}{fix} ({:.2} s)",
                    d.device, d.kind, d.detail, d.connect_s
                )
            })
            .collect();
        let bad = self.devices.iter().filter(|d| !d.usable).count();
        let slowest = self.devices.iter().map(|d| d.connect_s).fold(0.0, f64::max);
        let verdict = if bad == 0 {
            format!("all {} devices usable", self.devices.len())
        } else {
            format!("{bad} of {} devices not usable", self.devices.len())
        };
        out.push(format!(
            "{}: {verdict} (checked in {:.2} s; slowest device {slowest:.2} s)",
            self.profile, self.took_s
        ));
        out
    }
}

/// What to do about a device error of this kind, unless its message
/// already says (GRBL's settings and state errors carry their own fix).
fn fix_for(name: &str, e: &DeviceError) -> Option<String> {
    let says_fix = [
        "`configure = true`",
        "`$X`",
        "0° mark",
        "check ballast",
        "to what the camera offers",
        "--features genicam",
        "--features gphoto2",
    ]
    .iter()
    .any(|m| e.message.contains(m));
    if says_fix {
        return None;
    }
    Some(match e.kind {
        ErrorKind::Disconnected => format!(
            "check that the device is powered and cabled, and its port or address in `devices.{name}.transport`"
        ),
        ErrorKind::Timeout => format!(
            "the device does not answer: check its power, the baud rate or unit in `devices.{name}.transport`, and that no other program holds the port"
        ),
        ErrorKind::BadFrame => format!(
            "the device answers in a way rigd cannot read: check `devices.{name}.protocol` and the firmware (GRBL 1.1, ACL, PTP, Modbus)"
        ),
        ErrorKind::NotReady => {
            format!("fix `devices.{name}.transport` and `devices.{name}.protocol` in the profile")
        }
        ErrorKind::DeviceFault | ErrorKind::OutOfLimits | ErrorKind::Storage => {
            "see the device's own message above".to_string()
        }
    })
}

fn failed(name: &str, dev: &Device, e: &DeviceError) -> DeviceCheck {
    DeviceCheck {
        device: name.to_string(),
        kind: dev.kind().to_string(),
        usable: false,
        detail: e.message.clone(),
        fix: fix_for(name, e),
        connect_s: 0.0,
    }
}

/// Checks one lamp or laser on an open bus.
async fn check_coil(
    name: &str,
    dev: &Device,
    bus: super::drivers::modbus::SharedBus,
    status_registers: bool,
    clock: &Clock,
) -> DeviceCheck {
    let coil = dev.coil().unwrap_or(0);
    let mut cfg = ModbusConfig::new(name, coil, Duration::ZERO, Duration::ZERO);
    cfg.status_registers = status_registers;
    match probe_coil(cfg, clock.clone(), bus).await {
        Err(e) => failed(name, dev, &e.into_device(name)),
        Ok(p) => {
            let relay = if p.on { "on" } else { "off" };
            let warm_up = dev.as_lamp().map_or(0.0, |l| l.warm_up_s);
            let (status, fault) = match p.status {
                Some((_, fault)) if dev.kind() == DeviceKind::Laser => {
                    ("module with status registers".to_string(), fault)
                }
                Some((ready, fault)) => (
                    format!("ready bit {}, fault bit {}", u8::from(ready), u8::from(fault)),
                    fault,
                ),
                None if dev.kind() == DeviceKind::Lamp => (
                    format!("coil-only module: rigd times the {warm_up} s warm-up from the coil's read-back"),
                    false,
                ),
                None => ("coil-only module".to_string(), false),
            };
            DeviceCheck {
                device: name.to_string(),
                kind: dev.kind().to_string(),
                usable: !fault,
                detail: format!("relay coil {coil} {relay}; {status}"),
                fix: fault.then(|| {
                    "the module reports a fault on this lamp: check ballast and bulb; switching the lamp off clears the module's latch".to_string()
                }),
                connect_s: 0.0,
            }
        }
    }
}

/// Connects every device of `profile` through `links` and reports each.
pub async fn check_rig(
    profile: &Profile,
    links: &BTreeMap<String, Link>,
    clock: &Clock,
) -> RigCheck {
    let start = clock.now_s();
    let own = join_all(profile.devices.iter().filter_map(|(name, dev)| {
        let link = links.get(name)?;
        if matches!(link, Link::Modbus { .. }) {
            return None;
        }
        let link = link.clone();
        Some(async move {
            let mut check = match connect_device(name, dev, link, clock).await {
                Err(e) => failed(name, dev, &e),
                Ok((_connected, id)) => match id.unusable {
                    None => DeviceCheck {
                        device: name.clone(),
                        kind: dev.kind().to_string(),
                        usable: true,
                        detail: id.about,
                        fix: None,
                        connect_s: 0.0,
                    },
                    Some((problem, fix)) => DeviceCheck {
                        device: name.clone(),
                        kind: dev.kind().to_string(),
                        usable: false,
                        detail: format!("{}; {problem}", id.about),
                        fix: Some(fix),
                        connect_s: 0.0,
                    },
                },
            };
            check.connect_s = clock.now_s() - start;
            (name.clone(), check)
        })
    }));
    // Coils: one connection per module, its devices asked one at a time
    // (Modbus allows one outstanding request per master).
    let mut modules: BTreeMap<String, Vec<(&String, &Device, Link)>> = BTreeMap::new();
    for (name, dev) in &profile.devices {
        if let Some(link @ Link::Modbus { bus, .. }) = links.get(name) {
            modules
                .entry(bus.clone())
                .or_default()
                .push((name, dev, link.clone()));
        }
    }
    let coils = join_all(modules.into_values().map(|devices| async move {
        let mut out = Vec::new();
        let Some((
            first,
            _,
            Link::Modbus {
                opener,
                framing,
                unit,
                status_registers,
                ..
            },
        )) = devices.first().cloned()
        else {
            return out;
        };
        match open_stream(clock, first, opener.as_ref()).await {
            Err(e) => {
                for (name, dev, _) in &devices {
                    let mut check = failed(name, dev, &e);
                    check.connect_s = clock.now_s() - start;
                    out.push(((*name).clone(), check));
                }
            }
            Ok(stream) => {
                let bus = std::sync::Arc::new(tokio::sync::Mutex::new(modbus_context(
                    stream, framing, unit,
                )));
                for (name, dev, _) in &devices {
                    let mut c = check_coil(name, dev, bus.clone(), status_registers, clock).await;
                    c.connect_s = clock.now_s() - start;
                    out.push(((*name).clone(), c));
                }
            }
        }
        out
    }));
    let (own, coils) = tokio::join!(own, coils);
    let mut by_name: BTreeMap<String, DeviceCheck> = own.into_iter().collect();
    by_name.extend(coils.into_iter().flatten());
    let devices: Vec<DeviceCheck> = profile
        .devices
        .iter()
        .map(|(name, dev)| {
            by_name.remove(name).unwrap_or_else(|| {
                failed(
                    name,
                    dev,
                    &DeviceError::new(
                        name,
                        ErrorKind::NotReady,
                        "no link configured for this device",
                    ),
                )
            })
        })
        .collect();
    RigCheck {
        profile: profile.name.clone(),
        usable: devices.iter().all(|d| d.usable),
        devices,
        took_s: clock.now_s() - start,
    }
}
