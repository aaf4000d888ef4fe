//! Hostile clients against the real daemon (`rigd serve --sim` as a
//! process, with the common soft and hard limit of 1024 open files) while
//! a small capture runs beside them: a flood of idle connections beyond
//! the connection cap, slow-loris heads and bodies, huge and deeply nested
//! bodies, and every name a client can send tried as a path (the token
//! file, `/etc/passwd`, `/proc/self/environ`, `/dev/zero`, a FIFO).
//! Throughout, `/health` is probed on fresh connections and the daemon's
//! memory is watched (and the daemon killed past the bound, so a leak
//! cannot take the machine down). Then: the capture completed without a
//! pause or a retry, `/health` always answered within 1 s (one probe
//! alone may take up to the 2 s header timeout, see [`probe_health`]), the memory
//! stayed under 500 MB, slow connections were closed within the timeout,
//! and no answer held the token, a line of `/etc/passwd` or the daemon's
//! environment. The CLI's file options are tried with devices and FIFOs
//! too.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::http::{run_body, small_plan};
use serde_json::{json, Value};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// The acceptance's bounds.
const MEMORY_BOUND_KB: u64 = 500 * 1024;
const HEALTH_BOUND: Duration = Duration::from_secs(1);
/// The timeouts the test configures (`[http]`); the defaults are 10 s.
const HEADER_TIMEOUT_S: f64 = 2.0;
const BODY_TIMEOUT_S: f64 = 2.0;
/// What "closed within the timeout" allows beyond it.
const CLOSE_MARGIN: Duration = Duration::from_millis(1500);
/// The daemon's open-file limit (soft and hard), as on many machines.
const FD_LIMIT: u32 = 1024;
/// Idle connections in the flood: more than the daemon may open at all.
const FLOOD: usize = 1100;

struct Daemon {
    child: Child,
    pid: u32,
    addr: String,
    token: String,
    log: Arc<Mutex<String>>,
    /// The largest resident memory seen, kB ([`watch_memory`]).
    peak_kb: Arc<AtomicU64>,
}

impl Daemon {
    /// For a failed request: whether the daemon still lives, and its memory.
    fn condition(&self) -> String {
        let peak = self.peak_kb.load(Ordering::SeqCst) / 1024;
        match status_kb(self.pid, "VmRSS:") {
            Some(rss) => format!("the daemon lives, at {} MB (peak {peak} MB)", rss / 1024),
            None => format!("the daemon is gone (killed past 500 MB? peak {peak} MB)"),
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `rigd serve --sim` under `ulimit -n 1024`, on a free port, with short
/// request timeouts and every other limit at its default.
fn spawn_daemon(data: &Path, speed: f64) -> Daemon {
    let config = data.join("rigd.toml");
    std::fs::create_dir_all(data).expect("data dir");
    std::fs::write(
        &config,
        format!(
            "[http]\nheader_timeout_s = {HEADER_TIMEOUT_S}\nbody_timeout_s = {BODY_TIMEOUT_S}\n"
        ),
    )
    .expect("config");
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -n {FD_LIMIT} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_rigd"))
        .args(["serve", "--sim", "--listen", "127.0.0.1:0", "--sim-speed"])
        .arg(speed.to_string())
        .arg("--data")
        .arg(data)
        .arg("--config")
        .arg(&config)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn rigd serve");
    let stderr = child.stderr.take().expect("stderr");
    let log = Arc::new(Mutex::new(String::new()));
    let (tx, rx) = std::sync::mpsc::channel();
    let kept = log.clone();
    // Drained to the end: a full pipe would stall the daemon's logging.
    std::thread::spawn(move || {
        let mut tx = Some(tx);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("on http://").nth(1) {
                if let Some(t) = tx.take() {
                    let _ = t.send(rest.split('/').next().unwrap_or("").to_string());
                }
            }
            let mut log = kept.lock().unwrap_or_else(|p| p.into_inner());
            if log.len() < 1 << 20 {
                log.push_str(&line);
                log.push('\n');
            }
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_secs(30))
        .unwrap_or_else(|_| panic!("the daemon says where it listens: {}", log.lock().unwrap()));
    let token = std::fs::read_to_string(data.join("token"))
        .expect("token file")
        .trim()
        .to_string();
    Daemon {
        pid: child.id(),
        child,
        addr,
        token,
        log,
        peak_kb: Arc::new(AtomicU64::new(0)),
    }
}

fn status_kb(pid: u32, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Samples the daemon's resident memory; past the bound it kills the
/// daemon (the test then fails on it) rather than let it take the machine.
fn watch_memory(pid: u32, stop: Arc<AtomicBool>, peak_kb: Arc<AtomicU64>) {
    std::thread::spawn(move || {
        while !stop.load(Ordering::SeqCst) {
            let Some(rss) = status_kb(pid, "VmRSS:") else {
                return;
            };
            peak_kb.fetch_max(rss, Ordering::SeqCst);
            if rss > MEMORY_BOUND_KB {
                let _ = Command::new("kill").args(["-9", &pid.to_string()]).status();
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    });
}

#[derive(Default)]
struct Probes {
    count: usize,
    slowest: Duration,
    failures: Vec<String>,
}

/// Asks `/health` every 100 ms, each time on a new connection, until told
/// to stop. A probe fails when it errs, is not 200, or takes longer than
/// the header timeout (what a connection starved behind the slow clients
/// would wait); two probes in a row over [`HEALTH_BOUND`] fail too. One
/// probe alone a little over the bound is the machine's other tests
/// taking the cores for a moment (this test runs beside them), not the
/// daemon: a daemon that stops answering is slow on every probe.
fn probe_health(addr: String, stop: Arc<AtomicBool>) -> tokio::task::JoinHandle<Probes> {
    tokio::spawn(async move {
        let client = reqwest::Client::builder()
            .pool_max_idle_per_host(0)
            .timeout(Duration::from_secs(3))
            .build()
            .expect("client");
        let url = format!("http://{addr}/api/v1/health");
        let mut probes = Probes::default();
        let starved = Duration::from_secs_f64(HEADER_TIMEOUT_S);
        let mut last_slow = false;
        while !stop.load(Ordering::SeqCst) {
            let started = Instant::now();
            let answer = client.get(&url).send().await;
            let took = started.elapsed();
            probes.count += 1;
            probes.slowest = probes.slowest.max(took);
            let slow = took > HEALTH_BOUND;
            match answer {
                Ok(r) if r.status() == 200 && took <= starved && !(slow && last_slow) => {}
                Ok(r) => probes
                    .failures
                    .push(format!("{} after {took:?}", r.status())),
                Err(e) => probes.failures.push(format!("{e} after {took:?}")),
            }
            last_slow = slow;
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        probes
    })
}

/// Everything the daemon answered, to search for leaks at the end.
#[derive(Default, Clone)]
struct Answers(Arc<Mutex<Vec<String>>>);

impl Answers {
    fn keep(&self, what: &str, text: String) {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(format!("{what} => {text}"));
    }
}

/// Sends raw bytes and reads what comes back until the server closes the
/// connection (or `wait` passes): the answer and how long the close took.
async fn raw(addr: &str, head: &[u8], wait: Duration) -> (String, Option<Duration>) {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let started = Instant::now();
    let _ = s.write_all(head).await;
    let mut got = Vec::new();
    let closed = read_to_close(&mut s, &mut got, wait).await;
    (
        String::from_utf8_lossy(&got).into_owned(),
        closed.then(|| started.elapsed()),
    )
}

/// Reads until EOF or a reset (true), or until `wait` passes (false).
async fn read_to_close(s: &mut TcpStream, got: &mut Vec<u8>, wait: Duration) -> bool {
    let deadline = tokio::time::Instant::now() + wait;
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
            Err(_) => return false,
            Ok(Ok(0)) | Ok(Err(_)) => return true,
            Ok(Ok(n)) => got.extend_from_slice(&buf[..n.min(1 << 16)]),
        }
    }
}

fn status_of(answer: &str) -> u16 {
    answer
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_clients_beside_a_capture() {
    raise_own_fd_limit();
    let dir = tempfile::tempdir().expect("tempdir");
    let data = dir.path().join("data");
    let daemon = spawn_daemon(&data, 40.0);
    let addr = daemon.addr.clone();
    let base = format!("http://{addr}");
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(5))
        .build()
        .expect("client");

    let stop = Arc::new(AtomicBool::new(false));
    let peak_kb = daemon.peak_kb.clone();
    watch_memory(daemon.pid, stop.clone(), peak_kb.clone());
    let probes = probe_health(addr.clone(), stop.clone());
    let answers = Answers::default();

    // The capture beside the abuse: 36 frames, about 20 s of wall time.
    let started = client
        .post(format!("{base}/api/v1/runs"))
        .bearer_auth(&daemon.token)
        .json(&run_body("beside", small_plan(6)))
        .send()
        .await
        .expect("start the capture");
    assert_eq!(started.status(), 201);
    let run: Value = started.json().await.expect("run");
    let id = run["id"].as_str().expect("run id").to_string();
    let total = run["steps_total"].as_u64().expect("steps_total");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, run) = get_json(&client, &format!("{base}/api/v1/runs/{id}")).await;
        if run["steps_done"].as_u64() > Some(0) {
            break;
        }
        assert!(Instant::now() < deadline, "the capture never began: {run}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    flood(&addr).await;
    let (status, run) = get_json(&client, &format!("{base}/api/v1/runs/{id}")).await;
    assert_eq!(status, 200);
    assert!(
        run["state"] == "running" && run["steps_done"].as_u64() < Some(total),
        "the capture must still be running after the flood, to have been beside it: {run}"
    );

    slow_clients(&addr, &daemon.token).await;
    names_are_never_paths(&client, &base, &daemon, &data, &id, &answers).await;
    big_and_deep_bodies(&addr, &daemon.token, &answers).await;

    // The capture goes on and completes, untouched.
    let deadline = Instant::now() + Duration::from_secs(120);
    let run = loop {
        let (_, run) = get_json(&client, &format!("{base}/api/v1/runs/{id}")).await;
        if run["state"] != "running" && run["state"] != "preparing" {
            break run;
        }
        assert!(Instant::now() < deadline, "the capture never ended: {run}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    stop.store(true, Ordering::SeqCst);
    let probes = probes.await.expect("probes");
    let hwm = status_kb(daemon.pid, "VmHWM:").unwrap_or(0);
    let peak = peak_kb.load(Ordering::SeqCst).max(hwm);
    let log = daemon.log.lock().map(|l| l.clone()).unwrap_or_default();
    assert!(
        peak <= MEMORY_BOUND_KB,
        "the daemon's memory reached {} MB (bound 500 MB)",
        peak / 1024
    );
    assert_eq!(run["state"], "completed", "{run}\n{log}");
    assert_eq!(run["last_error"], Value::Null, "{run}");
    let history = engine_events(&base, &id).await;
    let troubles: Vec<&Value> = history
        .iter()
        .filter(|e| e["type"] == "retry" || (e["type"] == "state" && e["to"] == "paused"))
        .collect();
    assert!(
        troubles.is_empty(),
        "the capture paused or retried: {troubles:?}"
    );
    common::assert_complete_run(&data.join("runs").join(&id), total as usize);
    assert!(
        probes.failures.is_empty() && probes.count >= 20,
        "/health, asked {} times, slowest {:?}: {:?}",
        probes.count,
        probes.slowest,
        probes.failures
    );
    assert_no_leak(&answers, &daemon);
    eprintln!(
        "abuse: {} health probes, slowest {:?}; daemon peak memory {} MB",
        probes.count,
        probes.slowest,
        peak / 1024
    );
}

fn raise_own_fd_limit() {
    // The flood needs more sockets than a default soft limit may allow.
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit/setrlimit read and write the struct given.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) == 0 && lim.rlim_cur < lim.rlim_max {
            lim.rlim_cur = lim.rlim_max;
            libc::setrlimit(libc::RLIMIT_NOFILE, &lim);
        }
    }
}

async fn get_json(client: &reqwest::Client, url: &str) -> (u16, Value) {
    let r = client.get(url).send().await.expect("GET");
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// More idle connections than the daemon may open: it keeps its cap by
/// closing the quietest, and every one of them is closed within the
/// header timeout.
async fn flood(addr: &str) {
    let mut conns = Vec::with_capacity(FLOOD);
    for _ in 0..FLOOD {
        match TcpStream::connect(addr).await {
            Ok(s) => conns.push(s),
            Err(e) => panic!("connecting the flood: {e}"),
        }
    }
    let opened = Instant::now();
    let wait = Duration::from_secs_f64(HEADER_TIMEOUT_S) + CLOSE_MARGIN;
    let mut still_open = 0;
    for s in &mut conns {
        let mut got = Vec::new();
        let left = wait.saturating_sub(opened.elapsed());
        if !read_to_close(s, &mut got, left).await {
            still_open += 1;
        }
    }
    assert_eq!(
        still_open,
        0,
        "idle connections of the flood still open {:?} after it",
        opened.elapsed()
    );
}

/// Heads and bodies that never finish are closed within their timeouts.
async fn slow_clients(addr: &str, token: &str) {
    let head_wait = Duration::from_secs_f64(HEADER_TIMEOUT_S) + CLOSE_MARGIN;
    let body_wait = Duration::from_secs_f64(BODY_TIMEOUT_S) + CLOSE_MARGIN;
    let partial_head = raw(
        addr,
        b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\nX-Slow: ",
        head_wait,
    );
    let nothing = raw(addr, b"", head_wait);
    let authorised_short_body = format!(
        "POST /api/v1/runs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n\
         Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{{\"sample\": "
    );
    let short_body = raw(addr, authorised_short_body.as_bytes(), body_wait);
    let anonymous_short_body = raw(
        addr,
        b"POST /api/v1/runs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n\
          Content-Length: 100\r\n\r\n{\"sample\": ",
        body_wait,
    );
    // A keep-alive connection left idle after its answer.
    let idle_after_answer = raw(
        addr,
        b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\n\r\n",
        head_wait,
    );
    let trickle = async {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        let started = Instant::now();
        for b in b"GET /api/v1/health HTTP/1.1\r\nHost: slowly-sent\r\n" {
            if s.write_all(&[*b]).await.is_err() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let mut got = Vec::new();
        let closed = read_to_close(
            &mut s,
            &mut got,
            head_wait.saturating_sub(started.elapsed()),
        )
        .await;
        closed.then(|| started.elapsed())
    };
    let (partial_head, nothing, short_body, anonymous, idle, trickle) = tokio::join!(
        partial_head,
        nothing,
        short_body,
        anonymous_short_body,
        idle_after_answer,
        trickle
    );
    for (what, closed) in [
        ("a partial head", partial_head.1),
        ("a connection that sends nothing", nothing.1),
        ("a head sent a byte at a time", trickle),
        ("an idle keep-alive connection", idle.1),
    ] {
        assert!(
            closed.is_some_and(|t| t <= head_wait),
            "{what} was not closed within the header timeout: {closed:?}"
        );
    }
    assert_eq!(status_of(&idle.0), 200, "{}", idle.0);
    assert!(
        short_body.1.is_some_and(|t| t <= body_wait),
        "a body shorter than its Content-Length was not closed in time: {short_body:?}"
    );
    assert_eq!(status_of(&short_body.0), 408, "{}", short_body.0);
    assert!(short_body.0.contains("request_timeout"), "{}", short_body.0);
    assert!(
        anonymous.1.is_some_and(|t| t <= body_wait),
        "an unauthorised slow body was not closed in time: {anonymous:?}"
    );
    assert_eq!(status_of(&anonymous.0), 401, "{}", anonymous.0);
}

/// Every name a client sends, tried as a path: refused (404 for names in
/// the URL, naming those there are; 422 in a body), quickly, and never
/// read.
async fn names_are_never_paths(
    client: &reqwest::Client,
    base: &str,
    daemon: &Daemon,
    data: &Path,
    run: &str,
    answers: &Answers,
) {
    let fifo = data.join("fifo.toml");
    let made = Command::new("mkfifo").arg(&fifo).status().expect("mkfifo");
    assert!(made.success());
    let token_file = data.join("token");
    let paths: Vec<String> = [
        token_file.clone(),
        PathBuf::from("/etc/passwd"),
        PathBuf::from("/proc/self/environ"),
        PathBuf::from("/dev/zero"),
        fifo.clone(),
        data.join("runs").join(run).join("journal.ndjson"),
    ]
    .iter()
    .map(|p| p.display().to_string())
    .chain(["../token".to_string(), "token".to_string()])
    .collect();
    let url = |path: &str, segments: &[&str], query: &[(&str, &str)]| {
        let mut u = reqwest::Url::parse(&format!("{base}{path}")).expect("url");
        u.path_segments_mut().expect("segments").extend(segments);
        if !query.is_empty() {
            u.query_pairs_mut().extend_pairs(query);
        }
        u
    };
    for p in &paths {
        let p = p.as_str();
        let gets = [
            (
                url(
                    "/api/v1/sim/render",
                    &[],
                    &[("scene", p), ("size", "16x12")],
                ),
                404,
            ),
            (
                url(
                    "/api/v1/sim/render",
                    &[],
                    &[("camera", p), ("size", "16x12")],
                ),
                404,
            ),
            (url("/api/v1/plans", &[p], &[]), 404),
            (url("/api/v1/runs", &[p], &[]), 404),
            (url("/api/v1/runs", &[p, "manifest"], &[]), 404),
            (url("/api/v1/runs", &[run, "frames", p], &[]), 400),
            (url("/api/v1/runs", &[run, "btf", "mesh", p], &[]), 404),
            (url("/api/v1/runs", &[p, "btf", "data"], &[]), 404),
            (url("/api/v1/tradeoff/choice", &[], &[("budget", p)]), 0),
        ];
        for (u, want) in gets {
            let started = Instant::now();
            let r = client.get(u.clone()).send().await.unwrap_or_else(|e| {
                panic!(
                    "GET {u}: {e} after {:?}; {}",
                    started.elapsed(),
                    daemon.condition()
                )
            });
            let status = r.status().as_u16();
            let text = r.text().await.unwrap_or_default();
            answers.keep(u.as_str(), text.clone());
            assert_no_leak_in(&text, daemon, u.as_str());
            if want != 0 {
                assert_eq!(status, want, "GET {u}: {text}");
            } else {
                assert!((400..500).contains(&status), "GET {u}: {status} {text}");
            }
        }
        let scene_404 = client
            .get(url("/api/v1/sim/render", &[], &[("scene", p)]))
            .send()
            .await
            .expect("render")
            .text()
            .await
            .unwrap_or_default();
        assert!(
            scene_404.contains("flat-calibration") && scene_404.contains("corduroy"),
            "an unknown scene's answer lists the scenes: {scene_404}"
        );
        let posts = [
            ("/api/v1/tradeoff".to_string(), json!({ "scene": p }), 422),
            (
                "/api/v1/queue".to_string(),
                json!({ "sample": "x", "plan": p }),
                422,
            ),
            (
                format!("/api/v1/runs/{run}/process"),
                json!({ "steps": [p] }),
                422,
            ),
            (
                "/api/v1/rig/manual/lamp".to_string(),
                json!({ "device": p, "on": true }),
                0,
            ),
        ];
        for (path, body, want) in posts {
            let started = Instant::now();
            let r = client
                .post(format!("{base}{path}"))
                .bearer_auth(&daemon.token)
                .json(&body)
                .send()
                .await
                .unwrap_or_else(|e| {
                    panic!(
                        "POST {path} {body}: {e} after {:?}; {}",
                        started.elapsed(),
                        daemon.condition()
                    )
                });
            let status = r.status().as_u16();
            let text = r.text().await.unwrap_or_default();
            answers.keep(&path, text.clone());
            assert_no_leak_in(&text, daemon, &path);
            if want != 0 {
                assert_eq!(status, want, "POST {path} {body}: {text}");
            } else {
                assert!(
                    (400..500).contains(&status),
                    "POST {path} {body}: {status} {text}"
                );
            }
        }
        for path in [
            format!("/api/v1/peers/{}/pause", urlencode(p)),
            format!("/api/v1/queue/{}", urlencode(p)),
        ] {
            let method = if path.starts_with("/api/v1/queue") {
                reqwest::Method::DELETE
            } else {
                reqwest::Method::POST
            };
            let r = client
                .request(method, format!("{base}{path}"))
                .bearer_auth(&daemon.token)
                .send()
                .await
                .expect("request");
            let status = r.status().as_u16();
            let text = r.text().await.unwrap_or_default();
            answers.keep(&path, text.clone());
            assert_eq!(status, 404, "{path}: {text}");
        }
    }
}

fn urlencode(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'-' | b'_' | b'.' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// Bodies far over the limit, headers far over theirs, and JSON nested
/// deeper than any request needs: each refused at once, none read whole.
async fn big_and_deep_bodies(addr: &str, token: &str, answers: &Answers) {
    let wait = Duration::from_secs(5);
    let post = |path: &str, extra: &str| {
        format!(
            "POST {path} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n\
             Content-Type: application/json\r\n{extra}\r\n"
        )
    };
    // A gigabyte announced, eight megabytes sent.
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let _ = s
        .write_all(post("/api/v1/runs", "Content-Length: 1000000000\r\n").as_bytes())
        .await;
    let chunk = vec![b'a'; 1 << 16];
    for _ in 0..128 {
        if s.write_all(&chunk).await.is_err() {
            break;
        }
    }
    let mut got = Vec::new();
    let closed = read_to_close(&mut s, &mut got, wait).await;
    let answer = String::from_utf8_lossy(&got).into_owned();
    answers.keep("huge body", answer.clone());
    assert!(closed, "a huge body's connection stays open");
    assert!(
        status_of(&answer) == 413 || answer.is_empty(),
        "a huge body: {answer}"
    );
    // The same without a length: chunked.
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let _ = s
        .write_all(post("/api/v1/queue", "Transfer-Encoding: chunked\r\n").as_bytes())
        .await;
    let mut chunk = format!("{:x}\r\n", 1 << 16).into_bytes();
    chunk.extend(vec![b' '; 1 << 16]);
    chunk.extend_from_slice(b"\r\n");
    for _ in 0..128 {
        if s.write_all(&chunk).await.is_err() {
            break;
        }
    }
    let mut got = Vec::new();
    let closed = read_to_close(&mut s, &mut got, wait).await;
    let answer = String::from_utf8_lossy(&got).into_owned();
    answers.keep("huge chunked body", answer.clone());
    assert!(closed, "a huge chunked body's connection stays open");
    assert!(
        status_of(&answer) == 413 || answer.is_empty(),
        "a huge chunked body: {answer}"
    );
    // Headers beyond their limit.
    let big_header = format!(
        "GET /api/v1/health HTTP/1.1\r\nHost: x\r\nX-Big: {}\r\n\r\n",
        "b".repeat(200_000)
    );
    let (answer, closed) = raw(addr, big_header.as_bytes(), wait).await;
    answers.keep("huge header", answer.clone());
    assert!(closed.is_some(), "a huge header's connection stays open");
    assert_eq!(status_of(&answer), 431, "{answer}");
    // JSON nested 30,000 deep, within the body limit.
    for (path, body) in [
        (
            "/api/v1/runs",
            format!(
                "{{\"sample\": \"a\", \"plan\": {}{}}}",
                "[".repeat(30_000),
                "]".repeat(30_000)
            ),
        ),
        ("/api/v1/queue", "{\"a\":".repeat(10_000)),
        (
            "/api/v1/tradeoff",
            format!("{{\"scene\": {}", "{\"x\":".repeat(9_000)),
        ),
    ] {
        let head = post(
            path,
            &format!("Content-Length: {}\r\nConnection: close\r\n", body.len()),
        );
        let mut bytes = head.into_bytes();
        bytes.extend_from_slice(body.as_bytes());
        let (answer, closed) = raw(addr, &bytes, wait).await;
        answers.keep(path, answer.clone());
        assert!(
            closed.is_some(),
            "{path}: deep JSON's connection stays open"
        );
        let status = status_of(&answer);
        assert!(
            [400, 409, 422].contains(&status),
            "{path}: deep JSON answered {status}: {}",
            answer.chars().take(300).collect::<String>()
        );
    }
}

/// The engine's own events of the run, replayed from the daemon's ring.
async fn engine_events(base: &str, run: &str) -> Vec<Value> {
    let client = reqwest::Client::new();
    let (status, reader) =
        common::http::SseReader::connect(&client, &format!("{base}/api/v1/events"), Some(0)).await;
    assert_eq!(status, 200);
    let mut reader = reader.expect("event stream");
    let mut events = Vec::new();
    while let Some((_, e)) = reader.next(Duration::from_millis(500)).await {
        if e["run"] == run && e["kind"] == "engine" {
            events.push(e["event"].clone());
        }
    }
    assert!(
        events
            .iter()
            .any(|e| e["type"] == "state" && e["to"] == "completed"),
        "the run's events hold its completion: {events:?}"
    );
    events
}

/// What must never reach a client: the token, a line of `/etc/passwd`,
/// a variable of the daemon's environment.
fn secrets(daemon: &Daemon) -> Vec<String> {
    let mut secrets = vec![daemon.token.clone()];
    if let Ok(passwd) = std::fs::read_to_string("/etc/passwd") {
        secrets.extend(passwd.lines().filter(|l| l.len() >= 8).map(String::from));
    }
    if let Ok(env) = std::fs::read(format!("/proc/{}/environ", daemon.pid)) {
        secrets.extend(
            env.split(|&b| b == 0)
                .map(|v| String::from_utf8_lossy(v).into_owned())
                .filter(|v| v.len() >= 12 && v.contains('=')),
        );
    }
    secrets
}

fn assert_no_leak_in(text: &str, daemon: &Daemon, what: &str) {
    for secret in secrets(daemon) {
        assert!(
            !text.contains(&secret),
            "{what}: the answer holds `{secret}`: {text}"
        );
    }
}

fn assert_no_leak(answers: &Answers, daemon: &Daemon) {
    let all = answers.0.lock().map(|a| a.clone()).unwrap_or_default();
    for a in &all {
        assert_no_leak_in(a, daemon, "an answer");
    }
}

/// The CLI's file options, given devices, FIFOs and files that are not
/// what they should be: refused at once (exit 2), naming the file,
/// quoting none of its content, and never reading a device.
#[test]
fn cli_file_options_refuse_devices_and_fifos() {
    let dir = tempfile::tempdir().expect("tempdir");
    let fifo = dir.path().join("plan.toml");
    let made = Command::new("mkfifo").arg(&fifo).status().expect("mkfifo");
    assert!(made.success());
    let fifo = fifo.display().to_string();
    let out = dir.path().join("out").display().to_string();
    let passwd = std::fs::read_to_string("/etc/passwd").unwrap_or_default();
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["run", "--sim", "--scene", "/dev/zero"],
            "not a regular file",
        ),
        (
            vec!["run", "--sim", "--plan", "/dev/zero"],
            "not a regular file",
        ),
        (vec!["run", "--profile", "/dev/zero"], "not a regular file"),
        (
            vec!["run", "--sim", "--scene", &fifo],
            "not a regular file (a FIFO)",
        ),
        (
            vec!["run", "--sim", "--plan", &fifo],
            "not a regular file (a FIFO)",
        ),
        (
            vec!["run", "--profile", &fifo],
            "not a regular file (a FIFO)",
        ),
        (vec!["plan", "show", "/dev/zero"], "not a regular file"),
        (
            vec![
                "sim",
                "render",
                "--scene",
                "/dev/zero",
                "--light",
                "0,0",
                "--view",
                "0,0",
            ],
            "not a regular file",
        ),
        (
            vec!["run", "--sim", "--scene", "/etc/passwd"],
            "/etc/passwd",
        ),
        (
            vec!["holder", "check", &fifo],
            "not a regular file (a FIFO)",
        ),
        (vec!["holder", "check", "/dev/zero"], "not a regular file"),
        (
            vec![
                "camera",
                "colour",
                &fifo,
                "--corners",
                "1,1",
                "9,1",
                "9,9",
                "1,9",
            ],
            "not a regular file (a FIFO)",
        ),
    ];
    for (args, expect) in cases {
        let mut cmd = common::rigd();
        cmd.args(&args)
            .args(["--sample", "x", "--out", &out])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        if args[0] != "run" {
            cmd = common::rigd();
            cmd.args(&args)
                .stdin(Stdio::null())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped());
            if args[0] == "sim" {
                cmd.args(["--out", &format!("{out}.png")]);
            }
        }
        let (code, stderr) = run_bounded(cmd, &args);
        assert_eq!(code, Some(2), "rigd {args:?}: {stderr}");
        assert!(stderr.contains(expect), "rigd {args:?}: {stderr}");
        for line in passwd.lines().filter(|l| l.len() >= 8) {
            assert!(
                !stderr.contains(line),
                "rigd {args:?} quotes /etc/passwd: {stderr}"
            );
        }
    }
}

/// Runs a command for at most 10 s and 500 MB: its exit code (None when it
/// had to be killed) and its stderr.
fn run_bounded(mut cmd: Command, args: &[&str]) -> (Option<i32>, String) {
    let mut child = cmd.spawn().expect("spawn rigd");
    let started = Instant::now();
    loop {
        if let Some(status) = child.try_wait().expect("wait") {
            let out = child.wait_with_output().expect("output");
            return (
                status.code(),
                String::from_utf8_lossy(&out.stderr).into_owned(),
            );
        }
        let rss = status_kb(child.id(), "VmRSS:").unwrap_or(0);
        if started.elapsed() > Duration::from_secs(10) || rss > MEMORY_BOUND_KB {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "rigd {args:?} still running after {:?} at {} MB: it reads what it should refuse",
                started.elapsed(),
                rss / 1024
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Reads until the end of an answer's head (or the connection's end), at
/// most `wait`: the head as text.
async fn read_head(s: &mut TcpStream, wait: Duration) -> String {
    let deadline = tokio::time::Instant::now() + wait;
    let mut got = Vec::new();
    let mut buf = [0u8; 1024];
    while !got.windows(4).any(|w| w == b"\r\n\r\n") {
        match tokio::time::timeout_at(deadline, s.read(&mut buf)).await {
            Ok(Ok(n)) if n > 0 => got.extend_from_slice(&buf[..n]),
            _ => break,
        }
    }
    String::from_utf8_lossy(&got).into_owned()
}

/// With every connection busy, a new one is refused with `503` naming the
/// reason; event streams beyond theirs too; and a connection's last
/// allowed request is answered with `Connection: close`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_caps_are_refused_with_503() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut config = rigd::server::ServerConfig::new(dir.path());
    config.listen = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
    config.http = rigd::server::http::HttpLimits {
        max_connections: rigd::server::http::MIN_CONNECTIONS,
        max_event_streams: 6,
        max_requests_per_connection: 3,
        ..Default::default()
    };
    let (addr, handle) = rigd::server::start(config).await.expect("server starts");
    let addr = addr.to_string();
    let token = handle.token.secret().to_string();
    let mut busy = Vec::new();
    // Six event streams (busy for as long as they are open), the seventh
    // refused.
    for i in 0..7 {
        let mut s = TcpStream::connect(&addr).await.expect("connect");
        s.write_all(b"GET /api/v1/events HTTP/1.1\r\nHost: x\r\n\r\n")
            .await
            .expect("write");
        let head = read_head(&mut s, Duration::from_secs(5)).await;
        if i < 6 {
            assert_eq!(status_of(&head), 200, "stream {i}: {head}");
            busy.push(s);
        } else {
            assert_eq!(status_of(&head), 503, "stream {i}: {head}");
            let mut rest = Vec::new();
            read_to_close(&mut s, &mut rest, Duration::from_millis(200)).await;
            let answer = format!("{head}{}", String::from_utf8_lossy(&rest));
            assert!(answer.contains("too many event streams"), "{answer}");
        }
    }
    // Two requests whose bodies are still coming fill the cap of eight.
    for _ in 0..2 {
        let mut s = TcpStream::connect(&addr).await.expect("connect");
        let head = format!(
            "POST /api/v1/runs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n\
             Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{{"
        );
        s.write_all(head.as_bytes()).await.expect("write");
        busy.push(s);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (answer, closed) = raw(
        &addr,
        b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\n\r\n",
        Duration::from_secs(5),
    )
    .await;
    assert_eq!(status_of(&answer), 503, "{answer}");
    assert!(
        answer.contains("too many connections: all 8 are busy"),
        "{answer}"
    );
    assert!(
        answer.to_ascii_lowercase().contains("retry-after: 1"),
        "{answer}"
    );
    assert!(closed.is_some(), "a refused connection is closed");
    // Room again once the streams end.
    drop(busy);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let three = b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\n\r\n".repeat(3);
    let (answer, closed) = raw(&addr, &three, Duration::from_secs(5)).await;
    assert_eq!(answer.matches("HTTP/1.1 200 OK").count(), 3, "{answer}");
    let last = answer.rsplit("HTTP/1.1 200 OK").next().unwrap_or("");
    assert!(
        last.to_ascii_lowercase().contains("connection: close"),
        "{answer}"
    );
    assert!(
        closed.is_some(),
        "the connection closes after its last request"
    );
    handle.shutdown().await;
}
