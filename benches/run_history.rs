//! The run history at scale: 30,000 runs in the data directory.
//!
//! Makes one small real run (a simulated capture of one image at 16×12),
//! copies its record (run.json, state.json, journal, manifest; never its
//! frames) under 30,000 ids with varied samples, plans, states and start
//! times (`tests/common/history.rs`), then measures, in this process over
//! HTTP on 127.0.0.1:
//!
//! 1. start-up to the first answer of `GET /api/v1/runs?limit=50`, with no
//!    run index (every run's files read) and with it (`DATA/runs-index.json`);
//! 2. p50/p99 of `GET /api/v1/runs?limit=50`: the first page, a page 5,000
//!    runs down through a cursor, and a filtered page (sample and state).
//!
//! Goals: p99 < 20 ms a page, start-up < 2 s. `cargo bench --bench
//! run_history` (env: `RIGD_HISTORY_RUNS`, default 30000;
//! `RIGD_HISTORY_REQUESTS`, default 500 a case; `RIGD_HISTORY_DIR`, where
//! the temporary data directory goes, default the system's). It takes
//! about 25 KB of disk a run (the record's files), removed at the end.

#[path = "../tests/common/history.rs"]
#[allow(dead_code)]
mod history;
#[path = "../tests/common/http.rs"]
#[allow(dead_code)]
mod http;
#[path = "support/stats.rs"]
mod stats;

use stats::{env_or, pct};
use std::time::{Duration, Instant};

use http::{run_body, small_plan, start_in, Srv};
use serde_json::Value;

fn du(dir: &std::path::Path) -> u64 {
    let mut total = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            match e.metadata() {
                Ok(m) if m.is_dir() => stack.push(e.path()),
                Ok(m) => total += m.len(),
                Err(_) => {}
            }
        }
    }
    total
}

/// Starts the daemon and times it to its first answer of a page.
async fn timed_start(data: &std::path::Path) -> (Srv, f64) {
    let t = Instant::now();
    let s = start_in(data, 1000.0).await;
    let (status, page) = s.get("/api/v1/runs?limit=50").await;
    let secs = t.elapsed().as_secs_f64();
    assert_eq!(status, 200, "{page}");
    (s, secs)
}

/// `n` sequential GETs of `path`; latencies in ms, sorted.
async fn latencies(s: &Srv, path: &str, n: usize) -> Vec<f64> {
    let url = s.url(path);
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        let r = s.client.get(&url).send().await.expect("GET");
        let status = r.status().as_u16();
        let body = r.bytes().await.expect("body");
        out.push(t.elapsed().as_secs_f64() * 1e3);
        assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
    }
    out.sort_by(|a, b| a.total_cmp(b));
    out
}

fn main() {
    let runs: usize = env_or("RIGD_HISTORY_RUNS", 30_000);
    let requests: usize = env_or("RIGD_HISTORY_REQUESTS", 500);
    let tmp = match std::env::var_os("RIGD_HISTORY_DIR") {
        Some(d) => tempfile::tempdir_in(d),
        None => tempfile::tempdir(),
    }
    .expect("temporary data directory");
    let data = tmp.path().to_path_buf();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        // One real run.
        let mut s = start_in(&data, 20_000.0).await;
        let (status, v) = s
            .post("/api/v1/runs", Some(run_body("seed", small_plan(1))))
            .await;
        assert_eq!(status, 201, "{v}");
        let seed = v["id"].as_str().expect("id").to_string();
        s.wait_ended(&seed, "completed").await;
        s.shutdown().await;
        let runs_dir = data.join("runs");
        let t = Instant::now();
        let copies = history::clone_runs(&runs_dir.join(&seed), &runs_dir, runs);
        std::fs::remove_dir_all(runs_dir.join(&seed)).expect("remove the seed");
        println!(
            "{} runs made in {:.1} s, {:.0} MB on disk",
            copies.len(),
            t.elapsed().as_secs_f64(),
            du(&data) as f64 / 1e6
        );

        // Start-up, without and with the index (the files are in the page
        // cache either way: they were just written or read).
        let (mut s, cold) = timed_start(&data).await;
        s.shutdown().await;
        let index_mb = std::fs::metadata(data.join("runs-index.json")).map_or(0, |m| m.len()) as f64 / 1e6;
        let mut warm = Vec::new();
        for _ in 0..3 {
            let (mut s, secs) = timed_start(&data).await;
            warm.push(secs);
            s.shutdown().await;
        }
        warm.sort_by(|a, b| a.total_cmp(b));
        println!();
        println!("start to first page, no index:   {cold:.2} s");
        println!(
            "start to first page, with index: {:.2} s (median of 3: {:.2} {:.2} {:.2} s; index {index_mb:.1} MB)",
            warm[1], warm[0], warm[1], warm[2]
        );

        // Pages.
        let (s, _) = timed_start(&data).await;
        // A cursor 5,000 runs down, reached 1,000 at a time.
        let mut cursor = String::new();
        for _ in 0..5 {
            let q = if cursor.is_empty() {
                "/api/v1/runs?limit=1000".to_string()
            } else {
                format!("/api/v1/runs?limit=1000&cursor={cursor}")
            };
            let (status, page): (u16, Value) = s.get(&q).await;
            assert_eq!(status, 200, "{page}");
            cursor = page["next"].as_str().expect("next").to_string();
        }
        let filtered = "/api/v1/runs?limit=50&sample=felt&state=aborted";
        let (_, f) = s.get(filtered).await;
        let cases = [
            ("first page".to_string(), "/api/v1/runs?limit=50".to_string()),
            (
                "page at run 5,000 (cursor)".to_string(),
                format!("/api/v1/runs?limit=50&cursor={cursor}"),
            ),
            (
                format!("filtered (sample=felt&state=aborted, total {})", f["total"]),
                filtered.to_string(),
            ),
        ];
        // Warm-up.
        for (_, path) in &cases {
            latencies(&s, path, 20).await;
        }
        println!();
        println!(
            "{:<48} {:>6} {:>9} {:>9} {:>9}",
            "GET /api/v1/runs, 30,000 runs", "n", "p50 ms", "p99 ms", "max ms"
        );
        let mut worst: f64 = 0.0;
        for (what, path) in &cases {
            let lat = latencies(&s, path, requests).await;
            let p99 = pct(&lat, 0.99);
            worst = worst.max(p99);
            println!(
                "{:<48} {:>6} {:>9.2} {:>9.2} {:>9.2}",
                what,
                lat.len(),
                pct(&lat, 0.5),
                p99,
                lat.last().copied().unwrap_or(f64::NAN)
            );
        }
        println!();
        println!(
            "goals: p99 < 20 ms: {}; start < 2 s: {}",
            if worst < 20.0 { "met" } else { "NOT met" },
            if warm[1] < 2.0 { "met" } else { "NOT met" }
        );
        let mut s = s;
        tokio::time::timeout(Duration::from_secs(60), s.shutdown())
            .await
            .expect("shutdown");
    });
    drop(rt);
    // The temporary directory goes with `tmp`.
    drop(tmp);
}
