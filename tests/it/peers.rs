//! Several rigs in one view (`rigd serve --peers FILE`): a bad peers file
//! stops the start with one line naming the file and the peer; a dead peer
//! shows as unreachable and blocks nothing; pause and abort reach a peer's
//! active run through this daemon, with the peer's answer.

use crate::common;

use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

use common::http::{run_body, small_plan, Srv};
use common::rigd;
use rigd::server::peers::Peer;
use serde_json::Value;

const FAST: f64 = 20_000.0;

/// A daemon in this process with these peers.
async fn daemon(data: &Path, speed: f64, peers: Vec<Peer>) -> Srv {
    let mut config = rigd::server::ServerConfig::new(data);
    config.listen = SocketAddr::from(([127, 0, 0, 1], 0));
    config.sim_speed = speed;
    config.peers = peers;
    let (addr, handle) = rigd::server::start(config).await.expect("server starts");
    Srv {
        addr,
        base: format!("http://{addr}"),
        token: handle.token.secret().to_string(),
        data: data.to_path_buf(),
        handle: Some(handle),
        client: reqwest::Client::new(),
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}

/// `GET /api/v1/peers` until the entry `name` satisfies `pred` (at most
/// `secs`); that entry and how long it took.
async fn wait_peer(
    s: &Srv,
    name: &str,
    secs: u64,
    what: &str,
    pred: impl Fn(&Value) -> bool,
) -> (Value, Duration) {
    let started = Instant::now();
    loop {
        let (status, v) = s.get("/api/v1/peers").await;
        assert_eq!(status, 200, "{v}");
        let entry = v["peers"]
            .as_array()
            .and_then(|a| a.iter().find(|p| p["name"] == name))
            .cloned()
            .unwrap_or_else(|| panic!("no peer {name} in {v}"));
        if pred(&entry) {
            return (entry, started.elapsed());
        }
        assert!(
            started.elapsed() < Duration::from_secs(secs),
            "peer {name} never {what}: {entry}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[test]
fn bad_peers_files_stop_the_start_naming_file_and_peer() {
    let dir = tempfile::tempdir().expect("tempdir");
    let token = dir.path().join("b.token");
    std::fs::write(&token, "0123456789abcdef0123\n").expect("token");
    let cases = [
        (
            "duplicate.toml",
            "[[peer]]\nname = \"b\"\nurl = \"http://127.0.0.1:9\"\ntoken_file = \"b.token\"\n\
             [[peer]]\nname = \"b\"\nurl = \"http://127.0.0.1:10\"\ntoken_file = \"b.token\"\n",
            "peer `b` (entries 1 and 2): the name is used twice",
        ),
        (
            "no-token.toml",
            "[[peer]]\nname = \"msra\"\nurl = \"http://127.0.0.1:9\"\n",
            "peer `msra` (entry 1): give exactly one of `token` and `token_file`",
        ),
        (
            "unknown-field.toml",
            "[[peer]]\nname = \"msra\"\nurl = \"http://127.0.0.1:9\"\ntoken_file = \"b.token\"\nport = 9\n",
            "[[peer]] entry 1: unknown field `port`",
        ),
        (
            "missing-token-file.toml",
            "[[peer]]\nname = \"msra\"\nurl = \"http://127.0.0.1:9\"\ntoken_file = \"gone.token\"\n",
            "peer `msra` (entry 1): token file",
        ),
        (
            "https.toml",
            "[[peer]]\nname = \"msra\"\nurl = \"https://127.0.0.1:9\"\ntoken_file = \"b.token\"\n",
            "peer `msra` (entry 1): url `https://127.0.0.1:9`: https is not supported",
        ),
    ];
    let data = dir.path().join("data");
    for (file, text, want) in cases {
        let path = dir.path().join(file);
        std::fs::write(&path, text).expect("write");
        let out = rigd()
            .args(["serve", "--listen", "127.0.0.1:0", "--data"])
            .arg(&data)
            .arg("--peers")
            .arg(&path)
            .output()
            .expect("spawn rigd serve");
        let stderr = String::from_utf8_lossy(&out.stderr).to_string();
        assert_eq!(out.status.code(), Some(2), "{file}: {stderr}");
        assert!(stderr.starts_with("error: peers file "), "{file}: {stderr}");
        assert!(
            stderr.contains(&path.display().to_string()),
            "{file}: {stderr}"
        );
        assert!(stderr.contains(want), "{file}: {stderr}\nwanted: {want}");
        assert_eq!(stderr.trim_end().lines().count(), 1, "one line: {stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
    }
    // Refused before anything was done: no data directory, no token made.
    assert!(!data.exists(), "the daemon started anyway");
    // A missing peers file is bad input too.
    let out = rigd()
        .args(["serve", "--listen", "127.0.0.1:0", "--peers"])
        .arg(dir.path().join("nope.toml"))
        .output()
        .expect("spawn rigd serve");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("nope.toml: cannot read"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_peer_is_unreachable_and_blocks_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let port = free_port();
    let gone = Peer::new(
        "gone",
        &format!("http://127.0.0.1:{port}"),
        "0123456789abcdef0123",
    )
    .expect("peer");
    let mut a = daemon(dir.path(), FAST, vec![gone]).await;
    let (entry, took) = wait_peer(&a, "gone", 5, "marked unreachable", |p| {
        p["error"]
            .as_str()
            .is_some_and(|e| e.starts_with("cannot connect"))
    })
    .await;
    eprintln!("closed port unreachable after {took:?}: {entry}");
    assert_eq!(entry["reachable"], false);
    assert_eq!(entry["local"], false);
    assert_eq!(entry["last_seen"], Value::Null);
    assert_eq!(entry["state"], Value::Null);
    assert_eq!(entry["url"], format!("http://127.0.0.1:{port}"));
    // This rig comes first, reachable, with its own state.
    let (_, list) = a.get("/api/v1/peers").await;
    let me = &list["peers"][0];
    assert_eq!(me["name"], "this rig");
    assert_eq!(me["local"], true);
    assert_eq!(me["reachable"], true);
    assert_eq!(me["url"], a.base.as_str());
    assert_eq!(me["profile"], "bonn-gonioreflectometer");
    assert_eq!(me["state"], "idle");
    assert_eq!(me["queue_length"], 0);
    assert_eq!(me["active_run"], Value::Null);
    // The daemon's own run goes on, and its routes answer at once.
    let (status, v) = a
        .post("/api/v1/runs", Some(run_body("solo", small_plan(3))))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let mut slowest = Duration::ZERO;
    for _ in 0..20 {
        let t = Instant::now();
        let (status, _) = a.get("/api/v1/peers").await;
        assert_eq!(status, 200);
        slowest = slowest.max(t.elapsed());
    }
    assert!(
        slowest < Duration::from_millis(500),
        "GET /peers took {slowest:?}"
    );
    a.wait_ended(&id, "completed").await;
    common::assert_complete_run(&dir.path().join("runs").join(&id), 9);
    // Forwarding to it fails as a gateway error, naming the peer.
    let (status, v) = a.post("/api/v1/peers/gone/pause", None).await;
    assert_eq!(status, 502, "{v}");
    assert_eq!(v["error"], "peer_unreachable");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.starts_with("peer `gone` at http://127.0.0.1:")),
        "{v}"
    );
    a.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pause_and_abort_reach_a_peers_run() {
    let dir_b = tempfile::tempdir().expect("tempdir");
    let dir_a = tempfile::tempdir().expect("tempdir");
    // B captures slowly enough (64 images at 60×: about 16 s) to be caught running.
    let mut b = daemon(dir_b.path(), 60.0, vec![]).await;
    let peers = vec![
        Peer::new("rig-b", &b.base, &b.token).expect("peer"),
        Peer::new("rig-b-wrong", &b.base, "not-the-token-of-b").expect("peer"),
    ];
    let mut a = daemon(dir_a.path(), FAST, peers).await;

    let (idle, _) = wait_peer(&a, "rig-b", 5, "reachable", |p| p["reachable"] == true).await;
    assert_eq!(idle["state"], "idle", "{idle}");
    assert_eq!(idle["profile"], "bonn-gonioreflectometer");
    assert_eq!(idle["faults"], serde_json::json!([]));
    assert!(idle["last_seen"].is_string(), "{idle}");
    // No active run on B: nothing to pause.
    let (status, v) = a.post("/api/v1/peers/rig-b/pause", None).await;
    assert_eq!(status, 409, "{v}");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("no active run")),
        "{v}"
    );

    // B runs; A sees its run and its queue.
    let (status, v) = b
        .post("/api/v1/runs", Some(run_body("on-b", small_plan(8))))
        .await;
    assert_eq!(status, 201, "{v}");
    let id = v["id"].as_str().expect("id").to_string();
    let (status, _) = b
        .post("/api/v1/queue", Some(run_body("later", small_plan(2))))
        .await;
    assert_eq!(status, 201);
    let (running, _) = wait_peer(&a, "rig-b", 10, "running with frames", |p| {
        p["active_run"]["id"] == id.as_str()
            && p["active_run"]["steps_done"]
                .as_u64()
                .is_some_and(|n| n > 0)
    })
    .await;
    assert_eq!(running["active_run"]["steps_total"], 64, "{running}");
    assert_eq!(running["queue_length"], 1, "{running}");
    // A wrong token in the peers file: B's reads are open to loopback
    // clients, its commands are not. B's 401 is not passed on as A's own
    // (the dashboard would ask for A's token again).
    wait_peer(&a, "rig-b-wrong", 5, "reachable", |p| {
        p["reachable"] == true
    })
    .await;
    let (status, v) = a.post("/api/v1/peers/rig-b-wrong/pause", None).await;
    assert_eq!(status, 502, "{v}");
    assert_eq!(v["error"], "peer_unreachable");
    assert!(
        v["detail"]
            .as_str()
            .is_some_and(|d| d.contains("refused the token of the peers file")),
        "{v}"
    );

    // Pause needs A's token, and is refused for an unknown peer.
    let (status, _) = a
        .send("POST", "/api/v1/peers/rig-b/pause", None, None)
        .await;
    assert_eq!(status, 401);
    let (status, _) = a
        .send("POST", "/api/v1/peers/rig-b/pause", None, Some(&b.token))
        .await;
    assert_eq!(status, 401, "B's token is not A's");
    let (status, v) = a.post("/api/v1/peers/nope/pause", None).await;
    assert_eq!(status, 404, "{v}");
    // Pause: B's answer comes back, and B's run pauses.
    let (status, v) = a.post("/api/v1/peers/rig-b/pause", None).await;
    assert_eq!(status, 202, "{v}");
    assert_eq!(v["command"], "pause");
    assert_eq!(v["run"]["id"], id.as_str());
    b.wait_state(&id, "paused").await;
    wait_peer(&a, "rig-b", 5, "paused", |p| p["state"] == "paused").await;
    // Pausing again: B's own refusal (409), passed on.
    let (status, v) = a.post("/api/v1/peers/rig-b/pause", None).await;
    assert_eq!(status, 409, "{v}");
    assert_eq!(v["error"], "conflict");
    // Abort (stop) from A.
    let (status, v) = a.post("/api/v1/peers/rig-b/abort", None).await;
    assert!(status == 202 || status == 200, "{status} {v}");
    b.wait_state(&id, "aborted").await;

    // B dies: A marks it unreachable within 5 s and keeps capturing.
    let (status, v) = a
        .post("/api/v1/runs", Some(run_body("on-a", small_plan(3))))
        .await;
    assert_eq!(status, 201, "{v}");
    let mine = v["id"].as_str().expect("id").to_string();
    b.shutdown().await;
    let (gone, took) = wait_peer(&a, "rig-b", 5, "unreachable", |p| p["reachable"] == false).await;
    eprintln!(
        "peer unreachable {took:?} after its shutdown: {}",
        gone["error"]
    );
    assert!(gone["last_seen"].is_string(), "{gone}");
    assert!(gone["error"].is_string(), "{gone}");
    a.wait_ended(&mine, "completed").await;
    let (status, v) = a.post("/api/v1/peers/rig-b/abort", None).await;
    assert!(status == 502 || status == 504, "{status} {v}");
    a.shutdown().await;
}
