//! Replays every ```transcript block of `firmware-protocols/grbl.md`
//! against the simulated firmware (the test is the host) and against the
//! driver (the test is the device), so the spec, the simulator and the
//! driver cannot drift apart. Matching rules are in the spec.

use std::sync::Arc;
use std::time::Duration;

use rigd::model::profile::{Limits, Motion};
use rigd::rig::drivers::grbl::{GrblAxis, GrblConfig};
use rigd::rig::hal::{Axis, DeviceError};
use rigd_core::Clock;
use rigd_proto::grbl::LineSplitter;
use rigd_sim::firmware::grbl::{serve, Eeprom, GrblParams};
use rigd_sim::{FaultInjector, FaultRule};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

#[derive(Debug, Clone)]
enum Step {
    Send(String),
    Recv(String),
    Call(String, Option<String>),
    Expect(String),
    Sleep(f64),
    Fault(String),
    /// `@ sim KEY=VALUE`: how the simulated board is set up.
    Sim(String, String),
    /// `@ driver KEY=VALUE`: how the driver is configured.
    Driver(String, String),
}

struct Transcript {
    title: String,
    steps: Vec<Step>,
}

fn parse_step(line: &str) -> Step {
    if let Some(x) = line.strip_prefix("> ") {
        Step::Send(x.to_string())
    } else if let Some(x) = line.strip_prefix("< ") {
        Step::Recv(x.to_string())
    } else if let Some(x) = line.strip_prefix("@ call ") {
        let mut it = x.splitn(2, ' ');
        let op = it.next().unwrap_or_default().to_string();
        Step::Call(op, it.next().map(str::to_string))
    } else if let Some(x) = line.strip_prefix("@ expect ") {
        Step::Expect(x.to_string())
    } else if let Some(x) = line.strip_prefix("@ sleep ") {
        Step::Sleep(x.trim().parse().expect("sleep seconds"))
    } else if let Some(x) = line.strip_prefix("@ fault ") {
        Step::Fault(x.to_string())
    } else if let Some((k, v)) = line.strip_prefix("@ sim ").and_then(|x| x.split_once('=')) {
        Step::Sim(k.to_string(), v.to_string())
    } else if let Some((k, v)) = line
        .strip_prefix("@ driver ")
        .and_then(|x| x.split_once('='))
    {
        Step::Driver(k.to_string(), v.to_string())
    } else {
        panic!("bad transcript line `{line}`")
    }
}

fn transcripts() -> Vec<Transcript> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/firmware-protocols/grbl.md");
    let text = std::fs::read_to_string(path).expect("read grbl.md");
    let mut out = Vec::new();
    let mut title = String::new();
    let mut current: Option<Vec<Step>> = None;
    for line in text.lines() {
        if let Some(steps) = current.as_mut() {
            if line.trim() == "```" {
                out.push(Transcript {
                    title: title.clone(),
                    steps: current.take().unwrap_or_default(),
                });
            } else if !line.trim().is_empty() && !line.starts_with('#') {
                steps.push(parse_step(line));
            }
        } else if let Some(h) = line.strip_prefix("### ") {
            title = h.to_string();
        } else if line.trim() == "```transcript" {
            current = Some(Vec::new());
        }
    }
    assert!(current.is_none(), "unterminated transcript block");
    out
}

/// The bytes a `>` line stands for.
fn wire(x: &str) -> Vec<u8> {
    match x {
        "^X" => vec![0x18],
        "?" | "!" | "~" => x.as_bytes().to_vec(),
        _ => format!("{x}\n").into_bytes(),
    }
}

/// `*` matches any run of characters other than `|`, `<`, `>`.
fn glob(p: &[u8], s: &[u8]) -> bool {
    match p.split_first() {
        None => s.is_empty(),
        Some((b'*', rest)) => {
            let mut i = 0;
            loop {
                if glob(rest, &s[i..]) {
                    return true;
                }
                if i == s.len() || matches!(s[i], b'|' | b'<' | b'>') {
                    return false;
                }
                i += 1;
            }
        }
        Some((c, rest)) => s.first() == Some(c) && glob(rest, &s[1..]),
    }
}

#[test]
fn glob_rules() {
    assert!(glob(
        b"<Run|MPos:*|FS:*>",
        b"<Run|MPos:1.000,0.000,0.000|FS:1200,0>"
    ));
    assert!(!glob(
        b"<Run|MPos:*|FS:*>",
        b"<Idle|MPos:1.000,0.000,0.000|FS:0,0>"
    ));
    assert!(!glob(b"<Run|MPos:*>", b"<Run|MPos:1|FS:0,0>"));
    assert!(glob(b"ok", b"ok") && !glob(b"ok", b"okay"));
}

struct Host {
    io: DuplexStream,
    split: LineSplitter,
    lines: Vec<String>,
}

impl Host {
    async fn line(&mut self) -> Option<String> {
        loop {
            if !self.lines.is_empty() {
                return Some(self.lines.remove(0));
            }
            let mut b = [0u8; 256];
            let n = self.io.read(&mut b).await.ok()?;
            if n == 0 {
                return None;
            }
            for &x in &b[..n] {
                self.lines.extend(self.split.push(x));
            }
        }
    }
}

async fn replay_against_sim(t: &Transcript) {
    let rules: Vec<FaultRule> = t
        .steps
        .iter()
        .filter_map(|s| match s {
            Step::Fault(r) => Some(r.parse().expect("fault rule")),
            _ => None,
        })
        .collect();
    let mut params = GrblParams::default();
    for step in &t.steps {
        if let Step::Sim(k, v) = step {
            match (k.as_str(), v.as_str()) {
                ("reset_on_open", v) => params.reset_on_open = v == "true",
                ("settings", "factory") => params.settings = Eeprom::factory(),
                ("answer_delay", v) => params.answer_delay_s = v.parse().expect("seconds"),
                _ => panic!("{}: unknown `@ sim {k}={v}`", t.title),
            }
        }
    }
    let clock = Clock::virtual_time();
    let (a, b) = tokio::io::duplex(4096);
    tokio::spawn(serve(
        b,
        params,
        clock.clone(),
        Arc::new(FaultInjector::new(rules)),
    ));
    let mut host = Host {
        io: a,
        split: LineSplitter::new(256),
        lines: Vec::new(),
    };
    for (i, step) in t.steps.iter().enumerate() {
        match step {
            Step::Send(x) => host.io.write_all(&wire(x)).await.expect("send"),
            Step::Recv(p) => {
                let got = clock
                    .deadline(Duration::from_secs(30), host.line())
                    .await
                    .unwrap_or_else(|_| {
                        panic!("{}: step {i}: nothing received, expected `{p}`", t.title)
                    })
                    .unwrap_or_else(|| panic!("{}: step {i}: EOF, expected `{p}`", t.title));
                assert!(
                    glob(p.as_bytes(), got.as_bytes()),
                    "{}: step {i}: expected `{p}`, got `{got}`",
                    t.title
                );
            }
            Step::Sleep(s) => clock.sleep_s(*s).await,
            Step::Call(..)
            | Step::Expect(_)
            | Step::Fault(_)
            | Step::Sim(..)
            | Step::Driver(..) => {}
        }
    }
    // Nothing unexpected may follow.
    let extra = clock.deadline(Duration::from_secs(5), host.line()).await;
    assert!(
        matches!(extra, Err(_) | Ok(None)),
        "{}: unexpected extra line {extra:?}",
        t.title
    );
}

/// Plays the device side: sends `<` lines, checks the driver sends exactly
/// the `>` bytes, and finally that the driver sends nothing more.
async fn play_device(mut io: DuplexStream, steps: Vec<Step>) -> Result<(), String> {
    for (i, step) in steps.iter().enumerate() {
        match step {
            Step::Recv(x) => {
                let line = format!("{}\r\n", x.replace('*', "0"));
                io.write_all(line.as_bytes())
                    .await
                    .map_err(|e| format!("step {i}: {e}"))?;
            }
            Step::Send(x) => {
                let want = wire(x);
                let mut got = Vec::new();
                while got.len() < want.len() {
                    let mut b = [0u8; 1];
                    let n = io
                        .read(&mut b)
                        .await
                        .map_err(|e| format!("step {i}: {e}"))?;
                    if n == 0 {
                        return Err(format!("step {i}: driver closed, expected `{x}`"));
                    }
                    got.push(b[0]);
                    if want.len() > 1 && b[0] == b'\n' {
                        break;
                    }
                }
                if got != want {
                    return Err(format!(
                        "step {i}: expected `{x}`, driver sent `{}`",
                        String::from_utf8_lossy(&got).escape_debug()
                    ));
                }
            }
            _ => {}
        }
    }
    let mut rest = Vec::new();
    io.read_to_end(&mut rest).await.map_err(|e| e.to_string())?;
    if rest.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "driver sent extra bytes `{}`",
            String::from_utf8_lossy(&rest).escape_debug()
        ))
    }
}

fn check(title: &str, call: &str, expect: &str, got: &Result<Option<f64>, DeviceError>) {
    let (what, arg) = match expect.split_once(' ') {
        Some((w, a)) => (w, Some(a)),
        None => (expect, None),
    };
    match (what, got) {
        ("ok", Ok(v)) => {
            if let Some(a) = arg {
                let want: f64 = a.parse().expect("expected value");
                let v = v.unwrap_or(f64::NAN);
                assert!(
                    (v - want).abs() <= 1e-3,
                    "{title}: {call}: got {v}, expected {want}"
                );
            }
        }
        (kind, Err(e)) if kind != "ok" => {
            assert_eq!(
                crate::common::kind_name(e.kind),
                kind,
                "{title}: {call}: {e}"
            );
            if let Some(text) = arg {
                assert!(
                    e.message.contains(text),
                    "{title}: {call}: `{}` lacks `{text}`",
                    e.message
                );
            }
        }
        _ => panic!("{title}: {call}: expected {expect}, got {got:?}"),
    }
}

async fn replay_against_driver(t: &Transcript) {
    let clock = Clock::virtual_time();
    let (drv, dev) = tokio::io::duplex(4096);
    let device = play_device(dev, t.steps.clone());
    let title = t.title.clone();
    let steps = t.steps.clone();
    let driver = async move {
        let mut cfg = GrblConfig::new(
            "grbl",
            Limits {
                min: -180.0,
                max: 180.0,
            },
            Motion {
                max_velocity: 20.0,
                acceleration: 40.0,
                settle_s: 0.05,
            },
        );
        for step in &steps {
            if let Step::Driver(k, v) = step {
                match k.as_str() {
                    "homing" => cfg.homing = v == "true",
                    "configure" => cfg.configure = v == "true",
                    _ => panic!("{title}: unknown `@ driver {k}={v}`"),
                }
            }
        }
        let mut stream = Some(drv);
        let mut axis: Option<GrblAxis<DuplexStream>> = None;
        let mut last: Option<(String, Result<Option<f64>, DeviceError>)> = None;
        let mut checked = 0;
        for step in steps {
            match step {
                Step::Call(op, arg) => {
                    let r = match (op.as_str(), axis.as_mut()) {
                        ("connect", _) => {
                            let s = stream.take().expect("connect twice");
                            match GrblAxis::connect(s, cfg.clone(), clock.clone()).await {
                                Ok(a) => {
                                    axis = Some(a);
                                    Ok(None)
                                }
                                Err(e) => Err(e),
                            }
                        }
                        ("home", Some(a)) => a.home().await.map(Some),
                        ("move_to", Some(a)) => {
                            let x: f64 = arg.as_deref().unwrap_or("").parse().expect("move_to arg");
                            a.move_to(x).await.map(Some)
                        }
                        ("position", Some(a)) => a.position().await.map(Some),
                        ("feed_hold", Some(a)) => a.feed_hold().await.map(|_| None),
                        ("cycle_start", Some(a)) => a.cycle_start().await.map(|_| None),
                        ("soft_reset", Some(a)) => a.soft_reset().await.map(|_| None),
                        (op, _) => panic!("{title}: unknown call `{op}` or not connected"),
                    };
                    last = Some((op, r));
                }
                Step::Expect(e) => {
                    let (op, r) = last.as_ref().expect("expect without call");
                    check(&title, op, &e, r);
                    checked += 1;
                }
                _ => {}
            }
        }
        drop(axis);
        checked
    };
    let (dev_result, checked) = tokio::join!(device, driver);
    if let Err(e) = dev_result {
        panic!("{}: {e}", t.title);
    }
    assert!(checked > 0, "{}: no expectations checked", t.title);
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_simulated_firmware() {
    let ts = transcripts();
    assert!(ts.len() >= 4, "only {} transcripts found", ts.len());
    for t in &ts {
        replay_against_sim(t).await;
    }
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_driver() {
    let ts = transcripts();
    assert!(ts.len() >= 4, "only {} transcripts found", ts.len());
    for t in &ts {
        replay_against_driver(t).await;
    }
}
