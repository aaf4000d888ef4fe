//! Fault injection for simulated devices: a rule fires on a device's N-th
//! call of an operation, once or until an operator clears it.

use std::collections::HashMap;
use std::fmt;
use std::str::FromStr;
use std::sync::Mutex;

/// What goes wrong.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FaultKind {
    /// The device does not answer; the caller's deadline must catch it.
    Timeout,
    /// The link is gone.
    Disconnect,
    /// The device reports a fault in its own words (GRBL `ALARM:1`, ...).
    Alarm(String),
    /// The camera delivers a truncated or corrupted frame.
    BadFrame,
    /// The camera's exposure misses the light: a whole, valid, dark frame
    /// (a lamp that did not fire). Only a camera's `expose` suffers it.
    Dark,
    /// Something covers the holder's point markers (dust, a cable): a
    /// whole, valid frame with dark spots where they are. Only a camera's
    /// `expose` suffers it.
    MaskMarkers,
}

impl fmt::Display for FaultKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FaultKind::Timeout => f.write_str("timeout"),
            FaultKind::Disconnect => f.write_str("disconnect"),
            FaultKind::Alarm(m) => write!(f, "alarm={m}"),
            FaultKind::BadFrame => f.write_str("bad-frame"),
            FaultKind::Dark => f.write_str("dark"),
            FaultKind::MaskMarkers => f.write_str("mask-markers"),
        }
    }
}

/// One armed fault: `device` fails on its `at_call`-th call (1-based) of
/// `op` (`None`: any operation). A sticky fault keeps failing every call
/// until [`FaultInjector::clear`], like a tripped limit switch.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FaultRule {
    /// Name of the device the fault hits (e.g. `arm`).
    pub device: String,
    /// The operation whose calls are counted (e.g. `move`); `None`: every
    /// call of the device counts.
    pub op: Option<String>,
    /// The call, counted from 1, on which the fault first fires.
    pub at_call: u64,
    /// What goes wrong.
    pub kind: FaultKind,
    /// Keep failing every later matching call until cleared.
    pub sticky: bool,
}

/// Parses `DEVICE:OP:N:KIND[:sticky]`, with OP `*` for any operation and KIND
/// one of `timeout`, `disconnect`, `bad-frame`, `dark`, `mask-markers`,
/// `alarm=TEXT`.
impl FromStr for FaultRule {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let parts: Vec<&str> = s.split(':').collect();
        let usage = || {
            format!("bad fault `{s}`: expected DEVICE:OP:N:KIND[:sticky], KIND = timeout | disconnect | bad-frame | dark | mask-markers | alarm=TEXT")
        };
        if !(4..=5).contains(&parts.len()) || parts[0].is_empty() {
            return Err(usage());
        }
        let at_call: u64 = parts[2].parse().map_err(|_| usage())?;
        if at_call == 0 {
            return Err(format!("bad fault `{s}`: calls count from 1"));
        }
        let kind = match parts[3] {
            "timeout" => FaultKind::Timeout,
            "disconnect" => FaultKind::Disconnect,
            "bad-frame" => FaultKind::BadFrame,
            "dark" => FaultKind::Dark,
            "mask-markers" => FaultKind::MaskMarkers,
            k if k.starts_with("alarm=") => FaultKind::Alarm(k["alarm=".len()..].to_string()),
            _ => return Err(usage()),
        };
        let sticky = match parts.get(4) {
            None => false,
            Some(&"sticky") => true,
            Some(_) => return Err(usage()),
        };
        Ok(FaultRule {
            device: parts[0].to_string(),
            op: (parts[1] != "*").then(|| parts[1].to_string()),
            at_call,
            kind,
            sticky,
        })
    }
}

#[derive(Debug, Default)]
struct State {
    rules: Vec<(FaultRule, bool)>,
    calls: HashMap<(String, String), u64>,
    any_calls: HashMap<String, u64>,
}

/// Shared by all simulated devices of a rig; each call asks it first.
#[derive(Debug, Default)]
pub struct FaultInjector {
    state: Mutex<State>,
}

impl FaultInjector {
    /// An injector armed with `rules`; call counters start at zero.
    pub fn new(rules: Vec<FaultRule>) -> FaultInjector {
        FaultInjector {
            state: Mutex::new(State {
                rules: rules.into_iter().map(|r| (r, false)).collect(),
                ..State::default()
            }),
        }
    }

    /// Adds a rule while the rig runs.
    pub fn arm(&self, rule: FaultRule) {
        self.lock().rules.push((rule, false));
    }

    /// Counts a call of `op` on `device` and returns the fault it must suffer, if any.
    pub fn check(&self, device: &str, op: &str) -> Option<FaultKind> {
        let mut st = self.lock();
        let n_op = {
            let c = st
                .calls
                .entry((device.to_string(), op.to_string()))
                .or_insert(0);
            *c += 1;
            *c
        };
        let n_any = {
            let c = st.any_calls.entry(device.to_string()).or_insert(0);
            *c += 1;
            *c
        };
        for (rule, fired) in st.rules.iter_mut() {
            if rule.device != device {
                continue;
            }
            let (matches, n) = match &rule.op {
                Some(o) => (o == op, n_op),
                None => (true, n_any),
            };
            if !matches {
                continue;
            }
            if *fired && rule.sticky {
                return Some(rule.kind.clone());
            }
            if !*fired && n >= rule.at_call {
                *fired = true;
                return Some(rule.kind.clone());
            }
        }
        None
    }

    /// How many calls of `op` `device` has had so far (what the simulated
    /// firmware was asked to do, for tests that count protocol traffic).
    pub fn calls(&self, device: &str, op: &str) -> u64 {
        self.lock()
            .calls
            .get(&(device.to_string(), op.to_string()))
            .copied()
            .unwrap_or(0)
    }

    /// The operator fixed `device`: its sticky faults stop firing.
    pub fn clear(&self, device: &str) {
        self.lock()
            .rules
            .retain(|(r, fired)| !(r.device == device && *fired));
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic while holding this lock cannot leave the counters invalid,
        // so a poisoned lock is still safe to use.
        rigd_core::sync::lock(&self.state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_documented_syntax() {
        // A colon in the alarm text would be read as the sticky slot: refused.
        assert!("rail:move:3:alarm=ALARM:1".parse::<FaultRule>().is_err());
        let r: FaultRule = "rail:move:3:alarm=ALARM 1"
            .parse()
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(r.kind, FaultKind::Alarm("ALARM 1".into()));
        assert!(!r.sticky);
        assert!("rail:move:3:alarm=hard limit:sticky"
            .parse::<FaultRule>()
            .is_ok());
        assert!("rail:move:0:timeout".parse::<FaultRule>().is_err());
        assert!("rail:move:x:timeout".parse::<FaultRule>().is_err());
        assert!("rail:move:2:melt".parse::<FaultRule>().is_err());
        let any: FaultRule = "camera:*:5:bad-frame"
            .parse()
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(any.op, None);
        for (text, kind) in [
            ("camera:expose:2:dark", FaultKind::Dark),
            ("camera:expose:2:mask-markers", FaultKind::MaskMarkers),
        ] {
            let r: FaultRule = text.parse().unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(r.kind, kind);
            assert_eq!(r.kind.to_string(), text.split(':').nth(3).unwrap_or(""));
        }
    }

    #[test]
    fn one_shot_fires_once_on_the_nth_call() {
        let f = FaultInjector::new(vec!["rail:move:3:timeout"
            .parse()
            .unwrap_or_else(|e| panic!("{e}"))]);
        assert_eq!(f.check("rail", "move"), None);
        assert_eq!(f.check("rail", "home"), None);
        assert_eq!(f.check("rail", "move"), None);
        assert_eq!(f.check("rail", "move"), Some(FaultKind::Timeout));
        assert_eq!(f.check("rail", "move"), None);
    }

    #[test]
    fn sticky_fires_until_cleared() {
        let f = FaultInjector::new(vec!["hmi:*:2:alarm=ballast fault:sticky"
            .parse()
            .unwrap_or_else(|e| panic!("{e}"))]);
        assert_eq!(f.check("hmi", "set"), None);
        let alarm = Some(FaultKind::Alarm("ballast fault".into()));
        assert_eq!(f.check("hmi", "set"), alarm);
        assert_eq!(f.check("hmi", "ready"), alarm);
        f.clear("hmi");
        assert_eq!(f.check("hmi", "set"), None);
    }
}
