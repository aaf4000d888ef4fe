//! Replays every ```transcript block of `firmware-protocols/ptp-camera.md`
//! twice: against the simulated firmware (this test is the host) and against
//! the driver (this test is the camera). The syntax is defined in the spec.

use std::sync::Arc;
use std::time::Duration;

use rigd::rig::drivers::ptp::{PtpCamera, PtpConfig};
use rigd::rig::drivers::usb::{memory_pair, MemoryDevice, MemoryPipe, PtpPipe};
use rigd::rig::hal::{Camera, ErrorKind};
use rigd_core::{Cfa, Clock};
use rigd_proto::ptp::{Container, ContainerKind, EventCode, Header, OpCode, ResponseCode};
use rigd_sim::devices::{CameraTimes, SimContext};
use rigd_sim::firmware::ptp::{PtpCameraSpec, PtpFirmware};
use rigd_sim::scene::Shot;
use rigd_sim::{FaultInjector, FaultRule};

const SPEC: &str = include_str!("../../firmware-protocols/ptp-camera.md");

#[derive(Debug, Clone, Copy, PartialEq)]
enum Dir {
    ToDevice,
    ToHost,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Ep {
    Out,
    In,
    Int,
}

#[derive(Debug, Clone, PartialEq)]
struct Wire {
    dir: Dir,
    ep: Ep,
    kind: ContainerKind,
    code: u16,
    tid: u32,
    params: Vec<u32>,
    /// Payload length (data containers); `data.len()` unless elided.
    len: usize,
    data: Vec<u8>,
    elided: bool,
    text: String,
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Call {
    Connect,
    SetExposure(f64),
    Expose,
    Transfer,
    Close,
}

#[derive(Debug, Clone, PartialEq)]
enum Line {
    Call(Call, Option<ErrorKind>),
    Fault(FaultRule),
    Wire(Wire),
}

pub(crate) fn kind_of(s: &str) -> ErrorKind {
    match s {
        "timeout" => ErrorKind::Timeout,
        "disconnected" => ErrorKind::Disconnected,
        "device_fault" => ErrorKind::DeviceFault,
        "out_of_limits" => ErrorKind::OutOfLimits,
        "bad_frame" => ErrorKind::BadFrame,
        "not_ready" => ErrorKind::NotReady,
        other => panic!("unknown error kind `{other}`"),
    }
}

pub(crate) fn number(s: &str) -> u32 {
    let s = s.trim();
    let r = match s.strip_prefix("0x") {
        Some(h) => u32::from_str_radix(h, 16),
        None => s.parse(),
    };
    r.unwrap_or_else(|e| panic!("bad number `{s}`: {e}"))
}

fn code_of(kind: ContainerKind, s: &str) -> u16 {
    let c = match kind {
        ContainerKind::Command | ContainerKind::Data => OpCode::parse(s).map(|c| c.0),
        ContainerKind::Response => ResponseCode::parse(s).map(|c| c.0),
        ContainerKind::Event => EventCode::parse(s).map(|c| c.0),
    };
    c.unwrap_or_else(|| panic!("unknown {kind} code `{s}`"))
}

/// Hex digits (spaces ignored) as bytes; `line` names the line in a panic.
pub(crate) fn hex_bytes(hex: &str, line: &str) -> Vec<u8> {
    let hex: String = hex.chars().filter(|c| !c.is_whitespace()).collect();
    (0..hex.len())
        .step_by(2)
        .map(|i| {
            hex.get(i..i + 2)
                .and_then(|b| u8::from_str_radix(b, 16).ok())
                .unwrap_or_else(|| panic!("bad hex in `{line}`"))
        })
        .collect()
}

fn parse_wire(line: &str) -> Wire {
    let (head, data_text) = match line.split_once(" data=") {
        Some((h, d)) => (h, Some(d)),
        None => (line, None),
    };
    let (data, elided) = match data_text {
        None => (Vec::new(), false),
        Some(d) => {
            let d = d.trim();
            let (hex, elided) = match d.strip_suffix("...") {
                Some(h) => (h, true),
                None => (d, false),
            };
            (hex_bytes(hex, line), elided)
        }
    };
    let (head, params) = match head.split_once(" params=[") {
        Some((h, rest)) => {
            let (list, after) = rest
                .split_once(']')
                .unwrap_or_else(|| panic!("unclosed params in `{line}`"));
            let p = list
                .split(',')
                .filter(|s| !s.trim().is_empty())
                .map(number)
                .collect();
            (format!("{h}{after}"), p)
        }
        None => (head.to_string(), Vec::new()),
    };
    let mut words = head.split_whitespace();
    let mut next = || {
        words
            .next()
            .unwrap_or_else(|| panic!("short line `{line}`"))
    };
    let dir = match next() {
        ">" => Dir::ToDevice,
        "<" => Dir::ToHost,
        d => panic!("bad direction `{d}`"),
    };
    let ep = match next() {
        "OUT" => Ep::Out,
        "IN" => Ep::In,
        "INT" => Ep::Int,
        e => panic!("bad endpoint `{e}`"),
    };
    let kind_text = next();
    let kind = ContainerKind::from_name(kind_text)
        .unwrap_or_else(|| panic!("bad container type `{kind_text}`"));
    let code = code_of(kind, next());
    let mut tid = None;
    let mut len = None;
    for w in words {
        match w.split_once('=') {
            Some(("tid", v)) => tid = Some(number(v)),
            Some(("len", v)) => len = Some(number(v) as usize),
            _ => panic!("unknown field `{w}` in `{line}`"),
        }
    }
    let len = len.unwrap_or(data.len());
    assert!(
        elided || len == data.len(),
        "len disagrees with data: `{line}`"
    );
    Wire {
        dir,
        ep,
        kind,
        code,
        tid: tid.unwrap_or_else(|| panic!("no tid in `{line}`")),
        params,
        len,
        data,
        elided,
        text: line.to_string(),
    }
}

/// A line that is not a container: a driver call with its outcome, or a
/// fault armed on the camera.
pub(crate) enum Control {
    /// `! CALL -> OUTCOME`.
    Call(Call, Option<ErrorKind>),
    /// `% fault RULE`.
    Fault(FaultRule),
}

/// `line` as a call or a fault; None for anything else.
pub(crate) fn parse_control(line: &str) -> Option<Control> {
    if let Some(rest) = line.strip_prefix("! ") {
        let (call, outcome) = rest
            .split_once(" -> ")
            .unwrap_or_else(|| panic!("call without outcome: `{line}`"));
        let mut w = call.split_whitespace();
        let call = match (w.next(), w.next()) {
            (Some("connect"), None) => Call::Connect,
            (Some("set_exposure"), Some(s)) => {
                Call::SetExposure(s.parse().unwrap_or_else(|e| panic!("{e}")))
            }
            (Some("expose"), None) => Call::Expose,
            (Some("transfer"), None) => Call::Transfer,
            (Some("close"), None) => Call::Close,
            _ => panic!("unknown call `{call}`"),
        };
        let outcome = match outcome.trim() {
            "ok" => None,
            o => Some(kind_of(
                o.strip_prefix("error ")
                    .unwrap_or_else(|| panic!("bad outcome `{o}`")),
            )),
        };
        return Some(Control::Call(call, outcome));
    }
    let rule = line.strip_prefix("% fault ")?;
    Some(Control::Fault(
        rule.parse().unwrap_or_else(|e| panic!("{e}")),
    ))
}

fn parse_line(line: &str) -> Option<Line> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return None;
    }
    match parse_control(line) {
        Some(Control::Call(c, o)) => Some(Line::Call(c, o)),
        Some(Control::Fault(r)) => Some(Line::Fault(r)),
        None => Some(Line::Wire(parse_wire(line))),
    }
}

fn transcripts() -> Vec<Vec<Line>> {
    let mut out = Vec::new();
    let mut current: Option<Vec<Line>> = None;
    for line in SPEC.lines() {
        match (&mut current, line.trim()) {
            (None, "```transcript") => current = Some(Vec::new()),
            (Some(_), "```") => out.extend(current.take()),
            (Some(block), l) => block.extend(parse_line(l)),
            (None, _) => {}
        }
    }
    assert!(current.is_none(), "unclosed transcript block");
    out
}

/// The reference camera of the spec, started on the device end of a link
/// each time the returned function is called.
pub(crate) fn reference_camera(
    clock: &Clock,
    faults: Vec<FaultRule>,
) -> impl Fn(MemoryDevice) + Send + Sync + 'static {
    let injector = Arc::new(FaultInjector::new(faults));
    let ctx = SimContext::new(clock.clone(), injector);
    let spec = PtpCameraSpec {
        name: "cam".into(),
        manufacturer: "rigd".into(),
        model: "SimCam PTP-12".into(),
        version: "1.0".into(),
        serial: "SIM0001".into(),
        times: CameraTimes {
            exposure_s: 0.1,
            readout_s: 0.2,
            transfer_s: 0.3,
        },
        cfa: Some(Cfa::Rggb),
    };
    move |dev| {
        let shot = || Shot {
            light: [0.0, 0.0, 1.0],
            view: [0.0, 0.0, 1.0],
            width: 4,
            height: 2,
            bit_depth: 12,
            ..Shot::default()
        };
        PtpFirmware::new(spec.clone(), ctx.clone(), Box::new(shot)).spawn(dev);
    }
}

fn firmware(clock: &Clock, faults: Vec<FaultRule>) -> MemoryPipe {
    let (host, dev) = memory_pair();
    reference_camera(clock, faults)(dev);
    host
}

fn container_of(w: &Wire) -> Vec<u8> {
    let c = if w.kind == ContainerKind::Data {
        let mut payload = w.data.clone();
        payload.resize(w.len, 0);
        Container::data(w.code, w.tid, payload)
    } else {
        Container::with_params(w.kind, w.code, w.tid, &w.params).unwrap_or_else(|e| panic!("{e}"))
    };
    c.encode().unwrap_or_else(|e| panic!("{e}"))
}

/// Bytes as the transcripts write them: hex in groups of four bytes.
pub(crate) fn hex_groups(bytes: &[u8]) -> String {
    bytes
        .chunks(4)
        .map(|c| c.iter().map(|b| format!("{b:02x}")).collect::<String>())
        .collect::<Vec<_>>()
        .join(" ")
}

fn check(w: &Wire, bytes: &[u8]) {
    let h = Header::decode(bytes).unwrap_or_else(|e| panic!("{}: {e}", w.text));
    assert_eq!(
        h.length as usize,
        bytes.len(),
        "{}: whole container",
        w.text
    );
    let c = Container::decode(bytes).unwrap_or_else(|e| panic!("{}: {e}", w.text));
    assert_eq!(
        (c.kind, c.code, c.transaction_id),
        (w.kind, w.code, w.tid),
        "{}",
        w.text
    );
    if c.kind == ContainerKind::Data {
        // On a mismatch, show what was sent in the transcript's own syntax,
        // ready to paste once the change is meant.
        let sent = || format!("len={} data={}", c.payload.len(), hex_groups(&c.payload));
        assert_eq!(
            c.payload.len(),
            w.len,
            "{}: payload length; sent {}",
            w.text,
            sent()
        );
        assert!(
            c.payload.get(..w.data.len()) == Some(&w.data[..]),
            "{}: payload; sent {}",
            w.text,
            sent()
        );
    } else {
        assert_eq!(c.params(), w.params, "{}: params", w.text);
    }
}

/// Reads one whole bulk-in transfer, as a host does.
async fn read_transfer(host: &mut MemoryPipe) -> Vec<u8> {
    let mut buf = Vec::new();
    loop {
        let chunk = host.bulk_in(4096).await.unwrap_or_else(|e| panic!("{e}"));
        let ended = chunk.len() < 4096;
        buf.extend_from_slice(&chunk);
        if ended {
            return buf;
        }
    }
}

async fn replay_against_firmware(lines: &[Line]) {
    let clock = Clock::virtual_time();
    let faults = lines
        .iter()
        .filter_map(|l| match l {
            Line::Fault(r) => Some(r.clone()),
            _ => None,
        })
        .collect();
    let mut host = firmware(&clock, faults);
    for line in lines {
        let Line::Wire(w) = line else { continue };
        match (w.dir, w.ep) {
            (Dir::ToDevice, Ep::Out) => host
                .bulk_out(container_of(w))
                .unwrap_or_else(|e| panic!("{e}")),
            (Dir::ToHost, Ep::In) => {
                let b = clock
                    .deadline(Duration::from_secs(60), read_transfer(&mut host))
                    .await
                    .unwrap_or_else(|e| panic!("{}: {e}", w.text));
                check(w, &b);
            }
            (Dir::ToHost, Ep::Int) => {
                let b = clock
                    .deadline(Duration::from_secs(60), host.interrupt_in())
                    .await
                    .unwrap_or_else(|e| panic!("{}: {e}", w.text))
                    .unwrap_or_else(|e| panic!("{}: {e}", w.text));
                check(w, &b);
            }
            _ => panic!("impossible direction/endpoint: {}", w.text),
        }
    }
    // The camera must not say more than the transcript.
    let more = clock
        .deadline(Duration::from_secs(30), host.bulk_in(4096))
        .await;
    assert!(more.is_err(), "firmware sent more: {more:?}");
    let more = clock
        .deadline(Duration::from_secs(30), host.interrupt_in())
        .await;
    assert!(more.is_err(), "firmware sent more events: {more:?}");
}

/// Runs `calls` on the driver, in order; their outcomes (None for ok).
pub(crate) async fn run_calls<P: PtpPipe>(
    mut cam: PtpCamera<P>,
    calls: Vec<Call>,
) -> (Vec<Option<ErrorKind>>, PtpCamera<P>) {
    let mut outcomes = Vec::new();
    for call in calls {
        let r = match call {
            Call::Connect => cam.connect().await.map(|_| ()).map_err(|e| e.kind()),
            Call::SetExposure(s) => cam.set_exposure(s).await.map_err(|e| e.kind),
            Call::Expose => cam.expose().await.map_err(|e| e.kind),
            Call::Transfer => cam.transfer().await.map(|_| ()).map_err(|e| e.kind),
            Call::Close => cam.close().await.map_err(|e| e.kind()),
        };
        outcomes.push(r.err());
    }
    (outcomes, cam)
}

async fn replay_against_driver(lines: &[Line]) {
    let clock = Clock::virtual_time();
    let (host, mut dev): (MemoryPipe, MemoryDevice) = memory_pair();
    let config = PtpConfig {
        cfa: Some(Cfa::Rggb),
        ..PtpConfig::default()
    };
    let cam = PtpCamera::new("cam", host, clock.clone(), config);
    let mut calls = Vec::new();
    let mut expected = Vec::new();
    for line in lines {
        if let Line::Call(c, outcome) = line {
            calls.push(c.clone());
            expected.push(*outcome);
        }
    }
    let driver = tokio::spawn(run_calls(cam, calls));
    for line in lines {
        let Line::Wire(w) = line else { continue };
        match (w.dir, w.ep) {
            (Dir::ToDevice, Ep::Out) => {
                let b = clock
                    .deadline(Duration::from_secs(60), dev.read_out())
                    .await
                    .unwrap_or_else(|e| panic!("{}: {e}", w.text))
                    .unwrap_or_else(|e| panic!("{}: {e}", w.text));
                check(w, &b);
            }
            (Dir::ToHost, Ep::In) => dev
                .write_in(container_of(w))
                .unwrap_or_else(|e| panic!("{e}")),
            (Dir::ToHost, Ep::Int) => dev
                .write_interrupt(container_of(w))
                .unwrap_or_else(|e| panic!("{e}")),
            _ => panic!("impossible direction/endpoint: {}", w.text),
        }
    }
    let (outcomes, _cam) = driver.await.unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(outcomes, expected, "driver call outcomes");
    let more = clock
        .deadline(Duration::from_secs(30), dev.read_out())
        .await;
    assert!(more.is_err(), "driver sent more: {more:?}");
}

#[test]
fn the_spec_has_the_required_transcripts() {
    let t = transcripts();
    assert!(t.len() >= 3, "{} transcripts", t.len());
    let has = |pred: &dyn Fn(&Wire) -> bool| {
        t.iter()
            .any(|b| b.iter().any(|l| matches!(l, Line::Wire(w) if pred(w))))
    };
    assert!(has(
        &|w| w.code == OpCode::OpenSession.0 && w.kind == ContainerKind::Command
    ));
    assert!(has(&|w| w.code == EventCode::ObjectAdded.0));
    assert!(has(
        &|w| w.kind == ContainerKind::Response && w.code != ResponseCode::OK.0
    ));
    // A whole frame file: the reference camera's DNG, byte for byte.
    assert!(has(&|w| w.code == OpCode::GetObject.0
        && w.kind == ContainerKind::Data
        && w.data.starts_with(b"II*\0")
        && !w.elided
        && w.len == w.data.len()));
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_the_firmware() {
    for (i, t) in transcripts().iter().enumerate() {
        println!("transcript {i}");
        replay_against_firmware(t).await;
    }
}

#[tokio::test(start_paused = true)]
async fn transcripts_replay_against_the_driver() {
    for (i, t) in transcripts().iter().enumerate() {
        println!("transcript {i}");
        replay_against_driver(t).await;
    }
}
