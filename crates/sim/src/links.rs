//! The simulated controllers as the hardware-abstraction layer reaches
//! them: each is a [`rigd_hal::Opener`], as a serial port or a Modbus
//! socket is, whose every open starts the firmware on a fresh in-memory
//! byte stream. The drivers on the other end are the real ones; only the
//! wire is simulated.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use async_trait::async_trait;
use rigd_core::Clock;
use rigd_hal::{ByteStream, Opener};
use rigd_proto::modbus::Framing;

use crate::firmware::acl::{self as acl_fw, AclParams};
use crate::firmware::grbl::{self as grbl_fw, GrblParams};
use crate::firmware::modbus::ModbusModule;
use crate::{FaultInjector, SharedWorld};

/// Bytes an in-memory serial pipe buffers each way.
const PIPE_BUFFER: usize = 64 * 1024;

/// Starts a GRBL controller per open. A re-opened link meets a controller
/// that reset (as GRBL does when the port opens): it lost its homing but
/// the axis physically stays where it was.
pub struct GrblOpener {
    params: GrblParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
    world: SharedWorld,
    opened: AtomicBool,
}

impl GrblOpener {
    /// The controller of `params`, its axis moving in `world`.
    pub fn new(
        params: GrblParams,
        clock: Clock,
        faults: Arc<FaultInjector>,
        world: SharedWorld,
    ) -> GrblOpener {
        GrblOpener {
            params,
            clock,
            faults,
            world,
            opened: AtomicBool::new(false),
        }
    }
}

#[async_trait]
impl Opener for GrblOpener {
    fn describe(&self) -> String {
        format!("simulated GRBL controller `{}`", self.params.name)
    }

    async fn open(&self) -> std::io::Result<ByteStream> {
        let mut params = self.params.clone();
        if self.opened.swap(true, Ordering::SeqCst) {
            if let Some(&p) = self.world.snapshot().axes.get(&params.name) {
                params.physical_start = p;
            }
        }
        let (host, dev) = tokio::io::duplex(PIPE_BUFFER);
        let (clock, faults) = (self.clock.clone(), self.faults.clone());
        // A closed link ends the firmware; the driver says what it lost.
        tokio::spawn(async move { grbl_fw::serve(dev, params, clock, faults).await });
        Ok(Box::new(host))
    }
}

/// Starts an ACL controller per open. The controller keeps its encoder
/// counts and homing across a re-opened serial link.
pub struct AclOpener {
    params: AclParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
    world: SharedWorld,
    opened: AtomicBool,
}

impl AclOpener {
    /// The controller of `params`, its arm moving in `world`.
    pub fn new(
        params: AclParams,
        clock: Clock,
        faults: Arc<FaultInjector>,
        world: SharedWorld,
    ) -> AclOpener {
        AclOpener {
            params,
            clock,
            faults,
            world,
            opened: AtomicBool::new(false),
        }
    }
}

#[async_trait]
impl Opener for AclOpener {
    fn describe(&self) -> String {
        format!("simulated ACL controller `{}`", self.params.name)
    }

    async fn open(&self) -> std::io::Result<ByteStream> {
        let mut params = self.params.clone();
        if self.opened.swap(true, Ordering::SeqCst) {
            if let Some(q) = self.world.snapshot().arm {
                params.power_up_counts = q
                    .iter()
                    .zip(&params.joints)
                    .map(|(deg, j)| (deg * j.counts_per_deg).round() as i64)
                    .collect();
                params.start_homed = true;
            }
        }
        let (host, dev) = tokio::io::duplex(PIPE_BUFFER);
        let (clock, faults) = (self.clock.clone(), self.faults.clone());
        // A closed link ends the firmware; the driver says what it lost.
        tokio::spawn(async move { acl_fw::serve(dev, params, clock, faults).await });
        Ok(Box::new(host))
    }
}

/// Connects to the (one, persistent) simulated Modbus module of a bus.
pub struct ModbusOpener {
    module: ModbusModule,
    framing: Framing,
    bus: String,
}

impl ModbusOpener {
    /// The bus `bus` (its identity, for messages) to `module`, framed as
    /// `framing`.
    pub fn new(module: ModbusModule, framing: Framing, bus: String) -> ModbusOpener {
        ModbusOpener {
            module,
            framing,
            bus,
        }
    }
}

#[async_trait]
impl Opener for ModbusOpener {
    fn describe(&self) -> String {
        format!("simulated Modbus module `{}`", self.bus)
    }

    async fn open(&self) -> std::io::Result<ByteStream> {
        let (host, dev) = tokio::io::duplex(PIPE_BUFFER);
        let module = self.module.clone();
        let framing = self.framing;
        // A closed link ends the module's session; the module lives on.
        tokio::spawn(async move { module.serve_stream(dev, framing).await });
        Ok(Box::new(host))
    }
}
