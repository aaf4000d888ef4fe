//! GenICam cameras against Aravis's fake GigE Vision camera
//! (`arv-fake-gv-camera-0.8`, Debian's aravis-tools): an implementation of
//! GVCP and GVSP that shares no code with rigd, served on 127.0.0.1. The
//! VirTex rig's camera is that fake camera; its lamps are the simulated
//! relay module of `rigd sim serve`, reached the way hardware is.
//!
//! The fake camera always listens on GVCP's port 3956, so one runs at a
//! time: every test here holds [`FAKE_CAMERA_PORT`] while its camera lives.

use crate::bring_up::{device, edit, line_of, rig_check};
use crate::common;

use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};

use common::{assert_complete_run, repo_file, rigd, serve_sim};
use rigd::rig::drivers::genicam::{GenicamCamera, GenicamConfig};
use rigd::rig::hal::{Camera, ErrorKind};
use rigd::rig::hardware::genicam_opener;
use rigd_core::{Clock, PixelFormat};

/// The fake camera's program, from Debian's aravis-tools.
const FAKE_CAMERA: &str = "arv-fake-gv-camera-0.8";
/// GigE Vision's control port, where the fake camera listens.
const GVCP_PORT: u16 = 3956;

/// Held while a fake camera runs: there is one GVCP port on 127.0.0.1.
static FAKE_CAMERA_PORT: Mutex<()> = Mutex::new(());

fn one_camera_at_a_time() -> MutexGuard<'static, ()> {
    // A test that failed while holding it leaves nothing behind (its
    // camera is killed on drop), so a poisoned lock is still good.
    FAKE_CAMERA_PORT.lock().unwrap_or_else(|e| e.into_inner())
}

/// Whether something holds GVCP's port on 127.0.0.1.
fn gvcp_port_taken() -> bool {
    UdpSocket::bind(("127.0.0.1", GVCP_PORT)).is_err()
}

fn wait_for(what: &str, secs: u64, mut ready: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while !ready() {
        assert!(Instant::now() < deadline, "{what} within {secs} s");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Aravis's fake GigE Vision camera on 127.0.0.1 with this serial number,
/// dropping `lost_per_mille` of its stream packets; killed on drop.
fn fake_camera(serial: &str, lost_per_mille: u32, log: &Path) -> common::Child {
    wait_for("the last fake camera's port free", 10, || {
        !gvcp_port_taken()
    });
    let out = std::fs::File::create(log).expect("fake camera log");
    let err = out.try_clone().expect("clone log");
    let mut cmd = Command::new(FAKE_CAMERA);
    cmd.args(["-i", "127.0.0.1", "-s", serial]);
    if lost_per_mille > 0 {
        cmd.args(["-r", &lost_per_mille.to_string()]);
    }
    let child = cmd
        .stdin(Stdio::null())
        .stdout(out)
        .stderr(err)
        .spawn()
        .unwrap_or_else(|e| {
            panic!("cannot start {FAKE_CAMERA} ({e}): scripts/test.sh installs it (Debian's aravis-tools)")
        });
    let mut child = common::Child(child);
    wait_for("the fake camera listening on 127.0.0.1:3956", 10, || {
        if let Ok(Some(status)) = child.0.try_wait() {
            panic!(
                "{FAKE_CAMERA} exited ({status}): {}",
                std::fs::read_to_string(log).unwrap_or_default()
            );
        }
        gvcp_port_taken()
    });
    child
}

/// Kills a fake camera and waits until its port is free.
fn kill(camera: common::Child) {
    drop(camera);
    wait_for("the killed fake camera's port free", 10, || {
        !gvcp_port_taken()
    });
}

/// The VirTex rig served by `rigd sim serve` at `speed`, its camera
/// replaced by the fake GigE Vision camera (`pixel_format`, 64×48 at
/// `bit_depth`).
fn virtex_on_fake_camera(
    tmp: &Path,
    pixel_format: &str,
    bit_depth: u8,
    speed: f64,
) -> (common::Child, PathBuf) {
    let served = tmp.join("served.toml");
    let (server, _) = serve_sim(
        &repo_file("rig-profiles/virtex-photometric-stereo.toml"),
        &served,
        speed,
    );
    let profile = tmp.join("virtex-genicam.toml");
    edit(&served, &profile, |t| {
        let cam = device(t, "camera");
        let mut transport = toml::Table::new();
        transport.insert("type".into(), "genicam".into());
        transport.insert("id".into(), "127.0.0.1".into());
        cam.insert("transport".into(), transport.into());
        cam.insert("protocol".into(), "genicam".into());
        let mut intrinsics = toml::Table::new();
        intrinsics.insert(
            "resolution".into(),
            toml::Value::Array(vec![64.into(), 48.into()]),
        );
        intrinsics.insert("focal_px".into(), 300.0.into());
        intrinsics.insert("bit_depth".into(), i64::from(bit_depth).into());
        cam.insert("intrinsics".into(), intrinsics.into());
        let mut timing = toml::Table::new();
        timing.insert("exposure_s".into(), 0.02.into());
        timing.insert("readout_s".into(), 0.01.into());
        timing.insert("transfer_s".into(), 0.01.into());
        cam.insert("timing".into(), timing.into());
        let mut features = toml::Table::new();
        features.insert("pixel_format".into(), pixel_format.into());
        cam.insert("genicam".into(), features.into());
    });
    (server, profile)
}

/// `rigd run --profile PROFILE --out RUN`: the profile's default plan (the
/// VirTex lamps) on its hardware.
fn capture(profile: &Path, run: &Path) -> std::process::Output {
    rigd()
        .args(["run", "--profile"])
        .arg(profile)
        .args(["--sample", "knit", "--progress", "none", "--out"])
        .arg(run)
        .output()
        .expect("rigd run")
}

/// The manifest's frames: every one labelled by the camera, in its
/// format and size, ids rising within one camera session.
fn assert_camera_labels(run: &Path, frames: usize) -> Vec<u64> {
    assert_camera_frames(run, frames, "Mono8")
}

fn assert_camera_frames(run: &Path, frames: usize, pixel_format: &str) -> Vec<u64> {
    let m = assert_complete_run(run, frames);
    let mut ids = Vec::new();
    for f in &m.frames {
        let d = f
            .device
            .as_ref()
            .unwrap_or_else(|| panic!("frame {} has no camera label", f.index));
        assert_eq!(d.pixel_format, pixel_format);
        assert!(d.timestamp_ns > 0, "{d:?}");
        assert_eq!((f.width, f.height, f.bit_depth), (64, 48, 8));
        let png = std::fs::read(run.join(&f.file)).expect("frame file");
        let (w, h, px) = rigd::rig::hal::decode_png(&png).expect("PNG");
        assert_eq!((w, h), (64, 48));
        let (lo, hi) = (px.iter().min(), px.iter().max());
        assert!(lo < hi, "the fake camera's pattern, not a flat frame");
        ids.push(d.frame_id);
    }
    ids
}

/// A complete VirTex capture whose frames come from the fake camera:
/// `rig check` names it as it names itself, and the manifest records each
/// frame's camera id, timestamp and pixel format.
#[test]
fn a_virtex_capture_takes_its_frames_from_aravis_fake_camera() {
    let _port = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let _camera = fake_camera("RIGD-GV1", 0, &tmp.path().join("camera.log"));
    let (_server, profile) = virtex_on_fake_camera(tmp.path(), "Mono8", 8, 20.0);

    let (code, out) = rig_check(&profile, false);
    assert_eq!(code, 0, "{out}");
    let line = line_of(&out, "camera");
    eprintln!("{line}");
    for part in [
        "GenICam camera Aravis Fake, serial RIGD-GV1",
        "Mono8 64x48, trigger Software",
    ] {
        assert!(line.contains(part), "{part}\n{line}");
    }

    let run = tmp.path().join("run");
    let o = capture(&profile, &run);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ids = assert_camera_labels(&run, 3);
    let mut sorted = ids.clone();
    sorted.sort_unstable();
    sorted.dedup();
    assert_eq!(sorted.len(), 3, "three distinct camera frames: {ids:?}");

    // The exposure the driver sets is the one the camera takes. Aravis's
    // fake camera draws its ramp `(x + y + frame id) mod 255` times
    // `1 + gain + log10(exposure / 10 ms)`: one level a column at 10 ms,
    // 0.70 at 5 ms (neither clips at 255).
    for (exposure_s, slope) in [(0.01, 1.0), (0.005, 1.0 + 0.5f64.log10())] {
        let at = tmp.path().join(format!("virtex-{exposure_s}.toml"));
        edit(&profile, &at, |t| {
            let timing = device(t, "camera")
                .get_mut("timing")
                .and_then(|v| v.as_table_mut())
                .expect("[devices.camera.timing]");
            timing.insert("exposure_s".into(), exposure_s.into());
        });
        let run = tmp.path().join(format!("run-{exposure_s}"));
        let o = capture(&at, &run);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        for f in &assert_complete_run(&run, 3).frames {
            let png = std::fs::read(run.join(&f.file)).expect("frame file");
            let (w, _, px) = rigd::rig::hal::decode_png(&png).expect("PNG");
            // Steps along a row, leaving out where the ramp wraps.
            let steps: Vec<f64> = px
                .chunks(w as usize)
                .flat_map(|row| row.windows(2))
                .map(|p| f64::from(p[1]) - f64::from(p[0]))
                .filter(|d| (0.0..=2.0).contains(d))
                .collect();
            let measured = steps.iter().sum::<f64>() / steps.len().max(1) as f64;
            assert!(
                (measured - slope).abs() < 0.05,
                "{exposure_s} s: the ramp rises {measured} a column, expected {slope}"
            );
        }
    }
}

/// A Bayer camera's frames are stored as their raw mosaic, labelled with
/// the colour filter array, and processing reads them as grey through the
/// bilinear demosaic.
#[test]
fn a_bayer_capture_is_stored_as_its_mosaic_and_processed_as_grey() {
    let _port = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let _camera = fake_camera("RIGD-GV6", 0, &tmp.path().join("camera.log"));
    let (_server, profile) = virtex_on_fake_camera(tmp.path(), "BayerRG8", 8, 20.0);
    let run = tmp.path().join("run");
    let o = capture(&profile, &run);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_camera_frames(&run, 3, "BayerRG8");
    let frames = rigd::postprocess::frames::RunFrames::open(&run).expect("run");
    for e in &frames.entries {
        let png = std::fs::read(run.join(&e.file)).expect("frame");
        let (_, _, mosaic) = rigd::rig::hal::decode_png(&png).expect("PNG");
        let grey = frames.image(e).expect("a grey image");
        assert_eq!((grey.width, grey.height, grey.channels), (64, 48, 1));
        assert!(grey.data.iter().all(|v| (0.0..=1.0).contains(v)));
        // The demosaic smooths the mosaic: no grey pixel lies outside the
        // range of the samples around it.
        let (lo, hi) = (
            f32::from(*mosaic.iter().min().unwrap_or(&0)) / 255.0,
            f32::from(*mosaic.iter().max().unwrap_or(&255)) / 255.0,
        );
        assert!(grey
            .data
            .iter()
            .all(|v| (lo - 1e-6..=hi + 1e-6).contains(v)));
    }
}

/// A camera asked for a pixel format it does not have: `rig check` names
/// the feature, the value and what the camera offers, and a run does not
/// start (exit 1, a device failure, not bad input).
#[test]
fn a_pixel_format_the_camera_refuses_is_named_with_what_it_offers() {
    let _port = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let _camera = fake_camera("RIGD-GV2", 0, &tmp.path().join("camera.log"));
    let (_server, profile) = virtex_on_fake_camera(tmp.path(), "Mono12", 12, 20.0);

    let (code, out) = rig_check(&profile, false);
    assert_eq!(code, 1, "{out}");
    let line = line_of(&out, "camera");
    eprintln!("{line}");
    assert!(line.starts_with("FAIL"), "{line}");
    assert!(!line.contains("fix:"), "the message is its own fix: {line}");
    for part in [
        "the camera refuses PixelFormat = Mono12",
        "it offers",
        "Mono8",
        "Mono16",
        "set `devices.camera.genicam.pixel_format` to what the camera offers",
    ] {
        assert!(line.contains(part), "{part}\n{line}");
    }
    let o = capture(&profile, &tmp.path().join("run"));
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("PixelFormat = Mono12"), "{err}");
}

/// The driver on a camera that loses 30 % of its stream packets: every
/// frame with a lost packet is a bad frame (which the engine retakes), and
/// no incomplete frame is ever delivered.
// The lock orders the tests around one GVCP port; it guards no data.
#[allow(clippy::await_holding_lock)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lost_packets_make_bad_frames_and_never_a_partial_one() {
    let _port = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let _camera = fake_camera("RIGD-GV3", 300, &tmp.path().join("camera.log"));
    let cfg = GenicamConfig {
        name: "camera".into(),
        id: "127.0.0.1".into(),
        pixel_format: PixelFormat::Mono(8),
        size: [64, 48],
        gain_db: None,
        trigger_source: "Software".into(),
        exposure_s: 0.005,
        readout_s: 0.0,
        transfer_s: 0.01,
    };
    let (mut cam, id) = GenicamCamera::connect(cfg, genicam_opener("127.0.0.1"), Clock::real())
        .await
        .expect("connect to the fake camera");
    assert_eq!((id.vendor.as_str(), id.model.as_str()), ("Aravis", "Fake"));
    let (mut complete, mut bad, mut silent) = (0, 0, 0);
    for _ in 0..60 {
        cam.expose().await.expect("trigger");
        match cam.transfer().await {
            Ok(f) => {
                assert_eq!((f.width, f.height, f.pixels.len()), (64, 48, 64 * 48));
                complete += 1;
            }
            Err(e) if e.kind == ErrorKind::BadFrame => {
                assert!(e.message.contains("incomplete"), "{e}");
                bad += 1;
            }
            // Every packet of a frame lost: no buffer at all. The engine
            // retries a timeout too, on a camera opened afresh.
            Err(e) => {
                assert_eq!(e.kind, ErrorKind::Timeout, "{e}");
                silent += 1;
            }
        }
    }
    eprintln!(
        "30 % packet loss, 60 triggers: {complete} complete frames, {bad} incomplete, {silent} never came"
    );
    assert!(complete > 0 && bad > 0, "{complete} complete, {bad} bad");
}

/// The camera's own `ExposureTime` range (the fake camera's: 10 µs to
/// 10 s) bounds the exposures the driver sets: beyond it the driver refuses,
/// naming the range, at connect and when a run sets its exposure.
// The lock orders the tests around one GVCP port; it guards no data.
#[allow(clippy::await_holding_lock)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_exposure_beyond_the_camera_s_range_is_refused() {
    let _port = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let _camera = fake_camera("RIGD-GV7", 0, &tmp.path().join("camera.log"));
    let cfg = |exposure_s: f64| GenicamConfig {
        name: "camera".into(),
        id: "127.0.0.1".into(),
        pixel_format: PixelFormat::Mono(8),
        size: [64, 48],
        gain_db: None,
        trigger_source: "Software".into(),
        exposure_s,
        readout_s: 0.0,
        transfer_s: 0.01,
    };
    let offers = "it offers 10 to 10000000 µs";
    match GenicamCamera::connect(cfg(100.0), genicam_opener("127.0.0.1"), Clock::real()).await {
        Ok(_) => panic!("a 100 s exposure was set on a camera that exposes up to 10 s"),
        Err(e) => {
            assert_eq!(e.kind, ErrorKind::OutOfLimits, "{e}");
            assert!(
                e.message.contains(offers) && e.message.contains("timing.exposure_s"),
                "{e}"
            );
        }
    }
    let (mut cam, _) =
        GenicamCamera::connect(cfg(0.005), genicam_opener("127.0.0.1"), Clock::real())
            .await
            .expect("connect to the fake camera");
    let e = cam.set_exposure(100.0).await.expect_err("beyond 10 s");
    assert_eq!(e.kind, ErrorKind::OutOfLimits, "{e}");
    assert!(e.message.contains(offers), "{e}");
    cam.set_exposure(2.0).await.expect("within the range");
}

/// A capture on a camera that loses 1 % of its packets completes: lost
/// frames are retaken, and every stored frame is whole.
#[test]
fn a_capture_on_a_lossy_camera_completes_with_whole_frames() {
    let _port = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let _camera = fake_camera("RIGD-GV4", 10, &tmp.path().join("camera.log"));
    let (_server, profile) = virtex_on_fake_camera(tmp.path(), "Mono8", 8, 20.0);
    let run = tmp.path().join("run");
    let o = capture(&profile, &run);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    eprintln!(
        "1 % packet loss: {} retakes",
        err.lines().filter(|l| l.contains("retrying")).count()
    );
    assert_camera_labels(&run, 3);
}

/// The camera vanishes in mid-run: the daemon's run pauses with a reason
/// naming the camera; after the camera is back, a resume reconnects it
/// and the run completes with every frame.
// The lock orders the tests around one GVCP port; it guards no data.
#[allow(clippy::await_holding_lock)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_killed_mid_run_pauses_it_and_a_resume_reconnects() {
    let guard = one_camera_at_a_time();
    let tmp = tempfile::tempdir().expect("tempdir");
    let log = tmp.path().join("camera.log");
    let camera = fake_camera("RIGD-GV5", 0, &log);
    // The lamps in real time: each frame waits for its lamp's 2 s warm-up,
    // so the operator's pause lands mid-run.
    let (_server, profile) = virtex_on_fake_camera(tmp.path(), "Mono8", 8, 1.0);
    let data = tmp.path().join("data");
    let mut s = common::http::start_with(&data, 1.0, profile.to_str(), false).await;
    let (status, v) = s
        .post(
            "/api/v1/runs",
            Some(serde_json::json!({"sample": "knit", "plan": "lamps"})),
        )
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("run id").to_string();
    s.wait_run(&id, "a first frame", |v| {
        v["steps_done"].as_u64() >= Some(1)
    })
    .await;
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/pause"), None).await;
    assert_eq!(status, 202, "{v}");
    let paused = s.wait_state(&id, "paused").await;
    let done = paused["steps_done"].as_u64().unwrap_or(0);
    assert!(done < 3, "paused before the end: {paused}");

    kill(camera);
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 202, "{v}");
    let faulted = s
        .wait_run(&id, "a pause for the lost camera", |v| {
            v["state"] == "paused" && v["reason"].as_str().is_some_and(|r| r.contains("camera"))
        })
        .await;
    eprintln!("camera gone: {}", faulted["reason"]);
    assert_eq!(faulted["steps_done"].as_u64(), Some(done), "{faulted}");

    let _camera = fake_camera("RIGD-GV5", 0, &log);
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 202, "{v}");
    s.wait_ended(&id, "completed").await;
    s.shutdown().await;
    drop(guard);
    let ids = assert_camera_labels(&data.join("runs").join(&id), 3);
    eprintln!("camera frame ids across the restart: {ids:?}");
}
