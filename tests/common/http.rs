//! HTTP helpers for the API tests and the load benchmark: an in-process
//! daemon on 127.0.0.1:0, a client, polling and an SSE reader.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use futures::StreamExt;
use rigd::server::{self, ServerConfig, ServerHandle};
use serde_json::{json, Value};

pub struct Srv {
    pub addr: SocketAddr,
    pub base: String,
    pub token: String,
    pub data: PathBuf,
    pub handle: Option<ServerHandle>,
    pub client: reqwest::Client,
}

/// Starts a daemon in this process on a free loopback port.
pub async fn start_in(data: &Path, speed: f64) -> Srv {
    start_with(data, speed, None, true).await
}

/// [`start_in`] with a profile (a file or an embedded name), on its
/// simulated rig or (`sim` false) on the hardware it names.
pub async fn start_with(data: &Path, speed: f64, profile: Option<&str>, sim: bool) -> Srv {
    let mut config = ServerConfig::new(data);
    config.listen = SocketAddr::from(([127, 0, 0, 1], 0));
    config.sim_speed = speed;
    config.profile = profile.map(str::to_string);
    config.sim = sim;
    let (addr, handle) = server::start(config).await.expect("server starts");
    let token = handle.token.secret().to_string();
    Srv {
        addr,
        base: format!("http://{addr}"),
        token,
        data: data.to_path_buf(),
        handle: Some(handle),
        client: reqwest::Client::new(),
    }
}

/// A small inline plan: `n` directions paired all with all (n² images).
pub fn small_plan(n: usize) -> Value {
    let dirs: Vec<Value> = (0..n)
        .map(|i| json!({"theta_deg": 10.0 + 60.0 * i as f64 / n.max(1) as f64, "phi_deg": 37.0 * i as f64}))
        .collect();
    json!({"name": "mini", "directions": dirs})
}

pub fn run_body(sample: &str, plan: Value) -> Value {
    json!({"sample": sample, "plan": plan, "frame_size": [16, 12], "operator": "tester"})
}

impl Srv {
    pub fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    pub async fn get(&self, path: &str) -> (u16, Value) {
        let r = self.client.get(self.url(path)).send().await.expect("GET");
        let status = r.status().as_u16();
        let body = r.json::<Value>().await.unwrap_or(Value::Null);
        (status, body)
    }

    pub async fn get_bytes(&self, path: &str) -> (u16, String, Vec<u8>) {
        let r = self.client.get(self.url(path)).send().await.expect("GET");
        let status = r.status().as_u16();
        let ct = r
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        (status, ct, r.bytes().await.expect("body").to_vec())
    }

    /// POST with the token and a JSON body (or none).
    pub async fn post(&self, path: &str, body: Option<Value>) -> (u16, Value) {
        self.send("POST", path, body, Some(&self.token.clone()))
            .await
    }

    pub async fn send(
        &self,
        method: &str,
        path: &str,
        body: Option<Value>,
        token: Option<&str>,
    ) -> (u16, Value) {
        let method = reqwest::Method::from_bytes(method.as_bytes()).expect("method");
        let mut req = self.client.request(method, self.url(path));
        if let Some(t) = token {
            req = req.bearer_auth(t);
        }
        if let Some(b) = body {
            req = req.json(&b);
        }
        let r = req.send().await.expect("request");
        let status = r.status().as_u16();
        let body = r.json::<Value>().await.unwrap_or(Value::Null);
        (status, body)
    }

    /// Polls a run until `pred` holds on its JSON (30 s at most).
    pub async fn wait_run(&self, id: &str, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let (status, v) = self.get(&format!("/api/v1/runs/{id}")).await;
            assert_eq!(status, 200, "GET run {id}: {v}");
            if pred(&v) {
                return v;
            }
            assert!(Instant::now() < deadline, "run {id} never got {what}: {v}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    pub async fn wait_state(&self, id: &str, state: &str) -> Value {
        self.wait_run(id, state, |v| v["state"] == state).await
    }

    /// Waits until a run reached `state` and its engine let go of the rig
    /// (the final state event comes a moment before the engine ends).
    pub async fn wait_ended(&self, id: &str, state: &str) -> Value {
        self.wait_run(id, state, |v| v["state"] == state && v["active"] == false)
            .await
    }

    pub async fn shutdown(&mut self) {
        if let Some(h) = self.handle.take() {
            h.shutdown().await;
        }
    }
}

/// Reads Server-Sent Events: `(id, data JSON)` pairs.
pub struct SseReader {
    stream: std::pin::Pin<Box<dyn futures::Stream<Item = reqwest::Result<Vec<u8>>> + Send>>,
    buf: String,
}

impl SseReader {
    pub async fn connect(
        client: &reqwest::Client,
        url: &str,
        last_event_id: Option<u64>,
    ) -> (u16, Option<SseReader>) {
        let mut req = client.get(url);
        if let Some(id) = last_event_id {
            req = req.header("Last-Event-ID", id.to_string());
        }
        let r = req.send().await.expect("SSE connect");
        let status = r.status().as_u16();
        if status != 200 {
            return (status, None);
        }
        let stream = r.bytes_stream().map(|c| c.map(|b| b.to_vec()));
        (
            status,
            Some(SseReader {
                stream: Box::pin(stream),
                buf: String::new(),
            }),
        )
    }

    /// The next event with data (keep-alive comments skipped), or None at
    /// the end of the stream or after `timeout`.
    pub async fn next(&mut self, timeout: Duration) -> Option<(Option<u64>, Value)> {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            while let Some(pos) = self.buf.find("\n\n") {
                let block: String = self.buf.drain(..pos + 2).collect();
                let mut id = None;
                let mut data = String::new();
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("id:") {
                        id = v.trim().parse().ok();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.trim_start());
                    }
                }
                if !data.is_empty() {
                    if let Ok(v) = serde_json::from_str(&data) {
                        return Some((id, v));
                    }
                }
            }
            let chunk = tokio::time::timeout_at(deadline, self.stream.next())
                .await
                .ok()??;
            let chunk = chunk.ok()?;
            self.buf.push_str(&String::from_utf8_lossy(&chunk));
        }
    }
}
