//! Simulated Modbus relay + I/O module for lamps and a laser line
//! (protocol: `firmware-protocols/modbus-lamps.md`).
//!
//! Why it is built this way:
//! - It serves any byte stream ([`ModbusModule::serve_stream`]), in both
//!   framings, through the frame codec of `rigd_proto::modbus`: the
//!   simulated rig runs under paused time, where real sockets are unsafe
//!   (tokio advances the clock while bytes sit in the kernel), so the rig
//!   wires driver and module over an in-memory `tokio::io::duplex` pair.
//!   [`ModbusModule::serve_tcp`] and [`ModbusModule::serve_rtu_over_tcp`] are
//!   an accept loop around the same path, for stock clients and tools. The
//!   driver keeps tokio-modbus's client codec, so the two sides do not share
//!   a codec (and cannot share its misunderstandings); the spec's
//!   transcripts pin both to the same bytes.
//! - Lamp physics: the FC05/FC0F reply
//!   comes after the relay switch time, and the ready bit is set `warm_up_s`
//!   after switch-on (measured through the [`Clock`], so paused-time tests
//!   cost no wall time) and cleared at switch-off.
//! - Faults come from the shared [`FaultInjector`] under the lamp's (or the
//!   laser's) device name: op `set` on FC05, op `ready` on every FC04 read.
//!   `Timeout` leaves that one request unanswered (later ones are served),
//!   `Disconnect` closes the stream, `Alarm` is exception 0x04 on a write
//!   (and the lamp's fault bit).
//! - Requests on one stream are served one at a time, in order, as a
//!   Modbus server does (one outstanding request per master).

use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use rigd_proto::modbus::{
    decode_request, encode_exception, encode_response, Exception, Header, RequestPdu, ResponsePdu,
};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::task::JoinHandle;

use crate::faults::{FaultInjector, FaultKind};
use rigd_core::clock::Clock;

use rigd_proto::modbus::Framing;

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
    /// The lamp's device name, under which faults are armed.
    pub name: String,
    /// Seconds from switch-on until the lamp's ready bit is set.
    pub warm_up_s: f64,
    /// Relay switch time in seconds; a write is answered after it.
    pub switch_s: f64,
}

/// What is wired to the module.
#[derive(Debug, Clone)]
pub struct ModuleConfig {
    /// The Modbus unit id the module answers to; it also answers 0xFF and
    /// executes broadcasts (unit 0) without answering.
    pub unit: u8,
    /// Lamps on coils 0..n (at most 16: the bitmask registers are 16 bits).
    pub lamps: Vec<LampSpec>,
    /// The laser, on coil n, if wired.
    pub laser: Option<String>,
    /// Relay switch time of the laser coil.
    pub laser_switch_s: f64,
    /// Whether the module has the ready, fault and burn-hour input
    /// registers. Without them (a coil-only relay module as sold) it
    /// answers FC04 with exception 0x01, illegal function.
    pub status_registers: bool,
    /// Whether the module takes FC0F (write multiple coils); some coil-only
    /// modules answer it with exception 0x01.
    pub write_multiple_coils: bool,
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

/// Why a request gets no normal reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Refusal {
    /// Answer with this exception.
    Exception(Exception),
    /// Never answer this request (injected `Timeout`).
    Silent,
    /// Close the stream without answering (injected `Disconnect`).
    Close,
}

impl From<Exception> for Refusal {
    fn from(e: Exception) -> Refusal {
        Refusal::Exception(e)
    }
}

/// What serving one request leaves to do on the stream.
#[derive(Debug)]
enum Answer {
    Send(Vec<u8>),
    Nothing,
    Close,
}

impl ModbusModule {
    /// A module with every coil off, its times measured on `clock`.
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
        rigd_core::sync::lock(&self.shared.state)
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
            if l.on && now + super::END_TOLERANCE_S >= l.on_at_s + spec.warm_up_s {
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
            } else if !on {
                if l.on {
                    l.burned_s += now - l.on_at_s;
                }
                // Writing off resets the ballast's fault latch, as on real
                // HMI supplies (also when a failed strike left it dark).
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

    /// Runs one decoded request and frames the answer, if any.
    async fn handle(&self, framing: Framing, hdr: Header, req: RequestPdu) -> Answer {
        // On RS-485 every module hears every frame: only our unit answers.
        // Unit 0 is broadcast (executed, never answered); TCP gateways
        // often send 0xFF, which a directly addressed module accepts.
        let broadcast = hdr.unit == 0;
        if !(broadcast || hdr.unit == self.shared.cfg.unit || hdr.unit == 0xFF) {
            return Answer::Nothing;
        }
        let function = req.function();
        match self.dispatch(req).await {
            Err(Refusal::Close) => Answer::Close,
            _ if broadcast => Answer::Nothing,
            Err(Refusal::Silent) => Answer::Nothing,
            Ok(resp) => Answer::Send(encode_response(framing, &hdr, &resp)),
            Err(Refusal::Exception(e)) => {
                Answer::Send(encode_exception(framing, &hdr, function, e))
            }
        }
    }

    /// Consults the fault injector; `Ok(())` means "behave normally".
    fn fault(&self, device: &str, op: &str) -> Result<(), Refusal> {
        match self.shared.faults.check(device, op) {
            None | Some(FaultKind::BadFrame | FaultKind::Dark | FaultKind::MaskMarkers) => Ok(()),
            Some(FaultKind::Alarm(_)) => {
                if let Some(k) = self.shared.cfg.lamps.iter().position(|l| l.name == device) {
                    if let Some(l) = self.lock().lamps.get_mut(k) {
                        l.fault = true;
                    }
                }
                Err(Exception::ServerDeviceFailure.into())
            }
            Some(FaultKind::Timeout) => Err(Refusal::Silent),
            Some(FaultKind::Disconnect) => Err(Refusal::Close),
        }
    }

    async fn dispatch(&self, req: RequestPdu) -> Result<ResponsePdu, Refusal> {
        let n = self.coil_count();
        match req {
            RequestPdu::ReadCoils { addr, count } => {
                if !self.in_range(addr, count, n) {
                    return Err(Exception::IllegalDataAddress.into());
                }
                let c = self.coils();
                let (a, b) = (usize::from(addr), usize::from(addr) + usize::from(count));
                Ok(ResponsePdu::ReadCoils(
                    c.get(a..b).unwrap_or_default().to_vec(),
                ))
            }
            RequestPdu::WriteSingleCoil { addr, on } => {
                let Some(name) = self.device_name(addr).map(str::to_string) else {
                    return Err(Exception::IllegalDataAddress.into());
                };
                self.fault(&name, "set")?;
                self.shared.clock.sleep_s(self.switch_s(addr)).await;
                self.set_coil(addr, on, self.shared.clock.now_s());
                Ok(ResponsePdu::WriteSingleCoil { addr, on })
            }
            RequestPdu::WriteMultipleCoils { .. } if !self.shared.cfg.write_multiple_coils => {
                Err(Exception::IllegalFunction.into())
            }
            RequestPdu::ReadInputRegisters { .. } if !self.shared.cfg.status_registers => {
                Err(Exception::IllegalFunction.into())
            }
            RequestPdu::WriteMultipleCoils { addr, values } => {
                let count = u16::try_from(values.len()).unwrap_or(u16::MAX);
                if !self.in_range(addr, count, n) {
                    return Err(Exception::IllegalDataAddress.into());
                }
                // The emergency-stop path: no fault injection, all relays
                // switch together, so the reply waits for the slowest one.
                let slowest = (addr..addr + count)
                    .map(|a| self.switch_s(a))
                    .fold(0.0, f64::max);
                self.shared.clock.sleep_s(slowest).await;
                let now = self.shared.clock.now_s();
                for (a, on) in (addr..=u16::MAX).zip(&values) {
                    self.set_coil(a, *on, now);
                }
                Ok(ResponsePdu::WriteMultipleCoils { addr, count })
            }
            RequestPdu::ReadInputRegisters { addr, count } => {
                let regs_len = IR_HOURS + u16::try_from(self.shared.cfg.lamps.len()).unwrap_or(0);
                if !self.in_range(addr, count, regs_len) {
                    return Err(Exception::IllegalDataAddress.into());
                }
                let names: Vec<String> = self
                    .shared
                    .cfg
                    .lamps
                    .iter()
                    .map(|l| l.name.clone())
                    .collect();
                for name in &names {
                    match self.fault(name, "ready") {
                        // An alarm on a poll shows up as the fault bit, not
                        // as an exception: the module itself is healthy.
                        Ok(()) | Err(Refusal::Exception(_)) => {}
                        Err(other) => return Err(other),
                    }
                }
                let regs = self.input_registers();
                let (a, b) = (usize::from(addr), usize::from(addr) + usize::from(count));
                Ok(ResponsePdu::ReadInputRegisters(
                    regs.get(a..b).unwrap_or_default().to_vec(),
                ))
            }
            RequestPdu::Rejected { exception, .. } => Err(exception.into()),
            _ => Err(Exception::IllegalFunction.into()),
        }
    }

    /// Serves the module on one byte stream until the peer closes it.
    ///
    /// Requests are decoded with `framing`, run one at a time in order, and
    /// answered on the same stream (no answer to broadcasts, to other
    /// units, or to a request hit by an injected `Timeout`). An injected
    /// `Disconnect` ends the call with `Ok(())`, dropping (closing) the
    /// stream. Bytes that are not a frame: on RTU the first byte is dropped
    /// and decoding retried (resync); on TCP the call returns an
    /// `InvalidData` error, dropping (closing) the stream, as real servers
    /// do. Read and write errors are returned.
    pub async fn serve_stream<S>(&self, mut stream: S, framing: Framing) -> io::Result<()>
    where
        S: AsyncRead + AsyncWrite + Unpin + Send,
    {
        let mut buf: Vec<u8> = Vec::with_capacity(512);
        let mut chunk = [0u8; 512];
        loop {
            loop {
                match decode_request(framing, &mut buf) {
                    Ok(Some((hdr, req))) => match self.handle(framing, hdr, req).await {
                        Answer::Send(bytes) => {
                            stream.write_all(&bytes).await?;
                            stream.flush().await?;
                        }
                        Answer::Nothing => {}
                        Answer::Close => return Ok(()),
                    },
                    Ok(None) => break,
                    Err(_) if framing == Framing::Rtu && !buf.is_empty() => {
                        buf.remove(0);
                    }
                    Err(e) => return Err(io::Error::new(io::ErrorKind::InvalidData, e)),
                }
            }
            let n = stream.read(&mut chunk).await?;
            if n == 0 {
                return Ok(());
            }
            buf.extend_from_slice(&chunk[..n]);
        }
    }

    /// Accepts connections on `listener`, serving each with
    /// [`ModbusModule::serve_stream`] in its own task. A broken connection
    /// only ends that connection.
    fn accept_loop(&self, listener: TcpListener, framing: Framing) -> JoinHandle<()> {
        let module = self.clone();
        tokio::spawn(async move {
            while let Ok((stream, _peer)) = listener.accept().await {
                let m = module.clone();
                tokio::spawn(async move {
                    let _ = m.serve_stream(stream, framing).await;
                });
            }
        })
    }

    /// Serves Modbus TCP on 127.0.0.1 (ephemeral port), for stock clients
    /// and tools. Real sockets: not for paused-time tests (use
    /// [`ModbusModule::serve_stream`] over `tokio::io::duplex`).
    pub async fn serve_tcp(&self) -> io::Result<(SocketAddr, JoinHandle<()>)> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        Ok((addr, self.accept_loop(listener, Framing::Tcp)))
    }

    /// Serves Modbus RTU framing (CRC, unit id first) over TCP on
    /// 127.0.0.1, as an RS-485-to-Ethernet gateway in transparent mode does.
    pub async fn serve_rtu_over_tcp(&self) -> io::Result<(SocketAddr, JoinHandle<()>)> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        Ok((addr, self.accept_loop(listener, Framing::Rtu)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;
    use tokio::io::DuplexStream;

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
                status_registers: true,
                write_multiple_coils: true,
            },
            Clock::virtual_time(),
            Arc::new(FaultInjector::new(rules)),
        )
    }

    /// The host end of an in-memory link to `m`, and the server task.
    fn connect(m: &ModbusModule, framing: Framing) -> (DuplexStream, JoinHandle<io::Result<()>>) {
        let (host, dev) = tokio::io::duplex(1024);
        let m = m.clone();
        let task = tokio::spawn(async move { m.serve_stream(dev, framing).await });
        (host, task)
    }

    async fn exchange(s: &mut DuplexStream, req: &[u8], reply_len: usize) -> Vec<u8> {
        s.write_all(req).await.unwrap_or_else(|e| panic!("{e}"));
        let mut buf = vec![0u8; reply_len];
        s.read_exact(&mut buf)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        buf
    }

    /// Reads what arrives within 10 s of virtual time: `None` on EOF.
    async fn next_bytes(s: &mut DuplexStream) -> Option<Vec<u8>> {
        let mut buf = [0u8; 64];
        match tokio::time::timeout(Duration::from_secs(10), s.read(&mut buf)).await {
            Ok(Ok(0)) | Ok(Err(_)) => None,
            Ok(Ok(n)) => Some(buf[..n].to_vec()),
            Err(_) => Some(Vec::new()),
        }
    }

    #[tokio::test(start_paused = true)]
    async fn tcp_frames_byte_for_byte() {
        let m = module(vec![]);
        let (mut s, _task) = connect(&m, Framing::Tcp);
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
        tokio::time::sleep(Duration::from_secs(1)).await;
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
        // FC03 is not implemented: exception 0x01.
        let req = [0, 4, 0, 0, 0, 6, 1, 0x03, 0, 0, 0, 1];
        assert_eq!(
            exchange(&mut s, &req, 9).await,
            vec![0, 4, 0, 0, 0, 3, 1, 0x83, 0x01]
        );
        // FC05 with a value other than FF00/0000: exception 0x03.
        let req = [0, 5, 0, 0, 0, 6, 1, 0x05, 0, 0, 0x12, 0x34];
        assert_eq!(
            exchange(&mut s, &req, 9).await,
            vec![0, 5, 0, 0, 0, 3, 1, 0x85, 0x03]
        );
    }

    #[tokio::test(start_paused = true)]
    async fn alarm_on_set_is_exception_4_and_fault_bit() {
        let m = module(vec!["lamp1:set:1:alarm=ballast"]);
        let (mut s, _task) = connect(&m, Framing::Tcp);
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 1, 0xFF, 0];
        assert_eq!(
            exchange(&mut s, &req, 9).await,
            vec![0, 1, 0, 0, 0, 3, 1, 0x85, 0x04]
        );
        assert_eq!(m.input_registers()[1], 0b10);
    }

    #[tokio::test(start_paused = true)]
    async fn disconnect_closes_the_stream() {
        let m = module(vec!["lamp0:set:1:disconnect"]);
        let (mut s, task) = connect(&m, Framing::Tcp);
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 0, 0xFF, 0];
        s.write_all(&req).await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(next_bytes(&mut s).await, None);
        assert!(task.await.unwrap_or_else(|e| panic!("{e}")).is_ok());
    }

    #[tokio::test(start_paused = true)]
    async fn timeout_fault_drops_one_request_and_serves_the_next() {
        let m = module(vec!["lamp0:set:1:timeout"]);
        let (mut s, _task) = connect(&m, Framing::Tcp);
        let req = [0, 1, 0, 0, 0, 6, 1, 0x05, 0, 0, 0xFF, 0];
        s.write_all(&req).await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(next_bytes(&mut s).await, Some(vec![]), "answered");
        assert_eq!(m.coils(), vec![false, false, false]);
        let req = [0, 2, 0, 0, 0, 6, 1, 0x05, 0, 0, 0xFF, 0];
        assert_eq!(exchange(&mut s, &req, 12).await, req.to_vec());
        assert_eq!(m.coils(), vec![true, false, false]);
    }

    #[tokio::test(start_paused = true)]
    async fn other_units_are_ignored_and_broadcasts_run_unanswered() {
        let m = module(vec![]);
        let (mut s, _task) = connect(&m, Framing::Rtu);
        // Unit 2, FC05 coil 0 on: not ours.
        let mut req = vec![0x02, 0x05, 0x00, 0x00, 0xFF, 0x00];
        req.extend(rigd_proto::modbus::crc16(&req).to_le_bytes());
        s.write_all(&req).await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(next_bytes(&mut s).await, Some(vec![]));
        assert_eq!(m.coils(), vec![false, false, false]);
        // Broadcast FC0F: all three on, no answer.
        let mut req = vec![0x00, 0x0F, 0x00, 0x00, 0x00, 0x03, 0x01, 0x07];
        req.extend(rigd_proto::modbus::crc16(&req).to_le_bytes());
        s.write_all(&req).await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(next_bytes(&mut s).await, Some(vec![]));
        assert_eq!(m.coils(), vec![true, true, true]);
    }

    #[tokio::test(start_paused = true)]
    async fn rtu_resyncs_after_garbage() {
        let m = module(vec![]);
        let (mut s, _task) = connect(&m, Framing::Rtu);
        // Noise (including a bad-CRC FC01 frame), then FC01 coils 0..3.
        let mut bytes = vec![0xFF, 0x01, 0x01, 0x00, 0x00, 0x00, 0x03, 0x00, 0x00, 0x13];
        bytes.extend([0x01, 0x01, 0x00, 0x00, 0x00, 0x03, 0x7C, 0x0B]);
        assert_eq!(
            rigd_proto::modbus::crc16(&[0x01, 0x01, 0x00, 0x00, 0x00, 0x03]),
            0x0B7C
        );
        s.write_all(&bytes).await.unwrap_or_else(|e| panic!("{e}"));
        let mut reply = vec![0x01, 0x01, 0x01, 0x00];
        reply.extend(rigd_proto::modbus::crc16(&reply).to_le_bytes());
        let mut got = vec![0u8; reply.len()];
        s.read_exact(&mut got)
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(got, reply);
    }

    #[tokio::test(start_paused = true)]
    async fn tcp_garbage_closes_the_connection() {
        let m = module(vec![]);
        let (mut s, task) = connect(&m, Framing::Tcp);
        // Protocol id 0x0102 is not Modbus.
        s.write_all(&[0, 1, 1, 2, 0, 6, 1, 1, 0, 0, 0, 1])
            .await
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(next_bytes(&mut s).await, None);
        let r = task.await.unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.map_err(|e| e.kind()), Err(io::ErrorKind::InvalidData));
    }

    #[tokio::test(start_paused = true)]
    async fn serve_stream_ends_when_the_peer_closes() {
        let m = module(vec![]);
        let (s, task) = connect(&m, Framing::Rtu);
        drop(s);
        assert!(task.await.unwrap_or_else(|e| panic!("{e}")).is_ok());
    }
}
