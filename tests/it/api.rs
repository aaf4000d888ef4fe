//! The HTTP API, in process: every route with good and bad input, with and
//! without the token; racing starts; the queue; events with replay; the
//! OpenAPI spec walked route by route; graceful shutdown and resume.

use crate::common;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use common::assert_complete_run;
use common::http::{run_body, small_plan, start_in, Srv, SseReader};
use serde_json::{json, Value};

const FAST: f64 = 20_000.0;

async fn srv(speed: f64) -> (tempfile::TempDir, Srv) {
    let dir = tempfile::tempdir().expect("tempdir");
    let s = start_in(dir.path(), speed).await;
    (dir, s)
}

/// Starts a run and returns its id.
async fn start_run(s: &Srv, body: Value) -> String {
    let (status, v) = s.post("/api/v1/runs", Some(body)).await;
    assert_eq!(status, 201, "start run: {v}");
    v["id"].as_str().expect("id").to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_static_files_and_docs() {
    let (_d, mut s) = srv(FAST).await;
    let (status, v) = s.get("/api/v1/health").await;
    assert_eq!(status, 200);
    assert_eq!(v["ok"], true);
    assert_eq!(v["profile"], "bonn-gonioreflectometer");
    assert_eq!(v["sim"], true);
    assert_eq!(v["version"], env!("CARGO_PKG_VERSION"));
    for (path, ct) in [
        ("/", "text/html"),
        ("/app.js", "text/javascript"),
        ("/style.css", "text/css"),
        ("/api/docs/", "text/html"),
        ("/api/v1/openapi.json", "application/json"),
    ] {
        let (status, got, body) = s.get_bytes(path).await;
        assert_eq!(status, 200, "{path}");
        assert!(got.starts_with(ct), "{path}: {got}");
        assert!(!body.is_empty(), "{path}");
    }
    let (status, v) = s.get("/api/v1/nothing-here").await;
    assert_eq!(status, 404);
    assert_eq!(v["error"], "not_found");
    let (status, v) = s
        .send("DELETE", "/api/v1/rig", None, Some(&s.token.clone()))
        .await;
    assert_eq!(status, 405);
    assert_eq!(v["error"], "method_not_allowed");
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rig_and_plans() {
    let (_d, mut s) = srv(FAST).await;
    let (status, rig) = s.get("/api/v1/rig").await;
    assert_eq!(status, 200);
    assert_eq!(rig["profile"], "bonn-gonioreflectometer");
    assert_eq!(rig["state"], "idle");
    assert_eq!(rig["active_run"], Value::Null);
    let devices = rig["devices"].as_array().expect("devices");
    let kinds: BTreeSet<&str> = devices.iter().filter_map(|d| d["kind"].as_str()).collect();
    for k in ["axis", "arm", "lamp", "camera"] {
        assert!(kinds.contains(k), "no {k} in {kinds:?}");
    }
    for d in devices {
        assert_eq!(d["connected"], true);
        assert_eq!(d["busy"], false);
    }
    // Bring-up: every device connected and reported, nothing moved.
    let (status, check) = s.get("/api/v1/rig/check").await;
    assert_eq!(status, 200, "{check}");
    assert_eq!(check["usable"], true, "{check}");
    let verdicts = check["devices"].as_array().expect("verdicts");
    assert_eq!(verdicts.len(), devices.len());
    let rail = verdicts
        .iter()
        .find(|d| d["device"] == "rail")
        .expect("the rail's verdict");
    assert!(
        rail["detail"]
            .as_str()
            .is_some_and(|t| t.contains("GRBL 1.1h") && t.contains("homes with `$H`")),
        "{rail}"
    );
    let cam = devices
        .iter()
        .find(|d| d["kind"] == "camera")
        .expect("camera");
    assert!(cam["camera"]["exposure_s"]
        .as_f64()
        .is_some_and(|e| e > 0.0));
    assert_eq!(rig["lamps"]["hmi"], false);

    // The plans are solved in the background: the list answers at once,
    // each entry saying whether it is ready, and fills in.
    let (status, v) = s.get("/api/v1/plans").await;
    assert_eq!(status, 200);
    let listed = v["plans"].as_array().expect("plans");
    assert!(listed.iter().all(|p| p["ready"].is_boolean()), "{v}");
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    let v = loop {
        let (status, v) = s.get("/api/v1/plans").await;
        assert_eq!(status, 200);
        let all_ready = v["plans"]
            .as_array()
            .is_some_and(|ps| ps.iter().all(|p| p["ready"] == true));
        if all_ready {
            break v;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "plans never ready: {v}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let plans = v["plans"].as_array().expect("plans");
    let h1 = plans.iter().find(|p| p["name"] == "h1").expect("h1");
    assert_eq!(h1["fits"], true);
    assert_eq!(h1["steps_total"], 6561);
    assert_eq!(h1["infeasible_total"], 81);
    let est = h1["estimated_physical_s"].as_f64().expect("estimate");
    assert!((30_000.0..40_000.0).contains(&est), "{est}");
    // Its raw data: 6561 images of one camera.
    let image = h1["image_bytes"].as_u64().expect("image bytes");
    assert!(image > 1_000_000, "{h1}");
    assert_eq!(h1["raw_bytes"].as_u64(), Some(6561 * image));
    // What it costs under each exposure policy: the profile's own (single)
    // first and as above, brackets of 2 and 3 exposures more in time and
    // data, `auto` as a lower bound.
    let costs = h1["exposure_estimates"].as_array().expect("estimates");
    let named: Vec<String> = costs
        .iter()
        .map(|e| {
            let p = &e["policy"];
            format!(
                "{}{}",
                p["policy"].as_str().expect("policy"),
                p["exposures_s"].as_array().map_or(0, Vec::len)
            )
        })
        .collect();
    assert_eq!(named, ["single0", "auto0", "brackets2", "brackets3"]);
    assert_eq!(costs[0]["profile_default"], true);
    assert_eq!(costs[0]["estimated_physical_s"].as_f64(), Some(est));
    assert_eq!(costs[1]["estimated_physical_s"].as_f64(), Some(est));
    assert_eq!(costs[1]["lower_bound"], true);
    let (two, three) = (
        costs[2]["estimated_physical_s"].as_f64().expect("two"),
        costs[3]["estimated_physical_s"].as_f64().expect("three"),
    );
    assert!(est * 1.5 < two && two < three, "{est} {two} {three}");
    assert_eq!(costs[3]["raw_bytes"].as_u64(), Some(3 * 6561 * image));
    let grid = plans
        .iter()
        .find(|p| p["name"] == "grid12x8")
        .expect("grid");
    assert_eq!(grid["fits"], false);
    assert!(grid["error"].as_str().is_some_and(|e| e.contains("arcs")));

    let (status, v) = s.get("/api/v1/plans/h2").await;
    assert_eq!(status, 200);
    let steps = v["steps"].as_array().expect("steps");
    assert_eq!(steps.len(), 6561);
    assert_eq!(v["steps_total"], 6561);
    assert_eq!(steps[0]["index"], 0);
    assert!(steps[0]["setpoints"]["axes"].is_object());
    assert_eq!(steps.iter().filter(|s| s["feasible"] == false).count(), 81);
    let (status, v) = s.get("/api/v1/plans/grid12x8").await;
    assert_eq!(status, 422, "{v}");
    for bad in ["nope", "..%2F..%2Fetc%2Fpasswd", "h1.json"] {
        let (status, v) = s.get(&format!("/api/v1/plans/{bad}")).await;
        assert_eq!(status, 404, "{bad}: {v}");
        assert_eq!(v["error"], "not_found");
    }
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutating_routes_need_the_token() {
    let (dir, mut s) = srv(FAST).await;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(dir.path().join("token"))
            .expect("token file")
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);
    }
    let body = run_body("t", small_plan(2));
    let routes = [
        ("POST", "/api/v1/runs", Some(body.clone())),
        ("POST", "/api/v1/queue", Some(body.clone())),
        ("DELETE", "/api/v1/queue/q1", None),
        ("POST", "/api/v1/runs/x/pause", None),
        ("POST", "/api/v1/runs/x/resume", None),
        ("POST", "/api/v1/runs/x/abort", None),
        ("POST", "/api/v1/estop", None),
    ];
    for (method, path, body) in &routes {
        for token in [None, Some("wrong-token-wrong-token")] {
            let (status, v) = s.send(method, path, body.clone(), token).await;
            assert_eq!(status, 401, "{method} {path} with {token:?}: {v}");
            assert_eq!(v["error"], "unauthorized");
            assert!(v["detail"].as_str().is_some_and(|d| !d.is_empty()));
        }
    }
    // Nothing happened.
    let (_, runs) = s.get("/api/v1/runs").await;
    assert_eq!(runs["runs"].as_array().map(Vec::len), Some(0));
    let (_, q) = s.get("/api/v1/queue").await;
    assert_eq!(q["items"].as_array().map(Vec::len), Some(0));
    // A malformed Authorization header is no token either.
    let r = s
        .client
        .post(s.url("/api/v1/estop"))
        .header("Authorization", "Basic Zm9vOmJhcg==")
        .send()
        .await
        .expect("post");
    assert_eq!(r.status().as_u16(), 401);
    // With the token it works.
    let (status, v) = s.post("/api/v1/estop", None).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["run"], Value::Null);
    s.shutdown().await;

    // The same token is read back at the next start; a token file wins.
    let s2 = start_in(dir.path(), FAST).await;
    assert_eq!(s2.token, s.token);
    let mut s2 = s2;
    s2.shutdown().await;
    let tf = dir.path().join("my-token");
    std::fs::write(&tf, "0123456789abcdef0123\n").expect("write token");
    let mut config = rigd::server::ServerConfig::new(dir.path());
    config.listen = "127.0.0.1:0".parse().expect("addr");
    config.token_file = Some(tf);
    let (_, h) = rigd::server::start(config).await.expect("start");
    assert_eq!(h.token.secret(), "0123456789abcdef0123");
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_bodies_are_json_errors() {
    let (_d, mut s) = srv(FAST).await;
    let t = s.token.clone();
    let post_raw = |body: Vec<u8>, ct: Option<&'static str>| {
        let mut req = s
            .client
            .post(s.url("/api/v1/runs"))
            .bearer_auth(&t)
            .body(body);
        if let Some(ct) = ct {
            req = req.header("content-type", ct);
        }
        async move {
            let r = req.send().await.expect("post");
            let status = r.status().as_u16();
            (status, r.json::<Value>().await.unwrap_or(Value::Null))
        }
    };
    let json_ct = Some("application/json");
    for (body, want) in [
        (&b"{not json"[..], 400),
        (b"", 400),
        (b"{\"sample\": \"a\", \"plan\"", 400),
        (b"{\"sample\": 1, \"plan\": \"h1\"}", 422),
        (b"{\"plan\": \"h1\"}", 422),
        (b"{\"sample\": \"a\"}", 422),
        (b"{\"sample\": \"a\", \"plan\": \"h1\", \"extra\": 1}", 422),
        (b"{\"sample\": \"a\", \"plan\": 5}", 422),
    ] {
        let (status, v) = post_raw(body.to_vec(), json_ct).await;
        assert_eq!(status, want, "{}: {v}", String::from_utf8_lossy(body));
        assert!(v["error"].is_string() && v["detail"].is_string(), "{v}");
    }
    let (status, v) = post_raw(b"{\"sample\":\"a\",\"plan\":\"h1\"}".to_vec(), None).await;
    assert_eq!(status, 415, "{v}");
    assert_eq!(v["error"], "unsupported_media_type");
    let big = format!("{{\"sample\":\"{}\",\"plan\":\"h1\"}}", "a".repeat(70_000));
    let (status, v) = post_raw(big.into_bytes(), json_ct).await;
    assert_eq!(status, 413, "{v}");
    assert_eq!(v["error"], "payload_too_large");
    // Well-formed but invalid: 422 with a reason, and no run directory made.
    for body in [
        json!({"sample": "", "plan": "h1"}),
        json!({"sample": "  ", "plan": "h1"}),
        json!({"sample": "a".repeat(200), "plan": "h1"}),
        json!({"sample": "a\u{7}b", "plan": "h1"}),
        json!({"sample": "a", "plan": "h9"}),
        json!({"sample": "a", "plan": "/etc/passwd"}),
        json!({"sample": "a", "plan": "../plans/x.json"}),
        json!({"sample": "a", "plan": "grid12x8"}),
        json!({"sample": "a", "plan": "h1", "exposure_s": -1.0}),
        json!({"sample": "a", "plan": "h1", "exposure_s": 0.0}),
        json!({"sample": "a", "plan": "h1", "exposure_s": 1e9}),
        json!({"sample": "a", "plan": "h1",
               "exposure_policy": {"policy": "brackets", "exposures_s": [0.1, 0.2]}}),
        json!({"sample": "a", "plan": "h1",
               "exposure_policy": {"policy": "brackets", "exposures_s": []}}),
        json!({"sample": "a", "plan": "h1", "exposure_policy": {"policy": "auto", "threshold": 0.0}}),
        json!({"sample": "a", "plan": "h1", "exposure_policy": {"policy": "auto", "factor": 1.0}}),
        json!({"sample": "a", "plan": "h1", "frame_size": [0, 10]}),
        json!({"sample": "a", "plan": "h1", "frame_size": [100000, 10]}),
        json!({"sample": "a", "plan": {"directions": []}}),
        json!({"sample": "a", "plan": {"directions": [{"theta_deg": 95.0, "phi_deg": 0.0}]}}),
        json!({"sample": "a", "plan": {"lights": [{"theta_deg": 5.0, "phi_deg": 0.0}]}}),
    ] {
        let (status, v) = s.post("/api/v1/runs", Some(body.clone())).await;
        assert_eq!(status, 422, "{body}: {v}");
        assert_eq!(v["error"], "invalid", "{v}");
        let (status, v) = s.post("/api/v1/queue", Some(body.clone())).await;
        assert_eq!(status, 422, "queue {body}: {v}");
    }
    let runs = std::fs::read_dir(s.data.join("runs"))
        .expect("runs dir")
        .count();
    assert_eq!(runs, 0);
    // Bad Last-Event-ID.
    let (status, _) = SseReader::connect(&s.client, &s.url("/api/v1/events"), None).await;
    assert_eq!(status, 200);
    let r = s
        .client
        .get(s.url("/api/v1/events"))
        .header("Last-Event-ID", "abc")
        .send()
        .await
        .expect("get");
    assert_eq!(r.status().as_u16(), 400);
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_completes_with_steps_frames_and_manifest() {
    let (_d, mut s) = srv(FAST).await;
    let (status, v) = s
        .post(
            "/api/v1/runs",
            Some(run_body("Felt #3 / blue", small_plan(3))),
        )
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    // The id is made by the server and safe on a filesystem.
    assert!(
        id.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'),
        "{id}"
    );
    assert!(id.contains("Felt__3___blue-mini"), "{id}");
    assert_eq!(v["steps_total"], 9);
    assert_eq!(v["active"], true);
    assert_eq!(v["operator"], "tester");
    let done = s.wait_ended(&id, "completed").await;
    assert_eq!(done["steps_done"], 9);
    assert_eq!(done["active"], false);
    assert_eq!(done["resumable"], false);
    assert!(done["finished_at"].is_string());
    assert!(done["physical_s"].as_f64().is_some_and(|t| t > 0.0));
    assert_complete_run(&s.data.join("runs").join(&id), 9);

    let (status, list) = s.get("/api/v1/runs").await;
    assert_eq!(status, 200);
    assert_eq!(list["runs"][0]["id"], id.as_str());
    assert_eq!(list["active"], Value::Null);

    let (status, steps) = s.get(&format!("/api/v1/runs/{id}/steps")).await;
    assert_eq!(status, 200);
    assert_eq!(steps["steps_total"], 9);
    assert_eq!(steps["steps_done"], 9);
    let st = steps["steps"].as_array().expect("steps");
    assert!(st
        .iter()
        .all(|s| s["done"] == true && s["light"]["theta_deg"].is_number()));
    assert!(st.iter().all(|s| s["achieved_view"]["phi_deg"].is_number()));

    let (status, m) = s.get(&format!("/api/v1/runs/{id}/manifest")).await;
    assert_eq!(status, 200);
    assert_eq!(m["state"], "completed");
    assert_eq!(m["frames_written"], 9);

    // The simulated PTP camera's DNG, served as stored.
    let (status, ct, dng) = s.get_bytes(&format!("/api/v1/runs/{id}/frames/4")).await;
    assert_eq!((status, ct.as_str()), (200, "image/x-adobe-dng"));
    let on_disk =
        std::fs::read(s.data.join("runs").join(&id).join("frames/000004.dng")).expect("frame");
    assert_eq!(dng, on_disk);
    let img = rigd::rig::camera_file::decode(&dng).expect("decodes");
    assert_eq!((img.width, img.height), (16, 12));
    let (status, ct, prev) = s
        .get_bytes(&format!("/api/v1/runs/{id}/frames/4/preview"))
        .await;
    assert_eq!((status, ct.as_str()), (200, "image/png"));
    let dec = png::Decoder::new(&prev[..])
        .read_info()
        .expect("preview png");
    assert_eq!(dec.info().bit_depth, png::BitDepth::Eight);
    assert_eq!((dec.info().width, dec.info().height), (16, 12));

    for (path, want) in [
        (format!("/api/v1/runs/{id}/frames/9"), 404),
        (format!("/api/v1/runs/{id}/frames/999999999"), 404),
        (
            format!("/api/v1/runs/{id}/frames/99999999999999999999"),
            400,
        ),
        (format!("/api/v1/runs/{id}/frames/-1"), 400),
        (format!("/api/v1/runs/{id}/frames/1.5"), 400),
        (format!("/api/v1/runs/{id}/frames/0x1"), 400),
        (format!("/api/v1/runs/{id}/frames/..%2F..%2Frun.json"), 400),
        // The client resolves `%2e%2e` itself: no such route.
        (format!("/api/v1/runs/{id}/frames/%2e%2e/preview"), 404),
        ("/api/v1/runs/..%2F..%2Ftoken/frames/0".to_string(), 404),
        ("/api/v1/runs/../token".to_string(), 404),
        ("/api/v1/runs/%2e%2e/frames/0".to_string(), 404),
        ("/api/v1/runs/nope".to_string(), 404),
        ("/api/v1/runs/%FF%FE".to_string(), 400),
        (format!("/api/v1/runs/{id}/frames/%FF"), 400),
        ("/api/v1/runs/nope/steps".to_string(), 404),
        ("/api/v1/runs/nope/manifest".to_string(), 404),
        ("/api/v1/runs/nope/frames/0/preview".to_string(), 404),
    ] {
        let (status, v) = s.get(&path).await;
        assert_eq!(status, want, "{path}: {v}");
        assert!(v["error"].is_string(), "{path}: {v}");
    }
    // Commands on a finished run: 409; on no run: 404.
    for c in ["pause", "resume", "abort"] {
        let (status, v) = s.post(&format!("/api/v1/runs/{id}/{c}"), None).await;
        assert_eq!(status, 409, "{c}: {v}");
        let (status, _) = s.post(&format!("/api/v1/runs/nope/{c}"), None).await;
        assert_eq!(status, 404, "{c}");
    }
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn racing_clients_exactly_one_wins() {
    let (_d, mut s) = srv(200.0).await;
    let bodies: Vec<Value> = (0..6)
        .map(|i| run_body(&format!("race{i}"), json!("h1")))
        .collect();
    let futs = bodies.into_iter().map(|b| {
        let client = reqwest::Client::new();
        let url = s.url("/api/v1/runs");
        let token = s.token.clone();
        async move {
            let r = client
                .post(url)
                .bearer_auth(token)
                .json(&b)
                .send()
                .await
                .expect("post");
            let status = r.status().as_u16();
            (status, r.json::<Value>().await.unwrap_or(Value::Null))
        }
    });
    let results = futures::future::join_all(futs).await;
    let winners: Vec<&Value> = results
        .iter()
        .filter(|(s, _)| *s == 201)
        .map(|(_, v)| v)
        .collect();
    assert_eq!(winners.len(), 1, "{results:?}");
    let id = winners[0]["id"].as_str().expect("id").to_string();
    for (status, v) in results.iter().filter(|(s, _)| *s != 201) {
        assert_eq!(*status, 409, "{v}");
        assert_eq!(v["error"], "conflict");
        assert!(v["detail"].as_str().is_some_and(|d| d.contains(&id)), "{v}");
    }
    assert_eq!(
        std::fs::read_dir(s.data.join("runs"))
            .expect("runs")
            .count(),
        1
    );
    let (_, rig) = s.get("/api/v1/rig").await;
    assert_eq!(rig["active_run"], id.as_str());
    let (status, _) = s.post(&format!("/api/v1/runs/{id}/abort"), None).await;
    assert_eq!(status, 202);
    let v = s.wait_ended(&id, "aborted").await;
    assert_eq!(v["active"], false);
    s.shutdown().await;
}

/// A command sent again before the engine has acted on it (a client
/// repeating itself) is on its way already: it is answered as sent, never
/// queued twice, so the engine's command queue never fills (which answered
/// 503 to a fuzzer's repeated pauses).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_command_repeated_before_the_engine_acts_is_sent_once() {
    let (_d, mut s) = srv(20.0).await;
    let id = start_run(&s, run_body("p", small_plan(9))).await;
    s.wait_run(&id, "running", |v| v["state"] == "running")
        .await;
    let pause = format!("/api/v1/runs/{id}/pause");
    let answers = futures::future::join_all((0..40).map(|_| s.post(&pause, None))).await;
    let statuses: Vec<u16> = answers.iter().map(|(status, _)| *status).collect();
    assert!(
        statuses.iter().all(|s| *s == 202 || *s == 409),
        "{statuses:?}"
    );
    assert!(statuses.contains(&202), "{statuses:?}");
    // Pauses and aborts alternating, as fast as a client can: after an
    // abort, nothing else goes to the engine.
    let abort = format!("/api/v1/runs/{id}/abort");
    let answers = futures::future::join_all((0..40).map(|i| {
        let path = if i % 2 == 0 { &abort } else { &pause };
        s.post(path, None)
    }))
    .await;
    let statuses: Vec<u16> = answers.iter().map(|(status, _)| *status).collect();
    assert!(
        statuses.iter().all(|s| *s == 202 || *s == 200 || *s == 409),
        "{statuses:?}"
    );
    s.wait_ended(&id, "aborted").await;
    s.shutdown().await;
}

/// A script that sees `completed` starts its next run at once: the run
/// that has reported its final state no longer holds the rig, although
/// its engine may still be closing it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_next_run_starts_as_soon_as_the_last_is_seen_completed() {
    let (_d, mut s) = srv(FAST).await;
    // Frames large enough that closing the run (its manifest hashes
    // every frame) takes a while after its final state.
    let body = || {
        let mut b = run_body("a", small_plan(3));
        b["frame_size"] = json!([640, 480]);
        b
    };
    let mut id = start_run(&s, body()).await;
    for round in 0..4 {
        // Polled as fast as a client can, to meet the run the moment its
        // state turns final.
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let (status, v) = s.get(&format!("/api/v1/runs/{id}")).await;
            assert_eq!(status, 200, "{v}");
            if v["state"] == "completed" {
                break;
            }
            assert!(Instant::now() < deadline, "run {id} did not complete: {v}");
        }
        let (status, v) = s.post("/api/v1/runs", Some(body())).await;
        assert_eq!(status, 201, "round {round}: the next run after {id}: {v}");
        id = v["id"].as_str().expect("id").to_string();
    }
    s.wait_ended(&id, "completed").await;
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pause_resume_abort_and_estop() {
    let (_d, mut s) = srv(300.0).await;
    let id = start_run(&s, run_body("p", small_plan(9))).await;
    s.wait_run(&id, "a step", |v| {
        v["state"] == "running" && v["steps_done"].as_u64() > Some(0)
    })
    .await;
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/pause"), None).await;
    assert_eq!(status, 202, "{v}");
    assert_eq!(v["sent_to_engine"], true);
    let paused = s.wait_state(&id, "paused").await;
    assert_eq!(paused["reason"], "paused by operator");
    assert_eq!(
        paused["last_error"],
        Value::Null,
        "an operator's pause is no error"
    );
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/pause"), None).await;
    assert_eq!(status, 409, "{v}");
    let (status, rig) = s.get("/api/v1/rig").await;
    assert_eq!(status, 200);
    assert_eq!(rig["state"], "paused");
    // The paused run holds the rig: no check now.
    let (status, v) = s.get("/api/v1/rig/check").await;
    assert_eq!(status, 409, "{v}");
    assert!(v["detail"].as_str().is_some_and(|d| d.contains(&id)), "{v}");
    assert!(rig["devices"]
        .as_array()
        .expect("devices")
        .iter()
        .any(|d| d["position_deg"].is_number()));
    let (status, _) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 202);
    s.wait_state(&id, "running").await;
    // Another start while active: 409 naming it.
    let (status, v) = s
        .post("/api/v1/runs", Some(run_body("other", small_plan(2))))
        .await;
    assert_eq!(status, 409);
    assert!(v["detail"].as_str().is_some_and(|d| d.contains(&id)));
    // Emergency stop: the run pauses with the stop's reason, resumes after re-homing.
    let (status, v) = s.post("/api/v1/estop", None).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["run"], id.as_str());
    let stopped = s.wait_state(&id, "paused").await;
    assert!(
        stopped["reason"]
            .as_str()
            .is_some_and(|r| r.contains("emergency stop")),
        "{stopped}"
    );
    let (status, _) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 202);
    let v = s
        .wait_run(&id, "running after estop", |v| v["state"] == "running")
        .await;
    assert_eq!(v["reason"], Value::Null);
    assert!(
        v["last_error"]
            .as_str()
            .is_some_and(|r| r.contains("emergency stop")),
        "{v}"
    );
    let (status, _) = s.post(&format!("/api/v1/runs/{id}/abort"), None).await;
    assert_eq!(status, 202);
    let v = s.wait_state(&id, "aborted").await;
    assert_eq!(v["resumable"], false);
    let (status, m) = s.get(&format!("/api/v1/runs/{id}/manifest")).await;
    assert_eq!(status, 200);
    assert_eq!(m["state"], "aborted");
    for c in ["resume", "abort", "pause"] {
        let (status, v) = s.post(&format!("/api/v1/runs/{id}/{c}"), None).await;
        assert_eq!(status, 409, "{c} after abort: {v}");
    }
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_queue_runs_in_order_and_persists() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut s = start_in(dir.path(), 1000.0).await;
    let first = start_run(&s, run_body("first", small_plan(4))).await;
    let (status, a) = s
        .post("/api/v1/queue", Some(run_body("second", small_plan(2))))
        .await;
    assert_eq!(status, 201, "{a}");
    assert_eq!(a["started_run"], Value::Null);
    let (status, b) = s
        .post("/api/v1/queue", Some(run_body("third", small_plan(2))))
        .await;
    assert_eq!(status, 201);
    let (status, c) = s
        .post("/api/v1/queue", Some(run_body("dropped", small_plan(2))))
        .await;
    assert_eq!(status, 201);
    let cid = c["item"]["id"].as_str().expect("id").to_string();
    let (_, q) = s.get("/api/v1/queue").await;
    let ids: Vec<&str> = q["items"]
        .as_array()
        .expect("items")
        .iter()
        .filter_map(|i| i["id"].as_str())
        .collect();
    assert_eq!(
        ids,
        vec![
            a["item"]["id"].as_str().unwrap_or(""),
            b["item"]["id"].as_str().unwrap_or(""),
            cid.as_str()
        ]
    );
    let on_disk: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("queue.json")).expect("queue.json"))
            .expect("json");
    assert_eq!(on_disk["items"].as_array().map(Vec::len), Some(3));
    let (status, _) = s
        .send(
            "DELETE",
            &format!("/api/v1/queue/{cid}"),
            None,
            Some(&s.token.clone()),
        )
        .await;
    assert_eq!(status, 204);
    let (status, v) = s
        .send(
            "DELETE",
            &format!("/api/v1/queue/{cid}"),
            None,
            Some(&s.token.clone()),
        )
        .await;
    assert_eq!(status, 404, "{v}");
    let (status, _) = s
        .send(
            "DELETE",
            "/api/v1/queue/..%2F..%2Ftoken",
            None,
            Some(&s.token.clone()),
        )
        .await;
    assert_eq!(status, 404);
    // Everything runs, in order, one at a time.
    s.wait_state(&first, "completed").await;
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        let (_, list) = s.get("/api/v1/runs").await;
        let runs = list["runs"].as_array().cloned().unwrap_or_default();
        let done = runs.iter().filter(|r| r["state"] == "completed").count();
        if runs.len() == 3 && done == 3 {
            let mut samples: Vec<(String, String)> = runs
                .iter()
                .map(|r| {
                    (
                        r["started_at"].as_str().unwrap_or("").to_string()
                            + r["id"].as_str().unwrap_or(""),
                        r["sample"].as_str().unwrap_or("").to_string(),
                    )
                })
                .collect();
            samples.sort();
            let order: Vec<&str> = samples.iter().map(|(_, s)| s.as_str()).collect();
            assert_eq!(order, vec!["first", "second", "third"]);
            for r in &runs {
                let n = r["steps_total"].as_u64().unwrap_or(0) as usize;
                assert_complete_run(
                    &dir.path().join("runs").join(r["id"].as_str().unwrap_or("")),
                    n,
                );
                // The final state event comes a moment before the engine
                // lets go of the rig; "starts at once" below needs it free.
                s.wait_ended(r["id"].as_str().unwrap_or(""), "completed")
                    .await;
            }
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "queue did not drain: {list}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let (_, q) = s.get("/api/v1/queue").await;
    assert_eq!(q["items"].as_array().map(Vec::len), Some(0));
    // A queued item on an idle rig starts at once, and the answer says
    // which run it became; items queued together wait their turn.
    let (a, b, c) = tokio::join!(
        s.post("/api/v1/queue", Some(run_body("now-a", small_plan(2)))),
        s.post("/api/v1/queue", Some(run_body("now-b", small_plan(2)))),
        s.post("/api/v1/queue", Some(run_body("now-c", small_plan(2)))),
    );
    let answers = [a, b, c];
    let mut started = Vec::new();
    for (status, v) in &answers {
        assert_eq!(*status, 201, "{v}");
        if !v["started_run"].is_null() {
            assert_eq!(
                v["started_run"]["sample"], v["item"]["request"]["sample"],
                "an answer names another item's run: {v}"
            );
            started.push(v["started_run"]["id"].as_str().unwrap_or("").to_string());
        }
    }
    assert!(!started.is_empty(), "none started at once: {answers:?}");
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        let (_, list) = s.get("/api/v1/runs").await;
        let runs = list["runs"].as_array().cloned().unwrap_or_default();
        let now: Vec<&Value> = runs
            .iter()
            .filter(|r| r["sample"].as_str().is_some_and(|x| x.starts_with("now-")))
            .collect();
        if now.len() == 3 && now.iter().all(|r| r["state"] == "completed") {
            for id in &started {
                assert!(now.iter().any(|r| r["id"] == id.as_str()), "{list}");
            }
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the items queued together did not all run once: {list}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let (_, q) = s.get("/api/v1/queue").await;
    assert_eq!(q["items"].as_array().map(Vec::len), Some(0));
    s.shutdown().await;

    // Queue persists across restarts: add while a run is active, stop, start again.
    let mut s = start_in(dir.path(), 100.0).await;
    let busy = start_run(&s, run_body("busy", json!("h1"))).await;
    let (status, _) = s
        .post("/api/v1/queue", Some(run_body("later", small_plan(2))))
        .await;
    assert_eq!(status, 201);
    s.shutdown().await;
    let mut s = start_in(dir.path(), FAST).await;
    let (_, q) = s.get("/api/v1/queue").await;
    assert_eq!(q["items"][0]["request"]["sample"], "later");
    let (_, v) = s.get(&format!("/api/v1/runs/{busy}")).await;
    assert_eq!(v["state"], "paused");
    assert_eq!(v["resumable"], true);
    // The queue waits while a run is left paused; aborting it lets the queue go on.
    let (status, v) = s.post(&format!("/api/v1/runs/{busy}/abort"), None).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["sent_to_engine"], false);
    assert_eq!(v["run"]["state"], "aborted");
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        let (_, list) = s.get("/api/v1/runs").await;
        if list["runs"].as_array().is_some_and(|r| {
            r.iter()
                .any(|r| r["sample"] == "later" && r["state"] == "completed")
        }) {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "queued run after restart did not run: {list}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_carry_run_ids_and_replay() {
    let (_d, mut s) = srv(FAST).await;
    let (status, sse) = SseReader::connect(&s.client, &s.url("/api/v1/events"), None).await;
    assert_eq!(status, 200);
    let mut sse = sse.expect("stream");
    let id = start_run(&s, run_body("ev", small_plan(2))).await;
    let mut seen = Vec::new();
    let mut last = 0;
    while let Some((eid, ev)) = sse.next(Duration::from_secs(20)).await {
        let eid = eid.expect("every event has an id");
        assert_eq!(ev["id"].as_u64(), Some(eid));
        assert!(eid > last, "ids increase");
        last = eid;
        let done = ev["kind"] == "run_ended";
        seen.push(ev);
        if done {
            break;
        }
    }
    let kinds: Vec<&str> = seen.iter().filter_map(|e| e["kind"].as_str()).collect();
    assert_eq!(kinds.first(), Some(&"run_created"), "{kinds:?}");
    assert_eq!(kinds.last(), Some(&"run_ended"));
    let engine: Vec<&Value> = seen.iter().filter(|e| e["kind"] == "engine").collect();
    assert!(engine.iter().all(|e| e["run"] == id.as_str()));
    let steps = engine
        .iter()
        .filter(|e| e["event"]["type"] == "step")
        .count();
    assert_eq!(steps, 4);
    let states: Vec<&str> = engine
        .iter()
        .filter(|e| e["event"]["type"] == "state")
        .filter_map(|e| e["event"]["to"].as_str())
        .collect();
    assert_eq!(states, vec!["preparing", "running", "completed"]);
    // Replay after an id: exactly the later events, in order.
    let from = seen[2]["id"].as_u64().expect("id");
    let (_, replay) = SseReader::connect(&s.client, &s.url("/api/v1/events"), Some(from)).await;
    let mut replay = replay.expect("stream");
    let mut got = Vec::new();
    while let Some((eid, _)) = replay.next(Duration::from_millis(500)).await {
        got.push(eid.expect("id"));
        if eid == Some(last) {
            break;
        }
    }
    let want: Vec<u64> = ((from + 1)..=last).collect();
    assert_eq!(got, want);
    // The queue and the stop are daemon events too.
    let (status, _) = s.post("/api/v1/estop", None).await;
    assert_eq!(status, 200);
    let (eid, ev) = replay
        .next(Duration::from_secs(5))
        .await
        .expect("estop event");
    assert_eq!(eid, Some(last + 1));
    assert_eq!(ev["kind"], "estop");
    // Shutdown ends the stream.
    s.shutdown().await;
    assert!(replay.next(Duration::from_secs(5)).await.is_none());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn graceful_shutdown_pauses_and_resume_completes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut s = start_in(dir.path(), 400.0).await;
    let id = start_run(&s, run_body("grace", small_plan(7))).await;
    s.wait_run(&id, "some steps", |v| v["steps_done"].as_u64() >= Some(3))
        .await;
    s.shutdown().await;
    let state: Value = serde_json::from_slice(
        &std::fs::read(dir.path().join("runs").join(&id).join("state.json")).expect("state"),
    )
    .expect("json");
    assert_eq!(state["state"], "paused");
    let mut s = start_in(dir.path(), FAST).await;
    let (_, v) = s.get(&format!("/api/v1/runs/{id}")).await;
    assert_eq!(v["state"], "paused");
    assert_eq!(v["resumable"], true);
    assert_eq!(v["active"], false);
    let before = v["steps_done"].as_u64().expect("done");
    assert!((3..49).contains(&before), "{v}");
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["sent_to_engine"], false);
    assert_eq!(v["run"]["active"], true);
    s.wait_state(&id, "completed").await;
    assert_complete_run(&dir.path().join("runs").join(&id), 49);
    s.shutdown().await;
}

/// Fills an OpenAPI path template with real values.
fn fill(path: &str, run: &str, item: &str) -> String {
    path.replace("{id}", run)
        .replace("{index}", "0")
        .replace("{name}", "h1")
        .replace("{item}", item)
        .replace("{kind}", "cloth")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn openapi_spec_validates_and_every_route_answers_as_documented() {
    let (_d, mut s) = srv(FAST).await;
    let (status, spec) = s.get("/api/v1/openapi.json").await;
    assert_eq!(status, 200);
    // Structure: OpenAPI 3, info, paths, and every $ref resolves.
    assert!(spec["openapi"]
        .as_str()
        .is_some_and(|v| v.starts_with("3.")));
    assert!(spec["info"]["title"].is_string() && spec["info"]["version"].is_string());
    let schemas = spec["components"]["schemas"].as_object().expect("schemas");
    fn refs(v: &Value, out: &mut Vec<String>) {
        match v {
            Value::Object(m) => {
                for (k, x) in m {
                    if k == "$ref" {
                        out.extend(x.as_str().map(str::to_string));
                    }
                    refs(x, out);
                }
            }
            Value::Array(a) => a.iter().for_each(|x| refs(x, out)),
            _ => {}
        }
    }
    let mut all = Vec::new();
    refs(&spec, &mut all);
    assert!(!all.is_empty());
    for r in &all {
        let name = r
            .strip_prefix("#/components/schemas/")
            .unwrap_or_else(|| panic!("odd $ref {r}"));
        assert!(schemas.contains_key(name), "dangling $ref {r}");
    }
    assert!(spec["components"]["securitySchemes"]["bearer"].is_object());
    let paths = spec["paths"].as_object().expect("paths");
    let documented: BTreeSet<&str> = paths.keys().map(String::as_str).collect();
    let expected: BTreeSet<&str> = [
        "/api/v1/health",
        "/api/v1/rig",
        "/api/v1/rig/check",
        "/api/v1/rig/manual/home",
        "/api/v1/rig/manual/jog",
        "/api/v1/rig/manual/pose",
        "/api/v1/rig/manual/lamp",
        "/api/v1/rig/manual/frame",
        "/api/v1/rig/manual/holder-check",
        "/api/v1/rig/manual/release",
        "/api/v1/plans",
        "/api/v1/plans/{name}",
        "/api/v1/runs",
        "/api/v1/runs/{id}",
        "/api/v1/runs/{id}/steps",
        "/api/v1/runs/{id}/manifest",
        "/api/v1/runs/{id}/pause",
        "/api/v1/runs/{id}/resume",
        "/api/v1/runs/{id}/abort",
        "/api/v1/runs/{id}/process",
        "/api/v1/runs/{id}/process/cancel",
        "/api/v1/estop",
        "/api/v1/events",
        "/api/v1/runs/{id}/frames/{index}",
        "/api/v1/runs/{id}/frames/{index}/preview",
        "/api/v1/queue",
        "/api/v1/queue/{item}",
        "/api/v1/peers",
        "/api/v1/peers/{name}/pause",
        "/api/v1/peers/{name}/abort",
        "/api/v1/sim/render",
        "/api/v1/sim/scenes",
        "/api/v1/runs/{id}/btf",
        "/api/v1/runs/{id}/btf/data",
        "/api/v1/runs/{id}/btf/mesh/{kind}",
        "/api/v1/runs/{id}/mdf",
        "/api/v1/runs/{id}/mdf/data",
        "/api/v1/tradeoff",
        "/api/v1/tradeoff/choice",
        "/api/v1/tradeoff/figure",
        "/api/v1/tradeoff/plot.svg",
    ]
    .into_iter()
    .collect();
    assert_eq!(documented, expected);

    // A finished run to point the path parameters at, and a queue item.
    let run = start_run(&s, run_body("walk", small_plan(2))).await;
    s.wait_state(&run, "completed").await;
    let mut checked = 0;
    for (path, ops) in paths {
        for (method, op) in ops.as_object().expect("operations") {
            let responses = op["responses"].as_object().expect("responses");
            let codes: BTreeSet<u16> = responses.keys().filter_map(|k| k.parse().ok()).collect();
            let secured = op["security"].as_array().is_some_and(|a| !a.is_empty());
            // A fresh queue item for each DELETE.
            let item = if path.contains("{item}") {
                let long = run_body("q", json!("h1"));
                let blocker = start_run(&s, long).await;
                let (_, v) = s
                    .post("/api/v1/queue", Some(run_body("qi", small_plan(2))))
                    .await;
                let item = v["item"]["id"].as_str().expect("item").to_string();
                let (st, _) = s.post(&format!("/api/v1/runs/{blocker}/abort"), None).await;
                assert_eq!(st, 202);
                s.wait_state(&blocker, "aborted").await;
                item
            } else {
                String::new()
            };
            let url_path = fill(path, &run, &item);
            let body = op
                .get("requestBody")
                .map(|_| run_body("walk2", small_plan(2)));
            if path == "/api/v1/events" {
                let (status, stream) =
                    SseReader::connect(&s.client, &s.url(&url_path), Some(0)).await;
                assert!(
                    codes.contains(&status),
                    "GET {path}: {status} not in {codes:?}"
                );
                let (_, ev) = stream
                    .expect("stream")
                    .next(Duration::from_secs(5))
                    .await
                    .expect("an event");
                assert!(ev["kind"].is_string());
                checked += 1;
                continue;
            }
            let upper = method.to_uppercase();
            let resp = {
                let m = reqwest::Method::from_bytes(upper.as_bytes()).expect("method");
                let mut req = s.client.request(m, s.url(&url_path)).bearer_auth(&s.token);
                if let Some(b) = &body {
                    req = req.json(b);
                }
                req.send().await.expect("request")
            };
            let status = resp.status().as_u16();
            assert!(
                codes.contains(&status),
                "{upper} {path}: {status} not documented ({codes:?})"
            );
            let ct = resp
                .headers()
                .get("content-type")
                .and_then(|v| v.to_str().ok())
                .unwrap_or("")
                .to_string();
            let documented_ct = responses[&status.to_string()]["content"]
                .as_object()
                .map(|c| c.keys().cloned().collect::<Vec<_>>())
                .unwrap_or_default();
            if status != 204 {
                assert!(
                    documented_ct.iter().any(|d| ct.starts_with(d.as_str())),
                    "{upper} {path}: content type {ct} not in {documented_ct:?}"
                );
            }
            if ct.starts_with("application/json") {
                let v: Value = resp.json().await.expect("json");
                if status >= 400 {
                    assert!(v["error"].is_string() && v["detail"].is_string(), "{v}");
                }
            }
            // Secured operations say 401 without the token, and do.
            if secured {
                assert!(codes.contains(&401), "{upper} {path} documents no 401");
                let (st, _) = s.send(&upper, &url_path, body.clone(), None).await;
                assert_eq!(st, 401, "{upper} {path} without token");
            }
            // Every started run is stopped again so the next call finds the rig free.
            if upper == "POST" && (path == "/api/v1/runs" || path == "/api/v1/queue") {
                let (_, list) = s.get("/api/v1/runs").await;
                if let Some(active) = list["active"].as_str() {
                    let active = active.to_string();
                    s.wait_run(&active, "an end", |v| v["active"] == false)
                        .await;
                }
            }
            checked += 1;
        }
    }
    assert_eq!(checked, 46, "operations checked");
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_device_fault_pauses_the_run_and_resume_completes_it() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut config = rigd::server::ServerConfig::new(dir.path());
    config.listen = "127.0.0.1:0".parse().expect("addr");
    config.sim_speed = FAST;
    config.sim_faults = vec!["camera:transfer:3:disconnect".parse().expect("fault")];
    let (addr, handle) = rigd::server::start(config).await.expect("start");
    let mut s = Srv {
        addr,
        base: format!("http://{addr}"),
        token: handle.token.secret().to_string(),
        data: dir.path().to_path_buf(),
        handle: Some(handle),
        client: reqwest::Client::new(),
    };
    let id = start_run(&s, run_body("fault", small_plan(3))).await;
    let v = s.wait_state(&id, "paused").await;
    let reason = v["reason"].as_str().expect("reason").to_string();
    assert!(reason.contains("camera"), "{v}");
    assert_eq!(v["last_error"], reason.as_str());
    let (_, rig) = s.get("/api/v1/rig").await;
    let cam = rig["devices"]
        .as_array()
        .and_then(|d| d.iter().find(|d| d["name"] == "camera").cloned())
        .expect("camera");
    assert_eq!(cam["fault"], reason.as_str());
    let (status, _) = s.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 202);
    let v = s.wait_state(&id, "completed").await;
    assert_eq!(v["last_error"], reason.as_str());
    assert_complete_run(&dir.path().join("runs").join(&id), 9);
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sim_render_returns_a_frame_with_its_effects() {
    let (_d, s) = srv(FAST).await;
    let resp = s
        .client
        .get(s.url("/api/v1/sim/render?scene=corduroy&light=80,0&view=30,90&size=64x48"))
        .send()
        .await
        .expect("request");
    assert_eq!(resp.status().as_u16(), 200);
    let effects = resp
        .headers()
        .get("x-rigd-effects")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_string();
    assert!(
        effects.contains("relief") && effects.contains("shadows"),
        "{effects}"
    );
    let png = resp.bytes().await.expect("body");
    let (w, h, pixels) = rigd::rig::hal::decode_png(&png).expect("a PNG");
    assert_eq!((w, h), (64, 48));
    assert!(pixels.iter().any(|&p| p > 0));
    // The flat calibration scene pays for nothing.
    let resp = s
        .client
        .get(s.url("/api/v1/sim/render?scene=flat-calibration&size=32x32"))
        .send()
        .await
        .expect("request");
    assert_eq!(
        resp.headers()
            .get("x-rigd-effects")
            .and_then(|v| v.to_str().ok()),
        Some("none")
    );
    for bad in [
        "light=95,0",
        "size=0x5",
        "effects=sparkle",
        "laser=a,b",
        "size=4096x4096",
    ] {
        let (status, v) = s.get(&format!("/api/v1/sim/render?{bad}")).await;
        assert_eq!(status, 400, "{bad}: {v}");
        assert!(v["detail"].is_string(), "{v}");
    }
    let (status, v) = s.get("/api/v1/sim/render?scene=no-such-scene").await;
    assert_eq!(status, 404, "{v}");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("flat-calibration")),
        "{v}"
    );
    let (status, v) = s.get("/api/v1/sim/scenes").await;
    assert_eq!(status, 200);
    let names: Vec<&str> = v
        .as_array()
        .expect("list")
        .iter()
        .filter_map(|x| x["name"].as_str())
        .collect();
    assert!(
        names.contains(&"knitted-wool") && names.contains(&"ps-target"),
        "{v}"
    );
}

/// A small compressed BTF written where `rigd process btf` writes.
fn write_tiny_btf(run_dir: &std::path::Path) -> usize {
    use rigd_process::btf::{compress_slot, CompressedBtf, TextureShape};
    use rigd_process::directions::{h1, Direction, DirectionTable};
    let shape = TextureShape::new(8, 8, 1).expect("shape");
    let lights = DirectionTable::new(h1()).expect("lights");
    let views = DirectionTable::new(vec![Direction::new(0.0, 0.0), Direction::new(45.0, 0.0)])
        .expect("views");
    let slots = (0..2)
        .map(|_| {
            let images: Vec<Vec<f32>> = lights
                .directions()
                .iter()
                .map(|l| {
                    (0..64)
                        .map(|i| (l.theta_deg.to_radians().cos() * (0.5 + 0.01 * i as f64)) as f32)
                        .collect()
                })
                .collect();
            let refs: Vec<&[f32]> = images.iter().map(Vec::as_slice).collect();
            compress_slot(&refs, shape, 3).expect("compress")
        })
        .collect();
    let store = CompressedBtf::new(shape, lights, views, slots).expect("store");
    store
        .write(&rigd::store::processed::btf_dir(run_dir))
        .expect("write the BTF");
    store.lights().len()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewer_routes_serve_a_processed_run_and_explain_the_rest() {
    let (dir, mut s) = srv(FAST).await;
    let run = start_run(&s, run_body("tiny", small_plan(2))).await;
    s.wait_state(&run, "completed").await;
    // Not processed yet: 404 naming the commands, and no `processed`.
    let (status, v) = s.get(&format!("/api/v1/runs/{run}/btf")).await;
    assert_eq!(status, 404);
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("rigd process btf")),
        "{v}"
    );
    let (_, v) = s.get(&format!("/api/v1/runs/{run}")).await;
    assert_eq!(v["processed"], Value::Null);
    let (status, _) = s.get("/api/v1/runs/no-such-run/btf").await;
    assert_eq!(status, 404);

    let lights = write_tiny_btf(&dir.path().join("runs").join(&run));
    let (_, list) = s.get("/api/v1/runs").await;
    assert_eq!(list["runs"][0]["processed"], "btf");
    let (status, m) = s.get(&format!("/api/v1/runs/{run}/btf?components=2")).await;
    assert_eq!(status, 200, "{m}");
    assert_eq!(m["kind"], "btf");
    assert_eq!(m["components"], 2);
    assert_eq!(m["layers"], 2 * 3);
    assert_eq!(m["light_table"]["rings"][0]["pole"], true);
    let data_url = m["data_url"].as_str().expect("data_url").to_string();
    let (status, _, blob) = s.get_bytes(&data_url).await;
    assert_eq!(status, 200);
    assert_eq!(Some(blob.len() as u64), m["bytes"].as_u64());
    assert_eq!(
        m["textures"]["bytes"].as_u64(),
        Some(2 * 6 * 64),
        "six f16 layers of 8×8 grey texels"
    );
    let (status, mesh) = s
        .get(&format!("/api/v1/runs/{run}/btf/mesh/cylinder"))
        .await;
    assert_eq!(status, 200);
    let verts = mesh["nu"].as_u64().unwrap_or(0) * mesh["nv"].as_u64().unwrap_or(0);
    assert_eq!(
        mesh["visibility"].as_array().map(Vec::len),
        Some(verts as usize * lights)
    );
    assert_eq!(
        mesh["positions"].as_array().map(Vec::len),
        Some(3 * verts as usize)
    );
    // No MDF texture yet: the manifest and the blob say how to make one.
    for route in ["mdf", "mdf/data"] {
        let (status, v) = s.get(&format!("/api/v1/runs/{run}/{route}")).await;
        assert_eq!(status, 404, "{route}: {v}");
        assert!(v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("rigd process mdf-texture")));
    }
    let (status, v) = s.get(&format!("/api/v1/runs/{run}/btf/mesh/torus")).await;
    assert_eq!(status, 404);
    assert!(v["detail"]
        .as_str()
        .is_some_and(|d| d.contains("flat, cylinder, cloth or sphere")));
    let (status, _) = s
        .get(&format!("/api/v1/runs/{run}/btf/mesh/flat?density=0"))
        .await;
    assert_eq!(status, 422);
    let (status, _) = s
        .get(&format!("/api/v1/runs/{run}/btf?components=many"))
        .await;
    assert_eq!(status, 400);
    // The page and its script.
    for (path, kind) in [
        (format!("/viewer/{run}"), "text/html"),
        ("/viewer.js".to_string(), "text/javascript"),
    ] {
        let (status, ct, _) = s.get_bytes(&path).await;
        assert_eq!(status, 200, "{path}");
        assert!(ct.starts_with(kind), "{path}: {ct}");
    }
    s.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_computes_and_serves_the_tradeoff_report() {
    let (dir, mut s) = srv(FAST).await;
    let (status, v) = s.get("/api/v1/tradeoff").await;
    assert_eq!(status, 404);
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("rigd tradeoff")),
        "{v}"
    );
    for (body, why) in [
        (json!({"texture": 2}), "texture"),
        (json!({"scene": "no-such-scene"}), "no-such-scene"),
        (json!({"render_size": [8, 8]}), "render_size"),
    ] {
        let (status, v) = s.post("/api/v1/tradeoff", Some(body)).await;
        assert_eq!(status, 422, "{v}");
        assert!(v["detail"].as_str().is_some_and(|d| d.contains(why)), "{v}");
    }
    let (status, sse) = SseReader::connect(&s.client, &s.url("/api/v1/events"), None).await;
    assert_eq!(status, 200);
    let mut sse = sse.expect("stream");
    let small = json!({"scene": "corduroy", "texture": 4, "held_out": 4, "render_size": [32, 24]});
    let (status, v) = s.post("/api/v1/tradeoff", Some(small.clone())).await;
    assert_eq!(status, 202, "{v}");
    assert_eq!(v["scene"], "corduroy");
    let (status, v) = s.post("/api/v1/tradeoff", Some(small)).await;
    assert_eq!(status, 409, "one at a time: {v}");
    // Progress, then the end, as events.
    let mut steps = 0;
    let end = loop {
        let (_, ev) = sse
            .next(Duration::from_secs(600))
            .await
            .expect("tradeoff events until it ends");
        if ev["kind"] != "tradeoff" {
            continue;
        }
        match ev["event"]["state"].as_str() {
            Some("computing") => steps += 1,
            Some("done") | Some("failed") => break ev,
            _ => {}
        }
    };
    assert_eq!(end["event"]["state"], "done", "{end}");
    assert!(steps >= 5, "{steps} progress events");
    let (status, report) = s.get("/api/v1/tradeoff").await;
    assert_eq!(status, 200);
    assert_eq!(report["scene"], "corduroy");
    assert!(report["rows"].as_array().is_some_and(|r| r.len() > 20));
    let (status, ct, svg) = s.get_bytes("/api/v1/tradeoff/plot.svg").await;
    assert_eq!(status, 200);
    assert_eq!(ct, "image/svg+xml");
    let svg = String::from_utf8(svg).expect("utf-8 svg");
    assert!(svg.starts_with("<svg") && svg.contains("polyline"));
    assert!(dir.path().join("tradeoff").join("tradeoff.csv").is_file());
    // The same figure with its layout: a panel per family, every point
    // inside its panel, at most the profile's default plan marked.
    let (status, f) = s.get("/api/v1/tradeoff/figure").await;
    assert_eq!(status, 200, "{f}");
    assert_eq!(f["svg"].as_str(), Some(svg.as_str()));
    let families: BTreeSet<&str> = f["panels"]
        .as_array()
        .expect("panels")
        .iter()
        .filter_map(|p| p["family"].as_str())
        .collect();
    assert_eq!(
        families,
        [
            "exposure",
            "fidelity",
            "laser",
            "pca",
            "photometric stereo",
            "plans"
        ]
        .into_iter()
        .collect()
    );
    let points = f["points"].as_array().expect("points");
    assert!(points.len() > 20, "{}", points.len());
    for p in points {
        let area = &f["panels"][p["panel"].as_u64().expect("panel") as usize]["area"];
        let (x, y) = (p["x"].as_f64().expect("x"), p["y"].as_f64().expect("y"));
        assert!(
            x >= area[0].as_f64().expect("x0") - 1.0
                && x <= area[2].as_f64().expect("x1") + 1.0
                && y >= area[1].as_f64().expect("y0") - 1.0
                && y <= area[3].as_f64().expect("y1") + 1.0,
            "{p} outside {area}"
        );
    }
    assert!(points.iter().filter(|p| p["marked"] == true).count() <= 1);
    assert!(points.iter().any(|p| p["frontier"] == true));
    // A budget and a target answered from it.
    let (status, c) = s.get("/api/v1/tradeoff/choice?budget=3h").await;
    assert_eq!(status, 200, "{c}");
    assert!(
        c["plan"]["physical_s"].as_f64() <= Some(3.0 * 3600.0),
        "{c}"
    );
    assert!(
        c["frontier"]
            .as_array()
            .is_some_and(|f| f.contains(&c["plan"])),
        "{c}"
    );
    assert!(
        c["answer"]
            .as_str()
            .is_some_and(|a| a.starts_with("within 3 h: ")),
        "{c}"
    );
    let (status, c) = s.get("/api/v1/tradeoff/choice?target=100%25").await;
    assert_eq!(status, 200, "{c}");
    assert!(c["plan"]["error"].as_f64() <= Some(1.0), "{c}");
    for (query, why) in [
        ("", "budget"),
        ("?budget=3h&target=15%25", "budget"),
        ("?budget=soon", "soon"),
        ("?budget=1s", "no measured plan fits"),
    ] {
        let (status, v) = s.get(&format!("/api/v1/tradeoff/choice{query}")).await;
        assert_eq!(status, 422, "{query}: {v}");
        assert!(
            v["detail"].as_str().is_some_and(|d| d.contains(why)),
            "{query}: {v}"
        );
    }
    s.shutdown().await;
}
