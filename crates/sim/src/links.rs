//! The simulated controllers as the hardware-abstraction layer reaches
//! them: each is a [`rigd_hal::Opener`], as a serial port or a Modbus
//! socket is, whose every open starts the firmware on a fresh in-memory
//! byte stream. The drivers on the other end are the real ones; only the
//! wire is simulated.

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use async_trait::async_trait;
use rigd_core::Clock;
use rigd_hal::{ByteStream, Opener};
use rigd_proto::modbus::Framing;
use tokio::io::DuplexStream;

use crate::firmware::acl::{self as acl_fw, AclParams};
use crate::firmware::grbl::{self as grbl_fw, GrblParams};
use crate::firmware::modbus::ModbusModule;
use crate::{FaultInjector, SharedWorld, World};

/// Bytes an in-memory serial pipe buffers each way.
const PIPE_BUFFER: usize = 64 * 1024;

/// A serial controller's firmware, as a [`LineOpener`] starts it on each
/// open.
pub trait LineController: Clone + Send + Sync + 'static {
    /// What the controller is, for messages (`GRBL`, `ACL`).
    const KIND: &'static str;
    /// The controller's device, as the profile names it.
    fn name(&self) -> &str;
    /// The controller a re-opened link meets, given where `world` says
    /// its device physically stands.
    fn reopened(&mut self, world: &World);
    /// Serves `link` until it closes.
    fn serve(
        self,
        link: DuplexStream,
        clock: Clock,
        faults: Arc<FaultInjector>,
    ) -> impl Future<Output = std::io::Result<()>> + Send + 'static;
}

/// A GRBL board resets when its port opens: a re-opened link meets one
/// that lost its homing, its axis physically where it was.
impl LineController for GrblParams {
    const KIND: &'static str = "GRBL";

    fn name(&self) -> &str {
        &self.name
    }

    fn reopened(&mut self, world: &World) {
        if let Some(&p) = world.axes.get(&self.name) {
            self.physical_start = p;
        }
    }

    fn serve(
        self,
        link: DuplexStream,
        clock: Clock,
        faults: Arc<FaultInjector>,
    ) -> impl Future<Output = std::io::Result<()>> + Send + 'static {
        grbl_fw::serve(link, self, clock, faults)
    }
}

/// An ACL controller keeps its encoder counts and homing across a
/// re-opened serial link.
impl LineController for AclParams {
    const KIND: &'static str = "ACL";

    fn name(&self) -> &str {
        &self.name
    }

    fn reopened(&mut self, world: &World) {
        if let Some(q) = &world.arm {
            self.power_up_counts = q
                .iter()
                .zip(&self.joints)
                .map(|(deg, j)| (deg * j.counts_per_deg).round() as i64)
                .collect();
            self.start_homed = true;
        }
    }

    fn serve(
        self,
        link: DuplexStream,
        clock: Clock,
        faults: Arc<FaultInjector>,
    ) -> impl Future<Output = std::io::Result<()>> + Send + 'static {
        acl_fw::serve(link, self, clock, faults)
    }
}

/// Starts a serial controller's firmware per open: the first as its
/// parameters say, every later one as [`LineController::reopened`] says.
pub struct LineOpener<C> {
    controller: C,
    clock: Clock,
    faults: Arc<FaultInjector>,
    world: SharedWorld,
    opened: AtomicBool,
}

impl<C: LineController> LineOpener<C> {
    /// The controller `controller`, its device moving in `world`.
    pub fn new(
        controller: C,
        clock: Clock,
        faults: Arc<FaultInjector>,
        world: SharedWorld,
    ) -> LineOpener<C> {
        LineOpener {
            controller,
            clock,
            faults,
            world,
            opened: AtomicBool::new(false),
        }
    }
}

#[async_trait]
impl<C: LineController> Opener for LineOpener<C> {
    fn describe(&self) -> String {
        format!(
            "simulated {} controller `{}`",
            C::KIND,
            self.controller.name()
        )
    }

    async fn open(&self) -> std::io::Result<ByteStream> {
        let mut controller = self.controller.clone();
        if self.opened.swap(true, Ordering::SeqCst) {
            controller.reopened(&self.world.snapshot());
        }
        let (host, dev) = tokio::io::duplex(PIPE_BUFFER);
        // A closed link ends the firmware; the driver says what it lost.
        tokio::spawn(controller.serve(dev, self.clock.clone(), self.faults.clone()));
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
