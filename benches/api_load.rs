//! Load benchmark of the daemon's API, on loopback only, bounded in time
//! and count, stopping by itself:
//!
//! 1. p50/p99 latency of `GET /api/v1/rig` and `GET /api/v1/runs/{id}` at a
//!    fixed open-loop rate (default 300 requests/s in total, for 10 s)
//!    while a simulated H1 run captures;
//! 2. SSE delivery to 100 connected clients: every client must receive
//!    every event; the latency from a `POST /api/v1/queue` to each client
//!    seeing its `queue_changed` event.
//!
//! `cargo bench --bench api_load` (env: `RIGD_LOAD_RPS`, `RIGD_LOAD_SECS`,
//! `RIGD_LOAD_SSE_CLIENTS`). The daemon runs in this process on its own
//! 2-thread runtime; the clients on another.

#[path = "../tests/common/http.rs"]
#[allow(dead_code)]
mod http;
#[path = "support/stats.rs"]
mod stats;

use stats::{env_or, pct};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use http::{start_in, SseReader};
use serde_json::{json, Value};

/// What one SSE client saw: event ids, marker latencies (ms), arrival times.
type ReaderResult = (Vec<u64>, Vec<f64>, Vec<(u64, Instant)>);

struct Row {
    what: String,
    n: usize,
    errors: usize,
    rate: f64,
    lat_ms: Vec<f64>,
}

fn print_table(rows: &mut [Row]) {
    println!();
    println!(
        "{:<44} {:>7} {:>6} {:>9} {:>9} {:>9} {:>9}",
        "what", "n", "errors", "rate/s", "p50 ms", "p99 ms", "max ms"
    );
    for r in rows.iter_mut() {
        r.lat_ms.sort_by(|a, b| a.total_cmp(b));
        println!(
            "{:<44} {:>7} {:>6} {:>9.1} {:>9.2} {:>9.2} {:>9.2}",
            r.what,
            r.n,
            r.errors,
            r.rate,
            pct(&r.lat_ms, 0.5),
            pct(&r.lat_ms, 0.99),
            r.lat_ms.last().copied().unwrap_or(f64::NAN)
        );
    }
}

fn main() {
    let rps: f64 = env_or("RIGD_LOAD_RPS", 300.0);
    let secs: f64 = env_or("RIGD_LOAD_SECS", 10.0);
    let sse_clients: usize = env_or("RIGD_LOAD_SSE_CLIENTS", 100);
    let markers: usize = 20;
    let dir = tempfile::tempdir().expect("tempdir");

    // The daemon on its own runtime.
    let server_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("server runtime");
    let mut srv = server_rt.block_on(start_in(dir.path(), 200.0));
    let base = srv.base.clone();
    let token = srv.token.clone();
    assert!(base.starts_with("http://127.0.0.1:"), "loopback only");

    let daemon = srv.handle.as_ref().expect("handle").daemon.clone();
    let client_rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("client runtime");
    let mut rows = client_rt.block_on(async move {
        let client = reqwest::Client::builder()
            .pool_max_idle_per_host(64)
            .timeout(Duration::from_secs(10))
            .build()
            .expect("client");
        // A demo H1 capture at the daemon's default speed, default frame size.
        let r = client
            .post(format!("{base}/api/v1/runs"))
            .bearer_auth(&token)
            .json(&json!({"sample": "load", "plan": "h1"}))
            .send()
            .await
            .expect("start run");
        assert_eq!(r.status().as_u16(), 201);
        let run: Value = r.json().await.expect("run");
        let id = run["id"].as_str().expect("id").to_string();
        // Let it get past homing.
        let t0 = Instant::now();
        loop {
            let v: Value = client
                .get(format!("{base}/api/v1/runs/{id}"))
                .send()
                .await
                .expect("get")
                .json()
                .await
                .expect("json");
            if v["state"] == "running" || t0.elapsed() > Duration::from_secs(20) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }

        // 1. Open-loop request load, alternating the two routes.
        let total = (rps * secs) as usize;
        let period = Duration::from_secs_f64(1.0 / rps);
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
        let mut tasks = Vec::with_capacity(total);
        let started = Instant::now();
        for i in 0..total {
            tick.tick().await;
            let url = if i % 2 == 0 {
                format!("{base}/api/v1/rig")
            } else {
                format!("{base}/api/v1/runs/{id}")
            };
            let c = client.clone();
            tasks.push(tokio::spawn(async move {
                let t = Instant::now();
                let ok = match c.get(url).send().await {
                    Ok(r) => r.status().is_success() && r.bytes().await.is_ok(),
                    Err(_) => false,
                };
                (i % 2, ok, t.elapsed().as_secs_f64() * 1e3)
            }));
        }
        let mut rig = Row { what: "GET /api/v1/rig".into(), n: 0, errors: 0, rate: 0.0, lat_ms: vec![] };
        let mut one = Row { what: "GET /api/v1/runs/{id}".into(), n: 0, errors: 0, rate: 0.0, lat_ms: vec![] };
        for t in tasks {
            let (which, ok, ms) = t.await.expect("task");
            let row = if which == 0 { &mut rig } else { &mut one };
            row.n += 1;
            if ok {
                row.lat_ms.push(ms);
            } else {
                row.errors += 1;
            }
        }
        let wall = started.elapsed().as_secs_f64();
        rig.rate = rig.n as f64 / wall;
        one.rate = one.n as f64 / wall;
        let progress: Value = client
            .get(format!("{base}/api/v1/runs/{id}"))
            .send()
            .await
            .expect("get")
            .json()
            .await
            .expect("json");
        eprintln!(
            "run {id}: {} of {} frames captured so far ({})",
            progress["steps_done"], progress["steps_total"], progress["state"]
        );

        // 2. SSE fan-out to many clients while the run captures.
        let received = Arc::new(AtomicUsize::new(0));
        let (mark_tx, _) = tokio::sync::broadcast::channel::<(String, Instant)>(markers * 2);
        let mut readers = Vec::new();
        let (ready_tx, mut ready_rx) = tokio::sync::mpsc::channel::<()>(sse_clients);
        for _ in 0..sse_clients {
            let c = reqwest::Client::new();
            let url = format!("{base}/api/v1/events");
            let received = received.clone();
            let mut marks = mark_tx.subscribe();
            let ready = ready_tx.clone();
            readers.push(tokio::spawn(async move {
                let (status, sse) = SseReader::connect(&c, &url, None).await;
                assert_eq!(status, 200);
                let mut sse = sse.expect("sse");
                let _ = ready.send(()).await;
                let mut ids = Vec::new();
                let mut times: Vec<(u64, Instant)> = Vec::new();
                let mut seen_items: Vec<(String, Instant)> = Vec::new();
                while let Some((id, ev)) = sse.next(Duration::from_secs(5)).await {
                    received.fetch_add(1, Ordering::Relaxed);
                    ids.extend(id);
                    if let Some(id) = id {
                        times.push((id, Instant::now()));
                    }
                    if ev["kind"] == "queue_changed" {
                        for item in ev["event"]["items"].as_array().into_iter().flatten() {
                            if let Some(i) = item["id"].as_str() {
                                if !seen_items.iter().any(|(s, _)| s == i) {
                                    seen_items.push((i.to_string(), Instant::now()));
                                }
                            }
                        }
                    }
                    if ev["kind"] == "bench_done" {
                        break;
                    }
                }
                let mut lat = Vec::new();
                while let Ok((item, sent)) = marks.try_recv() {
                    if let Some((_, at)) = seen_items.iter().find(|(s, _)| *s == item) {
                        lat.push(at.duration_since(sent).as_secs_f64() * 1e3);
                    }
                }
                (ids, lat, times)
            }));
        }
        drop(ready_tx);
        for _ in 0..sse_clients {
            let _ = ready_rx.recv().await;
        }
        let sse_start = Instant::now();
        let mut put_latencies = Vec::new();
        for _ in 0..markers {
            let sent = Instant::now();
            let r = client
                .post(format!("{base}/api/v1/queue"))
                .bearer_auth(&token)
                .json(&json!({"sample": "marker", "plan": "h1"}))
                .send()
                .await
                .expect("queue");
            assert_eq!(r.status().as_u16(), 201);
            let v: Value = r.json().await.expect("json");
            put_latencies.push(sent.elapsed().as_secs_f64() * 1e3);
            let item = v["item"]["id"].as_str().expect("item").to_string();
            let _ = mark_tx.send((item.clone(), sent));
            tokio::time::sleep(Duration::from_millis(100)).await;
            let _ = client
                .delete(format!("{base}/api/v1/queue/{item}"))
                .bearer_auth(&token)
                .send()
                .await;
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
        // Abort the run: its events end the stream for the readers.
        let _ = client
            .post(format!("{base}/api/v1/runs/{id}/abort"))
            .bearer_auth(&token)
            .send()
            .await;
        let sse_wall = sse_start.elapsed().as_secs_f64();
        // Tell the readers to stop, from the daemon's side.
        tokio::time::sleep(Duration::from_millis(300)).await;
        daemon.hub.publish(None, "bench_done", json!({}));
        let mut results: Vec<ReaderResult> = Vec::new();
        for r in readers {
            results.push(r.await.expect("reader"));
        }
        // Fan-out spread: for each event every client got, the time from the
        // first client receiving it to the last.
        let mut by_id: std::collections::BTreeMap<u64, (Instant, Instant, usize)> =
            std::collections::BTreeMap::new();
        for (_, _, times) in &results {
            for &(id, at) in times {
                let e = by_id.entry(id).or_insert((at, at, 0));
                e.0 = e.0.min(at);
                e.1 = e.1.max(at);
                e.2 += 1;
            }
        }
        let spread: Vec<f64> = by_id
            .values()
            .filter(|(_, _, n)| *n == results.len())
            .map(|(a, b, _)| b.duration_since(*a).as_secs_f64() * 1e3)
            .collect();
        let counts: Vec<usize> = results.iter().map(|(ids, _, _)| ids.len()).collect();
        let complete = results
            .iter()
            .filter(|(ids, _, _)| ids.windows(2).all(|w| w[1] == w[0] + 1))
            .count();
        let lat: Vec<f64> = results.iter().flat_map(|(_, l, _)| l.iter().copied()).collect();
        let delivered = received.load(Ordering::Relaxed);
        let min = counts.iter().min().copied().unwrap_or(0);
        let max = counts.iter().max().copied().unwrap_or(0);
        eprintln!(
            "SSE: {} clients, {delivered} events delivered in {:.1} s ({:.0}/s); per client {min}..{max} events, {complete} of {} saw every id in order",
            counts.len(),
            sse_wall,
            delivered as f64 / sse_wall,
            counts.len()
        );
        let n = lat.len();
        vec![
            rig,
            one,
            Row {
                what: "POST /api/v1/queue (during SSE fan-out)".into(),
                n: put_latencies.len(),
                errors: 0,
                rate: markers as f64 / sse_wall,
                lat_ms: put_latencies,
            },
            Row {
                what: format!("SSE: POST sent -> seen by each of {}", counts.len()),
                n,
                errors: markers * counts.len() - n,
                rate: delivered as f64 / sse_wall,
                lat_ms: lat,
            },
            Row {
                what: format!("SSE fan-out spread, first..last of {}", counts.len()),
                n: spread.len(),
                errors: 0,
                rate: spread.len() as f64 / sse_wall,
                lat_ms: spread,
            },
        ]
    });
    print_table(&mut rows);
    server_rt.block_on(srv.shutdown());
}
