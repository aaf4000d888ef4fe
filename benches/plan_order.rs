//! Plan solve and trigger ordering: H1 on the Bonn rig (6561 steps) and a
//! 100 000-step plan file (400 lights × 250 views), each resolved, solved
//! pose by pose and ordered for the shortest physical time, as `rigd run`
//! does before a capture. Criterion reports the wall time per plan; the
//! 100 000-step case also prints the resident memory it grew by.

use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use rigd::model::profile::Profile;
use rigd::plan::Order;

fn big_plan(dir: &std::path::Path) -> std::path::PathBuf {
    let dirs = |n: usize, seed: f64| -> Vec<serde_json::Value> {
        (0..n)
            .map(|k| {
                let t = 80.0 * ((k as f64 * 0.618_034 + seed) % 1.0);
                let p = (k as f64 * 137.507_764) % 360.0;
                serde_json::json!({"theta_deg": t, "phi_deg": p})
            })
            .collect()
    };
    let path = dir.join("big.json");
    let plan = serde_json::json!({"lights": dirs(400, 0.1), "views": dirs(250, 0.7)});
    std::fs::write(&path, plan.to_string()).expect("write plan");
    path
}

fn rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1).map(str::to_string))
        })
        .and_then(|v| v.parse().ok())
        .unwrap_or(0)
}

fn bench(c: &mut Criterion) {
    let profile = Profile::load("bonn-gonioreflectometer").expect("profile");
    let mut g = c.benchmark_group("plan_solve_and_order");
    g.sample_size(10).measurement_time(Duration::from_secs(20));
    for order in [Order::Naive, Order::Optimised] {
        g.bench_function(format!("h1_6561_{order:?}"), |b| {
            b.iter(|| rigd::engine::launch::solve_plan(&profile, "h1", Some(order)).expect("solve"))
        });
    }
    let dir = tempfile::tempdir().expect("tempdir");
    let path = big_plan(dir.path());
    let spec = path.to_string_lossy().into_owned();
    let before = rss_kib();
    let (_, _, s) =
        rigd::engine::launch::solve_plan(&profile, &spec, Some(Order::Optimised)).expect("solve");
    eprintln!(
        "100 000-step plan: {} images, resident memory grew by {} MiB",
        s.images.len(),
        rss_kib().saturating_sub(before) / 1024
    );
    drop(s);
    g.sample_size(10).measurement_time(Duration::from_secs(60));
    g.bench_function("file_100000_Optimised", |b| {
        b.iter(|| {
            rigd::engine::launch::solve_plan(&profile, &spec, Some(Order::Optimised))
                .expect("solve")
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
