//! Processing from the daemon: `POST /api/v1/runs/{id}/process` queues a
//! finished run's steps, `process` events report them, the run's view shows
//! the job and then the result, and asking again does no work twice.

use crate::common;

use std::time::{Duration, Instant};

use common::http::{small_plan, start_in, SseReader};
use serde_json::{json, Value};

/// A run the markers register: the Bonn rig's smallest registrable frame.
fn processable_run(sample: &str, n: usize) -> Value {
    json!({"sample": sample, "plan": small_plan(n), "frame_size": [320, 240], "operator": "tester"})
}

const SMALL: &str = r#"{"rectify": {"size": 128, "final": 32}, "btf": {"components": 4}}"#;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_finished_run_is_processed_by_the_daemon_once() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut s = start_in(dir.path(), 20_000.0).await;
    let options: Value = serde_json::from_str(SMALL).expect("options");
    let (_, mut sse) = SseReader::connect(&s.client, &s.url("/api/v1/events"), None).await;
    let mut sse = sse.take().expect("event stream");

    let (status, v) = s
        .post("/api/v1/runs", Some(processable_run("felt", 4)))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let process = format!("/api/v1/runs/{id}/process");
    // A run still capturing is not processed (it may already have ended
    // on a fast simulation; then this is the first real submission, so
    // only check the refusal when it is one).
    let (status, v) = s.post(&process, Some(options.clone())).await;
    if status == 409 {
        assert!(v["detail"].as_str().unwrap_or("").contains("ended"), "{v}");
    }
    s.wait_ended(&id, "completed").await;

    // Bad requests name what is wrong.
    for (body, want) in [
        (json!({"steps": ["sharpen"]}), "sharpen"),
        (json!({"rectify": {"bits": "9"}}), "bits"),
        (json!({"btf": {"components": 0}}), "components"),
        (json!({"steps": ["mdf"]}), "laser"),
        (json!({"rectify": {"sise": 3}}), "sise"),
    ] {
        let (status, v) = s.post(&process, Some(body.clone())).await;
        assert!(status == 422 || status == 400, "{body}: {status} {v}");
        assert!(
            v["detail"].as_str().unwrap_or("").contains(want),
            "{body}: {v}"
        );
    }
    let (status, v) = s
        .post("/api/v1/runs/no-such-run/process", Some(json!({})))
        .await;
    assert_eq!(status, 404, "{v}");
    let (status, v) = s.get("/api/v1/runs/no-such-run/process").await;
    assert_eq!(status, 404, "{v}");
    let (status, v) = s.send("POST", &process, Some(json!({})), None).await;
    assert_eq!(status, 401, "{v}");

    // Another processor has the run (a `rigd process` command; here this
    // test holds its lock): the job fails saying so and writes nothing.
    let root = dir.path().join("runs").join(&id);
    let held = rigd::store::ProcessingLock::acquire(&root).expect("the processing lock");
    let (status, job) = s.post(&process, Some(options.clone())).await;
    assert_eq!(status, 202, "{job}");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some((_, ev)) = sse.next(left).await else {
            panic!("the job never failed while the run was held");
        };
        if ev["kind"] == "process" && ev["run"] == id.as_str() && ev["event"]["state"] == "failed" {
            let error = ev["event"]["error"].as_str().unwrap_or("");
            assert!(
                error.contains("another rigd is processing this run"),
                "{ev}"
            );
            break;
        }
    }
    assert!(!root.join("processed/normtextures").exists());
    drop(held);

    // The job: queued, then done; asking again returns it.
    let (status, job) = s.post(&process, Some(options.clone())).await;
    assert!(status == 202 || status == 200, "{status} {job}");
    assert_eq!(job["run"], id.as_str());
    let steps: Vec<&str> = job["steps"]
        .as_array()
        .expect("steps")
        .iter()
        .filter_map(|s| s["step"].as_str())
        .collect();
    assert_eq!(
        steps,
        ["rectify", "btf"],
        "defaults for a multi-view run: {job}"
    );
    assert_eq!(job["options"]["rectify"]["final"], 32);
    assert_eq!(job["options"]["btf"]["components"], 4);

    let deadline = Instant::now() + Duration::from_secs(120);
    let mut seen_steps = Vec::new();
    let mut progress_events = 0;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some((_, ev)) = sse.next(left).await else {
            panic!("no `process` event said done; steps seen {seen_steps:?}");
        };
        if ev["kind"] != "process" || ev["run"] != id.as_str() {
            continue;
        }
        let e = &ev["event"];
        assert_ne!(e["state"], "failed", "{ev}");
        if let Some(step) = e["step"].as_str() {
            if !seen_steps.contains(&step.to_string()) {
                seen_steps.push(step.to_string());
            }
            if e["total"].as_u64() > Some(0) {
                progress_events += 1;
                assert!(e["done"].as_u64() <= e["total"].as_u64(), "{ev}");
            }
        }
        if e["state"] == "done" {
            assert_eq!(e["steps_done"], 2, "{ev}");
            break;
        }
    }
    assert_eq!(seen_steps, ["rectify", "btf"]);
    assert!(
        progress_events >= 2,
        "progress with done/total: {progress_events}"
    );

    let (status, v) = s.get(&format!("/api/v1/runs/{id}")).await;
    assert_eq!(status, 200);
    assert_eq!(v["processed"], "btf", "{v}");
    assert_eq!(v["processing"]["state"], "done", "{v}");
    let (status, job) = s.get(&process).await;
    assert_eq!(status, 200);
    for step in job["steps"].as_array().expect("steps") {
        assert_eq!(step["state"], "done", "{job}");
        assert!(
            step["summary"].as_str().is_some_and(|t| !t.is_empty()),
            "{job}"
        );
        assert_eq!(step["done"], step["total"], "{job}");
    }
    let root = dir.path().join("runs").join(&id);
    assert!(root.join("processed/btf/btf.json").is_file());
    assert!(root.join("processed/job.json").is_file());
    let written = std::fs::metadata(root.join("processed/btf/btf.json"))
        .and_then(|m| m.modified())
        .expect("btf.json time");

    // The same request again: the same job, nothing redone.
    let (status, again) = s.post(&process, Some(options.clone())).await;
    assert_eq!(status, 200, "{again}");
    assert_eq!(again["created_at"], job["created_at"]);
    assert_eq!(again["state"], "done");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let after = std::fs::metadata(root.join("processed/btf/btf.json"))
        .and_then(|m| m.modified())
        .expect("btf.json time");
    assert_eq!(written, after, "a done job is not run again");

    // btf alone on a rectified run is fine; on an unrectified one it names
    // the missing step.
    let (status, v) = s
        .post("/api/v1/runs", Some(processable_run("wool", 2)))
        .await;
    assert_eq!(status, 201, "{v}");
    let other = v["id"].as_str().expect("id").to_string();
    s.wait_ended(&other, "completed").await;
    let (status, v) = s
        .post(
            &format!("/api/v1/runs/{other}/process"),
            Some(json!({"steps": ["btf"]})),
        )
        .await;
    assert_eq!(status, 422, "{v}");
    assert!(
        v["detail"].as_str().unwrap_or("").contains("rectify"),
        "{v}"
    );
    let (status, v) = s.get(&format!("/api/v1/runs/{other}/process")).await;
    assert_eq!(status, 404, "no job: {v}");

    // Frames too small for the markers are refused with the reason.
    let (status, v) = s
        .post(
            "/api/v1/runs",
            Some(json!({"sample": "tiny", "plan": small_plan(2), "frame_size": [96, 64], "operator": "tester"})),
        )
        .await;
    assert_eq!(status, 201, "{v}");
    let tiny = v["id"].as_str().expect("id").to_string();
    s.wait_ended(&tiny, "completed").await;
    let (status, v) = s
        .post(&format!("/api/v1/runs/{tiny}/process"), Some(json!({})))
        .await;
    assert_eq!(status, 422, "{v}");
    let detail = v["detail"].as_str().unwrap_or("");
    assert!(
        detail.contains("288×216") && detail.contains("96×64"),
        "{v}"
    );
    s.shutdown().await;
}

/// `process` in the run request: the job is on disk before the first frame,
/// waits for the capture, then runs; frames too small for the markers
/// refuse the run before anything is created.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_asked_with_process_is_processed_when_it_completes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut s = start_in(dir.path(), 20_000.0).await;
    let options: Value = serde_json::from_str(SMALL).expect("options");

    let mut tiny = processable_run("tiny", 2);
    tiny["frame_size"] = json!([96, 64]);
    tiny["process"] = json!({});
    let (status, v) = s.post("/api/v1/runs", Some(tiny.clone())).await;
    assert_eq!(status, 422, "{v}");
    assert!(
        v["detail"].as_str().unwrap_or("").contains("288×216"),
        "{v}"
    );
    let (status, v) = s.post("/api/v1/queue", Some(tiny)).await;
    assert_eq!(status, 422, "queued runs are checked too: {v}");
    let mut laser_steps = processable_run("felt", 2);
    laser_steps["process"] = json!({"steps": ["mdf"]});
    let (status, v) = s.post("/api/v1/runs", Some(laser_steps)).await;
    assert_eq!(status, 422, "{v}");
    let (_, list) = s.get("/api/v1/runs").await;
    assert_eq!(list["runs"].as_array().map(Vec::len), Some(0), "{list}");

    let mut body = processable_run("felt", 4);
    body["process"] = options;
    let (status, v) = s.post("/api/v1/runs", Some(body)).await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let job: Value = serde_json::from_slice(
        &std::fs::read(dir.path().join("runs").join(&id).join("processed/job.json"))
            .expect("job.json written with the run"),
    )
    .expect("job JSON");
    assert_eq!(job["after_capture"], true, "{job}");
    let v = s
        .wait_run(&id, "processed", |v| {
            v["processing"]["state"] == "done" || v["processing"]["state"] == "failed"
        })
        .await;
    assert_eq!(v["processing"]["state"], "done", "{v}");
    assert_eq!(v["state"], "completed");
    assert_eq!(v["processed"], "btf", "{v}");
    s.shutdown().await;
}

/// `rigd run --process`: the capture, then its processing; a frame size
/// the markers cannot register is refused before anything is captured.
#[test]
fn rigd_run_process_captures_then_processes() {
    let dir = tempfile::tempdir().expect("tempdir");
    let plan = common::tiny_plan(dir.path());
    let small = dir.path().join("small");
    let out = common::rigd()
        .args(["run", "--sim", "--progress", "log", "--frame-size", "96x64"])
        .arg("--plan")
        .arg(&plan)
        .arg("--out")
        .arg(&small)
        .args(["--process", "rectify,btf"])
        .output()
        .expect("rigd run");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("288×216") && err.contains("96×64"), "{err}");
    assert!(!small.exists(), "nothing captured");
    let out = common::rigd()
        .args([
            "run",
            "--sim",
            "--progress",
            "log",
            "--frame-size",
            "320x240",
        ])
        .arg("--plan")
        .arg(&plan)
        .args(["--process", "sharpen"])
        .arg("--out")
        .arg(dir.path().join("never"))
        .output()
        .expect("rigd run");
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("sharpen"));

    let run = dir.path().join("run");
    let out = common::rigd()
        .args([
            "run",
            "--sim",
            "--progress",
            "log",
            "--frame-size",
            "320x240",
        ])
        .arg("--plan")
        .arg(&plan)
        .arg("--out")
        .arg(&run)
        .args(["--process", "rectify,btf"])
        .output()
        .expect("rigd run");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(run.join("processed/btf/btf.json").is_file(), "{err}");
    assert!(err.contains("rectify: 4 frames"), "{err}");
    // Progress in a log: whole lines, no carriage returns.
    assert!(!err.contains('\r'), "{err:?}");
    assert!(err.contains("rectify: 4/4 (100%)"), "{err}");
}

/// A job waiting for its run's capture is dropped when cancelled: it ends
/// `failed`, the worker never runs it, and asking again resumes it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_queued_job_cancelled_never_runs() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Slow: the capture of 16 images lasts long enough to cancel in.
    let mut s = start_in(dir.path(), 20.0).await;
    let mut body = processable_run("felt", 4);
    body["process"] = serde_json::from_str(SMALL).expect("options");
    let (status, v) = s.post("/api/v1/runs", Some(body)).await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let cancel = format!("/api/v1/runs/{id}/process/cancel");
    let (status, v) = s.send("POST", &cancel, None, None).await;
    assert_eq!(status, 401, "a cancel needs the token: {v}");
    let (status, job) = s.post(&cancel, None).await;
    assert_eq!(status, 200, "{job}");
    assert_eq!(job["state"], "failed", "{job}");
    assert_eq!(job["error"], "cancelled by the operator", "{job}");
    let (status, v) = s.post(&cancel, None).await;
    assert_eq!(status, 409, "nothing left to cancel: {v}");
    let (status, v) = s
        .post("/api/v1/runs/no-such-run/process/cancel", None)
        .await;
    assert_eq!(status, 404, "{v}");
    let (status, v) = s.post(&format!("/api/v1/runs/{id}/abort"), None).await;
    assert_eq!(status, 202, "{v}");
    let v = s.wait_ended(&id, "aborted").await;
    assert_eq!(
        v["processing"]["state"], "failed",
        "not run after the capture: {v}"
    );
    s.shutdown().await;
}
