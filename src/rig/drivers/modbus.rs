//! Modbus relay-module driver for lamps and a laser line (protocol:
//! `firmware-protocols/modbus-lamps.md`).
//!
//! Why it is built this way:
//! - All lamps of one module share one bus (one RS-485 line or one TCP
//!   connection) and Modbus allows one outstanding request per master, so
//!   they share one `tokio_modbus` [`Context`] behind an async mutex, held
//!   for one request at a time and never across a sleep.
//! - A relay reply only says the module accepted the write, so `set` reads
//!   the coil back before reporting success.
//! - The relay being closed does not mean the light is usable: arc lamps
//!   need minutes, so `wait_ready` polls the module's ready bit, and a set
//!   fault bit ends the wait at once instead of at the deadline.
//! - Relay modules as sold have coils only, no status registers: there
//!   `wait_ready` times the warm-up itself, from the moment the coil read
//!   back closed, and checks the coil again at the end, so only FC01, FC05
//!   and FC0F go on the wire.
//! - Every request runs under a [`Clock`] deadline, so a silent module is a
//!   `Timeout` in physical time, also under the simulator's paused clock.

use std::io;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::sync::Mutex;
use tokio_modbus::client::{Context, Reader, Writer};
use tokio_modbus::{ExceptionCode, Slave};

use crate::rig::hal::{DeviceError, ErrorKind, Lamp, LaserLine};
use rigd_core::Clock;

/// Input register holding the ready bitmask (bit k = lamp on coil k).
pub const IR_READY: u16 = 0;
/// Input register holding the fault bitmask (bit k = lamp on coil k).
pub const IR_FAULT: u16 = 1;

/// One module's bus, shared by the lamps and the laser wired to it.
pub type SharedBus = Arc<Mutex<Context>>;

/// Attaches to a module over an open Modbus TCP stream (MBAP framing).
pub fn tcp_bus<T>(stream: T, unit: u8) -> SharedBus
where
    T: AsyncRead + AsyncWrite + Send + Unpin + std::fmt::Debug + 'static,
{
    Arc::new(Mutex::new(tokio_modbus::client::tcp::attach_slave(
        stream,
        Slave(unit),
    )))
}

/// Connects to a module at a TCP address, within `timeout` of physical time.
pub async fn connect_tcp(
    clock: &Clock,
    addr: SocketAddr,
    unit: u8,
    timeout: Duration,
) -> Result<SharedBus, ModbusError> {
    let stream = clock
        .deadline(timeout, tokio::net::TcpStream::connect(addr))
        .await
        .map_err(|_| ModbusError::Timeout {
            what: format!("connect to {addr}"),
            timeout,
        })?
        .map_err(ModbusError::Io)?;
    Ok(tcp_bus(stream, unit))
}

/// Attaches to a module over any byte stream with RTU framing (a serial
/// port, a transparent RS-485 gateway socket, a test pipe).
pub fn rtu_bus<T>(transport: T, unit: u8) -> SharedBus
where
    T: AsyncRead + AsyncWrite + Send + Unpin + 'static,
{
    Arc::new(Mutex::new(tokio_modbus::client::rtu::attach_slave(
        transport,
        Slave(unit),
    )))
}

/// What went wrong talking to the module, in the driver's own terms.
#[derive(Debug, thiserror::Error)]
pub enum ModbusError {
    /// A connect or a request that got no answer before its deadline.
    #[error("no answer to {what} within {timeout:?}")]
    Timeout {
        /// The connect or request that timed out.
        what: String,
        /// The deadline it had.
        timeout: Duration,
    },
    /// Connecting or talking to the module failed at the transport.
    #[error("link lost: {0}")]
    Io(io::Error),
    /// The module answered with a Modbus exception (e.g. a coil or
    /// register that is not wired).
    #[error("{what} refused with Modbus exception {}", exception_name(.code))]
    Exception {
        /// The request it refused.
        what: String,
        /// The exception code of the reply.
        code: ExceptionCode,
    },
    /// A reply of the wrong shape or length for its request.
    #[error("malformed or mismatched reply: {0}")]
    Protocol(String),
    /// Reading the coil back after a write gave the other state.
    #[error("coil {coil} reads {read} after writing {wanted}")]
    NotConfirmed {
        /// The coil written.
        coil: u16,
        /// The state written.
        wanted: bool,
        /// The state read back.
        read: bool,
    },
    /// While waiting for a lamp, the module set its fault bit (the coil
    /// number).
    #[error("the module reports a fault on this lamp (fault bit {0} set): check ballast and bulb")]
    LampFault(u16),
    /// A lamp's ready bit did not come within its warm-up plus slack (the
    /// time waited).
    #[error("lamp not ready {0:?} after switch-on")]
    NotReady(Duration),
    /// Waiting for a lamp that this driver has not switched on.
    #[error("lamp is switched off; switch it on before waiting for it")]
    Off,
}

/// Names an exception the way the Modbus specification does.
pub fn exception_name(code: &ExceptionCode) -> String {
    match code {
        ExceptionCode::IllegalFunction => "0x01 illegal function".into(),
        ExceptionCode::IllegalDataAddress => {
            "0x02 illegal data address (coil or register not wired)".into()
        }
        ExceptionCode::IllegalDataValue => "0x03 illegal data value".into(),
        ExceptionCode::ServerDeviceFailure => "0x04 slave device failure".into(),
        ExceptionCode::ServerDeviceBusy => "0x06 slave device busy".into(),
        other => format!("{other:?}"),
    }
}

impl ModbusError {
    /// The kind the run engine acts on.
    pub fn kind(&self) -> ErrorKind {
        match self {
            ModbusError::Timeout { .. } | ModbusError::NotReady(_) => ErrorKind::Timeout,
            ModbusError::Io(_) => ErrorKind::Disconnected,
            ModbusError::Exception { .. }
            | ModbusError::NotConfirmed { .. }
            | ModbusError::LampFault(_) => ErrorKind::DeviceFault,
            ModbusError::Protocol(_) => ErrorKind::BadFrame,
            ModbusError::Off => ErrorKind::NotReady,
        }
    }

    /// As a [`DeviceError`] of the device `name`, with its engine kind.
    pub fn into_device(self, name: &str) -> DeviceError {
        DeviceError::new(name, self.kind(), self.to_string())
    }
}

/// How one coil on a module is driven.
#[derive(Debug, Clone)]
pub struct ModbusConfig {
    /// Device name used in errors.
    pub name: String,
    /// The coil (0-based); for a lamp also its bit in the ready/fault masks.
    pub coil: u16,
    /// Relay switch time: the module replies to a write after switching.
    pub switch: Duration,
    /// Warm-up from switch-on to stable light (lamps only).
    pub warm_up: Duration,
    /// Deadline for one request, on top of the switch time for writes.
    pub request_timeout: Duration,
    /// Ready-bit poll interval during warm-up.
    pub poll_interval: Duration,
    /// Whether the module has the ready and fault input registers; without
    /// them the warm-up is timed from the coil's read-back.
    pub status_registers: bool,
}

impl ModbusConfig {
    /// Defaults: 1 s per request, 250 ms polls.
    pub fn new(name: &str, coil: u16, warm_up: Duration, switch: Duration) -> ModbusConfig {
        ModbusConfig {
            name: name.to_string(),
            coil,
            switch,
            warm_up,
            request_timeout: Duration::from_secs(1),
            poll_interval: Duration::from_millis(250),
            status_registers: true,
        }
    }
}

/// One coil on a shared bus: the part lamps and lasers have in common.
struct Coil {
    cfg: ModbusConfig,
    clock: Clock,
    bus: SharedBus,
}

/// Unwraps tokio-modbus's nested result into the driver's error.
fn flatten<T>(what: &str, r: tokio_modbus::Result<T>) -> Result<T, ModbusError> {
    match r {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(code)) => Err(ModbusError::Exception {
            what: what.to_string(),
            code,
        }),
        Err(tokio_modbus::Error::Transport(e)) => Err(ModbusError::Io(e)),
        Err(tokio_modbus::Error::Protocol(e)) => Err(ModbusError::Protocol(e.to_string())),
    }
}

impl Coil {
    async fn request<T, F>(&self, what: &str, timeout: Duration, f: F) -> Result<T, ModbusError>
    where
        F: for<'a> FnOnce(
            &'a mut Context,
        ) -> std::pin::Pin<
            Box<dyn std::future::Future<Output = tokio_modbus::Result<T>> + Send + 'a>,
        >,
    {
        let bus = self.bus.clone();
        let fut = async move {
            let mut ctx = bus.lock().await;
            f(&mut ctx).await
        };
        let r = self
            .clock
            .deadline(timeout, fut)
            .await
            .map_err(|_| ModbusError::Timeout {
                what: what.to_string(),
                timeout,
            })?;
        flatten(what, r)
    }

    async fn set(&self, on: bool) -> Result<(), ModbusError> {
        let coil = self.cfg.coil;
        let t = self.cfg.request_timeout + self.cfg.switch;
        self.request(&format!("write coil {coil}"), t, move |c| {
            Box::pin(c.write_single_coil(coil, on))
        })
        .await?;
        match self.read().await? {
            r if r == on => Ok(()),
            r => Err(ModbusError::NotConfirmed {
                coil,
                wanted: on,
                read: r,
            }),
        }
    }

    /// The coil's state, read back with FC01.
    async fn read(&self) -> Result<bool, ModbusError> {
        let coil = self.cfg.coil;
        let read = self
            .request(
                &format!("read coil {coil}"),
                self.cfg.request_timeout,
                move |c| Box::pin(c.read_coils(coil, 1)),
            )
            .await?;
        read.first()
            .copied()
            .ok_or_else(|| ModbusError::Protocol("empty coil read-back".into()))
    }
}

/// A lamp switched by a relay coil, with a ready bit for stable output
/// (or, on a coil-only module, a warm-up timed by the host).
pub struct ModbusLamp {
    coil: Coil,
    /// When the coil read back closed (clock time), while the lamp is on.
    on_since: Option<Duration>,
}

impl ModbusLamp {
    /// A lamp on `cfg.coil` of the module behind `bus`, taken as off.
    pub fn new(cfg: ModbusConfig, clock: Clock, bus: SharedBus) -> ModbusLamp {
        ModbusLamp {
            coil: Coil { cfg, clock, bus },
            on_since: None,
        }
    }

    async fn wait_ready_inner(&mut self) -> Result<(), ModbusError> {
        let Some(on_since) = self.on_since else {
            return Err(ModbusError::Off);
        };
        if !self.coil.cfg.status_registers {
            return self.wait_warm_up(on_since).await;
        }
        let cfg = &self.coil.cfg;
        let bit = 1u16.checked_shl(u32::from(cfg.coil)).unwrap_or(0);
        // Slack: a few polls and one request beyond the nominal warm-up.
        let limit = cfg.warm_up + cfg.request_timeout + 4 * cfg.poll_interval;
        let start = self.coil.clock.now();
        // The warm-up runs from the coil's closing: asked at once, then when
        // it should be over, then every interval.
        let mut polls = super::Polls::new(cfg.poll_interval, cfg.warm_up);
        loop {
            let regs = self
                .coil
                .request("read ready/fault registers", cfg.request_timeout, |c| {
                    Box::pin(c.read_input_registers(IR_READY, 2))
                })
                .await?;
            let (ready, fault) = match regs.as_slice() {
                [r, f] => (*r, *f),
                _ => {
                    return Err(ModbusError::Protocol(format!(
                        "{} registers, expected 2",
                        regs.len()
                    )))
                }
            };
            if fault & bit != 0 {
                return Err(ModbusError::LampFault(cfg.coil));
            }
            if ready & bit != 0 {
                return Ok(());
            }
            // The floor of wall time a sped-up simulation keeps: there a
            // request's round trip on a loaded machine is seconds of
            // physical time, and a lamp is not dead for that.
            if self.coil.clock.has_passed(start, limit) {
                return Err(ModbusError::NotReady(limit));
            }
            let since_on = self.coil.clock.now().saturating_sub(on_since);
            self.coil.clock.sleep(polls.next_wait(since_on)).await;
        }
    }

    /// A coil-only module: the lamp is ready `warm_up` after its coil read
    /// back closed. The coil is read once more at the end, so a relay that
    /// dropped (a module power cycle, a panel switch) is not taken as light.
    async fn wait_warm_up(&self, on_since: Duration) -> Result<(), ModbusError> {
        let clock = &self.coil.clock;
        let ready_at = on_since + self.coil.cfg.warm_up;
        let now = clock.now();
        if ready_at > now {
            clock.sleep(ready_at - now).await;
        }
        if self.coil.read().await? {
            Ok(())
        } else {
            Err(ModbusError::NotConfirmed {
                coil: self.coil.cfg.coil,
                wanted: true,
                read: false,
            })
        }
    }
}

#[async_trait]
impl Lamp for ModbusLamp {
    async fn set(&mut self, on: bool) -> Result<(), DeviceError> {
        // Switching on an already-on lamp keeps its warm-up under way.
        let was = self.on_since.take();
        let r = self.coil.set(on).await;
        // Whatever happened, the state is unknown until confirmed.
        if on && r.is_ok() {
            self.on_since = Some(was.unwrap_or_else(|| self.coil.clock.now()));
        }
        r.map_err(|e| e.into_device(&self.coil.cfg.name))
    }

    async fn wait_ready(&mut self) -> Result<(), DeviceError> {
        self.wait_ready_inner()
            .await
            .map_err(|e| e.into_device(&self.coil.cfg.name))
    }
}

/// A laser line switched by a relay coil (no warm-up, no ready bit).
pub struct ModbusLaser {
    coil: Coil,
}

impl ModbusLaser {
    /// A laser line on `cfg.coil` of the module behind `bus`.
    pub fn new(cfg: ModbusConfig, clock: Clock, bus: SharedBus) -> ModbusLaser {
        ModbusLaser {
            coil: Coil { cfg, clock, bus },
        }
    }
}

#[async_trait]
impl LaserLine for ModbusLaser {
    async fn set(&mut self, on: bool) -> Result<(), DeviceError> {
        self.coil
            .set(on)
            .await
            .map_err(|e| e.into_device(&self.coil.cfg.name))
    }
}

/// A coil's state as its module reports it, read without switching it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CoilProbe {
    /// The relay is closed.
    pub on: bool,
    /// The coil's ready and fault bits (IR 0, IR 1); None on a coil-only
    /// module.
    pub status: Option<(bool, bool)>,
}

/// Reads a coil (FC01) and, if the module has them, its ready and fault
/// bits (FC04): what `rig check` reports of a lamp or laser.
pub async fn probe_coil(
    cfg: ModbusConfig,
    clock: Clock,
    bus: SharedBus,
) -> Result<CoilProbe, ModbusError> {
    let with_status = cfg.status_registers;
    let bit = 1u16.checked_shl(u32::from(cfg.coil)).unwrap_or(0);
    let timeout = cfg.request_timeout;
    let coil = Coil { cfg, clock, bus };
    let on = coil.read().await?;
    let status = if with_status {
        let regs = coil
            .request("read ready/fault registers", timeout, |c| {
                Box::pin(c.read_input_registers(IR_READY, 2))
            })
            .await?;
        match regs.as_slice() {
            [r, f] => Some((r & bit != 0, f & bit != 0)),
            _ => {
                return Err(ModbusError::Protocol(format!(
                    "{} registers, expected 2",
                    regs.len()
                )))
            }
        }
    } else {
        None
    };
    Ok(CoilProbe { on, status })
}

/// Emergency stop: every coil 0..`coils` off in one FC0F request, so all
/// relays drop together instead of one round trip per lamp. A module that
/// refuses FC0F (exception 0x01, illegal function) gets its coils switched
/// off one by one with FC05, all within the same `timeout`.
pub async fn all_off(
    clock: &Clock,
    bus: &SharedBus,
    coils: u16,
    timeout: Duration,
) -> Result<(), ModbusError> {
    let off = vec![false; usize::from(coils)];
    let fut = async {
        let mut ctx = bus.lock().await;
        let all = flatten(
            "write all coils off",
            ctx.write_multiple_coils(0, &off).await,
        );
        match all {
            Err(ModbusError::Exception {
                code: ExceptionCode::IllegalFunction,
                ..
            }) => {
                tracing::info!("the module refuses FC0F: switching its coils off one by one");
                for coil in 0..coils {
                    let what = format!("write coil {coil} off");
                    flatten(&what, ctx.write_single_coil(coil, false).await)?;
                }
                Ok(())
            }
            other => other,
        }
    };
    clock
        .deadline(timeout, fut)
        .await
        .map_err(|_| ModbusError::Timeout {
            what: "write all coils off".into(),
            timeout,
        })?
}
