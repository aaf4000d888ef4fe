//! GRBL 1.1 stepper axis driver (protocol: `firmware-protocols/grbl.md`).
//!
//! Units: one axis per controller, mapped to GRBL's X axis, with the
//! controller configured so that one GRBL unit ("mm") is one degree
//! (`$100` = steps per degree). Positions are machine positions (`MPos`).
//!
//! Why it is built this way:
//! - `ok` to a `G0` only means "queued in the planner", so a move is done
//!   when a polled status report says `Idle`, not when `ok` arrives.
//! - GRBL drops bytes silently when its 127-byte receive buffer is full, so
//!   the driver counts the bytes of unanswered lines (character counting)
//!   and never sends a line that would not fit.
//! - GRBL has no sequence numbers: after a timed-out command the driver
//!   cannot tell which `ok` belongs to which line, so the next call first
//!   drains the link up to a fresh status report before sending anything.
//! - After a (re)connect or an unexpected welcome banner the controller has
//!   reset, so the position is re-read from `MPos`, never taken from the
//!   last set-point.
//! - The controller, not the profile, decides how fast the axis moves: at
//!   connect the driver reads `$$`, compares the settings with the profile
//!   (or writes them, with `configure`), and sizes its motion deadlines
//!   from the controller's own `$110` and `$120`.

use std::collections::{BTreeMap, VecDeque};
use std::fmt;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use rigd_proto::grbl::{
    format_setting, parse_reply, AlarmCode, Command, ErrorCode, LineSplitter, MachineState,
    Realtime, Reply, Status, RX_BUFFER_SIZE,
};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, ReadHalf, WriteHalf};
use tokio::sync::Mutex;

use super::{stop_failed, write_locked};
use crate::model::profile::{Limits, Motion};
use crate::rig::hal::{Axis, DeviceError, EmergencyStop, ErrorKind};
use rigd_core::Clock;

/// How a GRBL axis is driven.
#[derive(Debug, Clone)]
pub struct GrblConfig {
    /// Device name used in errors.
    pub name: String,
    /// Soft limits in degrees; set-points outside are refused before sending.
    pub limits: Limits,
    /// The controller's motion model, used only to size motion deadlines.
    pub motion: Motion,
    /// Deadline for a reply to one line or one status query.
    pub command_timeout: Duration,
    /// Deadline for the homing cycle (GRBL answers `$H` when it is done).
    pub home_timeout: Duration,
    /// Status poll interval while waiting for motion to complete. GRBL's
    /// documentation recommends polling at no more than 5 Hz.
    pub poll_interval: Duration,
    /// Whether the controller homes the axis (`$H`). Without homing the
    /// operator sets the axis at its 0° mark and zeroes the controller
    /// there; the driver takes the machine position as it is.
    pub homing: bool,
    /// Write the settings the profile implies to the controller at connect
    /// (then read them back), instead of refusing a controller whose
    /// settings differ.
    pub configure: bool,
    /// `$100`, steps per degree, when the profile states it.
    pub steps_per_deg: Option<f64>,
}

impl GrblConfig {
    /// Defaults: 2 s per command, 120 s for homing, 200 ms polls (5 Hz).
    pub fn new(name: &str, limits: Limits, motion: Motion) -> GrblConfig {
        GrblConfig {
            name: name.to_string(),
            limits,
            motion,
            command_timeout: Duration::from_secs(2),
            home_timeout: Duration::from_secs(120),
            poll_interval: Duration::from_millis(200),
            homing: true,
            configure: false,
            steps_per_deg: None,
        }
    }

    /// The controller settings this axis needs, in the order they are
    /// written: `$22` first, since GRBL checks `$20` against it.
    pub fn expected_settings(&self) -> Vec<ExpectedSetting> {
        let m = self.motion;
        let mut v = vec![
            ExpectedSetting {
                number: 22,
                what: "homing cycle enable",
                wanted: Wanted::Exactly(if self.homing { 1.0 } else { 0.0 }),
                because: format!("homing = {}", self.homing),
            },
            ExpectedSetting {
                number: 20,
                what: "soft limits enable",
                wanted: Wanted::Exactly(0.0),
                because: "rigd checks `limits` itself before every move; GRBL's soft limits assume travel [-$130, 0] from the home switch".into(),
            },
            ExpectedSetting {
                number: 110,
                what: "X max rate, deg/min",
                wanted: Wanted::Exactly(m.max_velocity * 60.0),
                because: format!("motion.max_velocity = {} deg/s", m.max_velocity),
            },
            ExpectedSetting {
                number: 120,
                what: "X acceleration, deg/s²",
                wanted: Wanted::Exactly(m.acceleration),
                because: format!("motion.acceleration = {} deg/s²", m.acceleration),
            },
        ];
        if self.homing {
            let span = self.limits.max - self.limits.min;
            v.push(ExpectedSetting {
                number: 130,
                what: "X max travel, deg",
                wanted: Wanted::AtLeast(span),
                because: format!(
                    "limits span {span} deg; the homing cycle searches 1.5 × $130 for the switch"
                ),
            });
        }
        if let Some(steps) = self.steps_per_deg {
            v.push(ExpectedSetting {
                number: 100,
                what: "X steps/deg",
                wanted: Wanted::Exactly(steps),
                because: format!("steps_per_deg = {steps}"),
            });
        }
        v
    }
}

/// The modelled time of a move of `distance` degrees at `rates` (0 if the
/// model cannot say).
fn modelled_move_time(rates: Motion, distance: f64) -> Duration {
    let travel = rigd_core::Trapezoid::from(rates).move_time(distance);
    if travel.is_finite() && travel >= 0.0 {
        Duration::from_secs_f64(travel)
    } else {
        Duration::ZERO
    }
}

/// What a setting must be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Wanted {
    /// This value (to GRBL's three printed decimals).
    Exactly(f64),
    /// This value or more.
    AtLeast(f64),
}

impl Wanted {
    /// The value `configure` writes.
    pub fn value(self) -> f64 {
        match self {
            Wanted::Exactly(v) | Wanted::AtLeast(v) => v,
        }
    }

    /// Whether the controller's `value` satisfies it; GRBL keeps settings
    /// as 32-bit floats and prints three decimals.
    pub fn accepts(self, value: f64) -> bool {
        let tol = |w: f64| 0.0015_f64.max(w.abs() * 1e-6);
        match self {
            Wanted::Exactly(w) => (value - w).abs() <= tol(w),
            Wanted::AtLeast(w) => value >= w - tol(w),
        }
    }
}

/// One controller setting an axis needs, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct ExpectedSetting {
    /// GRBL's setting number (`110`).
    pub number: u16,
    /// What the setting is, in GRBL's terms with rigd's units.
    pub what: &'static str,
    /// The value it must have.
    pub wanted: Wanted,
    /// The profile key it comes from.
    pub because: String,
}

/// A setting the controller has wrong (or lacks).
#[derive(Debug, Clone, PartialEq)]
pub struct SettingMismatch {
    /// What was expected.
    pub expected: ExpectedSetting,
    /// The controller's value; None when `$$` did not list the setting.
    pub controller: Option<f64>,
}

impl fmt::Display for SettingMismatch {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let e = &self.expected;
        let n = e.number;
        let have = self
            .controller
            .map_or("missing".to_string(), |v| format_setting(n, v));
        let want = match e.wanted {
            Wanted::Exactly(w) => format_setting(n, w),
            Wanted::AtLeast(w) => format!("at least {}", format_setting(n, w)),
        };
        write!(
            f,
            "${n} ({}) is {have} on the controller, the profile needs {want} ({})",
            e.what, e.because
        )
    }
}

/// What went wrong talking to GRBL, in the driver's own terms.
#[derive(Debug, thiserror::Error)]
pub enum GrblError {
    /// No reply to a line or status query, or a move or homing cycle not
    /// finished, before its deadline.
    #[error("no answer to {what} within {timeout:?}")]
    Timeout {
        /// The line or wait that timed out.
        what: String,
        /// The deadline it had.
        timeout: Duration,
    },
    /// The link reached end of file: the controller closed it.
    #[error("link closed by the device")]
    Disconnected,
    /// Reading or writing the link failed.
    #[error("link I/O error: {0}")]
    Io(#[from] std::io::Error),
    /// GRBL answered a line with `error:N`.
    #[error("`{command}` refused with error:{} ({})", .code.0, .code.meaning())]
    Refused {
        /// The line it refused.
        command: String,
        /// GRBL's error code.
        code: ErrorCode,
    },
    /// GRBL raised `ALARM:N` (hard or soft limit, abort during a cycle,
    /// homing failure): it locks out motion until unlocked or homed.
    #[error("ALARM:{} ({}){}", .code.0, .code.meaning(), .detail.as_deref().map(|d| format!(": {d}")).unwrap_or_default())]
    Alarm {
        /// GRBL's alarm code.
        code: AlarmCode,
        /// The `[MSG:…]` lines that followed the alarm, if any.
        detail: Option<String>,
    },
    /// A status report showed a machine state (e.g. `Alarm`, `Door`) where
    /// the named states were expected.
    #[error("machine in state {0} where {1} was expected")]
    State(MachineState, &'static str),
    /// A welcome banner arrived unasked: the controller reset and its
    /// position is lost until it is homed again.
    #[error("controller reset (welcome banner); position lost, home again")]
    Reset,
    /// The controller's settings differ from what the profile needs.
    #[error("controller settings differ from the profile: {}; send {} on the controller, or put `configure = true` on the device to let rigd write them", list_mismatches(.0), fix_lines(.0))]
    Settings(Vec<SettingMismatch>),
    /// `configure = true` wrote the settings, but reading them back still
    /// shows a difference.
    #[error("wrote the controller's settings, but reading them back shows: {}", list_mismatches(.0))]
    NotConfigured(Vec<SettingMismatch>),
    /// An axis without homing whose controller may have reset since the
    /// operator zeroed it (its link was lost, or it sent its banner).
    #[error("no homing on this axis (`homing = false`) and its controller may have reset: set the axis at its 0° mark, zero the controller there, then resume")]
    Unreferenced,
    /// A set-point outside the axis's soft limits; refused before sending.
    #[error("target {target} deg outside soft limits [{min}, {max}]")]
    OutOfLimits {
        /// The requested position, degrees.
        target: f64,
        /// The lower soft limit, degrees.
        min: f64,
        /// The upper soft limit, degrees.
        max: f64,
    },
    /// A reply the driver cannot use: unparseable, a status without
    /// `MPos`, a GRBL version other than 1.1, a line too long to send.
    #[error("unexpected reply: {0}")]
    Protocol(String),
}

fn list_mismatches(m: &[SettingMismatch]) -> String {
    m.iter()
        .map(|m| m.to_string())
        .collect::<Vec<_>>()
        .join("; ")
}

/// The lines an operator sends to fix the settings by hand.
fn fix_lines(m: &[SettingMismatch]) -> String {
    m.iter()
        .map(|m| {
            let n = m.expected.number;
            format!("`${n}={}`", format_setting(n, m.expected.wanted.value()))
        })
        .collect::<Vec<_>>()
        .join(", ")
}

impl GrblError {
    /// The kind the run engine acts on.
    pub fn kind(&self) -> ErrorKind {
        match self {
            GrblError::Timeout { .. } => ErrorKind::Timeout,
            GrblError::Disconnected | GrblError::Io(_) => ErrorKind::Disconnected,
            GrblError::Refused { .. }
            | GrblError::Alarm { .. }
            | GrblError::State(..)
            | GrblError::Reset
            | GrblError::Unreferenced
            | GrblError::Settings(_)
            | GrblError::NotConfigured(_) => ErrorKind::DeviceFault,
            GrblError::OutOfLimits { .. } => ErrorKind::OutOfLimits,
            GrblError::Protocol(_) => ErrorKind::BadFrame,
        }
    }
}

/// A GRBL-controlled stepper axis on a byte stream (a serial port in
/// production, an in-memory duplex pipe in tests).
pub struct GrblAxis<S> {
    cfg: GrblConfig,
    clock: Clock,
    reader: ReadHalf<S>,
    /// Shared with [`GrblStop`], which writes realtime bytes mid-call.
    writer: Arc<Mutex<WriteHalf<S>>>,
    split: LineSplitter,
    lines: VecDeque<String>,
    /// Byte counts of sent lines not yet answered, oldest first.
    in_flight: VecDeque<usize>,
    /// Set when a deadline expired mid-exchange: the link must be drained.
    desync: bool,
    version: Option<String>,
    options: Option<String>,
    last_status: Option<Status>,
    /// The controller's settings from its last `$$`.
    settings: BTreeMap<u16, f64>,
    /// The controller's own rates (`$110`, `$120`), which size motion
    /// deadlines; the profile's until `$$` has been read.
    rates: Motion,
    /// An axis without homing still stands where the operator zeroed it:
    /// true from connect (bring-up is when the operator zeroes it), false
    /// once its controller may have reset, until the next `home`.
    referenced: bool,
}

impl<S> std::fmt::Debug for GrblAxis<S> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GrblAxis")
            .field("name", &self.cfg.name)
            .field("version", &self.version)
            .field("last_status", &self.last_status)
            .finish()
    }
}

impl<S> GrblAxis<S>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    /// Takes over a freshly opened link: waits for the welcome banner (sending
    /// a soft reset if the board did not reset on open), identifies the
    /// firmware with `$I`, and reads the position from a status report.
    pub async fn connect(stream: S, cfg: GrblConfig, clock: Clock) -> Result<Self, DeviceError> {
        let (reader, writer) = tokio::io::split(stream);
        let rates = cfg.motion;
        let mut axis = GrblAxis {
            cfg,
            rates,
            settings: BTreeMap::new(),
            clock,
            reader,
            writer: Arc::new(Mutex::new(writer)),
            split: LineSplitter::new(256),
            lines: VecDeque::new(),
            in_flight: VecDeque::new(),
            desync: false,
            version: None,
            options: None,
            last_status: None,
            referenced: true,
        };
        let r = axis.handshake().await;
        axis.map(r)?;
        Ok(axis)
    }

    /// Replaces a lost link with a new one and re-synchronises: the
    /// controller has reset, so the position comes from its status report.
    pub async fn reconnect(&mut self, stream: S) -> Result<(), DeviceError> {
        let (reader, writer) = tokio::io::split(stream);
        self.reader = reader;
        *self.writer.lock().await = writer;
        self.split = LineSplitter::new(256);
        self.lines.clear();
        self.in_flight.clear();
        self.desync = false;
        self.last_status = None;
        // Without homing nothing restores the position a reset lost.
        self.referenced = self.cfg.homing;
        let r = self.handshake().await;
        self.map(r)
    }

    /// The out-of-band emergency stop of this axis (it survives reconnects).
    pub fn stopper(&self) -> GrblStop<S> {
        GrblStop {
            name: self.cfg.name.clone(),
            writer: self.writer.clone(),
        }
    }

    /// How the axis is driven.
    pub fn config(&self) -> &GrblConfig {
        &self.cfg
    }

    /// The firmware version from `[VER:…]`, e.g. `1.1h.20190830:`.
    pub fn version(&self) -> Option<&str> {
        self.version.as_deref()
    }

    /// The build options from `[OPT:…]`.
    pub fn options(&self) -> Option<&str> {
        self.options.as_deref()
    }

    /// The last status report received.
    pub fn last_status(&self) -> Option<&Status> {
        self.last_status.as_ref()
    }

    /// The controller's settings as read at connect (after `configure`).
    pub fn settings(&self) -> &BTreeMap<u16, f64> {
        &self.settings
    }

    /// The rates motion deadlines are sized from: the controller's.
    pub fn rates(&self) -> Motion {
        self.rates
    }

    /// Realtime feed hold (`!`): GRBL decelerates and pauses; resume with
    /// [`GrblAxis::cycle_start`]. Sent out of band, so it works mid-move.
    pub async fn feed_hold(&mut self) -> Result<(), DeviceError> {
        let r = self.send_realtime(Realtime::FeedHold).await;
        self.map(r)
    }

    /// Realtime cycle start (`~`): resumes after a feed hold.
    pub async fn cycle_start(&mut self) -> Result<(), DeviceError> {
        let r = self.send_realtime(Realtime::CycleStart).await;
        self.map(r)
    }

    /// Realtime soft reset (Ctrl-X): stops at once, flushes GRBL's buffers
    /// and waits for the banner. A reset during motion leaves GRBL in
    /// `ALARM:3` (position lost), which the returned status shows.
    pub async fn soft_reset(&mut self) -> Result<Status, DeviceError> {
        let r = self.soft_reset_inner().await;
        self.map(r)
    }

    fn map<T>(&self, r: Result<T, GrblError>) -> Result<T, DeviceError> {
        r.map_err(|e| DeviceError::new(&self.cfg.name, e.kind(), e.to_string()))
    }

    async fn soft_reset_inner(&mut self) -> Result<Status, GrblError> {
        self.send_realtime(Realtime::SoftReset).await?;
        self.in_flight.clear();
        let clock = self.clock.clone();
        let timeout = self.cfg.command_timeout;
        let r = clock.deadline(timeout, self.await_banner()).await;
        self.deadline_result(r, "soft reset", timeout)?;
        self.desync = false;
        self.query_status().await
    }

    async fn handshake(&mut self) -> Result<(), GrblError> {
        let clock = self.clock.clone();
        let timeout = self.cfg.command_timeout;
        // Whichever comes first: the banner of a board that reset when its
        // port opened, or the status of one that kept running. A silent
        // controller, or one still busy with an earlier session's motion,
        // is reset.
        let reset = match clock.deadline(timeout, self.await_greeting()).await {
            Ok(Ok(Greeting::Banner)) => false,
            Ok(Ok(Greeting::Status(state))) => {
                !matches!(state, MachineState::Idle | MachineState::Alarm)
            }
            Ok(Err(e)) => return Err(e),
            Err(_) => true,
        };
        if reset {
            self.send_realtime(Realtime::SoftReset).await?;
            let r = clock.deadline(timeout, self.await_banner()).await;
            self.deadline_result(r, "connect (welcome banner)", timeout)?;
        }
        let replies = self.command(&Command::BuildInfo, timeout).await?;
        for r in replies {
            match r {
                Reply::Version(v) => self.version = Some(v),
                Reply::Options(o) => self.options = Some(o),
                _ => {}
            }
        }
        match &self.version {
            Some(v) if v.starts_with("1.1") => {}
            Some(v) => {
                return Err(GrblError::Protocol(format!(
                    "unsupported GRBL version {v} (need 1.1)"
                )))
            }
            None => return Err(GrblError::Protocol("`$I` gave no [VER:]".into())),
        }
        self.reconcile_settings().await?;
        self.query_status().await?;
        Ok(())
    }

    /// Reads `$$`.
    async fn read_settings(&mut self) -> Result<(), GrblError> {
        let replies = self
            .command(&Command::ReadSettings, self.cfg.command_timeout)
            .await?;
        self.settings = replies
            .into_iter()
            .filter_map(|r| match r {
                Reply::Setting { number, value } => Some((number, value)),
                _ => None,
            })
            .collect();
        Ok(())
    }

    fn mismatches(&self) -> Vec<SettingMismatch> {
        self.cfg
            .expected_settings()
            .into_iter()
            .filter_map(|expected| {
                let controller = self.settings.get(&expected.number).copied();
                match controller {
                    Some(v) if expected.wanted.accepts(v) => None,
                    _ => Some(SettingMismatch {
                        expected,
                        controller,
                    }),
                }
            })
            .collect()
    }

    /// Compares the controller's settings with the profile; with
    /// `configure`, writes the ones that differ and reads them back. Then
    /// takes the controller's rates for the motion deadlines.
    async fn reconcile_settings(&mut self) -> Result<(), GrblError> {
        self.read_settings().await?;
        let wrong = self.mismatches();
        if !wrong.is_empty() {
            if !self.cfg.configure {
                return Err(GrblError::Settings(wrong));
            }
            for m in &wrong {
                let write = Command::WriteSetting {
                    number: m.expected.number,
                    value: m.expected.wanted.value(),
                };
                tracing::info!(device = %self.cfg.name, "configuring: {m}; sending `{}`", write.line());
                self.command(&write, self.cfg.command_timeout).await?;
            }
            self.read_settings().await?;
            let still = self.mismatches();
            if !still.is_empty() {
                return Err(GrblError::NotConfigured(still));
            }
        }
        let get = |n: u16| self.settings.get(&n).copied().filter(|v| *v > 0.0);
        if let (Some(rate), Some(accel)) = (get(110), get(120)) {
            self.rates = Motion {
                max_velocity: rate / 60.0,
                acceleration: accel,
                settle_s: self.cfg.motion.settle_s,
            };
        }
        Ok(())
    }

    /// Worst-case time for a move of `distance` degrees to reach Idle at
    /// the controller's rates: twice the modelled time plus one command
    /// timeout of slack.
    fn motion_deadline(&self, distance: f64) -> Duration {
        let t = modelled_move_time(self.rates, distance).as_secs_f64();
        Duration::from_secs_f64(2.0 * t) + self.cfg.command_timeout + self.cfg.poll_interval
    }

    /// Asks for a status report every [`GREETING_POLL`] (a board's boot
    /// loader may eat the first) until the banner or a report arrives.
    async fn await_greeting(&mut self) -> Result<Greeting, GrblError> {
        let clock = self.clock.clone();
        loop {
            self.send_realtime(Realtime::StatusQuery).await?;
            let next = async {
                loop {
                    match self.next_reply().await? {
                        Reply::Welcome { .. } => return Ok(Greeting::Banner),
                        Reply::Status(s) => {
                            let state = s.state;
                            self.last_status = Some(s);
                            return Ok(Greeting::Status(state));
                        }
                        _ => {}
                    }
                }
            };
            // Reading lines is cancel-safe: a late answer is read next time.
            if let Ok(r) = clock.deadline(GREETING_POLL, next).await {
                return r;
            }
        }
    }

    /// Reads until the welcome banner, skipping anything before it.
    async fn await_banner(&mut self) -> Result<(), GrblError> {
        loop {
            if let Reply::Welcome { .. } = self.next_reply().await? {
                return Ok(());
            }
        }
    }

    fn deadline_result<T>(
        &mut self,
        r: Result<Result<T, GrblError>, rigd_core::DeadlineElapsed>,
        what: &str,
        timeout: Duration,
    ) -> Result<T, GrblError> {
        match r {
            Ok(inner) => inner,
            Err(_) => {
                self.desync = true;
                Err(GrblError::Timeout {
                    what: what.to_string(),
                    timeout,
                })
            }
        }
    }

    /// Next line from the device; EOF means the link is gone.
    async fn next_line(&mut self) -> Result<String, GrblError> {
        loop {
            if let Some(l) = self.lines.pop_front() {
                return Ok(l);
            }
            let mut buf = [0u8; 256];
            // `read` is cancel-safe: a deadline firing here loses no bytes.
            let n = self.reader.read(&mut buf).await?;
            if n == 0 {
                return Err(GrblError::Disconnected);
            }
            for &b in &buf[..n] {
                if let Some(l) = self.split.push(b) {
                    self.lines.push_back(l);
                }
            }
        }
    }

    /// Next parseable reply; lines the codec does not know (noise
    /// after a reset, a bootloader's bytes) are logged and skipped.
    async fn next_reply(&mut self) -> Result<Reply, GrblError> {
        loop {
            let line = self.next_line().await?;
            match parse_reply(&line) {
                Ok(r) => return Ok(r),
                Err(e) => tracing::debug!(device = %self.cfg.name, "skipping: {e}"),
            }
        }
    }

    async fn send_realtime(&mut self, r: Realtime) -> Result<(), GrblError> {
        Ok(write_locked(&self.writer, &[r.byte()]).await?)
    }

    /// Sends a line once it fits in GRBL's receive buffer (character
    /// counting): while it would not, answers to earlier lines are awaited.
    async fn send_line(&mut self, cmd: &Command) -> Result<(), GrblError> {
        let bytes = cmd.encode();
        if bytes.len() > RX_BUFFER_SIZE {
            return Err(GrblError::Protocol(format!(
                "line of {} bytes can never fit GRBL's {RX_BUFFER_SIZE}-byte buffer",
                bytes.len()
            )));
        }
        while self.in_flight.iter().sum::<usize>() + bytes.len() > RX_BUFFER_SIZE {
            let r = self.next_reply().await?;
            self.absorb(r).await?;
        }
        write_locked(&self.writer, &bytes).await?;
        self.in_flight.push_back(bytes.len());
        Ok(())
    }

    /// Handles a reply that is not the one being waited for.
    async fn absorb(&mut self, r: Reply) -> Result<(), GrblError> {
        match r {
            Reply::Ok | Reply::Error(_) => {
                self.in_flight.pop_front();
                Ok(())
            }
            Reply::Alarm(code) => Err(self.alarm(code).await),
            Reply::Welcome { .. } => Err(self.reset_seen()),
            Reply::Status(s) => {
                self.last_status = Some(s);
                Ok(())
            }
            Reply::Msg(m) => {
                tracing::info!(device = %self.cfg.name, "GRBL: {m}");
                Ok(())
            }
            _ => Ok(()),
        }
    }

    fn reset_seen(&mut self) -> GrblError {
        self.in_flight.clear();
        self.last_status = None;
        if self.cfg.homing {
            GrblError::Reset
        } else {
            self.referenced = false;
            GrblError::Unreferenced
        }
    }

    /// Refuses motion on an axis without homing whose zero may be gone.
    fn check_referenced(&self) -> Result<(), GrblError> {
        if self.cfg.homing || self.referenced {
            Ok(())
        } else {
            Err(GrblError::Unreferenced)
        }
    }

    /// After `ALARM:N` GRBL has flushed its buffers; its explanation, if
    /// any, follows as `[MSG:…]`. A status query collects it and refreshes
    /// the position.
    async fn alarm(&mut self, code: AlarmCode) -> GrblError {
        self.in_flight.clear();
        let clock = self.clock.clone();
        let timeout = self.cfg.command_timeout;
        let mut detail: Option<String> = None;
        let collect = async {
            self.send_realtime(Realtime::StatusQuery).await?;
            loop {
                match self.next_reply().await? {
                    Reply::Msg(m) => {
                        detail = Some(match detail.take() {
                            Some(d) => format!("{d}; {m}"),
                            None => m,
                        })
                    }
                    Reply::Status(s) => {
                        self.last_status = Some(s);
                        return Ok::<(), GrblError>(());
                    }
                    _ => {}
                }
            }
        };
        match clock.deadline(timeout, collect).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return e,
            Err(_) => self.desync = true,
        }
        GrblError::Alarm { code, detail }
    }

    /// Sends one line and waits, up to `timeout`, for its `ok`; returns the
    /// messages that came with it (`[VER:…]` …).
    async fn command(&mut self, cmd: &Command, timeout: Duration) -> Result<Vec<Reply>, GrblError> {
        let clock = self.clock.clone();
        let r = clock.deadline(timeout, self.exchange(cmd)).await;
        self.deadline_result(r, &format!("`{}`", cmd.line()), timeout)
    }

    async fn exchange(&mut self, cmd: &Command) -> Result<Vec<Reply>, GrblError> {
        self.send_line(cmd).await?;
        let mut extra = Vec::new();
        loop {
            let r = self.next_reply().await?;
            let ours = self.in_flight.len() == 1;
            match r {
                Reply::Ok if ours => {
                    self.in_flight.clear();
                    return Ok(extra);
                }
                Reply::Error(code) if ours => {
                    self.in_flight.clear();
                    return Err(GrblError::Refused {
                        command: cmd.line(),
                        code,
                    });
                }
                Reply::Version(_) | Reply::Options(_) | Reply::Msg(_) | Reply::Setting { .. } => {
                    extra.push(r)
                }
                other => self.absorb(other).await?,
            }
        }
    }

    /// Sends `?` and waits for the status report (with a deadline).
    async fn query_status(&mut self) -> Result<Status, GrblError> {
        let clock = self.clock.clone();
        let timeout = self.cfg.command_timeout;
        let r = clock.deadline(timeout, self.status_exchange()).await;
        self.deadline_result(r, "status query `?`", timeout)
    }

    async fn status_exchange(&mut self) -> Result<Status, GrblError> {
        self.send_realtime(Realtime::StatusQuery).await?;
        loop {
            match self.next_reply().await? {
                Reply::Status(s) => {
                    self.last_status = Some(s.clone());
                    return Ok(s);
                }
                other => self.absorb(other).await?,
            }
        }
    }

    /// After a timeout, drains stale answers up to a fresh status report,
    /// so the next `ok` read really answers the next line.
    async fn resync(&mut self) -> Result<(), GrblError> {
        if !self.desync {
            return Ok(());
        }
        let clock = self.clock.clone();
        let timeout = self.cfg.command_timeout;
        let drain = async {
            self.send_realtime(Realtime::StatusQuery).await?;
            loop {
                match self.next_reply().await? {
                    Reply::Status(s) => {
                        self.last_status = Some(s);
                        return Ok(());
                    }
                    Reply::Alarm(code) => return Err(self.alarm(code).await),
                    Reply::Welcome { .. } => return Err(self.reset_seen()),
                    _ => {}
                }
            }
        };
        let r = clock.deadline(timeout, drain).await;
        self.deadline_result(r, "resynchronising status query", timeout)?;
        self.in_flight.clear();
        self.desync = false;
        Ok(())
    }

    /// Before homing: reads away whatever a reset or an alarm left on the
    /// link (banner, `ALARM:N`, messages, stale answers) up to a fresh
    /// status report. Homing is the cure for both, so here neither is an
    /// error (after an emergency stop the banner is always there).
    async fn settle_link(&mut self) -> Result<(), GrblError> {
        let clock = self.clock.clone();
        let timeout = self.cfg.command_timeout;
        let drain = async {
            self.send_realtime(Realtime::StatusQuery).await?;
            loop {
                if let Reply::Status(s) = self.next_reply().await? {
                    self.last_status = Some(s);
                    return Ok(());
                }
            }
        };
        let r = clock.deadline(timeout, drain).await;
        self.deadline_result(r, "status query before homing", timeout)?;
        self.in_flight.clear();
        self.desync = false;
        Ok(())
    }

    fn x_of(s: &Status) -> Result<f64, GrblError> {
        s.x()
            .ok_or_else(|| GrblError::Protocol(format!("status report without MPos: {s}")))
    }

    async fn home_inner(&mut self) -> Result<f64, GrblError> {
        self.settle_link().await?;
        if !self.cfg.homing {
            return self.take_reference().await;
        }
        self.command(&Command::Home, self.cfg.home_timeout).await?;
        let s = self.query_status().await?;
        Self::x_of(&s)
    }

    /// An axis without homing: the operator has set it at its 0° mark and
    /// zeroed the controller (at bring-up, or before resuming), so an Idle
    /// controller's machine position is taken as it is.
    async fn take_reference(&mut self) -> Result<f64, GrblError> {
        let s = self.query_status().await?;
        match s.state {
            MachineState::Idle => {
                self.referenced = true;
                Self::x_of(&s)
            }
            other => Err(GrblError::State(
                other,
                "Idle (an axis without homing: set it at its 0° mark, zero the controller there, and unlock it with `$X` if it is in Alarm)",
            )),
        }
    }

    /// Refuses a target outside the soft limits before anything is sent.
    fn check_target(&self, target: f64) -> Result<(), GrblError> {
        let l = self.cfg.limits;
        if target.is_finite() && l.contains(target) {
            Ok(())
        } else {
            Err(GrblError::OutOfLimits {
                target,
                min: l.min,
                max: l.max,
            })
        }
    }

    async fn move_inner(&mut self, target: f64) -> Result<f64, GrblError> {
        self.check_target(target)?;
        self.check_referenced()?;
        self.resync().await?;
        let from = self
            .last_status
            .as_ref()
            .and_then(Status::x)
            .unwrap_or(target);
        self.command(&Command::Rapid { x: target }, self.cfg.command_timeout)
            .await?;
        let clock = self.clock.clone();
        let timeout = self.motion_deadline(target - from);
        let modelled = modelled_move_time(self.rates, target - from);
        let r = clock.deadline(timeout, self.wait_idle(modelled)).await;
        let s = self.deadline_result(r, "motion to reach Idle", timeout)?;
        Self::x_of(&s)
    }

    /// A jog (`$J=G90 X… F…`): the controller runs it at the feed given, and
    /// answers `ok` as soon as it is planned.
    async fn sweep_inner(&mut self, target: f64, velocity: f64) -> Result<(), GrblError> {
        self.check_target(target)?;
        self.check_referenced()?;
        self.resync().await?;
        let feed = velocity.abs().min(self.rates.max_velocity) * 60.0;
        self.command(&Command::Jog { x: target, feed }, self.cfg.command_timeout)
            .await?;
        Ok(())
    }

    /// Waits for a sweep to end. Its duration depends on the velocity the
    /// caller chose, so the caller sets the real deadline; this one only
    /// bounds a controller that never reports Idle.
    async fn wait_sweep(&mut self) -> Result<f64, GrblError> {
        let clock = self.clock.clone();
        let timeout = SWEEP_WAIT_LIMIT;
        // A sweep's length is the caller's: poll it all the way.
        let r = clock
            .deadline(timeout, self.wait_idle(Duration::ZERO))
            .await;
        let s = self.deadline_result(r, "sweep to reach Idle", timeout)?;
        Self::x_of(&s)
    }

    /// Polls `?` until the controller reports Idle, when
    /// [`super::Polls`] says for a move modelled to take `modelled`.
    async fn wait_idle(&mut self, modelled: Duration) -> Result<Status, GrblError> {
        let start = self.clock.now();
        let mut polls = super::Polls::new(self.cfg.poll_interval, modelled);
        loop {
            let elapsed = self.clock.now().saturating_sub(start);
            self.clock.sleep(polls.next_wait(elapsed)).await;
            let s = self.status_exchange().await?;
            match s.state {
                MachineState::Idle => return Ok(s),
                // Moving, or held by an operator: keep waiting (the motion
                // deadline bounds a hold that is never released).
                MachineState::Run | MachineState::Jog | MachineState::Hold(_) => {}
                other => return Err(GrblError::State(other, "Run or Idle")),
            }
        }
    }
}

/// How often a fresh link is asked for a status report until the
/// controller answers or greets.
const GREETING_POLL: Duration = Duration::from_millis(250);

/// The first thing a controller says on a fresh link.
enum Greeting {
    /// The welcome banner: the board reset when its port opened.
    Banner,
    /// A status report: the board kept running, in this state.
    Status(MachineState),
}

/// Longest a sweep may run before the driver gives up on it.
const SWEEP_WAIT_LIMIT: Duration = Duration::from_secs(3600);

/// Feed hold then soft reset, written while any call may be in flight:
/// GRBL acts on realtime bytes the moment its serial interrupt sees them,
/// so the stop is done once they are on the wire. The call in flight then
/// reads the reset banner and fails; the axis must re-home.
pub struct GrblStop<S> {
    name: String,
    writer: Arc<Mutex<WriteHalf<S>>>,
}

#[async_trait]
impl<S> EmergencyStop for GrblStop<S>
where
    S: AsyncWrite + Send + 'static,
{
    async fn emergency_stop(&self) -> Result<(), DeviceError> {
        let bytes = [Realtime::FeedHold.byte(), Realtime::SoftReset.byte()];
        write_locked(&self.writer, &bytes)
            .await
            .map_err(|e| stop_failed(&self.name, e))
    }
}

#[async_trait]
impl<S> Axis for GrblAxis<S>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    async fn home(&mut self) -> Result<f64, DeviceError> {
        let r = self.home_inner().await;
        self.map(r)
    }

    async fn move_to(&mut self, target: f64) -> Result<f64, DeviceError> {
        let r = self.move_inner(target).await;
        self.map(r)
    }

    async fn position(&mut self) -> Result<f64, DeviceError> {
        let r = async {
            self.resync().await?;
            let s = self.query_status().await?;
            Self::x_of(&s)
        }
        .await;
        self.map(r)
    }

    async fn start_sweep(&mut self, target: f64, velocity: f64) -> Result<(), DeviceError> {
        let r = self.sweep_inner(target, velocity).await;
        self.map(r)
    }

    async fn wait_idle(&mut self) -> Result<f64, DeviceError> {
        let r = self.wait_sweep().await;
        self.map(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncWriteExt, DuplexStream};

    fn raw(stream: DuplexStream) -> GrblAxis<DuplexStream> {
        let (reader, writer) = tokio::io::split(stream);
        GrblAxis {
            cfg: GrblConfig::new(
                "t",
                Limits {
                    min: -1e6,
                    max: 1e6,
                },
                Motion {
                    max_velocity: 1.0,
                    acceleration: 1.0,
                    settle_s: 0.0,
                },
            ),
            rates: Motion {
                max_velocity: 1.0,
                acceleration: 1.0,
                settle_s: 0.0,
            },
            settings: BTreeMap::new(),
            clock: Clock::virtual_time(),
            reader,
            writer: Arc::new(Mutex::new(writer)),
            split: LineSplitter::new(256),
            lines: VecDeque::new(),
            in_flight: VecDeque::new(),
            desync: false,
            version: None,
            options: None,
            last_status: None,
            referenced: true,
        }
    }

    #[tokio::test(start_paused = true)]
    async fn character_counting_never_overfills_the_rx_buffer() {
        let (drv, mut dev) = tokio::io::duplex(4096);
        let cmd = Command::Jog {
            x: 123456.789,
            feed: 123456.789,
        };
        let len = cmd.encode().len();
        assert_eq!(len, 31);
        let fit = RX_BUFFER_SIZE / len; // 4 lines = 124 bytes
        let sender = tokio::spawn(async move {
            let mut axis = raw(drv);
            for _ in 0..fit + 1 {
                axis.send_line(&cmd).await.map_err(|e| e.to_string())?;
            }
            Ok::<_, String>(axis.in_flight.iter().sum::<usize>())
        });
        tokio::time::sleep(Duration::from_secs(1)).await;
        let mut buf = vec![0u8; 1024];
        let n = dev.read(&mut buf).await.expect("read");
        assert_eq!(n, fit * len, "only what fits may be sent");
        assert!(!sender.is_finished(), "fifth line must wait for an ok");
        dev.write_all(b"ok\r\n").await.expect("write");
        let in_flight = sender.await.expect("join").expect("send");
        assert_eq!(in_flight, fit * len);
        let n = dev.read(&mut buf).await.expect("read");
        assert_eq!(n, len);
    }

    #[test]
    fn errors_map_to_engine_kinds() {
        let t = GrblError::Timeout {
            what: "x".into(),
            timeout: Duration::from_secs(1),
        };
        assert_eq!(t.kind(), ErrorKind::Timeout);
        assert_eq!(GrblError::Disconnected.kind(), ErrorKind::Disconnected);
        let refused = GrblError::Refused {
            command: "G90 G0 X1.000".into(),
            code: ErrorCode(9),
        };
        assert_eq!(refused.kind(), ErrorKind::DeviceFault);
        assert!(refused.to_string().contains("error:9 (G-code locked out"));
        let alarm = GrblError::Alarm {
            code: AlarmCode(1),
            detail: Some("limit X".into()),
        };
        assert_eq!(alarm.kind(), ErrorKind::DeviceFault);
        assert!(alarm.to_string().starts_with("ALARM:1 (hard limit"));
        assert!(alarm.to_string().ends_with(": limit X"));
        assert_eq!(GrblError::Reset.kind(), ErrorKind::DeviceFault);
    }
}
