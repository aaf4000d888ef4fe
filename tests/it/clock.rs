//! Physical time is the rig's: the command line's virtual time equals the
//! plan's estimate, and the daemon's sped-up simulation reports the same
//! physical time at any speed, with the host idle or loaded.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use serde_json::{json, Value};

use crate::common::http::start_in;
use crate::common::run_ok;

/// 2 views × 40 lights on the Bonn rig (80 images, about ten minutes).
fn plan_2x40() -> Value {
    let lights: Vec<Value> = (0..40)
        .map(
            |i| json!({"theta_deg": 10.0 + 15.0 * f64::from(i % 4), "phi_deg": 9.0 * f64::from(i)}),
        )
        .collect();
    json!({
        "name": "two-views",
        "lights": lights,
        "views": [{"theta_deg": 0.0, "phi_deg": 0.0}, {"theta_deg": 45.0, "phi_deg": 90.0}],
    })
}

fn manifest_physical_s(run: &std::path::Path) -> f64 {
    let bytes = std::fs::read(run.join("manifest.json")).expect("manifest.json");
    let m: Value = serde_json::from_slice(&bytes).expect("manifest parses");
    m["physical_duration_s"]
        .as_f64()
        .expect("physical_duration_s")
}

/// Two threads that keep both cores busy until dropped.
struct CpuHogs {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl CpuHogs {
    fn start(n: usize) -> CpuHogs {
        let stop = Arc::new(AtomicBool::new(false));
        let threads = (0..n)
            .map(|_| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let mut x = 1u64;
                    while !stop.load(Ordering::Relaxed) {
                        x = std::hint::black_box(
                            x.wrapping_mul(6364136223846793005).wrapping_add(1),
                        );
                    }
                })
            })
            .collect();
        CpuHogs { stop, threads }
    }
}

impl Drop for CpuHogs {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_reports_the_rigs_physical_time_at_any_speed_and_load() {
    let dir = tempfile::tempdir().expect("tempdir");
    let plan_file = dir.path().join("two-views.json");
    std::fs::write(&plan_file, plan_2x40().to_string()).expect("plan file");
    let plan = plan_file.to_str().expect("utf8");

    // The command line, in virtual time: exactly the timing model's estimate.
    let shown = run_ok(&["plan", "show", plan, "--json"]);
    let shown: Value = serde_json::from_slice(&shown.stdout).expect("json");
    let estimate = shown["estimated_physical_s"].as_f64().expect("estimate");
    let cli_run = dir.path().join("cli");
    run_ok(&[
        "run",
        "--sim",
        "--plan",
        plan,
        "--frame-size",
        "32x24",
        "--progress",
        "none",
        "--out",
        cli_run.to_str().expect("utf8"),
    ]);
    let cli = manifest_physical_s(&cli_run);
    assert!(
        (cli - estimate).abs() <= 1e-6 * estimate,
        "command line {cli} s, estimate {estimate} s"
    );
    // Brackets take every exposure at the pose, each transferred before the
    // next: the estimate says so (up to the camera's exposure changes,
    // which the model leaves out).
    let brackets = "brackets:0.25,0.0625";
    let shown = run_ok(&[
        "plan",
        "show",
        plan,
        "--json",
        "--exposure-policy",
        brackets,
    ]);
    let shown: Value = serde_json::from_slice(&shown.stdout).expect("json");
    let bracket_estimate = shown["estimated_physical_s"].as_f64().expect("estimate");
    let bracket_run = dir.path().join("brackets");
    run_ok(&[
        "run",
        "--sim",
        "--plan",
        plan,
        "--frame-size",
        "32x24",
        "--exposure-policy",
        brackets,
        "--progress",
        "none",
        "--out",
        bracket_run.to_str().expect("utf8"),
    ]);
    let bracketed = manifest_physical_s(&bracket_run);
    assert!(
        bracket_estimate > estimate * 1.5
            && (bracketed - bracket_estimate).abs() <= 1e-3 * bracket_estimate,
        "bracketed {bracketed} s, estimate {bracket_estimate} s (single {estimate} s)"
    );

    // The daemon, paced to the wall clock: the same physical time, idle and
    // with both cores busy, at 200x and 1000x.
    for speed in [200.0, 1000.0] {
        let data = tempfile::tempdir().expect("tempdir");
        let mut srv = start_in(data.path(), speed).await;
        for hogs in [false, true] {
            let _hogs = hogs.then(|| CpuHogs::start(2));
            let body = json!({"sample": "clock", "plan": plan_2x40(), "frame_size": [32, 24]});
            let (status, run) = srv.post("/api/v1/runs", Some(body)).await;
            assert_eq!(status, 201, "{run}");
            let id = run["id"].as_str().expect("id").to_string();
            if speed == 200.0 {
                // While it runs, its view says how fast it goes.
                srv.wait_run(&id, "its pace", |v| {
                    v["pace"]["asked_speed"] == speed && v["pace"]["achieved_speed"].is_number()
                })
                .await;
            }
            let ended = srv.wait_ended(&id, "completed").await;
            let daemon = manifest_physical_s(&data.path().join("runs").join(&id));
            assert!(
                (daemon - cli).abs() <= 1e-3 * cli,
                "speed {speed}, hogs {hogs}: daemon {daemon} s, command line {cli} s ({ended})"
            );
        }
        srv.shutdown().await;
    }
}
