//! Replays every ```ptpip-transcript block of
//! `firmware-protocols/ptp-camera.md` twice: against the simulated camera
//! behind `rigd sim serve`'s PTP/IP responder (this test is the initiator)
//! and against rigd's PTP/IP driver (this test is the camera). The syntax
//! is defined in the spec; calls and faults are written as in the USB
//! transcripts (`ptp_transcripts.rs`).

use std::sync::Arc;
use std::time::Duration;

use rigd::rig::drivers::ptp::{PtpCamera, PtpConfig};
use rigd::rig::drivers::ptpip::PtpIpPipe;
use rigd::rig::hal::ErrorKind;
use rigd::rig::sim::ptpip_serve::PtpIpResponder;
use rigd_core::{Cfa, Clock};
use rigd_proto::ptp::ip::{
    read_packet, write_packet, DataPhase, FailReason, Identity, IpError, Packet,
};
use rigd_proto::ptp::{EventCode, OpCode, ResponseCode};
use rigd_sim::FaultRule;
use tokio::io::{AsyncWriteExt, DuplexStream};

use crate::ptp_transcripts::{
    hex_bytes, hex_groups, number, parse_control, reference_camera, run_calls, Call, Control,
};

const SPEC: &str = include_str!("../../firmware-protocols/ptp-camera.md");

/// In-memory connections hold this much in flight, more than a frame of
/// the reference camera.
const PIPE: usize = 1 << 20;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Dir {
    ToCamera,
    ToInitiator,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Chan {
    Command,
    Event,
}

/// What a packet line stands for.
#[derive(Debug, Clone, PartialEq)]
enum Sent {
    /// A packet; for Data and End Data with `...`, only the first bytes of
    /// the payload are compared (`elided_len` is the whole payload's length).
    Packet(Packet, Option<usize>),
    /// Bytes that are no valid packet, sent as they are.
    Raw(Vec<u8>),
    /// The sender closes the connection.
    Closed,
}

#[derive(Debug, Clone)]
struct Wire {
    dir: Dir,
    chan: Chan,
    sent: Sent,
    text: String,
}

enum Line {
    Call(Call, Option<ErrorKind>),
    Fault(FaultRule),
    Wire(Wire),
}

/// `key=value` fields of a line; a value in double quotes may hold spaces,
/// and `data=` takes the rest of the line.
fn fields(rest: &str, line: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut s = rest.trim();
    while !s.is_empty() {
        let (key, after) = s
            .split_once('=')
            .unwrap_or_else(|| panic!("field without `=` in `{line}`"));
        let key = key.trim().to_string();
        let (value, next) = if key == "data" {
            (after.to_string(), "")
        } else if let Some(quoted) = after.strip_prefix('"') {
            let (v, next) = quoted
                .split_once('"')
                .unwrap_or_else(|| panic!("unclosed quote in `{line}`"));
            (v.to_string(), next)
        } else if let Some(list) = after.strip_prefix('[') {
            let (v, next) = list
                .split_once(']')
                .unwrap_or_else(|| panic!("unclosed list in `{line}`"));
            (v.to_string(), next)
        } else {
            let (v, next) = after.split_once(' ').unwrap_or((after, ""));
            (v.to_string(), next)
        };
        out.push((key, value));
        s = next.trim();
    }
    out
}

fn parse_wire(line: &str) -> Wire {
    let mut words = line.splitn(4, ' ');
    let mut next = || {
        words
            .next()
            .unwrap_or_else(|| panic!("short line `{line}`"))
    };
    let dir = match next() {
        ">" => Dir::ToCamera,
        "<" => Dir::ToInitiator,
        d => panic!("bad direction `{d}` in `{line}`"),
    };
    let chan = match next() {
        "CMD" => Chan::Command,
        "EVT" => Chan::Event,
        c => panic!("bad connection `{c}` in `{line}`"),
    };
    let ty = next();
    let rest = words.next().unwrap_or("");
    let sent = match ty {
        "closed" => Sent::Closed,
        "raw" => Sent::Raw(hex_bytes(rest, line)),
        _ => packet_of(ty, rest, line),
    };
    Wire {
        dir,
        chan,
        sent,
        text: line.to_string(),
    }
}

/// The packet of type `ty` with the fields `rest`.
fn packet_of(ty: &str, rest: &str, line: &str) -> Sent {
    // The code is the first word of an operation, response or event.
    let (code_text, rest) = match ty {
        "OperationRequest" | "OperationResponse" | "Event" => {
            rest.split_once(' ').unwrap_or((rest, ""))
        }
        _ => ("", rest),
    };
    let f = fields(rest, line);
    let get = |k: &str| f.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    let num = |k: &str| number(get(k).unwrap_or_else(|| panic!("no {k}= in `{line}`")));
    let params = || {
        get("params").map_or_else(Vec::new, |l| {
            l.split(',')
                .filter(|s| !s.trim().is_empty())
                .map(number)
                .collect()
        })
    };
    let identity = || Identity {
        guid: hex_bytes(
            get("guid").unwrap_or_else(|| panic!("no guid= in `{line}`")),
            line,
        )
        .try_into()
        .unwrap_or_else(|_| panic!("a GUID is 16 bytes: `{line}`")),
        name: get("name")
            .unwrap_or_else(|| panic!("no name= in `{line}`"))
            .to_string(),
        version: num("version"),
    };
    let code = |parse: fn(&str) -> Option<u16>| {
        parse(code_text).unwrap_or_else(|| panic!("unknown code `{code_text}` in `{line}`"))
    };
    let data = || {
        let d = get("data").unwrap_or("").trim();
        match d.strip_suffix("...") {
            Some(h) => {
                let bytes = hex_bytes(h, line);
                let len = get("len").map_or(bytes.len(), |l| number(l) as usize);
                (bytes, Some(len))
            }
            None => (hex_bytes(d, line), None),
        }
    };
    let packet = match ty {
        "InitCommandRequest" => Packet::InitCommandRequest(identity()),
        "InitCommandAck" => Packet::InitCommandAck {
            connection: num("connection"),
            identity: identity(),
        },
        "InitEventRequest" => Packet::InitEventRequest {
            connection: num("connection"),
        },
        "InitEventAck" => Packet::InitEventAck,
        "InitFail" => Packet::InitFail(match get("reason") {
            Some("rejected") => FailReason::Rejected,
            Some("busy") => FailReason::Busy,
            _ => FailReason::Unspecified,
        }),
        "OperationRequest" => Packet::OperationRequest {
            data_phase: match get("phase") {
                Some("out") => DataPhase::Out,
                None | Some("none") => DataPhase::NoneOrIn,
                Some(p) => panic!("bad phase `{p}` in `{line}`"),
            },
            code: code(|s| OpCode::parse(s).map(|c| c.0)),
            transaction_id: num("tid"),
            params: params(),
        },
        "OperationResponse" => Packet::OperationResponse {
            code: code(|s| ResponseCode::parse(s).map(|c| c.0)),
            transaction_id: num("tid"),
            params: params(),
        },
        "Event" => Packet::Event {
            code: code(|s| EventCode::parse(s).map(|c| c.0)),
            transaction_id: num("tid"),
            params: params(),
        },
        "StartData" => Packet::StartData {
            transaction_id: num("tid"),
            total: u64::from(num("total")),
        },
        "Data" | "EndData" => {
            let (payload, elided) = data();
            let transaction_id = num("tid");
            let p = if ty == "Data" {
                Packet::Data {
                    transaction_id,
                    payload,
                }
            } else {
                Packet::EndData {
                    transaction_id,
                    payload,
                }
            };
            return Sent::Packet(p, elided);
        }
        "Cancel" => Packet::Cancel {
            transaction_id: num("tid"),
        },
        "ProbeRequest" => Packet::ProbeRequest,
        "ProbeResponse" => Packet::ProbeResponse,
        other => panic!("unknown packet type `{other}` in `{line}`"),
    };
    Sent::Packet(packet, None)
}

fn parse_line(line: &str) -> Option<Line> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') {
        return None;
    }
    Some(match parse_control(line) {
        Some(Control::Call(c, o)) => Line::Call(c, o),
        Some(Control::Fault(r)) => Line::Fault(r),
        None => Line::Wire(parse_wire(line)),
    })
}

fn transcripts() -> Vec<Vec<Line>> {
    let mut out = Vec::new();
    let mut current: Option<Vec<Line>> = None;
    for line in SPEC.lines() {
        match (&mut current, line.trim()) {
            (None, "```ptpip-transcript") => current = Some(Vec::new()),
            (Some(_), "```") => out.extend(current.take()),
            (Some(block), l) => block.extend(parse_line(l)),
            (None, _) => {}
        }
    }
    assert!(current.is_none(), "unclosed ptpip-transcript block");
    out
}

/// A packet as the transcripts write it, for a mismatch's message.
fn shown(p: &Packet) -> String {
    match p {
        Packet::Data { payload, .. } | Packet::EndData { payload, .. } => {
            format!("{:?} data={}", p.packet_type(), hex_groups(payload))
        }
        other => format!("{other:?}"),
    }
}

/// Checks a received packet (or the connection's end) against the line.
fn check(w: &Wire, got: Result<Packet, IpError>) {
    match &w.sent {
        Sent::Closed => assert!(
            matches!(got, Err(IpError::Closed) | Err(IpError::Io(_))),
            "{}: the connection is still open; got {got:?}",
            w.text
        ),
        Sent::Raw(_) => panic!("{}: raw bytes are only sent", w.text),
        Sent::Packet(want, elided) => {
            let got = got.unwrap_or_else(|e| panic!("{}: {e}", w.text));
            match (want, &got, elided) {
                (
                    Packet::Data {
                        transaction_id: t,
                        payload: p,
                    },
                    Packet::Data {
                        transaction_id,
                        payload,
                    },
                    Some(len),
                )
                | (
                    Packet::EndData {
                        transaction_id: t,
                        payload: p,
                    },
                    Packet::EndData {
                        transaction_id,
                        payload,
                    },
                    Some(len),
                ) => {
                    assert_eq!((t, len), (transaction_id, &payload.len()), "{}", w.text);
                    assert!(payload.starts_with(p), "{}: got {}", w.text, shown(&got));
                }
                _ => assert!(want == &got, "{}: got {}", w.text, shown(&got)),
            }
        }
    }
}

/// Sends what the line says on `conn` (None once closed).
async fn send(w: &Wire, conn: &mut Option<DuplexStream>) {
    let stream = conn
        .as_mut()
        .unwrap_or_else(|| panic!("{}: the connection is closed", w.text));
    match &w.sent {
        Sent::Packet(p, elided) => {
            let mut p = p.clone();
            if let (Packet::Data { payload, .. } | Packet::EndData { payload, .. }, Some(len)) =
                (&mut p, elided)
            {
                payload.resize(*len, 0);
            }
            write_packet(stream, &p)
                .await
                .unwrap_or_else(|e| panic!("{}: {e}", w.text));
        }
        Sent::Raw(bytes) => {
            stream
                .write_all(bytes)
                .await
                .unwrap_or_else(|e| panic!("{}: {e}", w.text));
        }
        Sent::Closed => *conn = None,
    }
}

/// Reads the next packet on `conn`, within 60 s of (virtual) time.
async fn receive(
    clock: &Clock,
    w: &Wire,
    conn: &mut Option<DuplexStream>,
) -> Result<Packet, IpError> {
    let stream = conn
        .as_mut()
        .unwrap_or_else(|| panic!("{}: the connection is closed", w.text));
    clock
        .deadline(Duration::from_secs(60), read_packet(stream))
        .await
        .unwrap_or_else(|_| panic!("{}: nothing came within 60 s", w.text))
}

/// Whether the peer sends nothing more on `conn` (it may close it).
async fn says_nothing_more(clock: &Clock, conn: &mut Option<DuplexStream>) -> Option<Packet> {
    let stream = conn.as_mut()?;
    match clock
        .deadline(Duration::from_secs(30), read_packet(stream))
        .await
    {
        Ok(Ok(p)) => Some(p),
        _ => None,
    }
}

/// Whether the side sending in `dir` sends raw bytes or a Probe Request:
/// only the test plays that side, so the transcript is replayed against the
/// other end only.
fn hostile(lines: &[Line], dir: Dir) -> bool {
    lines.iter().any(|l| {
        matches!(l, Line::Wire(w) if w.dir == dir
            && matches!(w.sent, Sent::Raw(_) | Sent::Packet(Packet::ProbeRequest, _)))
    })
}

fn faults_of(lines: &[Line]) -> Vec<FaultRule> {
    lines
        .iter()
        .filter_map(|l| match l {
            Line::Fault(r) => Some(r.clone()),
            _ => None,
        })
        .collect()
}

/// The test is the initiator; the camera is the reference camera behind the
/// responder `rigd sim serve` runs.
async fn replay_against_the_served_camera(lines: &[Line]) {
    let clock = Clock::virtual_time();
    let start = reference_camera(&clock, faults_of(lines));
    let responder: PtpIpResponder<DuplexStream> =
        PtpIpResponder::new("SimCam PTP-12", "cam", Arc::new(start), clock.clone());
    let mut command: Option<DuplexStream> = None;
    let mut event: Option<DuplexStream> = None;
    let mut opened = [false, false];
    for line in lines {
        let Line::Wire(w) = line else { continue };
        let (conn, was_opened) = match w.chan {
            Chan::Command => (&mut command, &mut opened[0]),
            Chan::Event => (&mut event, &mut opened[1]),
        };
        if !*was_opened {
            // A connection opens at its first line.
            let (mine, theirs) = tokio::io::duplex(PIPE);
            responder.accept(theirs);
            *conn = Some(mine);
            *was_opened = true;
        }
        match w.dir {
            Dir::ToCamera => send(w, conn).await,
            Dir::ToInitiator => {
                let got = receive(&clock, w, conn).await;
                check(w, got);
            }
        }
    }
    for conn in [&mut command, &mut event] {
        let more = says_nothing_more(&clock, conn).await;
        assert!(more.is_none(), "the camera sent more: {more:?}");
    }
}

/// The test is the camera; the initiator is rigd's driver, with the
/// identity of the transcript's Init Command Request.
async fn replay_against_the_driver(lines: &[Line]) {
    let clock = Clock::virtual_time();
    let me = lines
        .iter()
        .find_map(|l| match l {
            Line::Wire(Wire {
                sent: Sent::Packet(Packet::InitCommandRequest(id), _),
                ..
            }) => Some(id.clone()),
            _ => None,
        })
        .expect("a transcript opens with Init Command Request");
    let (drivers_command, command) = tokio::io::duplex(PIPE);
    let (drivers_event, event) = tokio::io::duplex(PIPE);
    let mut command = Some(command);
    let mut event = Some(event);
    let mut calls = Vec::new();
    let mut expected = Vec::new();
    for line in lines {
        if let Line::Call(c, outcome) = line {
            calls.push(c.clone());
            expected.push(*outcome);
        }
    }
    let driver_clock = clock.clone();
    let driver = tokio::spawn(async move {
        let open_event = || async move { Ok::<_, IpError>(drivers_event) };
        let pipe = PtpIpPipe::handshake(drivers_command, open_event, &me)
            .await
            .unwrap_or_else(|e| panic!("the PTP/IP session did not open: {e}"));
        let config = PtpConfig {
            cfa: Some(Cfa::Rggb),
            ..PtpConfig::default()
        };
        let cam = PtpCamera::new("cam", pipe, driver_clock, config);
        run_calls(cam, calls).await.0
    });
    for line in lines {
        let Line::Wire(w) = line else { continue };
        let conn = match w.chan {
            Chan::Command => &mut command,
            Chan::Event => &mut event,
        };
        match w.dir {
            Dir::ToCamera => {
                let got = receive(&clock, w, conn).await;
                check(w, got);
            }
            Dir::ToInitiator => send(w, conn).await,
        }
    }
    let outcomes = driver.await.unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(outcomes, expected, "driver call outcomes");
    for conn in [&mut command, &mut event] {
        let more = says_nothing_more(&clock, conn).await;
        assert!(more.is_none(), "the driver sent more: {more:?}");
    }
}

#[test]
fn the_spec_has_the_required_ptpip_transcripts() {
    let t = transcripts();
    assert!(t.len() >= 3, "{} PTP/IP transcripts", t.len());
    let has = |pred: &dyn Fn(&Wire) -> bool| {
        t.iter()
            .any(|b| b.iter().any(|l| matches!(l, Line::Wire(w) if pred(w))))
    };
    let packet = |w: &Wire| match &w.sent {
        Sent::Packet(p, _) => Some(p.clone()),
        _ => None,
    };
    assert!(has(&|w| matches!(packet(w), Some(Packet::InitEventAck))));
    assert!(has(&|w| matches!(
        packet(w),
        Some(Packet::Event { code, .. }) if code == EventCode::ObjectAdded.0
    )));
    assert!(has(&|w| matches!(
        packet(w),
        Some(Packet::OperationRequest {
            data_phase: DataPhase::Out,
            ..
        })
    )));
    // A whole frame file: the reference camera's DNG, byte for byte.
    assert!(has(&|w| matches!(
        &w.sent,
        Sent::Packet(Packet::EndData { payload, .. }, None) if payload.starts_with(b"II*\0")
    )));
    // A hostile camera: bytes that are no packet.
    assert!(has(&|w| matches!(w.sent, Sent::Raw(_))));
}

#[tokio::test(start_paused = true)]
async fn ptpip_transcripts_replay_against_the_served_camera() {
    let mut replayed = 0;
    for (i, t) in transcripts().iter().enumerate() {
        if hostile(t, Dir::ToInitiator) {
            continue;
        }
        println!("PTP/IP transcript {i}");
        replay_against_the_served_camera(t).await;
        replayed += 1;
    }
    assert!(replayed >= 3, "{replayed} transcripts replayed");
}

#[tokio::test(start_paused = true)]
async fn ptpip_transcripts_replay_against_the_driver() {
    let mut replayed = 0;
    for (i, t) in transcripts().iter().enumerate() {
        if hostile(t, Dir::ToCamera) {
            continue;
        }
        println!("PTP/IP transcript {i}");
        replay_against_the_driver(t).await;
        replayed += 1;
    }
    assert!(replayed >= 3, "{replayed} transcripts replayed");
}
