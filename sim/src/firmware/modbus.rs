//! Simulated Modbus relay + I/O module for lamps and a laser line
//! (protocol: `firmware-protocols/modbus-lamps.md`).
//!
//! Why it is built this way:
//! - The wire codec is tokio-modbus's own server skeleton, so the bytes the
//!   daemon's driver sees are those of a real stack, not of a second
//!   hand-written codec that could share the driver's misunderstandings.
//! - Lamp physics follow [`crate::devices::SimLamp`]: the FC05/FC0F reply
//!   comes after the relay switch time, and the ready bit is set `warm_up_s`
//!   after switch-on (measured through the [`Clock`], so paused-time tests
//!   cost no wall time) and cleared at switch-off.
//! - Faults come from the shared [`FaultInjector`] under the lamp's (or the
//!   laser's) device name: op `set` on FC05, op `ready` on every FC04 read.
//!   `Disconnect` must close the socket, which a `Service` cannot do, so each
//!   connection's stream is wrapped in a [`KillSwitch`] the service trips.

use std::future::Future;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;
use tokio_modbus::server::Service;
use tokio_modbus::{ExceptionCode, Request, Response, SlaveRequest};

use crate::clock::Clock;
use crate::faults::{FaultInjector, FaultKind};

/// Input register holding the ready bitmask (bit k = lamp on coil k).
pub const IR_READY: u16 = 0;
/// Input register holding the fault bitmask (bit k = lamp on coil k).
pub const IR_FAULT: u16 = 1;
/// First of the per-lamp burn-hour registers (IR 2 + k = lamp k).
pub const IR_HOURS: u16 = 2;
/// Unit id a module answers to out of the box.
pub const DEFAULT_UNIT: u8 = 1;

/// One lamp on the module: its coil is its index in [`ModuleConfig::lamps`].
#[derive(Debug, Clone)]
pub struct LampSpec {
    pub name: String,
    pub warm_up_s: f64,
    pub switch_s: f64,
}

/// What is wired to the module.
#[derive(Debug, Clone)]
pub struct ModuleConfig {
    pub unit: u8,
    /// Lamps on coils 0..n (at most 16: the bitmask registers are 16 bits).
    pub lamps: Vec<LampSpec>,
    /// The laser, on coil n, if wired.
    pub laser: Option<String>,
    /// Relay switch time of the laser coil.
    pub laser_switch_s: f64,
}

#[derive(Debug, Clone, Default)]
struct LampState {
    on: bool,
    /// Physical time the relay closed.
    on_at_s: f64,
    /// Burn time accumulated before the current switch-on.
    burned_s: f64,
    fault: bool,
}

#[derive(Debug)]
struct State {
    lamps: Vec<LampState>,
    laser_on: bool,
}

#[derive(Debug)]
struct Shared {
    cfg: ModuleConfig,
    clock: Clock,
    faults: Arc<FaultInjector>,
    state: Mutex<State>,
}

/// The module's state, shared by every connection to it (as on a real
/// module, a TCP client and a panel both see the same coils).
#[derive(Debug, Clone)]
pub struct ModbusModule {
    shared: Arc<Shared>,
}

type Reply = Result<Option<Response>, ExceptionCode>;

impl ModbusModule {
    pub fn new(cfg: ModuleConfig, clock: Clock, faults: Arc<FaultInjector>) -> ModbusModule {
        let lamps = vec![LampState::default(); cfg.lamps.len()];
        ModbusModule {
            shared: Arc::new(Shared {
                cfg,
                clock,
                faults,
                state: Mutex::new(State {
                    lamps,
                    laser_on: false,
                }),
            }),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // Plain data: a panic elsewhere cannot leave it inconsistent.
        self.shared.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn coil_count(&self) -> u16 {
        let n = self.shared.cfg.lamps.len() + usize::from(self.shared.cfg.laser.is_some());
        u16::try_from(n).unwrap_or(u16::MAX)
    }

    /// Current coil states (lamps, then the laser), for tests and a panel.
    pub fn coils(&self) -> Vec<bool> {
        let st = self.lock();
        let mut v: Vec<bool> = st.lamps.iter().map(|l| l.on).collect();
        if self.shared.cfg.laser.is_some() {
            v.push(st.laser_on);
        }
        v
    }

    /// The input registers as the module would report them now.
    pub fn input_registers(&self) -> Vec<u16> {
        let now = self.shared.clock.now_s();
        let st = self.lock();
        let mut ready = 0u16;
        let mut fault = 0u16;
        let mut hours = Vec::with_capacity(st.lamps.len());
        for (k, (l, spec)) in st.lamps.iter().zip(&self.shared.cfg.lamps).enumerate() {
            let bit = 1u16.checked_shl(k as u32).unwrap_or(0);
            if l.on && now >= l.on_at_s + spec.warm_up_s {
                ready |= bit;
            }
            if l.fault {
                fault |= bit;
            }
            let burned = l.burned_s + if l.on { now - l.on_at_s } else { 0.0 };
            hours.push((burned / 3600.0).clamp(0.0, f64::from(u16::MAX)) as u16);
        }
        let mut regs = vec![ready, fault];
        regs.extend(hours);
        regs
    }

    fn set_coil(&self, addr: u16, on: bool, now: f64) {
        let mut st = self.lock();
        let k = usize::from(addr);
        if let Some(l) = st.lamps.get_mut(k) {
            if on && !l.on {
                l.on_at_s = now;
            } else if !on && l.on {
                l.burned_s += now - l.on_at_s;
                // Switching off resets the ballast, as on real HMI supplies.
                l.fault = false;
            }
            l.on = on;
        } else if k == st.lamps.len() {
            st.laser_on = on;
        }
    }

    fn device_name(&self, addr: u16) -> Option<&str> {
        let k = usize::from(addr);
        let cfg = &self.shared.cfg;
        match cfg.lamps.get(k) {
            Some(l) => Some(&l.name),
            None if k == cfg.lamps.len() => cfg.laser.as_deref(),
            None => None,
        }
    }

    fn switch_s(&self, addr: u16) -> f64 {
        match self.shared.cfg.lamps.get(usize::from(addr)) {
            Some(l) => l.switch_s,
            None => self.shared.cfg.laser_switch_s,
        }
    }

    fn in_range(&self, addr: u16, count: u16, len: u16) -> bool {
        count >= 1 && u32::from(addr) + u32::from(count) <= u32::from(len)
    }

    async fn handle(self, req: SlaveRequest<'static>, kill: Arc<AtomicBool>) -> Reply {
        // On RS-485 every module hears every frame: only our unit answers.
        // Unit 0 is broadcast (writes only, never answered); TCP gateways
        // often send 0xFF, which a directly addressed module accepts.
        let unit = req.slave;
        let broadcast = unit == 0;
        if !(broadcast || unit == self.shared.cfg.unit || unit == 0xFF) {
            return Ok(None);
        }
        let reply = self.dispatch(req.request, &kill).await;
        if broadcast {
            return Ok(None);
        }
        reply.map(Some)
    }

    /// Consults the fault injector; `Ok(())` means "behave normally".
    async fn fault(&self, device: &str, op: &str, kill: &AtomicBool) -> Result<(), ExceptionCode> {
        match self.shared.faults.check(device, op) {
            None | Some(FaultKind::BadFrame) => Ok(()),
            Some(FaultKind::Alarm(_)) => {
                if let Some(k) = self.shared.cfg.lamps.iter().position(|l| l.name == device) {
                    if let Some(l) = self.lock().lamps.get_mut(k) {
                        l.fault = true;
                    }
                }
                Err(ExceptionCode::ServerDeviceFailure)
            }
            Some(FaultKind::Timeout) => std::future::pending().await,
            Some(FaultKind::Disconnect) => {
                kill.store(true, Ordering::SeqCst);
                Err(ExceptionCode::ServerDeviceFailure)
            }
        }
    }

    async fn dispatch(
        &self,
        req: Request<'static>,
        kill: &AtomicBool,
    ) -> Result<Response, ExceptionCode> {
        let n = self.coil_count();
        match req {
            Request::ReadCoils(addr, count) => {
                if !self.in_range(addr, count, n) {
                    return Err(ExceptionCode::IllegalDataAddress);
                }
                let c = self.coils();
                Ok(Response::ReadCoils(
                    c[usize::from(addr)..usize::from(addr) + usize::from(count)].to_vec(),
                ))
            }
            Request::WriteSingleCoil(addr, on) => {
                let Some(name) = self.device_name(addr).map(str::to_string) else {
                    return Err(ExceptionCode::IllegalDataAddress);
                };
                self.fault(&name, "set", kill).await?;
                self.shared.clock.sleep_s(self.switch_s(addr)).await;
                self.set_coil(addr, on, self.shared.clock.now_s());
                Ok(Response::WriteSingleCoil(addr, on))
            }
            Request::WriteMultipleCoils(addr, values) => {
                let count = u16::try_from(values.len()).unwrap_or(u16::MAX);
                if !self.in_range(addr, count, n) {
                    return Err(ExceptionCode::IllegalDataAddress);
                }
                // The emergency-stop path: no fault injection, all relays
                // switch together, so the reply waits for the slowest one.
                let slowest = (addr..addr + count)
                    .map(|a| self.switch_s(a))
                    .fold(0.0, f64::max);
                self.shared.clock.sleep_s(slowest).await;
                let now = self.shared.clock.now_s();
                for (i, on) in values.iter().enumerate() {
                    self.set_coil(addr + i as u16, *on, now);
                }
                Ok(Response::WriteMultipleCoils(addr, count))
            }
            Request::ReadInputRegisters(addr, count) => {
                let regs_len = IR_HOURS + u16::try_from(self.shared.cfg.lamps.len()).unwrap_or(0);
                if !self.in_range(addr, count, regs_len) {
                    return Err(ExceptionCode::IllegalDataAddress);
                }
                let names: Vec<String> = self
                    .shared
                    .cfg
                    .lamps
                    .iter()
                    .map(|l| l.name.clone())
                    .collect();
                for name in &names {
                    self.fault(name, "ready", kill).await.or_else(|e| {
                        // An alarm on a poll shows up as the fault bit, not
                        // as an exception: the module itself is healthy.
                        if kill.load(Ordering::SeqCst) {
                            Err(e)
                        } else {
                            Ok(())
                        }
                    })?;
                }
                let regs = self.input_registers();
                Ok(Response::ReadInputRegisters(
                    regs[usize::from(addr)..usize::from(addr) + usize::from(count)].to_vec(),
                ))
            }
            _ => Err(ExceptionCode::IllegalFunction),
        }
    }

    /// A `Service` for one connection; `kill` closes that connection.
    fn service(&self, kill: Arc<AtomicBool>) -> ConnService {
        ConnService {
            module: self.clone(),
            kill,
        }
    }

    /// Serves Modbus TCP on 127.0.0.1 (ephemeral port).
    pub async fn serve_tcp(&self) -> io::Result<(SocketAddr, JoinHandle<()>)> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let module = self.clone();
        let task = tokio::spawn(async move {
            let server = tokio_modbus::server::tcp::Server::new(listener);
            let on_connected = |stream: TcpStream, _peer: SocketAddr| {
                let m = module.clone();
                async move {
                    let kill = Arc::new(AtomicBool::new(false));
                    Ok(Some((
                        m.service(kill.clone()),
                        KillSwitch::new(stream, kill),
                    )))
                }
            };
            // A broken connection only ends that connection.
            let _ = server.serve(&on_connected, |_err| {}).await;
        });
        Ok((addr, task))
    }

    /// Serves Modbus RTU framing (CRC, unit id first) over TCP on
    /// 127.0.0.1, as an RS-485-to-Ethernet gateway in transparent mode does.
    /// tokio-modbus's RTU server only takes a real serial port, so this is
    /// how tests reach the RTU codec without hardware.
    pub async fn serve_rtu_over_tcp(&self) -> io::Result<(SocketAddr, JoinHandle<()>)> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let module = self.clone();
        let task = tokio::spawn(async move {
            let server = tokio_modbus::server::rtu_over_tcp::Server::new(listener);
            let on_connected = |stream: TcpStream, _peer: SocketAddr| {
                let m = module.clone();
                async move {
                    let kill = Arc::new(AtomicBool::new(false));
                    Ok(Some((
                        m.service(kill.clone()),
                        KillSwitch::new(stream, kill),
                    )))
                }
            };
            let _ = server.serve(&on_connected, |_err| {}).await;
        });
        Ok((addr, task))
    }
}

/// The module as seen by one connection.
pub struct ConnService {
    module: ModbusModule,
    kill: Arc<AtomicBool>,
}

impl Service for ConnService {
    type Request = SlaveRequest<'static>;
    type Response = Option<Response>;
    type Exception = ExceptionCode;
    type Future = Pin<Box<dyn Future<Output = Reply> + Send>>;

    fn call(&self, req: Self::Request) -> Self::Future {
        Box::pin(self.module.clone().handle(req, self.kill.clone()))
    }
}

/// A stream that reads EOF and fails writes once tripped, so the server
/// skeleton ends the connection and drops (closes) the socket.
#[derive(Debug)]
pub struct KillSwitch<T> {
    inner: T,
    killed: Arc<AtomicBool>,
}

impl<T> KillSwitch<T> {
    pub fn new(inner: T, killed: Arc<AtomicBool>) -> KillSwitch<T> {
        KillSwitch { inner, killed }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for KillSwitch<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if self.killed.load(Ordering::SeqCst) {
            return Poll::Ready(Ok(()));
        }
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for KillSwitch<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if self.killed.load(Ordering::SeqCst) {
            return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into()));
        }
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        if self.killed.load(Ordering::SeqCst) {
            return Poll::Ready(Err(io::ErrorKind::BrokenPipe.into()));
        }
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    fn module(faults: Vec<&str>) -> ModbusModule {
        let rules = faults
            .into_iter()
            .map(|f| f.parse().unwrap_or_else(|e| panic!("{e}")))
            .collect();
        ModbusModule::new(
            ModuleConfig {
                unit: 1,
                lamps: vec![
                    LampSpec {
                        name: "lamp0".into(),
                        warm_up_s: 1.0,
                        switch_s: 0.2,
                    },
                    LampSpec {
                        name: "lamp1".into(),
                        warm_up_s: 1.0,
                        switch_s: 0.2,
                    },
                ],
                laser: Some("laser".into()),
                laser_switch_s: 0.01,
            },
            Clock::virtual_time(),
            Arc::new(FaultInjector::new(rules)),
        )
    }

    async fn exchange(s: &mut TcpStream, req: &[u8], reply_len: usize) -> Vec<u8> {
        s.write_all(req).await.unwrap_or_else(|e| panic!("{e}"));
        let mut buf = vec![0u8; reply_len];
        s.read_exact(&mut buf)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        buf
    }

    #[tokio::test(start_paused = true)]
    async fn tcp_frames_byte_for_byte() {
        let m = module(vec![]);
        let (addr, _task) = m.serve_tcp().await.unwrap_or_else(|e| panic!("{e}"));
        let mut s = TcpStream::connect(addr)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        // FC05 coil 0 on: echoed.
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 0, 0xFF, 0];
        assert_eq!(exchange(&mut s, &req, 12).await, req.to_vec());
        assert_eq!(m.coils(), vec![true, false, false]);
        // FC04 IR0..2 right away: not ready yet.
        let req = [0, 2, 0, 0, 0, 6, 1, 0x04, 0, 0, 0, 2];
        assert_eq!(
            exchange(&mut s, &req, 13).await,
            vec![0, 2, 0, 0, 0, 7, 1, 4, 4, 0, 0, 0, 0]
        );
        tokio::time::sleep(std::time::Duration::from_secs(1)).await;
        assert_eq!(
            exchange(&mut s, &req, 13).await,
            vec![0, 2, 0, 0, 0, 7, 1, 4, 4, 0, 1, 0, 0]
        );
        // Coil 9 does not exist: exception 0x02.
        let req = [0, 3, 0, 0, 0, 6, 1, 0x05, 0, 9, 0xFF, 0];
        assert_eq!(
            exchange(&mut s, &req, 9).await,
            vec![0, 3, 0, 0, 0, 3, 1, 0x85, 0x02]
        );
    }

    #[tokio::test(start_paused = true)]
    async fn alarm_on_set_is_exception_4_and_fault_bit() {
        let m = module(vec!["lamp1:set:1:alarm=ballast"]);
        let (addr, _task) = m.serve_tcp().await.unwrap_or_else(|e| panic!("{e}"));
        let mut s = TcpStream::connect(addr)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 1, 0xFF, 0];
        assert_eq!(
            exchange(&mut s, &req, 9).await,
            vec![0, 1, 0, 0, 0, 3, 1, 0x85, 0x04]
        );
        assert_eq!(m.input_registers()[1], 0b10);
    }

    #[tokio::test(start_paused = true)]
    async fn disconnect_closes_the_socket() {
        let m = module(vec!["lamp0:set:1:disconnect"]);
        let (addr, _task) = m.serve_tcp().await.unwrap_or_else(|e| panic!("{e}"));
        let mut s = TcpStream::connect(addr)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 0, 0xFF, 0];
        s.write_all(&req).await.unwrap_or_else(|e| panic!("{e}"));
        let mut buf = [0u8; 16];
        let n = s.read(&mut buf).await.unwrap_or(0);
        assert_eq!(n, 0, "expected EOF, got {:?}", &buf[..n]);
    }
}
