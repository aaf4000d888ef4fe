//! Manual control for bring-up, through the daemon's API on the simulated
//! Bonn rig: home and jog an axis, take a pose, switch the lamp, take a
//! test frame; bad input moves nothing; the emergency stop covers it; and
//! while a run is active every manual action answers 409.

use crate::common;

use common::http::{run_body, start_in, start_with};
use serde_json::json;

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
        (Some(320), Some(240)),
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
