//! The daemon as a process: killed (-9) or stopped (SIGTERM) in the middle
//! of a run, restarted, and the run resumed over the API: the dataset
//! completes with every frame exactly once and valid checksums. The
//! capture-and-process case also through `rigd run --process`, which runs
//! the same process job.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Stdio};
use std::time::Duration;

use common::assert_complete_run;
use common::http::{run_body, small_plan};
use serde_json::Value;

struct Daemon {
    child: Child,
    base: String,
    token: String,
    client: reqwest::Client,
}

fn spawn(data: &Path, speed: f64) -> Daemon {
    spawn_on(data, speed, None)
}

/// [`spawn`] on the simulated rig of `profile`, the embedded one if `None`.
fn spawn_on(data: &Path, speed: f64, profile: Option<&Path>) -> Daemon {
    let mut command = common::rigd();
    command
        .args(["serve", "--listen", "127.0.0.1:0", "--sim-speed"])
        .arg(speed.to_string())
        .arg("--data")
        .arg(data);
    if let Some(profile) = profile {
        command.arg("--sim").arg("--profile").arg(profile);
    }
    let mut child = command
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn rigd serve");
    let stderr = child.stderr.take().expect("stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut tx = Some(tx);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("on http://").nth(1) {
                if let Some(t) = tx.take() {
                    let _ = t.send(rest.split('/').next().unwrap_or("").to_string());
                }
            }
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_secs(30))
        .expect("the daemon says where it listens");
    let token = std::fs::read_to_string(data.join("token"))
        .expect("token file")
        .trim()
        .to_string();
    Daemon {
        child,
        base: format!("http://{addr}"),
        token,
        client: reqwest::Client::new(),
    }
}

impl Daemon {
    async fn get(&self, path: &str) -> Value {
        let r = self
            .client
            .get(format!("{}{path}", self.base))
            .send()
            .await
            .expect("GET");
        assert_eq!(r.status().as_u16(), 200, "GET {path}");
        r.json().await.expect("json")
    }

    async fn post(&self, path: &str, body: Option<Value>) -> (u16, Value) {
        let mut req = self
            .client
            .post(format!("{}{path}", self.base))
            .bearer_auth(&self.token);
        if let Some(b) = body {
            req = req.json(&b);
        }
        let r = req.send().await.expect("POST");
        let status = r.status().as_u16();
        (status, r.json().await.unwrap_or(Value::Null))
    }

    async fn wait_run(&self, id: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        loop {
            let v = self.get(&format!("/api/v1/runs/{id}")).await;
            if pred(&v) {
                return v;
            }
            assert!(std::time::Instant::now() < deadline, "run {id}: {v}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

const IMAGES: usize = 64;

/// Starts a run, waits for a few frames, stops the daemon with `stop`,
/// restarts it and resumes the run; returns the state seen after restart.
async fn cut_and_resume(stop: impl FnOnce(&mut Daemon)) -> String {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut d = spawn(dir.path(), 300.0);
    let (status, v) = d
        .post("/api/v1/runs", Some(run_body("cut", small_plan(8))))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    d.wait_run(&id, |v| v["steps_done"].as_u64() >= Some(5))
        .await;
    stop(&mut d);
    drop(d);

    let d = spawn(dir.path(), 20_000.0);
    let v = d.get(&format!("/api/v1/runs/{id}")).await;
    let state = v["state"].as_str().unwrap_or("").to_string();
    assert_eq!(v["resumable"], true, "{v}");
    assert_eq!(v["active"], false);
    let done = v["steps_done"].as_u64().unwrap_or(0) as usize;
    assert!((5..IMAGES).contains(&done), "{v}");
    // Nothing starts by itself after a cut: the rig is free.
    let rig = d.get("/api/v1/rig").await;
    assert_eq!(rig["active_run"], Value::Null);
    let (status, v) = d.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 200, "{v}");
    let v = d.wait_run(&id, |v| v["state"] == "completed").await;
    assert_eq!(v["steps_done"], IMAGES);
    assert_complete_run(&dir.path().join("runs").join(&id), IMAGES);
    // Completed is final.
    let (status, _) = d.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 409);
    state
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_mid_run_then_resume_completes() {
    let state = cut_and_resume(|d| {
        d.child.kill().expect("kill -9");
        let _ = d.child.wait();
    })
    .await;
    assert_eq!(state, "interrupted");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_mid_run_pauses_then_resume_completes() {
    let state = cut_and_resume(|d| {
        let pid = d.child.id() as libc::pid_t;
        // SAFETY: signalling our own child process.
        let rc = unsafe { libc::kill(pid, libc::SIGTERM) };
        assert_eq!(rc, 0);
        let status = d.child.wait().expect("wait");
        assert!(status.success(), "graceful exit: {status:?}");
    })
    .await;
    assert_eq!(state, "paused");
}

#[test]
fn serve_help_and_bad_options() {
    let out = common::run_ok(&["serve", "--help"]);
    let help = String::from_utf8_lossy(&out.stdout);
    for want in [
        "--listen",
        "127.0.0.1:8080",
        "--data",
        "rigd-data",
        "--sim-speed",
        "200",
        "--token-file",
        "--profile",
        "3 minutes",
    ] {
        assert!(help.contains(want), "`{want}` missing from:\n{help}");
    }
    let dir = tempfile::tempdir().expect("tempdir");
    for (args, want) in [
        (vec!["serve", "--sim-speed", "0"], "--sim-speed"),
        (vec!["serve", "--sim-speed", "-5"], "--sim-speed"),
        (
            vec!["serve", "--profile", "no-such-rig", "--sim"],
            "no-such-rig",
        ),
        (
            vec!["serve", "--listen", "not-an-address"],
            "not-an-address",
        ),
    ] {
        let out = common::rigd()
            .args(&args)
            .arg("--data")
            .arg(dir.path())
            .output()
            .expect("run rigd");
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(want), "{args:?}: {err}");
    }
}

/// A daemon killed (-9) while it processes a run takes the job up again at
/// its next start, and the BTF it ends with is byte for byte the one the
/// command line makes from the same frames without interruption.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_mid_processing_resumes_to_the_same_btf() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut d = spawn(dir.path(), 20_000.0);
    let body = serde_json::json!({"sample": "corduroy", "plan": small_plan(8),
        "frame_size": [320, 240], "operator": "tester"});
    let (status, v) = d.post("/api/v1/runs", Some(body)).await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    d.wait_run(&id, |v| v["state"] == "completed" && v["active"] == false)
        .await;
    let run = dir.path().join("runs").join(&id);
    let reference = tempfile::tempdir().expect("tempdir");
    let reference = reference.path().join(&id);
    crate::common::copy_dir(&run, &reference);

    let options =
        serde_json::json!({"rectify": {"size": 512, "final": 64}, "btf": {"components": 8}});
    let (status, job) = d
        .post(&format!("/api/v1/runs/{id}/process"), Some(options))
        .await;
    assert_eq!(status, 202, "{job}");
    let v = d
        .wait_run(&id, |v| {
            v["processing"]["steps"][0]["done"].as_u64() >= Some(4)
                || v["processing"]["state"] == "done"
        })
        .await;
    assert_eq!(
        v["processing"]["state"], "running",
        "killed while the job runs: {v}"
    );
    d.child.kill().expect("kill -9");
    let _ = d.child.wait();
    drop(d);
    let on_disk: Value =
        serde_json::from_slice(&std::fs::read(run.join("processed/job.json")).expect("job.json"))
            .expect("job.json is JSON");
    assert_eq!(on_disk["state"], "running", "{on_disk}");

    let d = spawn(dir.path(), 20_000.0);
    let v = d
        .wait_run(&id, |v| {
            matches!(v["processing"]["state"].as_str(), Some("done" | "failed"))
        })
        .await;
    assert_eq!(v["processing"]["state"], "done", "{v}");
    assert_eq!(v["processing"]["resumed"], 1, "{v}");
    // The frames registered before the kill were not registered again.
    let summary = v["processing"]["steps"][0]["summary"]
        .as_str()
        .unwrap_or("");
    let taken = done_before(summary);
    assert!(
        taken >= 4,
        "frames taken from the interrupted run: {summary}"
    );
    assert!(
        !run.join("processed/normtextures/first-pass").exists(),
        "the first-pass store is removed with the step's end"
    );
    assert_eq!(v["processed"], "btf", "{v}");

    assert_same_btf_as_cli(&run, &reference, DAEMON_RECTIFY, "8");
}

/// Processes the copy `reference` of a run from the command line in one go
/// (`rectify` with `rectify_args`, `btf --components components`) and
/// checks that the BTF of `run` is byte for byte the same.
fn assert_same_btf_as_cli(run: &Path, reference: &Path, rectify_args: &[&str], components: &str) {
    let rectify: Vec<&str> = ["process", "rectify"]
        .iter()
        .chain(rectify_args)
        .copied()
        .collect();
    for args in [rectify, vec!["process", "btf", "--components", components]] {
        let o = common::rigd()
            .args(&args)
            .arg(reference)
            .output()
            .expect("rigd process");
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    let got = crate::common::tree_bytes(&run.join("processed/btf"));
    let want = crate::common::tree_bytes(&reference.join("processed/btf"));
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        want.keys().collect::<Vec<_>>()
    );
    for (name, bytes) in &want {
        if name == "report.json" {
            // Holds the compression's wall time.
            continue;
        }
        assert!(got[name] == *bytes, "processed/btf/{name} differs");
    }
}

/// `rectify` as the daemon's jobs in these tests ask for it (`size 512,
/// final 64`), with the default blend of a quarter of the final size.
const DAEMON_RECTIFY: &[&str] = &["--size", "512", "--final", "64", "--blend", "16"];

/// The number at the start of a step summary's second clause: the frames
/// `rectify` took from first passes done before it ran, or the view slots
/// `btf` took as compressed during the capture.
fn done_before(summary: &str) -> usize {
    summary
        .split("; ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or(0)
}

/// A run asked for with `process` registers its frames while it captures.
/// Killed (-9) in the middle, restarted and resumed, it completes both the
/// capture and the processing: the frames registered before the kill are
/// not registered again, and the BTF is byte for byte the one the command
/// line makes from the same frames in one go.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_mid_streaming_resumes_capture_and_processing_to_the_same_btf() {
    let dir = tempfile::tempdir().expect("tempdir");
    // A monochrome camera, so frames are registered from the first one: a
    // colour run calibrated on its own patches waits for its most frontal
    // frames (`docs/processing.md`, "During the capture"), which this plan
    // takes late.
    let monochrome = common::bonn_monochrome(dir.path());
    // Slow enough (about 0.2 s per frame) that frames are registered
    // while the capture runs, even on a loaded machine.
    let mut d = spawn_on(dir.path(), 25.0, Some(&monochrome));
    // `slots`: each view's triggers together, so view slots complete and
    // are compressed during the capture (on this small plan the order
    // costs 3.8 %, more than a run would take by itself).
    let body = serde_json::json!({"sample": "corduroy", "plan": small_plan(8),
        "frame_size": [320, 240], "operator": "tester", "order": "slots",
        "process": {"rectify": {"size": 512, "final": 64}, "btf": {"components": 8}}});
    let (status, v) = d.post("/api/v1/runs", Some(body)).await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let v = d
        .wait_run(&id, |v| {
            v["processing"]["streamed"].as_u64() >= Some(8) || v["active"] == false
        })
        .await;
    assert_eq!(v["state"], "running", "killed while capturing: {v}");
    assert_eq!(v["processing"]["state"], "queued", "{v}");
    d.child.kill().expect("kill -9");
    let _ = d.child.wait();
    drop(d);
    let run = dir.path().join("runs").join(&id);
    let kept = std::fs::read_dir(run.join("processed/normtextures/first-pass"))
        .expect("first passes kept during the capture")
        .count();
    assert!(kept >= 8, "{kept} first passes kept");

    let d = spawn_on(dir.path(), 25.0, Some(&monochrome));
    let (status, v) = d.post(&format!("/api/v1/runs/{id}/resume"), None).await;
    assert_eq!(status, 200, "{v}");
    let v = d
        .wait_run(&id, |v| {
            matches!(v["processing"]["state"].as_str(), Some("done" | "failed"))
        })
        .await;
    assert_eq!(v["state"], "completed", "{v}");
    assert_eq!(v["processing"]["state"], "done", "{v}");
    assert_complete_run(&run, IMAGES);
    let summary = v["processing"]["steps"][0]["summary"]
        .as_str()
        .unwrap_or("");
    let before = done_before(summary);
    assert!(
        before >= kept && before <= IMAGES,
        "{kept} kept at the kill, {before} taken by the step: {summary}"
    );
    assert!(!run.join("processed/normtextures/first-pass").exists());
    // View slots were compressed while the run captured, and `btf` took
    // them.
    let meta: Value =
        serde_json::from_slice(&std::fs::read(run.join("run.json")).expect("run.json"))
            .expect("run.json is JSON");
    assert_eq!(meta["plan"]["order"], "slots");
    let btf = v["processing"]["steps"][1]["summary"]
        .as_str()
        .unwrap_or("");
    let ahead = done_before(btf);
    assert!(ahead >= 1, "{btf}; the job: {}", v["processing"]);
    assert!(!run.join("processed/btf-ahead").exists());

    let reference = tempfile::tempdir().expect("tempdir");
    let reference = reference.path().join(&id);
    crate::common::copy_dir(&run, &reference);
    std::fs::remove_dir_all(reference.join("processed")).expect("a fresh copy");
    assert_same_btf_as_cli(&run, &reference, DAEMON_RECTIFY, "8");
}

/// `rigd run --process` runs the same process job: killed (-9) while it
/// captures and registers, then resumed with `rigd run --resume` and no
/// `--process` (the job kept in the run follows), it completes both; the
/// frames registered before the kill are not registered again, view slots
/// are compressed during the capture, and the BTF is byte for byte the one
/// the command line makes from the same frames in one go.
#[test]
fn kill_9_mid_streaming_on_the_command_line_resumes_to_the_same_btf() {
    let dir = tempfile::tempdir().expect("tempdir");
    // Monochrome: see the daemon's case above.
    let monochrome = common::bonn_monochrome(dir.path());
    let plan = dir.path().join("plan.json");
    std::fs::write(&plan, small_plan(8).to_string()).expect("plan");
    let run = dir.path().join("run");
    let first_passes = run.join("processed/normtextures/first-pass");
    // Paced to 25× the wall (about 0.2 s per frame), so frames are
    // registered while the capture runs, even on a loaded machine.
    let mut child = common::rigd()
        .args(["run", "--sim", "--profile"])
        .arg(&monochrome)
        .args([
            "--scene",
            "corduroy",
            "--frame-size",
            "320x240",
            "--order",
            "slots",
        ])
        .args([
            "--sim-speed",
            "25",
            "--progress",
            "log",
            "--process",
            "rectify,btf",
        ])
        .arg("--plan")
        .arg(&plan)
        .arg("--out")
        .arg(&run)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("rigd run");
    let started = std::time::Instant::now();
    let count = |d: &Path| std::fs::read_dir(d).map_or(0, |r| r.count());
    while count(&first_passes) < 8 {
        assert!(
            child.try_wait().expect("wait").is_none(),
            "the capture ended before 8 frames were registered"
        );
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "no frame registered"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().expect("kill -9");
    let _ = child.wait();
    let kept = count(&first_passes);
    let journaled = std::fs::read_to_string(run.join(rigd::store::JOURNAL_FILE))
        .expect("journal")
        .lines()
        .count();
    assert!(
        journaled < IMAGES,
        "killed while capturing: {journaled} frames"
    );
    let job: Value =
        serde_json::from_slice(&std::fs::read(run.join("processed/job.json")).expect("job.json"))
            .expect("job.json is JSON");
    assert_eq!(job["state"], "queued", "{job}");
    assert_eq!(job["after_capture"], true, "{job}");

    let out = common::rigd()
        .args(["run", "--progress", "log", "--sim-speed", "200", "--resume"])
        .arg(&run)
        .output()
        .expect("rigd run --resume");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("its processing, asked with the capture, follows: rectify, btf"),
        "{err}"
    );
    assert_complete_run(&run, IMAGES);
    let job: Value =
        serde_json::from_slice(&std::fs::read(run.join("processed/job.json")).expect("job.json"))
            .expect("job.json is JSON");
    assert_eq!(job["state"], "done", "{job}");
    let before = done_before(job["steps"][0]["summary"].as_str().unwrap_or(""));
    assert!(
        before >= kept && before <= IMAGES,
        "{kept} kept at the kill, {before} taken by the step: {job}"
    );
    assert!(
        done_before(job["steps"][1]["summary"].as_str().unwrap_or("")) >= 1,
        "{job}"
    );
    assert!(!first_passes.exists());
    assert!(!run.join("processed/btf-ahead").exists());

    let reference = dir.path().join("reference");
    crate::common::copy_dir(&run, &reference);
    std::fs::remove_dir_all(reference.join("processed")).expect("a fresh copy");
    // `--process` takes the daemon's defaults: final 128, a quarter of it
    // blended, C = 16.
    let defaults = ["--size", "512", "--final", "128", "--blend", "32"];
    assert_same_btf_as_cli(&run, &reference, &defaults, "16");
}
