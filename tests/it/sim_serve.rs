//! `rigd sim serve`: the simulated firmware of the MSRA rig on ptys and
//! loopback sockets, reached by a stock Modbus TCP client and by `rigd run`
//! with the profile it prints, in real time; and its PTP/IP camera behind
//! a relay that sends a malformed packet mid-run.

use crate::common;

use std::time::{Duration, Instant};

use crate::bring_up::{device, edit};
use common::{assert_complete_run, repo_file, rigd, serve_sim, served_ptpip_port};
use tokio_modbus::client::Reader;

#[test]
fn served_msra_rig_answers_a_modbus_client_and_completes_a_run() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let served = tmp.path().join("served.toml");
    let (_server, lines) = serve_sim(&repo_file("rig-profiles/msra-btf-mdf.toml"), &served, 20.0);
    let modbus = lines
        .iter()
        .find(|l| l.contains("Modbus TCP"))
        .and_then(|l| l.split_whitespace().last())
        .expect("a Modbus TCP endpoint line");
    let addr: std::net::SocketAddr = modbus.parse().expect("host:port");
    assert!(addr.ip().is_loopback(), "{addr}");
    for dev in ["turntable", "light_arc", "laser_tilt"] {
        let line = lines
            .iter()
            .find(|l| l.split_whitespace().nth(1) == Some(dev))
            .unwrap_or_else(|| panic!("no endpoint for {dev}: {lines:?}"));
        assert!(line.contains("/dev/pts/"), "{line}");
    }
    for cam in 0..8 {
        let name = format!("cam{cam}");
        assert!(
            lines
                .iter()
                .any(|l| l.split_whitespace().nth(1) == Some(name.as_str())
                    && l.contains("PTP/IP")),
            "{name}"
        );
    }

    // A stock Modbus TCP client reads the eight lamp coils and the laser.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let coils = runtime.block_on(async {
        let mut ctx = tokio_modbus::client::tcp::connect(addr)
            .await
            .expect("connect");
        ctx.read_coils(0, 9)
            .await
            .expect("transport")
            .expect("reply")
    });
    assert_eq!(coils, vec![false; 9]);

    // `rigd run` with the printed profile drives the served rig.
    let plan = common::tiny_plan(tmp.path());
    let out = tmp.path().join("run");
    let start = Instant::now();
    let o = rigd()
        .args([
            "run",
            "--profile",
            served.to_str().expect("utf8"),
            "--plan",
            plan.to_str().expect("utf8"),
            "--sample",
            "served",
            "--progress",
            "none",
            "--out",
            out.to_str().expect("utf8"),
        ])
        .output()
        .expect("rigd run");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(start.elapsed() < Duration::from_secs(60));
    let m = assert_complete_run(&out, 4);
    assert_eq!(m.profile, "msra-btf-mdf-sim-served");
}

/// What the relay does instead of passing on the `nth` InitiateCapture.
#[derive(Clone, Copy)]
pub(crate) enum Misbehaviour {
    /// Answers with a packet of type 99, which no PTP/IP packet has.
    Garbage,
    /// Closes both ends of the connection, as a camera that vanished.
    HangUp,
}

/// A TCP relay in front of the served camera at `upstream`. On the
/// command connection it reads the initiator's packets, and when the
/// initiator asks for the `nth` InitiateCapture (counted over every
/// connection) it withholds the request and misbehaves; everything else
/// is relayed as it is.
pub(crate) fn hostile_relay(upstream: u16, nth: usize, misbehaviour: Misbehaviour) -> u16 {
    use std::io::{Read, Write};
    use std::net::{Shutdown, TcpListener, TcpStream};
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    const OPERATION_REQUEST: u32 = 6;
    const INITIATE_CAPTURE: u16 = 0x100E;
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind the relay");
    let port = listener.local_addr().expect("relay address").port();
    let captures = Arc::new(AtomicUsize::new(0));
    std::thread::spawn(move || {
        for initiator in listener.incoming() {
            let Ok(mut initiator) = initiator else { return };
            let Ok(camera) = TcpStream::connect(("127.0.0.1", upstream)) else {
                return;
            };
            let (Ok(mut to_initiator), Ok(mut from_camera)) =
                (initiator.try_clone(), camera.try_clone())
            else {
                return;
            };
            // Either side's end ends both connections, as a relay that
            // vanished would: the camera must not stay held.
            std::thread::spawn(move || {
                let _ = std::io::copy(&mut from_camera, &mut to_initiator);
                let _ = to_initiator.shutdown(Shutdown::Both);
                let _ = from_camera.shutdown(Shutdown::Both);
            });
            let captures = captures.clone();
            let mut to_camera = camera;
            std::thread::spawn(move || {
                loop {
                    let mut header = [0u8; 8];
                    if initiator.read_exact(&mut header).is_err() {
                        break;
                    }
                    let len = u32::from_le_bytes([header[0], header[1], header[2], header[3]]);
                    let ty = u32::from_le_bytes([header[4], header[5], header[6], header[7]]);
                    let mut body = vec![0u8; (len as usize).saturating_sub(8).min(1 << 26)];
                    if initiator.read_exact(&mut body).is_err() {
                        break;
                    }
                    let capture = ty == OPERATION_REQUEST
                        && body.get(4..6) == Some(&INITIATE_CAPTURE.to_le_bytes()[..]);
                    if capture && captures.fetch_add(1, Ordering::SeqCst) + 1 == nth {
                        match misbehaviour {
                            Misbehaviour::Garbage => {
                                let _ = initiator.write_all(&[8, 0, 0, 0, 99, 0, 0, 0]);
                                continue;
                            }
                            Misbehaviour::HangUp => break,
                        }
                    }
                    if to_camera.write_all(&header).is_err() || to_camera.write_all(&body).is_err()
                    {
                        break;
                    }
                }
                let _ = to_camera.shutdown(Shutdown::Both);
                let _ = initiator.shutdown(Shutdown::Both);
            });
        }
    });
    port
}

/// A PTP/IP camera that sends a malformed packet mid-run: the driver
/// closes the session, the run pauses naming the packet, and a resume
/// opens a new session and completes the run.
#[test]
fn a_malformed_ptpip_packet_pauses_the_run_with_the_reason_and_resume_completes() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let served = tmp.path().join("served.toml");
    let (_server, lines) = serve_sim(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        &served,
        20.0,
    );
    let port = served_ptpip_port(&lines);
    let relay = hostile_relay(port, 2, Misbehaviour::Garbage);
    let profile = tmp.path().join("through-relay.toml");
    edit(&served, &profile, |t| {
        let transport = device(t, "camera")
            .get_mut("transport")
            .and_then(|t| t.as_table_mut())
            .expect("the camera's transport");
        assert_eq!(
            transport.get("type").and_then(|v| v.as_str()),
            Some("ptpip")
        );
        transport.insert("port".into(), i64::from(relay).into());
    });
    let run = tmp.path().join("run");
    let o = rigd()
        .args(["run", "--profile"])
        .arg(&profile)
        .args(["--sample", "knit", "--progress", "none", "--out"])
        .arg(&run)
        .output()
        .expect("rigd run");
    paused_naming_then_resumed(&o, &["camera", "packet type 99"], &run, 3);
}

/// Asserts that `rigd run` paused (exit 3) saying each of `parts` and how
/// to resume; then resumes the run and asserts it completes with `frames`
/// frames.
pub(crate) fn paused_naming_then_resumed(
    o: &std::process::Output,
    parts: &[&str],
    run: &std::path::Path,
    frames: usize,
) -> rigd::store::Manifest {
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    for part in parts.iter().chain(&["--resume"]) {
        assert!(stderr.contains(part), "{part}\n{stderr}");
    }
    let o = rigd()
        .args(["run", "--resume"])
        .arg(run)
        .args(["--progress", "none"])
        .output()
        .expect("rigd run --resume");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_complete_run(run, frames)
}
