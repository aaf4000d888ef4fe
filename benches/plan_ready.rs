//! How soon a daemon that has just started takes a run: the latency of
//! `POST /api/v1/runs` with a built-in plan (`h2`, 6,561 images) sent the
//! moment the daemon answers, with a thread spinning on the other core all
//! the while. Three cases:
//!
//! 1. a restarted daemon: its solved plans kept on disk (`DATA/plan-cache/`)
//!    by an earlier start, the goal being p99 under 100 ms;
//! 2. a daemon on a new data directory, nothing solved yet: it waits for the
//!    solve (stated, not a goal);
//! 3. a custom inline plan of 81 × 81 = 6,561 images, always solved on the
//!    request (stated).
//!
//! `cargo bench --bench plan_ready` (env `RIGD_PLAN_READY_STARTS`, default
//! 20 starts for case 1). The daemons run in this process on 127.0.0.1.

#[path = "../tests/common/http.rs"]
#[allow(dead_code)]
mod http;
#[path = "support/stats.rs"]
mod stats;

use stats::{env_or, pct};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::{json, Value};

/// Keeps one core busy until dropped.
struct Hog(Arc<AtomicBool>, Option<std::thread::JoinHandle<()>>);

impl Hog {
    fn start() -> Hog {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut x = 0u64;
            while !flag.load(Ordering::Relaxed) {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
        });
        Hog(stop, Some(thread))
    }
}

impl Drop for Hog {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
        if let Some(t) = self.1.take() {
            let _ = t.join();
        }
    }
}

/// Starts a daemon on `data`, posts `body` at once, and returns the
/// answer's latency in ms; the run is aborted and the daemon stopped.
async fn post_on_fresh_daemon(data: &std::path::Path, body: &Value) -> f64 {
    let mut s = http::start_in(data, 1000.0).await;
    let t = Instant::now();
    let (status, v) = s.post("/api/v1/runs", Some(body.clone())).await;
    let ms = t.elapsed().as_secs_f64() * 1e3;
    assert_eq!(status, 201, "{v}");
    if let Some(id) = v["id"].as_str() {
        let _ = s.post(&format!("/api/v1/runs/{id}/abort"), None).await;
        s.wait_run(id, "ended", |v| v["active"] == false).await;
    }
    s.shutdown().await;
    ms
}

fn dir81() -> Vec<Value> {
    (0..81)
        .map(|i| json!({"theta_deg": 5.0 + (i % 9) as f64 * 9.0, "phi_deg": (i / 9) as f64 * 40.0}))
        .collect()
}

fn main() {
    let starts: usize = env_or("RIGD_PLAN_READY_STARTS", 20);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let h2 = json!({"sample": "bench", "plan": "h2", "frame_size": [16, 12]});
    let custom = json!({"sample": "bench", "order": "optimised", "frame_size": [16, 12],
        "plan": {"name": "custom81", "lights": dir81(), "views": dir81()}});
    rt.block_on(async {
        let dir = tempfile::tempdir().expect("tempdir");
        // The first start solves every built-in plan and keeps them.
        let t = Instant::now();
        let mut s = http::start_in(dir.path(), 1000.0).await;
        loop {
            let (_, plans) = s.get("/api/v1/plans").await;
            let all = plans["plans"].as_array().cloned().unwrap_or_default();
            if !all.is_empty() && all.iter().all(|p| p["ready"] == true) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        println!(
            "first start: every built-in plan solved and kept in {:.1} s",
            t.elapsed().as_secs_f64()
        );
        s.shutdown().await;

        let _hog = Hog::start();
        let mut warm = Vec::new();
        for _ in 0..starts {
            warm.push(post_on_fresh_daemon(dir.path(), &h2).await);
        }
        warm.sort_by(f64::total_cmp);
        println!(
            "POST /runs h2, restarted daemon, plans on disk, other core busy: n={} p50 {:.1} ms p99 {:.1} ms max {:.1} ms",
            warm.len(),
            pct(&warm, 0.5),
            pct(&warm, 0.99),
            warm.last().copied().unwrap_or(f64::NAN)
        );
        let mut cold = Vec::new();
        for _ in 0..3 {
            let fresh = tempfile::tempdir().expect("tempdir");
            cold.push(post_on_fresh_daemon(fresh.path(), &h2).await);
        }
        cold.sort_by(f64::total_cmp);
        println!(
            "POST /runs h2, new data directory (solved on the request), other core busy: {}",
            cold.iter().map(|ms| format!("{ms:.0} ms")).collect::<Vec<_>>().join(", ")
        );
        let mut inline = Vec::new();
        for _ in 0..3 {
            inline.push(post_on_fresh_daemon(dir.path(), &custom).await);
        }
        println!(
            "POST /runs custom 81 × 81 = 6561 images, optimised order, other core busy: {}",
            inline.iter().map(|ms| format!("{ms:.0} ms")).collect::<Vec<_>>().join(", ")
        );
    });
}
