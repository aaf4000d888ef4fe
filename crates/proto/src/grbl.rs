//! GRBL 1.1 line protocol (see `firmware-protocols/grbl.md`).
//!
//! The host sends newline-terminated ASCII lines (system `$` commands and
//! G-code) plus single realtime bytes that GRBL picks off its serial stream
//! at once. GRBL answers every line with exactly one `ok` or `error:N`, and
//! pushes other messages (`ALARM:N`, `[MSG:…]`, status reports, the welcome
//! banner) whenever it likes. This module encodes and parses both sides;
//! every parser accepts arbitrary input without panicking.

use std::fmt;

/// Usable bytes of GRBL's serial receive buffer (a 128-byte ring that keeps
/// one slot free). A host must never have more unanswered line bytes in
/// flight than this, or GRBL silently drops characters.
pub const RX_BUFFER_SIZE: usize = 127;

/// GRBL's line buffer: longer lines are refused with `error:11`.
pub const LINE_BUFFER_SIZE: usize = 80;

/// Realtime status query.
pub const STATUS_QUERY: u8 = b'?';
/// Realtime feed hold: decelerate and pause the current motion.
pub const FEED_HOLD: u8 = b'!';
/// Realtime cycle start: resume after a feed hold.
pub const CYCLE_START: u8 = b'~';
/// Realtime soft reset (Ctrl-X): stops everything, reprints the banner.
pub const SOFT_RESET: u8 = 0x18;

/// True for the bytes GRBL handles out of band, even in the middle of a line.
pub fn is_realtime(b: u8) -> bool {
    matches!(b, STATUS_QUERY | FEED_HOLD | CYCLE_START | SOFT_RESET)
}

/// The realtime commands rigd uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Realtime {
    /// `?`: ask for a status report.
    StatusQuery,
    /// `!`: decelerate and pause the current motion.
    FeedHold,
    /// `~`: resume after a feed hold.
    CycleStart,
    /// Ctrl-X (0x18): stop everything and restart GRBL.
    SoftReset,
}

impl Realtime {
    /// The single byte sent on the wire for this command.
    pub fn byte(self) -> u8 {
        match self {
            Realtime::StatusQuery => STATUS_QUERY,
            Realtime::FeedHold => FEED_HOLD,
            Realtime::CycleStart => CYCLE_START,
            Realtime::SoftReset => SOFT_RESET,
        }
    }

    /// The realtime command a byte stands for, or `None` for any other byte.
    pub fn from_byte(b: u8) -> Option<Realtime> {
        match b {
            STATUS_QUERY => Some(Realtime::StatusQuery),
            FEED_HOLD => Some(Realtime::FeedHold),
            CYCLE_START => Some(Realtime::CycleStart),
            SOFT_RESET => Some(Realtime::SoftReset),
            _ => None,
        }
    }
}

/// A line command, as the host encodes it and the firmware parses it.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// `$H`: run the homing cycle (blocks until done, then `ok`).
    Home,
    /// `$X`: kill the alarm lock without homing.
    Unlock,
    /// `$I`: build info (`[VER:…]`, `[OPT:…]`, `ok`).
    BuildInfo,
    /// `G90 G0 X…`: absolute rapid move of the X axis.
    Rapid {
        /// Target machine position of X (rigd's unit: degrees).
        x: f64,
    },
    /// `$J=G90 X… F…`: absolute jog at `feed` units/min.
    Jog {
        /// Target machine position of X (rigd's unit: degrees).
        x: f64,
        /// Feed rate in units/min (rigd: degrees/min); must be positive.
        feed: f64,
    },
    /// `$$`: list every setting (`$N=V` lines, then `ok`).
    ReadSettings,
    /// `$N=V`: store setting `N` in the controller's EEPROM.
    WriteSetting {
        /// The setting's number (`110` for X's maximum rate).
        number: u16,
        /// The value to store.
        value: f64,
    },
    /// A line that parses but moves nothing (empty, or modal words only);
    /// GRBL acknowledges it with `ok`.
    Nop,
}

/// GRBL 1.1's settings, as `(number, factory value)`, in the order `$$`
/// lists them: the defaults a board ships with (`DEFAULTS_GENERIC`).
pub const FACTORY_SETTINGS: &[(u16, f64)] = &[
    (0, 10.0),
    (1, 25.0),
    (2, 0.0),
    (3, 0.0),
    (4, 0.0),
    (5, 0.0),
    (6, 0.0),
    (10, 1.0),
    (11, 0.010),
    (12, 0.002),
    (13, 0.0),
    (20, 0.0),
    (21, 0.0),
    (22, 0.0),
    (23, 0.0),
    (24, 25.0),
    (25, 500.0),
    (26, 250.0),
    (27, 1.0),
    (30, 1000.0),
    (31, 0.0),
    (32, 0.0),
    (100, 250.0),
    (101, 250.0),
    (102, 250.0),
    (110, 500.0),
    (111, 500.0),
    (112, 500.0),
    (120, 10.0),
    (121, 10.0),
    (122, 10.0),
    (130, 200.0),
    (131, 200.0),
    (132, 200.0),
];

/// Whether GRBL stores and prints setting `number` as a decimal (`250.000`)
/// rather than an integer or mask (`10`).
pub fn setting_is_decimal(number: u16) -> bool {
    matches!(number, 11 | 12 | 24 | 25 | 27 | 100..=132)
}

/// A setting's value as GRBL prints it: three decimals for decimal
/// settings, an integer for the others.
pub fn format_setting(number: u16, value: f64) -> String {
    if setting_is_decimal(number) {
        format!("{value:.3}")
    } else {
        format!("{}", value.round() as i64)
    }
}

/// Formats a coordinate like GRBL's reports: three decimals. Non-finite
/// values cannot be sent; callers check limits before encoding.
fn coord(v: f64) -> String {
    format!("{v:.3}")
}

impl Command {
    /// The line without its terminator.
    pub fn line(&self) -> String {
        match self {
            Command::Home => "$H".into(),
            Command::Unlock => "$X".into(),
            Command::BuildInfo => "$I".into(),
            Command::Rapid { x } => format!("G90 G0 X{}", coord(*x)),
            Command::Jog { x, feed } => format!("$J=G90 X{} F{}", coord(*x), coord(*feed)),
            Command::ReadSettings => "$$".into(),
            Command::WriteSetting { number, value } => {
                format!("${number}={}", format_setting(*number, *value))
            }
            Command::Nop => String::new(),
        }
    }

    /// The bytes to send: the line and a single `\n` (GRBL counts `\r\n`
    /// as two line ends, so the host never sends `\r`).
    pub fn encode(&self) -> Vec<u8> {
        let mut v = self.line().into_bytes();
        v.push(b'\n');
        v
    }
}

/// A GRBL `error:N` code, with the meaning from GRBL's documentation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ErrorCode(pub u16);

/// `error:1`: a G-code word without a letter.
pub const ERR_EXPECTED_LETTER: ErrorCode = ErrorCode(1);
/// `error:2`: a numeric value missing or badly formatted.
pub const ERR_BAD_NUMBER: ErrorCode = ErrorCode(2);
/// `error:3`: a `$` system command not recognised or not supported.
pub const ERR_INVALID_STATEMENT: ErrorCode = ErrorCode(3);
/// `error:4`: a negative value where a positive one is required.
pub const ERR_NEGATIVE_VALUE: ErrorCode = ErrorCode(4);
/// `error:5`: `$H` while homing is disabled (`$22=0`, the factory setting).
pub const ERR_HOMING_DISABLED: ErrorCode = ErrorCode(5);
/// `error:8`: a `$` command that is only valid while Idle.
pub const ERR_NOT_IDLE: ErrorCode = ErrorCode(8);
/// `error:9`: G-code locked out during the alarm or jog state.
pub const ERR_ALARM_LOCK: ErrorCode = ErrorCode(9);
/// `error:10`: soft limits (`$20=1`) while homing is disabled.
pub const ERR_SOFT_LIMIT_WITHOUT_HOMING: ErrorCode = ErrorCode(10);
/// `error:11`: the line is longer than [`LINE_BUFFER_SIZE`].
pub const ERR_LINE_OVERFLOW: ErrorCode = ErrorCode(11);
/// GRBL's step generator limit (`MAX_STEP_RATE_HZ`): it refuses settings
/// whose `$100 × $110 / 60` would exceed it with `error:12`.
pub const MAX_STEP_RATE_HZ: f64 = 30_000.0;
/// `error:12`: a setting that would step faster than the build allows.
pub const ERR_MAX_STEP_RATE: ErrorCode = ErrorCode(12);
/// `error:16`: a jog without `=` or with a prohibited G-code.
pub const ERR_INVALID_JOG: ErrorCode = ErrorCode(16);
/// `error:20`: unsupported or invalid G-code command.
pub const ERR_UNSUPPORTED_GCODE: ErrorCode = ErrorCode(20);
/// `error:22`: feed rate not set or undefined (a jog without a positive `F`).
pub const ERR_UNDEFINED_FEED: ErrorCode = ErrorCode(22);

impl ErrorCode {
    /// What the code means (paraphrased from GRBL 1.1's error table).
    pub fn meaning(self) -> &'static str {
        match self.0 {
            1 => "G-code word without a letter",
            2 => "numeric value missing or badly formatted",
            3 => "'$' system command not recognized or not supported",
            4 => "negative value where a positive one is required",
            5 => "homing cycle is not enabled in the settings",
            6 => "step pulse time must be at least 3 microseconds",
            7 => "EEPROM read failed, settings restored to defaults",
            8 => "'$' command only valid while Idle",
            9 => "G-code locked out during alarm or jog state",
            10 => "soft limits need homing to be enabled",
            11 => "line exceeds the maximum number of characters",
            12 => "setting exceeds the maximum step rate",
            13 => "safety door opened",
            14 => "build info or startup line too long for EEPROM",
            15 => "jog target exceeds machine travel",
            16 => "jog command without '=' or with a prohibited G-code",
            17 => "laser mode requires PWM output",
            20 => "unsupported or invalid G-code command",
            21 => "more than one G-code command of a modal group in a block",
            22 => "feed rate not set or undefined",
            23 => "G-code command requires an integer value",
            24 => "more than one G-code command using axis words in a block",
            25 => "G-code word repeated in the block",
            26 => "no axis words in a command that requires them",
            27 => "line number out of range",
            28 => "G-code command is missing a required value word",
            29 => "G59.x work coordinate systems are not supported",
            30 => "G53 only allowed with G0 and G1",
            31 => "axis words found in a block that uses none",
            32 => "G2/G3 arcs require at least one in-plane axis word",
            33 => "motion target is invalid",
            34 => "arc radius value is invalid",
            35 => "G2/G3 arcs require at least one in-plane offset word",
            36 => "unused value words found in the block",
            37 => "G43.1 tool length offset not assigned to the tool axis",
            38 => "tool number greater than the maximum supported",
            _ => "unknown error code",
        }
    }
}

impl fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "error:{} ({})", self.0, self.meaning())
    }
}

/// A GRBL `ALARM:N` code, with its meaning.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AlarmCode(pub u16);

/// `ALARM:1`: a hard limit switch triggered; position likely lost.
pub const ALARM_HARD_LIMIT: AlarmCode = AlarmCode(1);
/// `ALARM:2`: a motion target beyond machine travel (soft limit); position
/// retained.
pub const ALARM_SOFT_LIMIT: AlarmCode = AlarmCode(2);
/// `ALARM:3`: soft reset while in motion; position likely lost.
pub const ALARM_RESET_IN_MOTION: AlarmCode = AlarmCode(3);

impl AlarmCode {
    /// What the alarm means (paraphrased from GRBL 1.1's alarm table).
    pub fn meaning(self) -> &'static str {
        match self.0 {
            1 => "hard limit triggered; position likely lost, re-homing recommended",
            2 => "motion target exceeds machine travel (soft limit); position retained",
            3 => "reset while in motion; position likely lost, re-homing recommended",
            4 => "probe fail: probe not in the expected initial state",
            5 => "probe fail: probe did not contact within the programmed travel",
            6 => "homing fail: reset during the homing cycle",
            7 => "homing fail: safety door opened during homing",
            8 => "homing fail: pull-off did not clear the limit switch",
            9 => "homing fail: limit switch not found within the search distance",
            10 => "homing fail: second limit switch of a dual axis not found",
            _ => "unknown alarm code",
        }
    }
}

impl fmt::Display for AlarmCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "ALARM:{} ({})", self.0, self.meaning())
    }
}

/// The machine state at the start of a status report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MachineState {
    /// `Idle`: no motion pending; a move is complete.
    Idle,
    /// `Run`: executing motion.
    Run,
    /// `Hold:0` hold complete (ready to resume), `Hold:1` decelerating.
    Hold(u8),
    /// `Jog`: executing a `$J=` jog.
    Jog,
    /// `Alarm`: stopped after an alarm; G-code locked out until `$H` or `$X`.
    Alarm,
    /// `Door:0`…`Door:3`: safety door states.
    Door(u8),
    /// `Check`: G-code check mode (`$C`), lines parsed but not executed.
    Check,
    /// `Home`: running the homing cycle.
    Home,
    /// `Sleep`: sleep mode (`$SLP`).
    Sleep,
}

impl MachineState {
    fn parse(s: &str) -> Option<MachineState> {
        let (name, sub) = match s.split_once(':') {
            Some((n, sub)) => (n, Some(sub.parse::<u8>().ok()?)),
            None => (s, None),
        };
        Some(match (name, sub) {
            ("Idle", None) => MachineState::Idle,
            ("Run", None) => MachineState::Run,
            ("Hold", s) => MachineState::Hold(s.unwrap_or(0)),
            ("Jog", None) => MachineState::Jog,
            ("Alarm", None) => MachineState::Alarm,
            ("Door", s) => MachineState::Door(s.unwrap_or(0)),
            ("Check", None) => MachineState::Check,
            ("Home", None) => MachineState::Home,
            ("Sleep", None) => MachineState::Sleep,
            _ => return None,
        })
    }
}

impl fmt::Display for MachineState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            MachineState::Idle => f.write_str("Idle"),
            MachineState::Run => f.write_str("Run"),
            MachineState::Hold(n) => write!(f, "Hold:{n}"),
            MachineState::Jog => f.write_str("Jog"),
            MachineState::Alarm => f.write_str("Alarm"),
            MachineState::Door(n) => write!(f, "Door:{n}"),
            MachineState::Check => f.write_str("Check"),
            MachineState::Home => f.write_str("Home"),
            MachineState::Sleep => f.write_str("Sleep"),
        }
    }
}

/// A realtime status report `<State|MPos:x,y,z|FS:f,s|…>`. Fields rigd does
/// not use (WPos, Bf, Ln, Pn, A, …) are skipped when parsing; `WCO` and
/// `Ov`, which stock firmware sends every few reports, are kept so the
/// simulated firmware can send them too.
#[derive(Debug, Clone, PartialEq)]
pub struct Status {
    /// The machine state, the report's first field.
    pub state: MachineState,
    /// Machine position per axis (X first), if reported.
    pub mpos: Option<Vec<f64>>,
    /// Current feed rate (units/min) and spindle speed, if reported.
    pub feed: Option<f64>,
    /// Spindle speed, the second value of `FS`, if reported.
    pub spindle: Option<f64>,
    /// Work coordinate offset per axis (`WCO:`), if this report has it.
    pub wco: Option<Vec<f64>>,
    /// Feed, rapid and spindle overrides in percent (`Ov:`), if this report
    /// has them.
    pub overrides: Option<[u16; 3]>,
}

impl Status {
    /// The X axis machine position, which rigd maps to an axis in degrees.
    pub fn x(&self) -> Option<f64> {
        self.mpos.as_ref().and_then(|m| m.first().copied())
    }
}

impl fmt::Display for Status {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "<{}", self.state)?;
        if let Some(m) = &self.mpos {
            let parts: Vec<String> = m.iter().map(|v| coord(*v)).collect();
            write!(f, "|MPos:{}", parts.join(","))?;
        }
        if let Some(feed) = self.feed {
            write!(f, "|FS:{:.0},{:.0}", feed, self.spindle.unwrap_or(0.0))?;
        }
        if let Some(w) = &self.wco {
            let parts: Vec<String> = w.iter().map(|v| coord(*v)).collect();
            write!(f, "|WCO:{}", parts.join(","))?;
        }
        if let Some([feed, rapid, spindle]) = self.overrides {
            write!(f, "|Ov:{feed},{rapid},{spindle}")?;
        }
        f.write_str(">")
    }
}

/// One line from GRBL.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// The line was accepted (for motion: queued in the planner, not done).
    Ok,
    /// The line was refused.
    Error(ErrorCode),
    /// An alarm: GRBL has stopped and locks out G-code.
    Alarm(AlarmCode),
    /// `[MSG:…]` feedback message.
    Msg(String),
    /// `[VER:…]` build version from `$I`.
    Version(String),
    /// `[OPT:…]` build options from `$I`.
    Options(String),
    /// Any other `[…]` message (`[GC:…]`, `[HLP:…]`, …), content kept.
    Bracket(String),
    /// `Grbl 1.1h ['$' for help]`: GRBL (re)started; position is not trusted.
    Welcome {
        /// The version word of the banner, e.g. `1.1h`.
        version: String,
    },
    /// `<…>` status report.
    Status(Status),
    /// `$N=V`: one setting, a line of the answer to `$$`.
    Setting {
        /// The setting's number.
        number: u16,
        /// Its value.
        value: f64,
    },
}

impl fmt::Display for Reply {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Reply::Ok => f.write_str("ok"),
            Reply::Error(c) => write!(f, "error:{}", c.0),
            Reply::Alarm(c) => write!(f, "ALARM:{}", c.0),
            Reply::Msg(m) => write!(f, "[MSG:{m}]"),
            Reply::Version(v) => write!(f, "[VER:{v}]"),
            Reply::Options(o) => write!(f, "[OPT:{o}]"),
            Reply::Bracket(b) => write!(f, "[{b}]"),
            Reply::Welcome { version } => write!(f, "Grbl {version} ['$' for help]"),
            Reply::Status(s) => write!(f, "{s}"),
            Reply::Setting { number, value } => {
                write!(f, "${number}={}", format_setting(*number, *value))
            }
        }
    }
}

impl Reply {
    /// The line to send, with GRBL's `\r\n` terminator.
    pub fn encode(&self) -> Vec<u8> {
        let mut v = self.to_string().into_bytes();
        v.extend_from_slice(b"\r\n");
        v
    }
}

/// Why a line could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseError {
    /// The line starts like none of GRBL's replies (carries the line).
    #[error("unrecognized GRBL line `{0}`")]
    Unrecognized(String),
    /// The line starts like a known reply but its body does not parse
    /// (a bad code number, status field or unterminated message).
    #[error("malformed GRBL {what} `{line}`")]
    Malformed {
        /// Which kind of reply or status field was malformed.
        what: &'static str,
        /// The whole offending line.
        line: String,
    },
}

fn malformed(what: &'static str, line: &str) -> ParseError {
    ParseError::Malformed {
        what,
        line: line.to_string(),
    }
}

/// Parses a number the way GRBL reads one: optional sign, digits, optional
/// fraction; no exponents, no `inf`/`nan`.
pub fn parse_number(s: &str) -> Option<f64> {
    let body = s.strip_prefix(['+', '-']).unwrap_or(s);
    let mut digits = 0;
    let mut dots = 0;
    for c in body.chars() {
        match c {
            '0'..='9' => digits += 1,
            '.' => dots += 1,
            _ => return None,
        }
    }
    if digits == 0 || dots > 1 {
        return None;
    }
    s.parse::<f64>().ok().filter(|v| v.is_finite())
}

fn parse_numbers(s: &str) -> Option<Vec<f64>> {
    s.split(',').map(parse_number).collect()
}

fn parse_status(line: &str) -> Result<Status, ParseError> {
    let inner = line
        .strip_prefix('<')
        .and_then(|l| l.strip_suffix('>'))
        .ok_or_else(|| malformed("status report", line))?;
    let mut fields = inner.split('|');
    let state = fields
        .next()
        .and_then(MachineState::parse)
        .ok_or_else(|| malformed("status state", line))?;
    let mut status = Status {
        state,
        mpos: None,
        feed: None,
        spindle: None,
        wco: None,
        overrides: None,
    };
    for field in fields {
        let Some((name, value)) = field.split_once(':') else {
            continue;
        };
        match name {
            "MPos" => {
                let v = parse_numbers(value).ok_or_else(|| malformed("MPos", line))?;
                status.mpos = Some(v);
            }
            "FS" | "F" => {
                let v = parse_numbers(value).ok_or_else(|| malformed("FS", line))?;
                status.feed = v.first().copied();
                status.spindle = v.get(1).copied();
            }
            "WCO" => {
                let v = parse_numbers(value).ok_or_else(|| malformed("WCO", line))?;
                status.wco = Some(v);
            }
            "Ov" => {
                let v: Option<Vec<u16>> = value.split(',').map(|p| p.trim().parse().ok()).collect();
                match v.as_deref() {
                    Some(&[feed, rapid, spindle]) => {
                        status.overrides = Some([feed, rapid, spindle])
                    }
                    _ => return Err(malformed("Ov", line)),
                }
            }
            // WPos, Bf, Ln, Pn, A: not used by rigd.
            _ => {}
        }
    }
    Ok(status)
}

fn parse_code(rest: &str, what: &'static str, line: &str) -> Result<u16, ParseError> {
    if rest.is_empty() || !rest.bytes().all(|b| b.is_ascii_digit()) {
        return Err(malformed(what, line));
    }
    rest.parse().map_err(|_| malformed(what, line))
}

/// Parses one line from GRBL (terminator and surrounding whitespace ignored).
pub fn parse_reply(line: &str) -> Result<Reply, ParseError> {
    let line = line.trim_matches(|c: char| c == '\r' || c == '\n' || c == ' ');
    if line == "ok" {
        return Ok(Reply::Ok);
    }
    if let Some(rest) = line.strip_prefix("error:") {
        return Ok(Reply::Error(ErrorCode(parse_code(rest, "error", line)?)));
    }
    if let Some(rest) = line.strip_prefix("ALARM:") {
        return Ok(Reply::Alarm(AlarmCode(parse_code(rest, "alarm", line)?)));
    }
    if line.starts_with('<') {
        return parse_status(line).map(Reply::Status);
    }
    if let Some(inner) = line.strip_prefix('[') {
        let inner = inner
            .strip_suffix(']')
            .ok_or_else(|| malformed("message", line))?;
        return Ok(if let Some(m) = inner.strip_prefix("MSG:") {
            Reply::Msg(m.to_string())
        } else if let Some(v) = inner.strip_prefix("VER:") {
            Reply::Version(v.to_string())
        } else if let Some(o) = inner.strip_prefix("OPT:") {
            Reply::Options(o.to_string())
        } else {
            Reply::Bracket(inner.to_string())
        });
    }
    if let Some(rest) = line.strip_prefix('$') {
        let (number, value) = rest
            .split_once('=')
            .ok_or_else(|| malformed("setting", line))?;
        let number = parse_code(number, "setting", line)?;
        let value = parse_number(value).ok_or_else(|| malformed("setting", line))?;
        return Ok(Reply::Setting { number, value });
    }
    if let Some(rest) = line.strip_prefix("Grbl ") {
        let version = rest
            .strip_suffix("['$' for help]")
            .map(str::trim)
            .filter(|v| !v.is_empty())
            .ok_or_else(|| malformed("welcome banner", line))?;
        return Ok(Reply::Welcome {
            version: version.to_string(),
        });
    }
    Err(ParseError::Unrecognized(line.to_string()))
}

/// Parses raw bytes from the wire (lossy UTF-8), for callers holding bytes.
pub fn parse_reply_bytes(line: &[u8]) -> Result<Reply, ParseError> {
    parse_reply(&String::from_utf8_lossy(line))
}

/// Parses the words of a G-code block: `G90 G0 X1.5` or `G90G0X1.5`.
fn gcode_words(s: &str) -> Result<Vec<(char, String)>, ErrorCode> {
    let mut words = Vec::new();
    let mut chars = s.chars().filter(|c| !c.is_whitespace()).peekable();
    while let Some(c) = chars.next() {
        if !c.is_ascii_alphabetic() {
            return Err(ERR_EXPECTED_LETTER);
        }
        let mut value = String::new();
        while let Some(&n) = chars.peek() {
            if n.is_ascii_alphabetic() {
                break;
            }
            value.push(n);
            chars.next();
        }
        words.push((c.to_ascii_uppercase(), value));
    }
    Ok(words)
}

/// Parses a command line as the firmware receives it (terminator stripped).
/// This is the subset the simulated GRBL implements: `$H`, `$X`, `$I`,
/// `$$`, `$N=V`, absolute `G0` on X, and absolute X jogs; anything else gets the error
/// code real GRBL would send for it or, for valid G-code outside the
/// subset, `error:20`.
pub fn parse_command(line: &str) -> Result<Command, ErrorCode> {
    let t = line.trim_matches(|c: char| c == '\r' || c == '\n' || c == ' ');
    if t.is_empty() {
        return Ok(Command::Nop);
    }
    if let Some(sys) = t.strip_prefix('$') {
        if let Some(jog) = sys.strip_prefix("J=").or_else(|| sys.strip_prefix("j=")) {
            return parse_jog(jog);
        }
        if let Some((number, value)) = sys.split_once('=') {
            if !number.is_empty() && number.bytes().all(|b| b.is_ascii_digit()) {
                let number = number.parse().map_err(|_| ERR_INVALID_STATEMENT)?;
                let value = parse_number(value).ok_or(ERR_BAD_NUMBER)?;
                return Ok(Command::WriteSetting { number, value });
            }
        }
        return match sys.to_ascii_uppercase().as_str() {
            "$" => Ok(Command::ReadSettings),
            "H" => Ok(Command::Home),
            "X" => Ok(Command::Unlock),
            "I" => Ok(Command::BuildInfo),
            s if s.starts_with('J') => Err(ERR_INVALID_JOG),
            _ => Err(ERR_INVALID_STATEMENT),
        };
    }
    let words = gcode_words(t)?;
    let mut x = None;
    let mut rapid = false;
    for (letter, value) in words {
        let v = parse_number(&value).ok_or(ERR_BAD_NUMBER)?;
        match letter {
            'G' if v == 0.0 => rapid = true,
            'G' if v == 90.0 => {}
            'X' => x = Some(v),
            _ => return Err(ERR_UNSUPPORTED_GCODE),
        }
    }
    match (rapid, x) {
        (true, Some(x)) => Ok(Command::Rapid { x }),
        // An axis word without a motion mode: the sim has no modal G0 state.
        (false, Some(_)) => Err(ERR_UNSUPPORTED_GCODE),
        (_, None) => Ok(Command::Nop),
    }
}

fn parse_jog(body: &str) -> Result<Command, ErrorCode> {
    let words = gcode_words(body)?;
    let mut x = None;
    let mut feed = None;
    for (letter, value) in words {
        let v = parse_number(&value).ok_or(ERR_BAD_NUMBER)?;
        match letter {
            'G' if v == 90.0 => {}
            'X' => x = Some(v),
            'F' => feed = Some(v),
            _ => return Err(ERR_INVALID_JOG),
        }
    }
    let feed = feed.filter(|f| *f > 0.0).ok_or(ERR_UNDEFINED_FEED)?;
    let x = x.ok_or(ERR_INVALID_JOG)?;
    Ok(Command::Jog { x, feed })
}

/// Splits a byte stream into lines at `\n` or `\r`, dropping empty lines
/// (the host's view: GRBL ends replies with `\r\n`). Lines longer than
/// `max` are cut to `max` bytes so a babbling device cannot exhaust memory.
#[derive(Debug, Clone)]
pub struct LineSplitter {
    buf: Vec<u8>,
    max: usize,
}

impl LineSplitter {
    /// An empty splitter that cuts lines at `max` bytes.
    pub fn new(max: usize) -> LineSplitter {
        LineSplitter {
            buf: Vec::new(),
            max,
        }
    }

    /// Feeds one byte; returns a completed non-empty line.
    pub fn push(&mut self, b: u8) -> Option<String> {
        if b == b'\n' || b == b'\r' {
            if self.buf.is_empty() {
                return None;
            }
            let line = String::from_utf8_lossy(&self.buf).into_owned();
            self.buf.clear();
            return Some(line);
        }
        if self.buf.len() < self.max {
            self.buf.push(b);
        }
        None
    }

    /// Bytes of an unfinished line.
    pub fn pending(&self) -> usize {
        self.buf.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn status(line: &str) -> Status {
        match parse_reply(line) {
            Ok(Reply::Status(s)) => s,
            other => panic!("{line}: {other:?}"),
        }
    }

    #[test]
    fn encodes_host_commands() {
        assert_eq!(Command::Home.encode(), b"$H\n");
        assert_eq!(Command::Unlock.line(), "$X");
        assert_eq!(Command::BuildInfo.line(), "$I");
        assert_eq!(Command::Rapid { x: 90.0 }.line(), "G90 G0 X90.000");
        assert_eq!(Command::Rapid { x: -2.25 }.line(), "G90 G0 X-2.250");
        assert_eq!(
            Command::Jog {
                x: 1.5,
                feed: 600.0
            }
            .line(),
            "$J=G90 X1.500 F600.000"
        );
        assert_eq!(Realtime::SoftReset.byte(), 0x18);
        assert_eq!(Realtime::from_byte(b'!'), Some(Realtime::FeedHold));
        assert!(is_realtime(b'~') && !is_realtime(b'G'));
    }

    #[test]
    fn parses_replies() {
        assert_eq!(parse_reply("ok\r\n"), Ok(Reply::Ok));
        assert_eq!(parse_reply("error:9"), Ok(Reply::Error(ERR_ALARM_LOCK)));
        assert!(ERR_ALARM_LOCK.meaning().contains("alarm"));
        assert_eq!(parse_reply("ALARM:1"), Ok(Reply::Alarm(ALARM_HARD_LIMIT)));
        assert!(ALARM_HARD_LIMIT.meaning().contains("hard limit"));
        assert!(parse_reply("error:").is_err());
        assert!(parse_reply("error:x1").is_err());
        assert_eq!(
            parse_reply("[MSG:'$H'|'$X' to unlock]"),
            Ok(Reply::Msg("'$H'|'$X' to unlock".into()))
        );
        assert_eq!(
            parse_reply("[VER:1.1h.20190830:]"),
            Ok(Reply::Version("1.1h.20190830:".into()))
        );
        assert_eq!(
            parse_reply("[OPT:V,15,128]"),
            Ok(Reply::Options("V,15,128".into()))
        );
        assert_eq!(
            parse_reply("[GC:G0 G54]"),
            Ok(Reply::Bracket("GC:G0 G54".into()))
        );
        assert_eq!(
            parse_reply("Grbl 1.1h ['$' for help]"),
            Ok(Reply::Welcome {
                version: "1.1h".into()
            })
        );
        assert!(parse_reply("Grbl ['$' for help]").is_err());
        assert!(matches!(
            parse_reply("hello"),
            Err(ParseError::Unrecognized(_))
        ));
    }

    #[test]
    fn parses_status_reports_and_skips_unknown_fields() {
        let s = status("<Idle|MPos:1.000,2.500,-3.000|FS:0,0>");
        assert_eq!(s.state, MachineState::Idle);
        assert_eq!(s.mpos, Some(vec![1.0, 2.5, -3.0]));
        assert_eq!(s.x(), Some(1.0));
        assert_eq!(s.feed, Some(0.0));
        let s = status("<Hold:1|MPos:5.000,0.000,0.000|Bf:15,128|FS:500,8000|WCO:0,0,0>");
        assert_eq!(s.state, MachineState::Hold(1));
        assert_eq!(s.feed, Some(500.0));
        assert_eq!(s.spindle, Some(8000.0));
        assert_eq!(s.wco, Some(vec![0.0, 0.0, 0.0]));
        // What a stock 1.1h board sends: pins, then WCO on one report and
        // the overrides on the next.
        let s = status("<Idle|MPos:0.000,0.000,0.000|FS:0,0|Pn:PXYZRHS|WCO:0.000,0.000,0.000>");
        assert_eq!(
            (s.state, s.x(), s.overrides),
            (MachineState::Idle, Some(0.0), None)
        );
        let s = status("<Idle|MPos:0.000,0.000,0.000|FS:0,0|Pn:PXYZRHS|Ov:100,100,100>");
        assert_eq!((s.wco.clone(), s.overrides), (None, Some([100, 100, 100])));
        assert_eq!(
            s.to_string(),
            "<Idle|MPos:0.000,0.000,0.000|FS:0,0|Ov:100,100,100>"
        );
        assert!(parse_reply("<Idle|MPos:0,0,0|Ov:100,100>").is_err());
        for (text, st) in [
            ("Run", MachineState::Run),
            ("Jog", MachineState::Jog),
            ("Alarm", MachineState::Alarm),
            ("Door:2", MachineState::Door(2)),
            ("Check", MachineState::Check),
            ("Home", MachineState::Home),
            ("Sleep", MachineState::Sleep),
        ] {
            assert_eq!(status(&format!("<{text}|MPos:0,0,0>")).state, st);
        }
        assert!(parse_reply("<Dance|MPos:0,0,0>").is_err());
        assert!(parse_reply("<Idle|MPos:1,x,0>").is_err());
        assert!(parse_reply("<Idle|MPos:1,0,0").is_err());
    }

    #[test]
    fn formatted_replies_parse_back() {
        let st = Status {
            state: MachineState::Run,
            mpos: Some(vec![12.3456, 0.0, 0.0]),
            feed: Some(1200.0),
            spindle: Some(0.0),
            wco: None,
            overrides: None,
        };
        assert_eq!(st.to_string(), "<Run|MPos:12.346,0.000,0.000|FS:1200,0>");
        for r in [
            Reply::Ok,
            Reply::Error(ERR_UNSUPPORTED_GCODE),
            Reply::Alarm(ALARM_RESET_IN_MOTION),
            Reply::Msg("Caution: Unlocked".into()),
            Reply::Welcome {
                version: "1.1h".into(),
            },
        ] {
            assert_eq!(parse_reply_bytes(&r.encode()), Ok(r.clone()));
        }
    }

    #[test]
    fn settings_lines_round_trip_as_grbl_prints_them() {
        for (number, value, line) in [
            (0, 10.0, "$0=10"),
            (22, 1.0, "$22=1"),
            (110, 1800.0, "$110=1800.000"),
            (11, 0.01, "$11=0.010"),
        ] {
            let r = Reply::Setting { number, value };
            assert_eq!(r.to_string(), line);
            assert_eq!(parse_reply(line), Ok(r.clone()));
            let cmd = Command::WriteSetting { number, value };
            assert_eq!(cmd.line(), line);
            assert_eq!(parse_command(line), Ok(cmd));
        }
        assert_eq!(parse_command("$$"), Ok(Command::ReadSettings));
        assert_eq!(Command::ReadSettings.line(), "$$");
        assert_eq!(parse_command("$110=fast"), Err(ERR_BAD_NUMBER));
        assert_eq!(parse_command("$110="), Err(ERR_BAD_NUMBER));
        assert!(matches!(
            parse_reply("$110=fast"),
            Err(ParseError::Malformed {
                what: "setting",
                ..
            })
        ));
        assert!(parse_reply("$=1").is_err());
        // Every factory setting prints and parses back.
        for &(number, value) in FACTORY_SETTINGS {
            let r = Reply::Setting { number, value };
            assert_eq!(parse_reply_bytes(&r.encode()), Ok(r));
        }
    }

    #[test]
    fn parses_firmware_commands() {
        assert_eq!(parse_command("$H"), Ok(Command::Home));
        assert_eq!(parse_command("$x\r"), Ok(Command::Unlock));
        assert_eq!(parse_command("$I"), Ok(Command::BuildInfo));
        assert_eq!(parse_command(""), Ok(Command::Nop));
        assert_eq!(parse_command("G90"), Ok(Command::Nop));
        assert_eq!(
            parse_command("G90 G0 X90.000"),
            Ok(Command::Rapid { x: 90.0 })
        );
        assert_eq!(parse_command("g90g0x-1.5"), Ok(Command::Rapid { x: -1.5 }));
        assert_eq!(
            parse_command("$J=G90 X10 F600"),
            Ok(Command::Jog {
                x: 10.0,
                feed: 600.0
            })
        );
        assert_eq!(parse_command("$J=G90 X10"), Err(ERR_UNDEFINED_FEED));
        assert_eq!(parse_command("$J G90 X10"), Err(ERR_INVALID_JOG));
        assert_eq!(parse_command("$Q"), Err(ERR_INVALID_STATEMENT));
        assert_eq!(parse_command("G91 G0 X1"), Err(ERR_UNSUPPORTED_GCODE));
        assert_eq!(parse_command("G0 Xabc"), Err(ERR_BAD_NUMBER));
        assert_eq!(parse_command("G0 X1.2.3"), Err(ERR_BAD_NUMBER));
        assert_eq!(parse_command("1 G0"), Err(ERR_EXPECTED_LETTER));
        for c in [
            Command::Home,
            Command::Rapid { x: 3.25 },
            Command::Jog {
                x: -4.0,
                feed: 90.0,
            },
        ] {
            assert_eq!(parse_command(&c.line()), Ok(c.clone()));
        }
    }

    #[test]
    fn splitter_handles_crlf_and_caps_length() {
        let mut s = LineSplitter::new(4);
        let mut out = Vec::new();
        for &b in b"ok\r\nlonger line\n\n" {
            out.extend(s.push(b));
        }
        assert_eq!(out, vec!["ok".to_string(), "long".to_string()]);
        assert_eq!(s.pending(), 0);
    }

    proptest! {
        #[test]
        fn reply_parser_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = parse_reply_bytes(&bytes);
        }

        #[test]
        fn reply_parser_never_panics_on_near_misses(s in "(ok|error:[0-9x]{0,4}|ALARM:[0-9]{0,3}|<[A-Za-z:0-9]{0,6}(\\|[A-Za-z]{1,4}:[-0-9.,]{0,12}){0,4}>?|\\[[A-Z]{0,4}:?.{0,10}\\]?|Grbl .{0,8})") {
            let _ = parse_reply(&s);
        }

        #[test]
        fn command_parser_never_panics(s in ".{0,100}") {
            let _ = parse_command(&s);
        }

        #[test]
        fn command_parser_never_panics_on_gcode_like(s in "[$GgXxFJ=0-9. +-]{0,40}") {
            let _ = parse_command(&s);
        }

        #[test]
        fn status_round_trips(x in -1.0e4f64..1.0e4, feed in 0.0f64..1.0e5, held in any::<bool>()) {
            let st = Status {
                state: if held { MachineState::Hold(1) } else { MachineState::Run },
                mpos: Some(vec![x, 0.0, 0.0]),
                feed: Some(feed.round()),
                spindle: Some(0.0),
                wco: None,
                overrides: None,
            };
            let back = status(&st.to_string());
            prop_assert_eq!(back.state, st.state);
            let bx = back.x().unwrap_or(f64::NAN);
            prop_assert!((bx - x).abs() <= 0.0005 + 1e-9, "{} vs {}", bx, x);
            prop_assert_eq!(back.feed, st.feed);
        }

        #[test]
        fn rapid_round_trips(x in -1.0e4f64..1.0e4) {
            match parse_command(&Command::Rapid { x }.line()) {
                Ok(Command::Rapid { x: back }) => prop_assert!((back - x).abs() <= 0.0005 + 1e-9),
                other => prop_assert!(false, "{:?}", other),
            }
        }
    }
}
