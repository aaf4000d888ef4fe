//! An independent PTP/IP initiator: the `gphoto2` tool, through
//! libgphoto2's own ptp2 driver, reads the summary and settings of the
//! camera `rigd sim serve` offers over PTP/IP, captures and downloads a
//! frame, and gets the same bytes that rigd's own driver gets over PTP/IP
//! from a fresh session.

use crate::common;

use std::process::Command;
use std::time::Duration;

use common::{repo_file, serve_sim, served_ptpip_port};
use rigd::rig::drivers::ptp::{PtpCamera, PtpConfig};
use rigd::rig::drivers::ptpip::PtpIpPipe;
use rigd::rig::hal::Camera;
use rigd_core::Clock;

/// Runs `gphoto2` on the served camera (libgphoto2 takes the event port
/// as a third field, 15740 otherwise) with a bounded time.
fn gphoto2(port: u16, dir: &std::path::Path, args: &[&str]) -> String {
    let out = Command::new("timeout")
        .arg("60")
        .arg("gphoto2")
        .arg("--port")
        .arg(format!("ptpip:127.0.0.1:{port}:{port}"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("gphoto2 runs (scripts/test.sh installs it)");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "gphoto2 {args:?} failed:\n{text}");
    text
}

#[test]
fn gphoto2_lists_sets_and_captures_from_the_served_camera_byte_for_byte() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let served = tmp.path().join("served.toml");
    let (_server, lines) = serve_sim(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        &served,
        20.0,
    );
    let port = served_ptpip_port(&lines);

    let summary = gphoto2(port, tmp.path(), &["--summary"]);
    assert!(summary.contains("Model: simulated PTP camera"), "{summary}");
    assert!(summary.contains("Capture Formats: DNG"), "{summary}");
    // The properties, with the lists tools choose from.
    assert!(
        summary.contains("Exposure Time(0x500d):(readwrite) (type=0x6) Enumeration"),
        "{summary}"
    );
    assert!(summary.contains("ISO 100"), "{summary}");

    // A setting by name, through libgphoto2's configuration widgets.
    let set = gphoto2(
        port,
        tmp.path(),
        &[
            "--set-config",
            "shutterspeed=0.1000s",
            "--get-config",
            "shutterspeed",
        ],
    );
    assert!(set.contains("Current: 0.1000s"), "{set}");

    let capture = gphoto2(
        port,
        tmp.path(),
        &["--capture-image-and-download", "--filename", "gphoto2.dng"],
    );
    assert!(capture.contains("Deleting file"), "{capture}");
    let from_gphoto2 = std::fs::read(tmp.path().join("gphoto2.dng")).expect("the download");
    assert!(from_gphoto2.starts_with(b"II*\0"), "not a DNG");

    // rigd's own driver, in a fresh session of the same camera at the same
    // exposure, gets the same first frame byte for byte.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let from_rigd = runtime.block_on(async {
        let pipe = tokio::time::timeout(
            Duration::from_secs(20),
            PtpIpPipe::connect("127.0.0.1", port),
        )
        .await
        .expect("in time")
        .expect("a PTP/IP session");
        assert_eq!(pipe.camera().name, "simulated PTP camera");
        let mut cam = PtpCamera::new("camera", pipe, Clock::real(), PtpConfig::default());
        cam.connect().await.expect("connect");
        cam.set_exposure(0.1).await.expect("exposure");
        cam.expose().await.expect("expose");
        let frame = cam.transfer().await.expect("transfer");
        frame.original.expect("the camera's file").bytes
    });
    assert_eq!(from_rigd.len(), from_gphoto2.len());
    assert!(from_rigd == from_gphoto2, "the two downloads differ");

    // LibRaw reads the download as rigd does.
    let id = Command::new("raw-identify")
        .arg(tmp.path().join("gphoto2.dng"))
        .output()
        .expect("raw-identify runs");
    assert!(
        String::from_utf8_lossy(&id.stdout).contains("rigd simulated PTP camera"),
        "{}",
        String::from_utf8_lossy(&id.stdout)
    );
}
