//! Manual control for bring-up, through the daemon's API on the simulated
//! Bonn rig: home and jog an axis, take a pose, switch the lamp, take a
//! test frame, check the holder in one; bad input moves nothing; the
//! emergency stop covers it; and while a run is active every manual action
//! answers 409.

use std::path::Path;

use crate::common;

use common::http::{run_body, start_in, start_with, Srv};
use serde_json::{json, Value};

/// The rail's reported position on the rig card (the simulated world).
async fn rail_on_card(s: &common::http::Srv) -> Option<f64> {
    let (_, rig) = s.get("/api/v1/rig").await;
    rig["devices"]
        .as_array()?
        .iter()
        .find(|d| d["name"] == "rail")?["position_deg"]
        .as_f64()
}

/// A jog of the rail before it was homed: refused, nothing moves.
async fn refused_until_homed(s: &common::http::Srv) {
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/jog",
            Some(json!({"device": "rail", "by_deg": 1.0})),
        )
        .await;
    assert_eq!(status, 422, "{v}");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("home `rail` first")),
        "{v}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn manual_control_moves_switches_and_shoots_and_yields_to_a_run() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut s = start_in(dir.path(), 20_000.0).await;

    // Nothing moves before it is homed: its position means nothing yet.
    refused_until_homed(&s).await;

    let (status, v) = s
        .post("/api/v1/rig/manual/home", Some(json!({"device": "rail"})))
        .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["position_deg"], json!([90.0]));
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/jog",
            Some(json!({"device": "rail", "by_deg": 5.0})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["position_deg"], json!([95.0]));
    assert_eq!(rail_on_card(&s).await, Some(95.0));
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/jog",
            Some(json!({"device": "rail", "to_deg": 120.0})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["position_deg"], json!([120.0]));

    // Bad input: a clear error and nothing moves.
    for (body, says) in [
        (
            json!({"device": "rail", "to_deg": 500.0}),
            "beyond its soft limits [12, 172]",
        ),
        (
            json!({"device": "rail", "by_deg": -200.0}),
            "beyond its soft limits",
        ),
        (
            json!({"device": "rail", "by_deg": 1.0, "to_deg": 2.0}),
            "exactly one",
        ),
        (
            json!({"device": "hmi", "by_deg": 1.0}),
            "`hmi` is a lamp, not an axis",
        ),
        (
            json!({"device": "turntable", "by_deg": 1.0}),
            "no device `turntable`",
        ),
    ] {
        let (status, v) = s.post("/api/v1/rig/manual/jog", Some(body.clone())).await;
        assert_eq!(status, 422, "{body}: {v}");
        assert!(
            v["detail"].as_str().is_some_and(|d| d.contains(says)),
            "{body}: {v}"
        );
    }
    assert_eq!(rail_on_card(&s).await, Some(120.0), "nothing moved");

    // A (light, view) pose: the rail and the arm move, the lamp is named.
    let (status, v) = s
        .post("/api/v1/rig/manual/home", Some(json!({"device": "arm"})))
        .await;
    assert_eq!(status, 200, "{v}");
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/pose",
            Some(json!({"light": {"theta_deg": 30.0, "phi_deg": 0.0},
                        "view": {"theta_deg": 30.0, "phi_deg": 180.0}})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["lamp"], "hmi");
    assert_eq!(v["camera"], "camera");
    assert_eq!(v["feasible"], true);
    let rail = v["axes"]["rail"].as_f64().expect("rail moved");
    assert_eq!(rail_on_card(&s).await, Some(rail));
    assert_eq!(v["arm"].as_array().map(Vec::len), Some(3));
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/pose",
            Some(json!({"light": {"theta_deg": 95.0, "phi_deg": 0.0},
                        "view": {"theta_deg": 30.0, "phi_deg": 0.0}})),
        )
        .await;
    assert_eq!(status, 422, "{v}");

    // The lamp, then a test frame lit by it.
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/lamp",
            Some(json!({"device": "hmi", "on": true})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["on"], true);
    let (_, rig) = s.get("/api/v1/rig").await;
    assert_eq!(rig["lamps"]["hmi"], true, "{rig}");
    let (status, _, _) = s.get_bytes("/api/v1/rig/manual/frame").await;
    assert_eq!(status, 404, "no frame yet");
    let (status, frame) = s.post("/api/v1/rig/manual/frame", Some(json!({}))).await;
    assert_eq!(status, 200, "{frame}");
    assert_eq!(frame["camera"], "camera");
    assert_eq!(
        (frame["width"].as_u64(), frame["height"].as_u64()),
        (Some(640), Some(480)),
        "the profile's [sim] frame_size"
    );
    assert!(frame["max"].as_u64() > Some(0), "a lit frame: {frame}");
    let (status, ct, png) = s.get_bytes("/api/v1/rig/manual/frame").await;
    assert_eq!((status, ct.as_str()), (200, "image/png"));
    assert!(png.starts_with(b"\x89PNG"));
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/frame",
            Some(json!({"exposure_s": -1.0})),
        )
        .await;
    assert_eq!(status, 422, "{v}");
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/lamp",
            Some(json!({"device": "hmi", "on": false})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    let (_, rig) = s.get("/api/v1/rig").await;
    assert_eq!(rig["lamps"]["hmi"], false, "{rig}");

    // Without the token: 401, nothing moves.
    let (status, _) = s
        .send(
            "POST",
            "/api/v1/rig/manual/jog",
            Some(json!({"device": "rail", "by_deg": 1.0})),
            None,
        )
        .await;
    assert_eq!(status, 401);

    // The emergency stop covers manual control: every device answers,
    // and the axes must home again.
    let (status, v) = s.post("/api/v1/estop", None).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["run"], serde_json::Value::Null);
    assert_eq!(v["all_stopped"], true, "{v}");
    assert_eq!(v["devices"].as_array().map(Vec::len), Some(3), "{v}");
    refused_until_homed(&s).await;

    // A run takes the rig; meanwhile every manual action answers 409.
    // An H1: long enough to still be running while the manual calls come.
    let (status, v) = s
        .post("/api/v1/runs", Some(run_body("after-manual", json!("h1"))))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    for (path, body) in [
        (
            "/api/v1/rig/manual/jog",
            json!({"device": "rail", "by_deg": 1.0}),
        ),
        ("/api/v1/rig/manual/home", json!({"device": "rail"})),
        (
            "/api/v1/rig/manual/lamp",
            json!({"device": "hmi", "on": true}),
        ),
        ("/api/v1/rig/manual/frame", json!({})),
        ("/api/v1/rig/manual/holder-check", json!({})),
    ] {
        let (status, v) = s.post(path, Some(body)).await;
        assert_eq!(status, 409, "{path}: {v}");
        assert!(v["detail"].as_str().is_some_and(|d| d.contains(&id)), "{v}");
    }
    let (_, run) = s.get(&format!("/api/v1/runs/{id}")).await;
    assert_eq!(run["active"], true, "the run outlived the checks: {run}");
    let (status, _) = s.post(&format!("/api/v1/runs/{id}/abort"), None).await;
    assert_eq!(status, 202);
    s.wait_ended(&id, "aborted").await;
    // Then the rig is free for manual control again.
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/lamp",
            Some(json!({"device": "hmi", "on": false})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    s.shutdown().await;
}

/// A daemon on the simulated rig of `profile` (the embedded default if
/// None) whose devices fail as `faults` say.
async fn start_faulty(data: &Path, profile: Option<&Path>, faults: &[&str]) -> Srv {
    let mut config = rigd::server::ServerConfig::new(data);
    config.listen = "127.0.0.1:0".parse().expect("addr");
    config.sim_speed = 20_000.0;
    config.profile = profile.map(|p| p.display().to_string());
    config.sim_faults = faults
        .iter()
        .map(|f| f.parse().expect("a fault rule"))
        .collect();
    let (addr, handle) = rigd::server::start(config).await.expect("server starts");
    Srv {
        addr,
        base: format!("http://{addr}"),
        token: handle.token.secret().to_string(),
        data: data.to_path_buf(),
        handle: Some(handle),
        client: reqwest::Client::new(),
    }
}

/// Homes the rail and the arm, takes the frontal pose (light 30°, view
/// 0°) and switches the lamp on: the holder lit, seen square on.
async fn pose_frontally(s: &Srv) {
    for device in ["rail", "arm"] {
        let (status, v) = s
            .post("/api/v1/rig/manual/home", Some(json!({"device": device})))
            .await;
        assert_eq!(status, 200, "{device}: {v}");
    }
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/pose",
            Some(json!({"light": {"theta_deg": 30.0, "phi_deg": 0.0},
                        "view": {"theta_deg": 0.0, "phi_deg": 0.0}})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["feasible"], true, "{v}");
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/lamp",
            Some(json!({"device": "hmi", "on": true})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
}

/// A holder check that found every marker of `markers` and registered.
fn assert_all_found(check: &Value, markers: usize) {
    assert_eq!(check["ok"], true, "{check}");
    assert_eq!(check["markers_found"], markers, "{check}");
    assert_eq!(check["markers"].as_array().map(Vec::len), Some(markers));
    assert_eq!(check["registered"], true, "{check}");
    assert!(check["rms_px"].as_f64().is_some_and(|r| r < 0.5), "{check}");
    assert_eq!(check["problems"], json!([]), "{check}");
    assert_eq!(check["camera"], "camera");
    assert!(
        check["view"]["theta_deg"]
            .as_f64()
            .is_some_and(|t| t.abs() < 1e-6),
        "the posed view: {check}"
    );
}

const HOLDER_CHECK: &str = "/api/v1/rig/manual/holder-check";

/// The holder check from manual control: refused until the rig has taken
/// a pose, and again once it has moved off it; at a frontal pose every
/// marker of the monochrome Bonn profile's standard plate found (no body, or an
/// empty one); a frame whose markers are covered (the camera's
/// `mask-markers` fault on its second exposure: a valid frame, as dirt on
/// the plate or a plate put elsewhere gives) is still answered 200, with
/// every missing marker named. On the ColorChecker profile's Bayer camera
/// the frame is demosaiced and the chart's 24 patches are read in colour.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_holder_check_needs_a_pose_and_names_the_markers_it_misses() {
    let dir = tempfile::tempdir().expect("tempdir");
    // The plate without colour patches: with the markers covered, the
    // standard row's middle patches lie within marker 3's search window,
    // and one is taken for it.
    let monochrome = crate::common::bonn_monochrome(dir.path());
    let mut s = start_faulty(
        &dir.path().join("bonn"),
        Some(&monochrome),
        &["camera:expose:2:mask-markers"],
    )
    .await;
    // Connected, the rail homed: no pose yet, and no frame is taken.
    let (status, v) = s
        .post("/api/v1/rig/manual/home", Some(json!({"device": "rail"})))
        .await;
    assert_eq!(status, 200, "{v}");
    let (status, v) = s.post(HOLDER_CHECK, None).await;
    assert_eq!(status, 409, "{v}");
    assert!(
        v["detail"].as_str().is_some_and(|d| d.starts_with(
            "move to a pose first: POST /api/v1/rig/manual/pose; the holder check needs the view"
        )),
        "{v}"
    );
    let (status, _, _) = s.get_bytes("/api/v1/rig/manual/frame").await;
    assert_eq!(status, 404, "no frame was taken");

    pose_frontally(&s).await;
    // Exposure 1, without a body: the standard plate's eight light
    // markers, no patches to read.
    let (status, check) = s.post(HOLDER_CHECK, None).await;
    assert_eq!(status, 200, "{check}");
    assert_all_found(&check, 8);
    assert_eq!(check["holder"], "standard");
    assert_eq!(check["profile"], "bonn-gonioreflectometer");
    assert_eq!(
        check["size"],
        json!([320, 240]),
        "the profile's [sim] frame_size"
    );
    assert_eq!(check["channels"], 1);
    assert_eq!(check["patches"], json!([]));
    assert_eq!(check["whites"], json!([]));
    // The frame is the last test frame.
    let (status, ct, png) = s.get_bytes("/api/v1/rig/manual/frame").await;
    assert_eq!((status, ct.as_str()), (200, "image/png"));
    assert!(png.starts_with(b"\x89PNG"));

    // Exposure 2: the markers covered. Still 200: the check was made.
    let (status, check) = s.post(HOLDER_CHECK, Some(json!({}))).await;
    assert_eq!(status, 200, "{check}");
    assert_eq!(check["ok"], false, "{check}");
    assert_eq!(check["markers_found"], 0, "{check}");
    assert_eq!(check["registered"], false, "{check}");
    let problems: Vec<&str> = check["problems"]
        .as_array()
        .expect("problems")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    for i in 0..8 {
        let marker = format!("marker {i} (light, at ");
        assert!(
            problems
                .iter()
                .any(|p| p.starts_with(&marker) && p.contains("not found near its predicted pixel")),
            "marker {i} named: {problems:?}"
        );
    }
    assert!(
        problems.iter().any(|p| p.starts_with("not registered")),
        "{problems:?}"
    );
    // Exposure 3: clean again, with the camera and exposure given.
    let (status, check) = s
        .post(
            HOLDER_CHECK,
            Some(json!({"camera": "camera", "exposure_s": 0.1})),
        )
        .await;
    assert_eq!(status, 200, "{check}");
    assert_all_found(&check, 8);

    // What the check cannot use: 422, naming it.
    for (body, says) in [
        (json!({"camera": "hmi"}), "`hmi` is a lamp, not a camera"),
        (json!({"camera": "nope"}), "no device `nope`"),
        (
            json!({"exposure_s": -1.0}),
            "expected a positive number of seconds",
        ),
        (json!({"view": [0, 0]}), "unknown field `view`"),
    ] {
        let (status, v) = s.post(HOLDER_CHECK, Some(body.clone())).await;
        assert_eq!(status, 422, "{body}: {v}");
        assert!(
            v["detail"].as_str().is_some_and(|d| d.contains(says)),
            "{body}: {v}"
        );
    }
    // A pose at the horizon is taken, but no camera model looks from there.
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/pose",
            Some(json!({"light": {"theta_deg": 30.0, "phi_deg": 0.0},
                        "view": {"theta_deg": 90.0, "phi_deg": 180.0}})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    let (status, v) = s.post(HOLDER_CHECK, None).await;
    assert_eq!(status, 422, "{v}");
    assert!(
        v["detail"].as_str().is_some_and(|d| d.contains("θ < 90")),
        "{v}"
    );
    // A jog leaves the pose: the view is unknown again.
    let (status, v) = s
        .post(
            "/api/v1/rig/manual/jog",
            Some(json!({"device": "rail", "by_deg": -1.0})),
        )
        .await;
    assert_eq!(status, 200, "{v}");
    let (status, v) = s.post(HOLDER_CHECK, None).await;
    assert_eq!(status, 409, "{v}");
    // Without the token: 401.
    let (status, _) = s.send("POST", HOLDER_CHECK, None, None).await;
    assert_eq!(status, 401);
    s.shutdown().await;

    // A Bayer camera and a plate with a ColorChecker: the mosaic
    // demosaiced, each of the chart's patches read per channel.
    let profile = common::repo_file("rig-profiles/bonn-colorchecker.toml");
    let mut s = start_faulty(&dir.path().join("colour"), Some(&profile), &[]).await;
    pose_frontally(&s).await;
    let (status, check) = s.post(HOLDER_CHECK, None).await;
    assert_eq!(status, 200, "{check}");
    assert_all_found(&check, 8);
    assert_eq!(check["channels"], 3);
    let patches = check["patches"].as_array().expect("patches");
    assert_eq!(patches.len(), 24, "{check}");
    assert_eq!(patches[0]["name"], "dark skin");
    assert_eq!(patches[18]["name"], "white 9.5");
    let mean = |i: usize, c: usize| patches[i]["mean"][c].as_f64().expect("a mean");
    // Red reads red, blue reads blue: the channels are where they belong.
    assert!(mean(14, 0) > 2.0 * mean(14, 2), "red: {}", patches[14]);
    assert!(mean(12, 2) > 2.0 * mean(12, 0), "blue: {}", patches[12]);
    assert!(mean(18, 1) > 4.0 * mean(23, 1), "white and black: {check}");
    s.shutdown().await;
}

/// A rig with an axis without homing: a resume asks the operator to
/// confirm its reference, since no homing can restore it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resume_on_an_axis_without_homing_needs_the_reference_confirmed() {
    let dir = tempfile::tempdir().expect("tempdir");
    let text = std::fs::read_to_string(common::repo_file("rig-profiles/msra-btf-mdf.toml"))
        .expect("profile");
    let from = "[devices.turntable]\nkind = \"axis\"\n";
    assert!(text.contains(from), "fixture drifted");
    let profile = dir.path().join("msra-no-homing.toml");
    std::fs::write(
        &profile,
        text.replacen(from, &format!("{from}homing = false\n"), 1),
    )
    .expect("write profile");
    let data = dir.path().join("data");
    let mut s = start_with(&data, 50.0, profile.to_str(), true).await;
    let (_, rig) = s.get("/api/v1/rig").await;
    let turntable = rig["devices"]
        .as_array()
        .and_then(|d| d.iter().find(|d| d["name"] == "turntable"))
        .expect("turntable");
    assert_eq!(turntable["homing"], false, "{turntable}");

    let plan = json!({"name": "few", "directions": [
        {"theta_deg": 30.0, "phi_deg": 0.0}, {"theta_deg": 45.0, "phi_deg": 90.0},
        {"theta_deg": 60.0, "phi_deg": 180.0}]});
    let (status, v) = s
        .post("/api/v1/runs", Some(run_body("confirm", plan)))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    s.wait_run(&id, "a step", |v| {
        v["state"] == "running" && v["steps_done"].as_u64() > Some(0)
    })
    .await;
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/pause"), None).await;
    assert_eq!(status, 202, "{v}");
    s.wait_state(&id, "paused").await;

    let (status, v) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 409, "{v}");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("turntable has no homing")
                && d.contains("?reference_confirmed=true")),
        "{v}"
    );
    let (_, run) = s.get(&format!("/api/v1/runs/{id}")).await;
    assert_eq!(run["state"], "paused", "nothing resumed: {run}");
    let (status, v) = s
        .post(
            &format!("/api/v1/runs/{id}/resume?reference_confirmed=maybe"),
            None,
        )
        .await;
    assert_eq!(status, 400, "{v}");
    let (status, v) = s
        .post(
            &format!("/api/v1/runs/{id}/resume?reference_confirmed=true"),
            None,
        )
        .await;
    assert_eq!(status, 202, "{v}");
    s.wait_ended(&id, "completed").await;
    s.shutdown().await;
}
