//! The libgphoto2 transport (`transport = { type = "gphoto2" }`) against the
//! camera `rigd sim serve` offers over PTP/IP: libgphoto2's own ptp2 driver
//! opens it, `rig check` names it and the widgets it set, a VirTex capture
//! stores the camera's files byte for byte as rigd's own PTP/IP driver gets
//! them, and an exposure the camera does not list is refused at connect,
//! naming the list.

use crate::common;

use std::path::{Path, PathBuf};

use crate::bring_up::{device, edit, line_of, rig_check};
use crate::sim_serve::{hostile_relay, paused_naming_then_resumed, Misbehaviour};
use common::{assert_complete_run, repo_file, rigd, serve_sim, served_ptpip_port};

/// The VirTex rig served by `rigd sim serve`, and the profile it printed
/// with the camera moved to libgphoto2 on its PTP/IP port (the event
/// channel on the same port: libgphoto2 takes it as a third field),
/// exposing `exposure_s` at ISO 100.
fn virtex_through_libgphoto2(tmp: &Path, exposure_s: f64) -> (common::Child, PathBuf, PathBuf) {
    let served = tmp.join("served.toml");
    let (server, lines) = serve_sim(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        &served,
        20.0,
    );
    let port = served_ptpip_port(&lines);
    let profile = tmp.join("virtex-gphoto2.toml");
    edit(&served, &profile, |t| {
        let cam = device(t, "camera");
        let mut transport = toml::Table::new();
        transport.insert("type".into(), "gphoto2".into());
        transport.insert(
            "port".into(),
            format!("ptpip:127.0.0.1:{port}:{port}").into(),
        );
        transport.insert("model".into(), "PTP/IP Camera".into());
        cam.insert("transport".into(), transport.into());
        cam.insert("protocol".into(), "gphoto2".into());
        let mut settings = toml::Table::new();
        settings.insert("iso".into(), "100".into());
        let mut table = toml::Table::new();
        table.insert("settings".into(), settings.into());
        cam.insert("gphoto2".into(), table.into());
        if let Some(timing) = cam.get_mut("timing").and_then(|t| t.as_table_mut()) {
            timing.insert("exposure_s".into(), exposure_s.into());
        }
    });
    (server, served, profile)
}

/// `rigd run --profile PROFILE --out RUN`: the VirTex lamps.
fn capture(profile: &Path, run: &Path) -> std::process::Output {
    rigd()
        .args(["run", "--profile"])
        .arg(profile)
        .args(["--sample", "knit", "--progress", "none", "--out"])
        .arg(run)
        .output()
        .expect("rigd run")
}

/// `rig check` names the camera as libgphoto2 found it and the widgets
/// set; a VirTex capture through libgphoto2 completes, and its frames are
/// the camera's DNG files, byte for byte the ones rigd's own PTP/IP driver
/// stores from the same served camera in the same capture.
#[test]
fn a_virtex_capture_through_libgphoto2_stores_the_camera_s_files() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (_server, served, profile) = virtex_through_libgphoto2(tmp.path(), 0.1);

    let (code, out) = rig_check(&profile, false);
    assert_eq!(code, 0, "{out}");
    let line = line_of(&out, "camera");
    eprintln!("{line}");
    for part in [
        "libgphoto2 camera rigd simulated PTP camera",
        "libgphoto2 model `PTP/IP Camera` on `ptpip:127.0.0.1:",
        "set iso 100, shutterspeed 0.1000s",
    ] {
        assert!(line.contains(part), "{part}\n{line}");
    }

    let through_gphoto2 = tmp.path().join("gphoto2-run");
    let o = capture(&profile, &through_gphoto2);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let m = assert_complete_run(&through_gphoto2, 3);

    // The same capture through rigd's own PTP/IP driver: each session
    // starts the served camera afresh, so the files must agree.
    let through_ptpip = tmp.path().join("ptpip-run");
    let o = capture(&served, &through_ptpip);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let reference = assert_complete_run(&through_ptpip, 3);
    for (f, r) in m.frames.iter().zip(&reference.frames) {
        assert!(f.file.ends_with(".dng"), "{}", f.file);
        assert_eq!((f.index, &f.file), (r.index, &r.file));
        assert_eq!(f.sha256, r.sha256, "frame {}", f.index);
        assert_eq!((f.width, f.height, f.bit_depth), (128, 96, 12));
        let a = std::fs::read(through_gphoto2.join(&f.file)).expect("frame");
        let b = std::fs::read(through_ptpip.join(&r.file)).expect("frame");
        assert!(a == b, "frame {} differs", f.index);
        assert!(a.starts_with(b"II*\0"), "not a DNG");
    }

    // The exposure set through libgphoto2's `shutterspeed` is the one the
    // camera exposes: half the time, half the signal above black in every
    // frame (the lamps and the sample are the same).
    let half_dir = tmp.path().join("half");
    std::fs::create_dir_all(&half_dir).expect("mkdir");
    let (_half_server, _, half_profile) = virtex_through_libgphoto2(&half_dir, 0.05);
    let half = tmp.path().join("gphoto2-half");
    let o = capture(&half_profile, &half);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let h = assert_complete_run(&half, 3);
    let signal = |run: &Path, file: &str| {
        let bytes = std::fs::read(run.join(file)).expect("frame");
        let image = rigd::rig::camera_file::decode_here(&bytes).expect("the camera DNG decodes");
        let sum: f64 = image
            .samples
            .iter()
            .map(|&v| (f64::from(v) - f64::from(image.black)).max(0.0))
            .sum();
        sum / image.samples.len().max(1) as f64
    };
    for (full, short) in m.frames.iter().zip(&h.frames) {
        let ratio = signal(&half, &short.file) / signal(&through_gphoto2, &full.file);
        assert!(
            (0.45..0.55).contains(&ratio),
            "frame {}: 0.05 s over 0.1 s reads {ratio}",
            full.index
        );
    }
}

/// An exposure the camera lists no `shutterspeed` for is refused at
/// connect, naming what it offers and the key to change: by `rig check`
/// (exit 1), and by `rigd run` before anything moves (exit 1).
#[test]
fn a_shutterspeed_the_camera_does_not_list_is_refused_naming_the_list() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (_server, _, profile) = virtex_through_libgphoto2(tmp.path(), 0.0123);

    let (code, out) = rig_check(&profile, false);
    assert_eq!(code, 1, "{out}");
    let line = line_of(&out, "camera");
    eprintln!("{line}");
    assert!(line.starts_with("FAIL"), "{line}");
    assert!(!line.contains("fix:"), "the message is its own fix: {line}");
    for part in [
        "shutterspeed 0.0123 s is not offered; the camera offers: 0.0005s, 0.0006s,",
        "0.0100s, 0.0125s,",
        "30.0000s; set `devices.camera.timing.exposure_s` to what the camera offers",
    ] {
        assert!(line.contains(part), "{part}\n{line}");
    }

    let run = tmp.path().join("run");
    let o = capture(&profile, &run);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("shutterspeed 0.0123 s is not offered"),
        "{err}"
    );
}

/// The camera vanishes mid-run: its connection closes when the second
/// capture is asked for. libgphoto2 reports an unspecified error, the run
/// pauses naming the camera, and a resume opens the camera afresh through
/// libgphoto2 and completes the run with every frame the camera's file.
#[test]
fn a_camera_that_vanishes_mid_run_pauses_it_and_a_resume_reconnects() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (_server, _, direct) = virtex_through_libgphoto2(tmp.path(), 0.1);
    let profile = tmp.path().join("through-relay.toml");
    edit(&direct, &profile, |t| {
        let transport = device(t, "camera")
            .get_mut("transport")
            .and_then(|t| t.as_table_mut())
            .expect("the camera's transport");
        let port: u16 = transport
            .get("port")
            .and_then(|p| p.as_str())
            .and_then(|p| p.rsplit(':').next())
            .and_then(|p| p.parse().ok())
            .expect("a ptpip: port");
        let relay = hostile_relay(port, 2, Misbehaviour::HangUp);
        transport.insert(
            "port".into(),
            format!("ptpip:127.0.0.1:{relay}:{relay}").into(),
        );
    });
    let run = tmp.path().join("run");
    let o = capture(&profile, &run);
    let m = paused_naming_then_resumed(&o, &["camera: device fault: capturing"], &run, 3);
    for f in &m.frames {
        let bytes = std::fs::read(run.join(&f.file)).expect("frame");
        assert!(bytes.starts_with(b"II*\0"), "frame {} is no DNG", f.index);
    }
}
