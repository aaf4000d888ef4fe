//! Codec for the ACL-style robot-arm protocol (`firmware-protocols/robot-arm.md`):
//! host-side command encoding and reply parsing, firmware-side command
//! parsing and reply formatting. Pure text; no I/O.
//!
//! Lines from the host end in `\r` (the controller accepts `\r`, `\n` or
//! `\r\n`); lines from the controller end in `\r\n`. Every answer ends with
//! the prompt line `>`, which is how the host knows an answer is complete.

use std::fmt;

/// Longest command line the controller accepts, without the line ending.
pub const MAX_LINE: usize = 64;
/// Longest position name (ACL names are short identifiers).
pub const MAX_NAME: usize = 16;
/// The reserved name of the current-position pseudo variable.
pub const CURRENT: &str = "POSITION";
/// The prompt the controller prints after every answer.
pub const PROMPT: &str = ">";

/// Why a line could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseError {
    /// The line holds nothing but whitespace.
    #[error("empty line")]
    Empty,
    /// The first word is not a known command keyword (carries that word).
    #[error("unknown command `{0}`")]
    UnknownCommand(String),
    /// A known command has the wrong number of arguments or one that is not
    /// a number.
    #[error("bad arguments to {cmd}: `{line}`")]
    BadArguments {
        /// The command (or group of commands) whose arguments were wrong.
        cmd: &'static str,
        /// The whole offending line.
        line: String,
    },
    /// A position name is empty, longer than [`MAX_NAME`], does not start
    /// with a letter or has a character outside `[A-Za-z0-9_]`.
    #[error("bad position name `{0}`")]
    BadName(String),
    /// A controller line is none of the replies the host knows (carries the
    /// line).
    #[error("unrecognised reply `{0}`")]
    UnknownReply(String),
}

/// A command from host to controller.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Command {
    /// Home all axes; answered when homing is complete.
    Home,
    /// Define a position variable (initialised to the current position).
    Defp(String),
    /// Set joint `joint` (1-based) of a position to `counts` encoder counts.
    Setpv {
        /// The position variable to change.
        name: String,
        /// Joint number, 1-based.
        joint: u8,
        /// Target in encoder counts.
        counts: i64,
    },
    /// Start a move; answered at once. `duration` in hundredths of a second.
    Move {
        /// The position variable to move to.
        name: String,
        /// Minimum duration of the move in hundredths of a second; `None`:
        /// as fast as the joints allow.
        duration: Option<u32>,
    },
    /// Move and answer only when the motion is complete.
    Moved {
        /// The position variable to move to.
        name: String,
        /// Minimum duration of the move in hundredths of a second; `None`:
        /// as fast as the joints allow.
        duration: Option<u32>,
    },
    /// Record the current position into a position variable.
    Here(String),
    /// List a position's joint counts (`POSITION`: where the arm is now).
    Listpv(String),
    /// Status query.
    Status,
    /// Abort: stop all motion immediately.
    Abort,
    /// Servo control on.
    Con,
    /// Servo control off.
    Coff,
}

/// Checks and normalises a position name: 1..=16 of `[A-Za-z0-9_]`,
/// starting with a letter, upper-cased (ACL names are case-insensitive).
pub fn normalise_name(s: &str) -> Result<String, ParseError> {
    let ok = !s.is_empty()
        && s.len() <= MAX_NAME
        && s.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if ok {
        Ok(s.to_ascii_uppercase())
    } else {
        Err(ParseError::BadName(s.to_string()))
    }
}

impl Command {
    /// The command line without line ending.
    pub fn line(&self) -> String {
        match self {
            Command::Home => "HOME".into(),
            Command::Defp(n) => format!("DEFP {n}"),
            Command::Setpv {
                name,
                joint,
                counts,
            } => format!("SETPV {name} {joint} {counts}"),
            Command::Move { name, duration } => match duration {
                Some(d) => format!("MOVE {name} {d}"),
                None => format!("MOVE {name}"),
            },
            Command::Moved { name, duration } => match duration {
                Some(d) => format!("MOVED {name} {d}"),
                None => format!("MOVED {name}"),
            },
            Command::Here(n) => format!("HERE {n}"),
            Command::Listpv(n) => format!("LISTPV {n}"),
            Command::Status => "STATUS".into(),
            Command::Abort => "A".into(),
            Command::Con => "CON".into(),
            Command::Coff => "COFF".into(),
        }
    }

    /// The bytes the host sends: the line and a carriage return.
    pub fn encode(&self) -> Vec<u8> {
        let mut b = self.line().into_bytes();
        b.push(b'\r');
        b
    }
}

impl fmt::Display for Command {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.line())
    }
}

/// Firmware side: parses one command line (without line ending). Keywords
/// are case-insensitive and separated by any run of spaces.
pub fn parse_command(line: &str) -> Result<Command, ParseError> {
    let words: Vec<&str> = line.split_ascii_whitespace().collect();
    let Some(first) = words.first() else {
        return Err(ParseError::Empty);
    };
    let kw = first.to_ascii_uppercase();
    let bad = |cmd: &'static str| ParseError::BadArguments {
        cmd,
        line: line.to_string(),
    };
    let args = &words[1..];
    let cmd = match kw.as_str() {
        "HOME" if args.is_empty() => Command::Home,
        "STATUS" if args.is_empty() => Command::Status,
        "A" if args.is_empty() => Command::Abort,
        "CON" if args.is_empty() => Command::Con,
        "COFF" if args.is_empty() => Command::Coff,
        "HOME" | "STATUS" | "A" | "CON" | "COFF" => return Err(bad("a command without arguments")),
        "DEFP" | "HERE" | "LISTPV" => {
            let [n] = args else {
                return Err(bad("DEFP/HERE/LISTPV"));
            };
            let n = normalise_name(n)?;
            match kw.as_str() {
                "DEFP" => Command::Defp(n),
                "HERE" => Command::Here(n),
                _ => Command::Listpv(n),
            }
        }
        "SETPV" => {
            let [n, j, c] = args else {
                return Err(bad("SETPV"));
            };
            let joint: u8 = j.parse().map_err(|_| bad("SETPV"))?;
            let counts: i64 = c.parse().map_err(|_| bad("SETPV"))?;
            Command::Setpv {
                name: normalise_name(n)?,
                joint,
                counts,
            }
        }
        "MOVE" | "MOVED" => {
            let (n, duration) = match args {
                [n] => (n, None),
                [n, d] => (n, Some(d.parse::<u32>().map_err(|_| bad("MOVE/MOVED"))?)),
                _ => return Err(bad("MOVE/MOVED")),
            };
            let name = normalise_name(n)?;
            if kw == "MOVE" {
                Command::Move { name, duration }
            } else {
                Command::Moved { name, duration }
            }
        }
        _ => return Err(ParseError::UnknownCommand(first.to_string())),
    };
    Ok(cmd)
}

/// The controller's status line: `HOMED=1 MOVING=0 CON=1`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Status {
    /// `HOMED=1`: the axes have been homed since power-up.
    pub homed: bool,
    /// `MOVING=1`: a motion is in progress.
    pub moving: bool,
    /// `CON=1`: servo control is on.
    pub control: bool,
}

/// A line from controller to host (the echo of the command is not a
/// reply; the host recognises and skips it).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reply {
    /// A position or motion command was accepted (MOVED: completed).
    Done,
    /// CON, COFF and A were executed.
    Ok,
    /// `*** text`: the command failed, in the controller's words.
    Error(String),
    /// `1:0 2:1500 3:-200`: joint counts, joints numbered from 1 in order.
    Joints(Vec<i64>),
    /// Answer to `STATUS`.
    Status(Status),
    /// `>`: the answer is complete.
    Prompt,
}

fn flag(b: bool) -> u8 {
    u8::from(b)
}

impl Reply {
    /// The reply line without line ending.
    pub fn line(&self) -> String {
        match self {
            Reply::Done => "Done.".into(),
            Reply::Ok => "OK".into(),
            Reply::Error(t) => format!("*** {t}"),
            Reply::Joints(j) => j
                .iter()
                .enumerate()
                .map(|(i, c)| format!("{}:{c}", i + 1))
                .collect::<Vec<_>>()
                .join(" "),
            Reply::Status(s) => format!(
                "HOMED={} MOVING={} CON={}",
                flag(s.homed),
                flag(s.moving),
                flag(s.control)
            ),
            Reply::Prompt => PROMPT.into(),
        }
    }

    /// The bytes the controller sends: the line and `\r\n`.
    pub fn encode(&self) -> Vec<u8> {
        let mut b = self.line().into_bytes();
        b.extend_from_slice(b"\r\n");
        b
    }
}

fn parse_flag(s: &str, key: &str) -> Option<bool> {
    match s.strip_prefix(key)? {
        "0" => Some(false),
        "1" => Some(true),
        _ => None,
    }
}

/// Host side: parses one reply line (without line ending).
pub fn parse_reply(line: &str) -> Result<Reply, ParseError> {
    let t = line.trim();
    let unknown = || ParseError::UnknownReply(line.to_string());
    match t {
        "Done." => return Ok(Reply::Done),
        "OK" => return Ok(Reply::Ok),
        PROMPT => return Ok(Reply::Prompt),
        _ => {}
    }
    if let Some(rest) = t.strip_prefix("***") {
        return Ok(Reply::Error(rest.trim().to_string()));
    }
    if t.starts_with("HOMED=") {
        let w: Vec<&str> = t.split_ascii_whitespace().collect();
        let [h, m, c] = w.as_slice() else {
            return Err(unknown());
        };
        return Ok(Reply::Status(Status {
            homed: parse_flag(h, "HOMED=").ok_or_else(unknown)?,
            moving: parse_flag(m, "MOVING=").ok_or_else(unknown)?,
            control: parse_flag(c, "CON=").ok_or_else(unknown)?,
        }));
    }
    let mut joints = Vec::new();
    for (i, w) in t.split_ascii_whitespace().enumerate() {
        let (n, c) = w.split_once(':').ok_or_else(unknown)?;
        if n.parse::<usize>().ok() != Some(i + 1) {
            return Err(unknown());
        }
        joints.push(c.parse::<i64>().map_err(|_| unknown())?);
    }
    if joints.is_empty() {
        return Err(unknown());
    }
    Ok(Reply::Joints(joints))
}

/// Splits a byte stream into lines at `\r`, `\n` or `\r\n`; empty lines
/// are dropped. Over-long lines are cut at `max` bytes (the rest up to the
/// line end is discarded) and flagged, so the receiver can refuse them.
#[derive(Debug, Clone)]
pub struct LineSplitter {
    buf: Vec<u8>,
    max: usize,
    overflow: bool,
}

/// One complete line from a [`LineSplitter`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Line {
    /// The line's text without its line ending (invalid UTF-8 replaced).
    pub text: String,
    /// The line was longer than the splitter's maximum.
    pub too_long: bool,
}

impl LineSplitter {
    /// An empty splitter that cuts lines at `max` bytes.
    pub fn new(max: usize) -> LineSplitter {
        LineSplitter {
            buf: Vec::new(),
            max,
            overflow: false,
        }
    }

    /// Feeds one byte; returns a line when one ends.
    pub fn push(&mut self, b: u8) -> Option<Line> {
        if b == b'\r' || b == b'\n' {
            if self.buf.is_empty() && !self.overflow {
                return None;
            }
            let text = String::from_utf8_lossy(&self.buf).into_owned();
            let too_long = self.overflow;
            self.buf.clear();
            self.overflow = false;
            return Some(Line { text, too_long });
        }
        if self.buf.len() >= self.max {
            self.overflow = true;
        } else {
            self.buf.push(b);
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn lines(bytes: &[u8]) -> Vec<Line> {
        let mut s = LineSplitter::new(MAX_LINE);
        bytes.iter().filter_map(|&b| s.push(b)).collect()
    }

    #[test]
    fn commands_parse_case_insensitively() {
        assert_eq!(
            parse_command("setpv  p1 2 -1500"),
            Ok(Command::Setpv {
                name: "P1".into(),
                joint: 2,
                counts: -1500
            })
        );
        assert_eq!(
            parse_command("MOVED P1 250"),
            Ok(Command::Moved {
                name: "P1".into(),
                duration: Some(250)
            })
        );
        assert_eq!(parse_command("a"), Ok(Command::Abort));
        assert!(parse_command("MOVE 1P").is_err());
        assert!(parse_command("MOVE P1 -3").is_err());
        assert!(parse_command("HOME X").is_err());
        assert!(matches!(
            parse_command("JUMP"),
            Err(ParseError::UnknownCommand(_))
        ));
    }

    #[test]
    fn replies_parse() {
        assert_eq!(parse_reply("Done."), Ok(Reply::Done));
        assert_eq!(
            parse_reply("*** position out of range"),
            Ok(Reply::Error("position out of range".into()))
        );
        assert_eq!(
            parse_reply("1:0 2:-4500 3:12"),
            Ok(Reply::Joints(vec![0, -4500, 12]))
        );
        assert!(parse_reply("1:0 3:1").is_err());
        assert!(parse_reply("HOMED=1 MOVING=2 CON=1").is_err());
        assert!(parse_reply("MOVE P1").is_err());
    }

    #[test]
    fn splitter_handles_all_line_endings_and_overflow() {
        let l = lines(b"A\rB\nC\r\n\r\n");
        let t: Vec<&str> = l.iter().map(|l| l.text.as_str()).collect();
        assert_eq!(t, ["A", "B", "C"]);
        let long = [b'X'; MAX_LINE + 5];
        let mut b = long.to_vec();
        b.extend_from_slice(b"\rOK\r");
        let l = lines(&b);
        assert!(l[0].too_long);
        assert_eq!(l[0].text.len(), MAX_LINE);
        assert!(!l[1].too_long);
    }

    fn name() -> impl Strategy<Value = String> {
        "[A-Z][A-Z0-9_]{0,15}"
    }

    fn command() -> impl Strategy<Value = Command> {
        prop_oneof![
            Just(Command::Home),
            Just(Command::Status),
            Just(Command::Abort),
            Just(Command::Con),
            Just(Command::Coff),
            name().prop_map(Command::Defp),
            name().prop_map(Command::Here),
            name().prop_map(Command::Listpv),
            (name(), any::<u8>(), any::<i64>()).prop_map(|(name, joint, counts)| {
                Command::Setpv {
                    name,
                    joint,
                    counts,
                }
            }),
            (name(), proptest::option::of(any::<u32>()))
                .prop_map(|(name, duration)| Command::Move { name, duration }),
            (name(), proptest::option::of(any::<u32>()))
                .prop_map(|(name, duration)| Command::Moved { name, duration }),
        ]
    }

    proptest! {
        #[test]
        fn parsers_never_panic(s in "\\PC*") {
            let _ = parse_command(&s);
            let _ = parse_reply(&s);
        }

        #[test]
        fn splitter_never_panics(b in proptest::collection::vec(any::<u8>(), 0..300)) {
            for l in lines(&b) {
                prop_assert!(l.text.len() <= MAX_LINE * 4);
            }
        }

        #[test]
        fn commands_round_trip(c in command()) {
            prop_assert_eq!(parse_command(&c.line()), Ok(c.clone()));
            let enc = c.encode();
            let l = lines(&enc);
            prop_assert_eq!(l.len(), 1);
            prop_assert_eq!(&l[0].text, &c.line());
        }

        #[test]
        fn replies_round_trip(
            joints in proptest::collection::vec(any::<i64>(), 1..8),
            text in "[a-z][a-z ]{0,30}[a-z]",
            flags in any::<(bool, bool, bool)>(),
        ) {
            let status = Reply::Status(Status { homed: flags.0, moving: flags.1, control: flags.2 });
            for r in [Reply::Done, Reply::Ok, Reply::Prompt, Reply::Joints(joints.clone()),
                      Reply::Error(text.clone()), status] {
                prop_assert_eq!(parse_reply(&r.line()), Ok(r.clone()));
            }
        }
    }
}
