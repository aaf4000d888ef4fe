//! A simulated GRBL 1.1 controller with one axis (X), speaking the protocol
//! of `firmware-protocols/grbl.md` over any byte stream.
//!
//! One task owns the stream: realtime bytes (`?`, `!`, `~`, Ctrl-X) are
//! handled the moment they are read, even mid-line; other bytes go into a
//! 127-byte receive buffer like GRBL's and are executed line by line.
//! Motion is not simulated step by step: a queued move is a [`Trapezoid`]
//! segment with a start time, and a status report evaluates it at the
//! clock's current time. Homing blocks line execution (as in GRBL), so
//! bytes sent meanwhile stay in the receive buffer, and overflowing that
//! buffer drops bytes exactly like the real firmware (counted in
//! [`GrblStats`] so tests can prove the host's flow control works).

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rigd_proto::grbl::{
    parse_command, AlarmCode, Command, MachineState, Realtime, Reply, Status, ALARM_HARD_LIMIT,
    ALARM_RESET_IN_MOTION, ERR_ALARM_LOCK, ERR_HOMING_DISABLED, ERR_INVALID_STATEMENT,
    ERR_LINE_OVERFLOW, ERR_MAX_STEP_RATE, ERR_NEGATIVE_VALUE, ERR_NOT_IDLE,
    ERR_SOFT_LIMIT_WITHOUT_HOMING, FACTORY_SETTINGS, LINE_BUFFER_SIZE, MAX_STEP_RATE_HZ,
    RX_BUFFER_SIZE,
};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};

use crate::faults::{FaultInjector, FaultKind};
use crate::world::SharedWorld;
use rigd_core::clock::Clock;
use rigd_core::motion::Trapezoid;

/// The banner's version and the `$I` answers of the simulated build.
pub const VERSION: &str = "1.1h";
/// The `[VER:…]` line's content in the answer to `$I`.
pub const BUILD_VERSION: &str = "1.1h.20190830:";
/// The `[OPT:…]` line's content in the answer to `$I` (variable spindle,
/// 15 planner blocks, 128-byte receive buffer).
pub const BUILD_OPTIONS: &str = "V,15,128";
/// GRBL's message after a reset that left it locked.
pub const UNLOCK_HINT: &str = "'$H'|'$X' to unlock";

/// The controller's settings, its EEPROM: shared by every connection to
/// one board, so a value written with `$N=V` survives a reconnect, as on
/// the real board. Its `$110` (max rate, units/min), `$120` (acceleration,
/// units/s²) and `$22` (homing enabled) decide how the simulated axis
/// moves and homes.
#[derive(Debug, Clone)]
pub struct Eeprom(Arc<Mutex<BTreeMap<u16, f64>>>);

impl Eeprom {
    /// GRBL as it ships: [`FACTORY_SETTINGS`] (`$22=0`, `$110=500`,
    /// `$120=10`, `$130=200`).
    pub fn factory() -> Eeprom {
        Eeprom(Arc::new(Mutex::new(
            FACTORY_SETTINGS.iter().copied().collect(),
        )))
    }

    /// A board set up for its axis: the factory settings with the axis's
    /// rates, its travel and, if it homes, homing enabled.
    pub fn configured(motion: Trapezoid, homing: bool, max_travel: f64) -> Eeprom {
        let e = Eeprom::factory();
        e.set(110, motion.max_velocity * 60.0);
        e.set(120, motion.acceleration);
        e.set(130, max_travel);
        e.set(22, if homing { 1.0 } else { 0.0 });
        e
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u16, f64>> {
        // Plain data: a panic elsewhere cannot leave it inconsistent.
        rigd_core::sync::lock(&self.0)
    }

    /// Setting `number`'s value, if the build has it.
    pub fn get(&self, number: u16) -> Option<f64> {
        self.lock().get(&number).copied()
    }

    /// Every setting in `$$` order.
    pub fn all(&self) -> Vec<(u16, f64)> {
        self.lock().iter().map(|(&n, &v)| (n, v)).collect()
    }

    /// Stores a value, as `$N=V` does once its checks pass.
    pub fn set(&self, number: u16, value: f64) {
        self.lock().insert(number, value);
    }

    fn homing_enabled(&self) -> bool {
        self.get(22).is_some_and(|v| v != 0.0)
    }
}

/// How the simulated controller is set up.
#[derive(Debug, Clone)]
pub struct GrblParams {
    /// Device name for the [`FaultInjector`].
    pub name: String,
    /// The axis's settle time after a move; its rates come from
    /// [`GrblParams::settings`] (`$110`, `$120`), and [`Eeprom::configured`]
    /// takes them from here.
    pub motion: Trapezoid,
    /// Machine position after a homing cycle.
    pub home_position: f64,
    /// Where the axis physically stands at power-up (homing travels from here).
    pub physical_start: f64,
    /// Start homed and Idle at `physical_start` (a controller that kept its
    /// position), instead of GRBL's usual Alarm with MPos 0.
    pub start_homed: bool,
    /// The controller's settings. With `$22=0` (homing disabled, as GRBL
    /// ships) the controller starts Idle (not locked) at MPos 0 and
    /// refuses `$H` with `error:5`.
    pub settings: Eeprom,
    /// The board resets when its port opens (an Arduino, through DTR) and
    /// greets with the banner; without, it was already running and says
    /// nothing until asked.
    pub reset_on_open: bool,
    /// Where to publish the physical position (under `name`) for the
    /// simulated cameras.
    pub world: Option<SharedWorld>,
    /// Seconds every answer waits before it goes out: a slow controller
    /// (one observed answering each line in about 150 ms). 0 by default.
    pub answer_delay_s: f64,
}

impl Default for GrblParams {
    /// The setup the transcripts in `firmware-protocols/grbl.md` assume.
    fn default() -> GrblParams {
        let motion = Trapezoid {
            max_velocity: 20.0,
            acceleration: 40.0,
            settle_s: 0.05,
        };
        GrblParams {
            name: "grbl".into(),
            motion,
            home_position: 0.0,
            physical_start: 10.0,
            start_homed: false,
            settings: Eeprom::configured(motion, true, 360.0),
            reset_on_open: true,
            world: None,
            answer_delay_s: 0.0,
        }
    }
}

/// Counters a test can inspect while or after the simulator runs.
#[derive(Debug, Default)]
pub struct GrblStats {
    /// Bytes dropped because the receive buffer was full (a host bug).
    pub rx_overflow_bytes: AtomicU64,
    /// Lines executed (each answered with `ok`/`error`, or swallowed by a fault).
    pub lines: AtomicU64,
}

#[derive(Debug, Clone, Copy)]
struct Segment {
    from: f64,
    to: f64,
    start_s: f64,
    motion: Trapezoid,
    jog: bool,
}

impl Segment {
    fn end_s(&self) -> f64 {
        self.start_s + self.motion.move_time(self.to - self.from)
    }
    fn at(&self, now_s: f64) -> f64 {
        self.motion
            .position_at(self.from, self.to, now_s - self.start_s)
    }
}

/// A move still to run after a feed hold: target, motion model, is a jog.
type Pending = (f64, Trapezoid, bool);

/// What the controller is doing besides holding still.
struct Machine {
    params: GrblParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
    stats: Arc<GrblStats>,
    alarm: bool,
    /// Reported MPos = physical position − offset (GRBL zeroes on power-up).
    offset: f64,
    /// Reported position when no segment is active.
    pos: f64,
    segments: VecDeque<Segment>,
    /// Feed hold: the frozen position and the targets still to go.
    held: Option<(f64, Vec<Pending>)>,
    /// Homing in progress: clock time it completes.
    homing_until: Option<f64>,
    rx: VecDeque<u8>,
    out: Vec<u8>,
    closed: bool,
    /// Reports until the next `WCO:` and `Ov:` fields, as GRBL counts them
    /// (both 0 after a reset, so the first report has `WCO:`, the next `Ov:`).
    wco_countdown: u8,
    ovr_countdown: u8,
}

/// Runs the simulated controller until the host closes the stream (or a
/// `Disconnect` fault closes it). Faults are checked once per executed line
/// command (ops `home`, `unlock`, `info`, `move`, `jog`, `nop`), never for
/// realtime bytes, so status polling does not shift call counts.
pub async fn serve<S>(
    stream: S,
    params: GrblParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
) -> std::io::Result<()>
where
    S: AsyncRead + AsyncWrite + Unpin,
{
    serve_with_stats(
        stream,
        params,
        clock,
        faults,
        Arc::new(GrblStats::default()),
    )
    .await
}

/// [`serve`], reporting into `stats`.
pub async fn serve_with_stats<S>(
    mut stream: S,
    params: GrblParams,
    clock: Clock,
    faults: Arc<FaultInjector>,
    stats: Arc<GrblStats>,
) -> std::io::Result<()>
where
    S: AsyncRead + AsyncWrite + Unpin,
{
    let mut m = Machine {
        // Power-up locks the controller only when homing is enabled.
        alarm: !params.start_homed && params.settings.homing_enabled(),
        offset: if params.start_homed {
            0.0
        } else {
            params.physical_start
        },
        pos: if params.start_homed {
            params.physical_start
        } else {
            0.0
        },
        params,
        clock,
        faults,
        stats,
        segments: VecDeque::new(),
        held: None,
        homing_until: None,
        rx: VecDeque::new(),
        out: Vec::new(),
        closed: false,
        wco_countdown: 0,
        ovr_countdown: 0,
    };
    if m.params.reset_on_open {
        m.banner();
    }
    stream.write_all(&std::mem::take(&mut m.out)).await?;
    let mut buf = [0u8; 256];
    loop {
        let homing_left = m.homing_until.map(|t| (t - m.clock.now_s()).max(0.0));
        let n = tokio::select! {
            r = stream.read(&mut buf) => Some(r?),
            _ = async {
                match homing_left {
                    Some(s) => m.clock.sleep(Duration::from_secs_f64(s)).await,
                    None => std::future::pending::<()>().await,
                }
            } => None,
        };
        match n {
            Some(0) => return Ok(()),
            Some(n) => {
                for &b in &buf[..n] {
                    m.receive(b);
                }
            }
            None => m.finish_homing(),
        }
        m.execute_lines();
        m.publish();
        if !m.out.is_empty() {
            if m.params.answer_delay_s > 0.0 {
                m.clock.sleep_s(m.params.answer_delay_s).await;
            }
            stream.write_all(&std::mem::take(&mut m.out)).await?;
            stream.flush().await?;
        }
        if m.closed {
            stream.shutdown().await.ok();
            return Ok(());
        }
    }
}

impl Machine {
    fn reply(&mut self, r: Reply) {
        self.out.extend_from_slice(&r.encode());
    }

    fn banner(&mut self) {
        self.reply(Reply::Welcome {
            version: VERSION.into(),
        });
        if self.alarm {
            self.reply(Reply::Msg(UNLOCK_HINT.into()));
        }
    }

    fn now(&self) -> f64 {
        self.clock.now_s()
    }

    /// Tells the world where the axis physically stands. Called after every
    /// exchange, so the report a driver saw last matches the world.
    fn publish(&mut self) {
        if let Some(world) = self.params.world.clone() {
            let physical = self.position() + self.offset;
            world.set_axis(&self.params.name, physical);
        }
    }

    /// Retires finished segments and returns the active one, if any.
    fn active(&mut self) -> Option<Segment> {
        let now = self.now();
        while let Some(s) = self.segments.front().copied() {
            if now + super::END_TOLERANCE_S >= s.end_s() {
                self.pos = s.to;
                self.segments.pop_front();
            } else {
                return Some(s);
            }
        }
        None
    }

    fn position(&mut self) -> f64 {
        let now = self.now();
        if let Some((p, _)) = &self.held {
            return *p;
        }
        match self.active() {
            Some(s) => s.at(now),
            None => self.pos,
        }
    }

    fn status(&mut self) -> Status {
        let active = self.active();
        let (state, feed) = if self.homing_until.is_some() {
            (MachineState::Home, 0.0)
        } else if self.alarm {
            (MachineState::Alarm, 0.0)
        } else if self.held.is_some() {
            (MachineState::Hold(0), 0.0)
        } else if let Some(s) = active {
            let state = if s.jog {
                MachineState::Jog
            } else {
                MachineState::Run
            };
            (state, s.motion.max_velocity * 60.0)
        } else {
            (MachineState::Idle, 0.0)
        };
        // GRBL refreshes these every 10 reports at rest, every 30 (WCO) or
        // 20 (Ov) while busy; a report with WCO defers Ov to the next one.
        let busy = matches!(
            state,
            MachineState::Home | MachineState::Run | MachineState::Jog | MachineState::Hold(_)
        );
        let wco = if self.wco_countdown > 0 {
            self.wco_countdown -= 1;
            None
        } else {
            self.wco_countdown = if busy { 29 } else { 9 };
            if self.ovr_countdown == 0 {
                self.ovr_countdown = 1;
            }
            Some(vec![0.0; 3])
        };
        let overrides = if self.ovr_countdown > 0 {
            self.ovr_countdown -= 1;
            None
        } else {
            self.ovr_countdown = if busy { 19 } else { 9 };
            Some([100; 3])
        };
        Status {
            state,
            mpos: Some(vec![self.position(), 0.0, 0.0]),
            feed: Some(feed),
            spindle: Some(0.0),
            wco,
            overrides,
        }
    }

    fn receive(&mut self, b: u8) {
        if self.closed {
            return;
        }
        match Realtime::from_byte(b) {
            Some(Realtime::StatusQuery) => {
                let s = self.status();
                self.reply(Reply::Status(s));
            }
            Some(Realtime::FeedHold) => self.feed_hold(),
            Some(Realtime::CycleStart) => self.cycle_start(),
            Some(Realtime::SoftReset) => self.soft_reset(),
            None => {
                if self.rx.len() < RX_BUFFER_SIZE {
                    self.rx.push_back(b);
                } else {
                    // GRBL drops the byte without telling anyone.
                    self.stats.rx_overflow_bytes.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }

    /// Stops at once (the sim has no deceleration ramp) and remembers
    /// what is left, reporting `Hold:0` until `~`.
    fn feed_hold(&mut self) {
        if self.alarm || self.homing_until.is_some() || self.held.is_some() {
            return;
        }
        let p = self.position();
        let rest = self
            .segments
            .drain(..)
            .map(|s| (s.to, s.motion, s.jog))
            .collect();
        self.held = Some((p, rest));
    }

    fn cycle_start(&mut self) {
        let Some((p, rest)) = self.held.take() else {
            return;
        };
        self.pos = p;
        let mut from = p;
        let mut start = self.now();
        for (to, motion, jog) in rest {
            let s = Segment {
                from,
                to,
                start_s: start,
                motion,
                jog,
            };
            start = s.end_s();
            from = to;
            self.segments.push_back(s);
        }
    }

    fn soft_reset(&mut self) {
        let moving = self.homing_until.is_some() || self.active().is_some();
        self.wco_countdown = 0;
        self.ovr_countdown = 0;
        let p = self.position();
        self.pos = p;
        self.segments.clear();
        self.held = None;
        if self.homing_until.take().is_some() {
            self.offset = 0.0;
        }
        self.rx.clear();
        if moving {
            self.reply(Reply::Alarm(ALARM_RESET_IN_MOTION));
            self.alarm = true;
        }
        self.banner();
    }

    fn finish_homing(&mut self) {
        if self.homing_until.take().is_some() {
            self.pos = self.params.home_position;
            self.offset = 0.0;
            self.alarm = false;
            self.reply(Reply::Ok);
        }
    }

    fn execute_lines(&mut self) {
        while self.homing_until.is_none() && !self.closed {
            let Some(end) = self.rx.iter().position(|&b| b == b'\n' || b == b'\r') else {
                return;
            };
            let line: Vec<u8> = self.rx.drain(..=end).take(end).collect();
            self.stats.lines.fetch_add(1, Ordering::Relaxed);
            self.execute(&String::from_utf8_lossy(&line));
        }
    }

    fn execute(&mut self, line: &str) {
        if line.len() > LINE_BUFFER_SIZE {
            self.reply(Reply::Error(ERR_LINE_OVERFLOW));
            return;
        }
        let cmd = match parse_command(line) {
            Ok(c) => c,
            Err(code) => {
                self.reply(Reply::Error(code));
                return;
            }
        };
        let op = match cmd {
            Command::Home => "home",
            Command::Unlock => "unlock",
            Command::BuildInfo => "info",
            Command::ReadSettings => "settings",
            Command::WriteSetting { .. } => "configure",
            Command::Rapid { .. } => "move",
            Command::Jog { .. } => "jog",
            Command::Nop => "nop",
        };
        match self.faults.check(&self.params.name, op) {
            None => {}
            // Swallowed: no answer ever comes for this line.
            Some(FaultKind::Timeout) => return,
            Some(FaultKind::Disconnect) => {
                self.closed = true;
                return;
            }
            Some(FaultKind::Alarm(text)) => {
                self.hard_limit(&text);
                return;
            }
            Some(FaultKind::BadFrame | FaultKind::Dark | FaultKind::MaskMarkers) => {}
        }
        match cmd {
            Command::Home if !self.params.settings.homing_enabled() => {
                self.reply(Reply::Error(ERR_HOMING_DISABLED));
            }
            Command::Home => {
                let physical = self.position() + self.offset;
                let t = self.rapid().move_time(physical - self.params.home_position);
                self.segments.clear();
                self.held = None;
                self.homing_until = Some(self.now() + t);
            }
            Command::Unlock => {
                if self.alarm {
                    self.alarm = false;
                    self.reply(Reply::Msg("Caution: Unlocked".into()));
                }
                self.reply(Reply::Ok);
            }
            Command::BuildInfo => {
                self.reply(Reply::Version(BUILD_VERSION.into()));
                self.reply(Reply::Options(BUILD_OPTIONS.into()));
                self.reply(Reply::Ok);
            }
            Command::ReadSettings => {
                for (number, value) in self.params.settings.all() {
                    self.reply(Reply::Setting { number, value });
                }
                self.reply(Reply::Ok);
            }
            Command::WriteSetting { number, value } => {
                let code = self.write_setting(number, value);
                self.reply(code.map_or(Reply::Ok, Reply::Error));
            }
            Command::Nop => self.reply(Reply::Ok),
            Command::Rapid { x } => {
                let jogging = self.active().is_some_and(|s| s.jog);
                if self.alarm || jogging {
                    self.reply(Reply::Error(ERR_ALARM_LOCK));
                } else {
                    let rapid = self.rapid();
                    self.queue(x, rapid, false);
                    self.reply(Reply::Ok);
                }
            }
            Command::Jog { x, feed } => {
                if self.alarm {
                    self.reply(Reply::Error(ERR_ALARM_LOCK));
                } else {
                    let mut motion = self.rapid();
                    motion.max_velocity = motion.max_velocity.min(feed / 60.0);
                    self.queue(x, motion, true);
                    self.reply(Reply::Ok);
                }
            }
        }
    }

    /// The rapid motion the settings give: `$110` units/min, `$120`
    /// units/s², and the axis's settle time.
    fn rapid(&self) -> Trapezoid {
        let e = &self.params.settings;
        let fallback = self.params.motion;
        Trapezoid {
            max_velocity: e.get(110).map_or(fallback.max_velocity, |v| v / 60.0),
            acceleration: e.get(120).unwrap_or(fallback.acceleration),
            settle_s: fallback.settle_s,
        }
    }

    /// `$N=V`, with GRBL's checks: a setting the build has, only while
    /// Idle or in Alarm, no negative value, soft limits only with homing.
    /// Returns the error code to answer, or None for `ok`.
    fn write_setting(&mut self, number: u16, value: f64) -> Option<rigd_proto::grbl::ErrorCode> {
        let idle = self.active().is_none() && self.homing_until.is_none() && self.held.is_none();
        if !(idle || self.alarm) {
            return Some(ERR_NOT_IDLE);
        }
        if self.params.settings.get(number).is_none() {
            return Some(ERR_INVALID_STATEMENT);
        }
        if value < 0.0 {
            return Some(ERR_NEGATIVE_VALUE);
        }
        if number == 20 && value != 0.0 && !self.params.settings.homing_enabled() {
            return Some(ERR_SOFT_LIMIT_WITHOUT_HOMING);
        }
        // Steps/unit times rate/min may not pass the step generator's limit.
        let other = match number {
            100 => self.params.settings.get(110),
            110 => self.params.settings.get(100),
            _ => None,
        };
        if other.is_some_and(|o| o * value > MAX_STEP_RATE_HZ * 60.0) {
            return Some(ERR_MAX_STEP_RATE);
        }
        self.params.settings.set(number, value);
        None
    }

    /// Appends a move after everything already planned (GRBL's planner
    /// chains moves; the sim runs them back to back, settle included).
    fn queue(&mut self, to: f64, motion: Trapezoid, jog: bool) {
        if let Some((_, rest)) = &mut self.held {
            rest.push((to, motion, jog));
            return;
        }
        let now = self.now();
        let (from, start_s) = match self.active() {
            Some(_) => match self.segments.back() {
                Some(last) => (last.to, last.end_s()),
                None => (self.pos, now),
            },
            None => (self.pos, now),
        };
        self.segments.push_back(Segment {
            from,
            to,
            start_s,
            motion,
            jog,
        });
    }

    /// A tripped limit switch: motion stops where it is, GRBL alarms and
    /// flushes its buffers; the line that was executing gets no answer.
    fn hard_limit(&mut self, text: &str) {
        let p = self.position();
        self.pos = p;
        self.segments.clear();
        self.held = None;
        self.homing_until = None;
        self.rx.clear();
        self.alarm = true;
        self.reply(Reply::Alarm(ALARM_HARD_LIMIT));
        self.reply(Reply::Msg(text.to_string()));
    }
}

/// The alarm code a fault of kind `Alarm` raises, for tests and docs.
pub const FAULT_ALARM: AlarmCode = ALARM_HARD_LIMIT;

#[cfg(test)]
mod tests {
    use super::*;
    use rigd_proto::grbl::{parse_reply, LineSplitter};
    use tokio::io::DuplexStream;

    struct Host {
        io: DuplexStream,
        split: LineSplitter,
        buf: Vec<String>,
    }

    impl Host {
        async fn send(&mut self, bytes: &[u8]) {
            self.io.write_all(bytes).await.expect("write");
        }
        async fn line(&mut self) -> String {
            loop {
                if !self.buf.is_empty() {
                    return self.buf.remove(0);
                }
                let mut b = [0u8; 64];
                let n = self.io.read(&mut b).await.expect("read");
                assert!(n > 0, "eof");
                for &x in &b[..n] {
                    self.buf.extend(self.split.push(x));
                }
            }
        }
        async fn status(&mut self) -> Status {
            self.send(b"?").await;
            match parse_reply(&self.line().await) {
                Ok(Reply::Status(s)) => s,
                other => panic!("{other:?}"),
            }
        }
    }

    fn start(params: GrblParams, faults: Arc<FaultInjector>) -> (Host, Arc<GrblStats>, Clock) {
        let (a, b) = tokio::io::duplex(4096);
        let clock = Clock::virtual_time();
        let stats = Arc::new(GrblStats::default());
        tokio::spawn(serve_with_stats(
            b,
            params,
            clock.clone(),
            faults,
            stats.clone(),
        ));
        (
            Host {
                io: a,
                split: LineSplitter::new(256),
                buf: Vec::new(),
            },
            stats,
            clock,
        )
    }

    #[tokio::test(start_paused = true)]
    async fn factory_settings_start_idle_at_zero_and_refuse_homing() {
        let p = GrblParams {
            settings: Eeprom::factory(),
            ..GrblParams::default()
        };
        let (mut h, _, _) = start(p, Arc::default());
        // No unlock hint: `$22=0` starts unlocked.
        assert_eq!(h.line().await, "Grbl 1.1h ['$' for help]");
        let s = h.status().await;
        assert_eq!((s.state, s.x()), (MachineState::Idle, Some(0.0)));
        h.send(b"$H\n").await;
        assert_eq!(h.line().await, "error:5");
        h.send(b"G90 G0 X1\n").await;
        assert_eq!(h.line().await, "ok");
    }

    #[tokio::test(start_paused = true)]
    async fn homing_blocks_lines_and_takes_trapezoid_time() {
        let p = GrblParams::default();
        let expect = p.motion.move_time(p.physical_start - p.home_position);
        let (mut h, stats, clock) = start(p, Arc::default());
        assert_eq!(h.line().await, "Grbl 1.1h ['$' for help]");
        assert_eq!(h.line().await, "[MSG:'$H'|'$X' to unlock]");
        assert_eq!(h.status().await.state, MachineState::Alarm);
        h.send(b"G90 G0 X1\n").await;
        assert_eq!(h.line().await, "error:9");
        // `$I` sent during homing waits in the RX buffer; `?` does not.
        h.send(b"$H\n$I\n").await;
        // Let the sim execute the line first: a `?` in the same read would
        // be answered before the line runs (realtime bytes jump the queue).
        clock.sleep_s(0.01).await;
        assert_eq!(h.status().await.state, MachineState::Home);
        assert_eq!(h.line().await, "ok");
        let t = clock.now_s();
        assert!((t - expect).abs() < 1e-3, "{t} vs {expect}");
        assert_eq!(h.line().await, "[VER:1.1h.20190830:]");
        assert_eq!(h.line().await, "[OPT:V,15,128]");
        assert_eq!(h.line().await, "ok");
        let s = h.status().await;
        assert_eq!((s.state, s.x()), (MachineState::Idle, Some(0.0)));
        assert_eq!(stats.rx_overflow_bytes.load(Ordering::Relaxed), 0);
    }

    #[tokio::test(start_paused = true)]
    async fn move_runs_then_idles_and_realtime_works_mid_line() {
        let p = GrblParams {
            start_homed: true,
            physical_start: 0.0,
            ..GrblParams::default()
        };
        let m = p.motion;
        let (mut h, _, clock) = start(p, Arc::default());
        assert_eq!(h.line().await, "Grbl 1.1h ['$' for help]");
        // A status query in the middle of a line is answered at once.
        h.send(b"G90 G0").await;
        assert_eq!(h.status().await.state, MachineState::Idle);
        h.send(b" X30\n").await;
        assert_eq!(h.line().await, "ok");
        let t0 = clock.now_s();
        clock.sleep_s(m.travel_time(30.0) / 2.0).await;
        let s = h.status().await;
        assert_eq!(s.state, MachineState::Run);
        let x = s.x().unwrap_or(f64::NAN);
        assert!((x - 15.0).abs() < 0.01, "{x}");
        // Feed hold freezes, cycle start resumes.
        h.send(b"!").await;
        let held = h.status().await;
        assert_eq!(held.state, MachineState::Hold(0));
        clock.sleep_s(5.0).await;
        assert_eq!(h.status().await.x(), held.x());
        h.send(b"~").await;
        clock.sleep_s(m.move_time(15.0) + 0.01).await;
        let s = h.status().await;
        assert_eq!((s.state, s.x()), (MachineState::Idle, Some(30.0)));
        assert!(clock.now_s() - t0 > m.move_time(30.0));
        // Soft reset mid-move: ALARM:3, banner, locked.
        h.send(b"G90 G0 X0\n").await;
        assert_eq!(h.line().await, "ok");
        h.send(&[0x18]).await;
        assert_eq!(h.line().await, "ALARM:3");
        assert_eq!(h.line().await, "Grbl 1.1h ['$' for help]");
        assert_eq!(h.line().await, "[MSG:'$H'|'$X' to unlock]");
        h.send(b"$X\n").await;
        assert_eq!(h.line().await, "[MSG:Caution: Unlocked]");
        assert_eq!(h.line().await, "ok");
    }

    #[tokio::test(start_paused = true)]
    async fn rx_overflow_drops_bytes_while_busy() {
        let (mut h, stats, clock) = start(GrblParams::default(), Arc::default());
        assert_eq!(h.line().await, "Grbl 1.1h ['$' for help]");
        assert_eq!(h.line().await, "[MSG:'$H'|'$X' to unlock]");
        h.send(b"$H\n").await;
        clock.sleep_s(0.01).await;
        assert_eq!(h.status().await.state, MachineState::Home);
        h.send(&[b' '; 200]).await;
        // The homing ok comes after the sim has read everything.
        assert_eq!(h.line().await, "ok");
        assert_eq!(stats.rx_overflow_bytes.load(Ordering::Relaxed), 200 - 127);
    }

    #[tokio::test(start_paused = true)]
    async fn faults_timeout_alarm_disconnect() {
        let faults = Arc::new(FaultInjector::new(vec![
            "grbl:info:1:timeout".parse().expect("rule"),
            "grbl:unlock:1:alarm=limit switch X".parse().expect("rule"),
            "grbl:info:2:disconnect".parse().expect("rule"),
        ]));
        let (mut h, _, _) = start(GrblParams::default(), faults);
        assert_eq!(h.line().await, "Grbl 1.1h ['$' for help]");
        assert_eq!(h.line().await, "[MSG:'$H'|'$X' to unlock]");
        h.send(b"$I\n").await; // swallowed
        h.send(b"$X\n").await;
        assert_eq!(h.line().await, "ALARM:1");
        assert_eq!(h.line().await, "[MSG:limit switch X]");
        assert_eq!(h.status().await.state, MachineState::Alarm);
        h.send(b"$I\n").await;
        let mut b = [0u8; 16];
        assert_eq!(h.io.read(&mut b).await.expect("read"), 0);
    }
}
