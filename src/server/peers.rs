//! Watching the other rigs (`rigd serve --peers FILE`): one task per peer
//! polls its daemon every second and keeps what it answered in memory, for
//! `GET /api/v1/peers` and the dashboard's "Rigs" panel; pause and abort
//! are forwarded to a peer's active run.
//!
//! Each rig stays autonomous: a peer that does not answer is marked
//! unreachable with the error and when it was last seen, and nothing of
//! this daemon (its routes, its capture) ever waits for a peer.
//!
//! - [`file`]: the peers file

pub mod file;

use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::http::{header, Method, StatusCode};
use serde::{Deserialize, Serialize};
use tokio::sync::{watch, Notify};
use utoipa::ToSchema;

pub use file::{load, Peer, PeerError, PeersError};

use crate::model::run_state::RunState;
use rigd_core::sync::lock;

/// How often each peer is asked for its state.
pub const POLL_EVERY: Duration = Duration::from_secs(1);
/// How long one request to a peer may take, connection included.
pub const REQUEST_TIMEOUT: Duration = Duration::from_millis(1500);
/// Largest answer read from a peer.
const MAX_ANSWER: usize = 1 << 20;

/// The name of this daemon's own entry in `GET /api/v1/peers`.
pub const LOCAL_NAME: &str = "this rig";

/// One rig in `GET /api/v1/peers`: this daemon's own (first, `local`) or
/// a peer's, as of its last answer.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PeerView {
    /// `this rig` for this daemon, else the name in the peers file.
    pub name: String,
    /// The rig's daemon (its dashboard is at this URL): the peers file's
    /// `url`, or the address this daemon listens on.
    pub url: String,
    /// True for this daemon's own entry.
    pub local: bool,
    /// The last poll was answered (always true for this daemon).
    pub reachable: bool,
    /// Why the last poll failed: the connection's error, a timeout, a
    /// refused token; null while reachable.
    pub error: Option<String>,
    /// When the peer last answered, RFC 3339 UTC; null if it never did.
    pub last_seen: Option<String>,
    /// Seconds since then, by this daemon's clock.
    pub seen_ago_s: Option<f64>,
    /// The rig profile it drives; null until it first answered. The fields
    /// below are those of its last answer: while `reachable` is false they
    /// are as of `last_seen`.
    pub profile: Option<String>,
    /// Whether it drives a simulated rig.
    pub sim: Option<bool>,
    /// The rig's state: its active run's, or `idle` when the rig is free.
    pub state: Option<RunState>,
    /// The run its engine drives, if any.
    pub active_run: Option<PeerRun>,
    /// Runs waiting in its queue.
    pub queue_length: Option<usize>,
    /// Its devices' faults (what paused its run), each once.
    pub faults: Vec<String>,
}

/// A rig's active run, in short.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PeerRun {
    /// The run's id on that rig.
    pub id: String,
    /// Sample name.
    pub sample: String,
    /// Plan name.
    pub plan: String,
    /// Where the run stands.
    pub state: RunState,
    /// Images with a journaled frame so far.
    pub steps_done: usize,
    /// Images in the plan.
    pub steps_total: usize,
    /// Why it is in its state (a pause's reason), if any.
    #[serde(default)]
    pub reason: Option<String>,
    /// Estimated wall seconds left.
    #[serde(default)]
    pub eta_wall_s: Option<f64>,
}

/// `GET /api/v1/peers`.
#[derive(Debug, Clone, Serialize, Deserialize, ToSchema)]
pub struct PeerList {
    /// This rig first, then every peer in the peers file's order.
    pub peers: Vec<PeerView>,
}

/// What a rig reported of itself.
#[derive(Debug, Clone)]
pub struct RigSummary {
    /// Its profile's name.
    pub profile: String,
    /// Simulated.
    pub sim: bool,
    /// Its state (`idle` when free).
    pub state: RunState,
    /// Its active run.
    pub active_run: Option<PeerRun>,
    /// Its queue's length.
    pub queue_length: usize,
    /// Its devices' faults, each once.
    pub faults: Vec<String>,
}

impl RigSummary {
    /// The view of a rig with this summary (reachable, seen now).
    pub fn view(self, name: &str, url: &str, local: bool) -> PeerView {
        PeerView {
            name: name.to_string(),
            url: url.to_string(),
            local,
            reachable: true,
            error: None,
            last_seen: Some(crate::store::now_rfc3339()),
            seen_ago_s: Some(0.0),
            profile: Some(self.profile),
            sim: Some(self.sim),
            state: Some(self.state),
            active_run: self.active_run,
            queue_length: Some(self.queue_length),
            faults: self.faults,
        }
    }
}

/// Device faults, each once, in the order first seen.
pub fn distinct_faults<'a>(faults: impl IntoIterator<Item = &'a str>) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for f in faults {
        if !out.iter().any(|o| o == f) {
            out.push(f.to_string());
        }
    }
    out
}

/// What the last polls of one peer found.
#[derive(Debug, Default)]
struct Status {
    /// The last poll's outcome: None before the first.
    outcome: Option<Result<(), String>>,
    last_seen: Option<(String, Instant)>,
    summary: Option<RigSummary>,
}

struct Slot {
    peer: Peer,
    status: Mutex<Status>,
    /// Wakes the poll task at once (after a forwarded command).
    wake: Notify,
}

type HttpClient = reqwest::Client;

/// The peers of this daemon and what each last answered.
pub struct Peers {
    slots: Vec<Arc<Slot>>,
    client: HttpClient,
    local_url: OnceLock<String>,
}

/// A request to a peer that got no usable answer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CallError {
    /// No answer within [`REQUEST_TIMEOUT`].
    #[error("no answer within {:.1} s", REQUEST_TIMEOUT.as_secs_f64())]
    Timeout,
    /// The connection failed or broke.
    #[error("{0}")]
    Unreachable(String),
}

/// A command for a peer's active run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PeerCommand {
    /// `POST /api/v1/runs/{id}/pause` on the peer.
    Pause,
    /// `POST /api/v1/runs/{id}/abort` on the peer.
    Abort,
}

impl PeerCommand {
    fn word(self) -> &'static str {
        match self {
            PeerCommand::Pause => "pause",
            PeerCommand::Abort => "abort",
        }
    }
}

/// Why a command could not be forwarded (the peer's own refusals come
/// back as its answer instead).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ForwardError {
    /// No peer of that name.
    #[error("no peer `{0}`")]
    UnknownPeer(String),
    /// The peer's rig has no active run.
    #[error("peer `{0}` has no active run")]
    NoActiveRun(String),
    /// The peer did not answer in time.
    #[error("peer `{name}` at {url}: {error}")]
    Timeout {
        /// The peer.
        name: String,
        /// Its URL.
        url: String,
        /// What happened.
        error: CallError,
    },
    /// The peer cannot be reached, refused the peers file's token, or
    /// answered something that is not rigd's API.
    #[error("peer `{name}` at {url}: {why}")]
    BadGateway {
        /// The peer.
        name: String,
        /// Its URL.
        url: String,
        /// What happened.
        why: String,
    },
}

impl Peers {
    /// The peers, not yet watched ([`start`] begins the polling).
    pub fn new(peers: &[Peer]) -> Peers {
        // Without a TLS back end the builder has nothing that can fail; the
        // plain client is the same but for the timeouts and the pool.
        let client = reqwest::Client::builder()
            .connect_timeout(REQUEST_TIMEOUT)
            .tcp_nodelay(true)
            .pool_idle_timeout(Duration::from_secs(30))
            .pool_max_idle_per_host(2)
            .build()
            .unwrap_or_default();
        Peers {
            slots: peers
                .iter()
                .map(|p| {
                    Arc::new(Slot {
                        peer: p.clone(),
                        status: Mutex::new(Status::default()),
                        wake: Notify::new(),
                    })
                })
                .collect(),
            client,
            local_url: OnceLock::new(),
        }
    }

    /// No peers configured.
    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Sets the URL of this daemon (once it listens).
    pub fn set_local_url(&self, url: String) {
        let _ = self.local_url.set(url);
    }

    /// This daemon's URL (empty before it listens).
    pub fn local_url(&self) -> &str {
        self.local_url.get().map(String::as_str).unwrap_or("")
    }

    /// Every peer as of its last poll, in the peers file's order.
    pub fn views(&self) -> Vec<PeerView> {
        self.slots
            .iter()
            .map(|slot| {
                let s = lock(&slot.status);
                let summary = s.summary.clone();
                let (reachable, error) = match &s.outcome {
                    None => (false, Some("waiting for its first answer".to_string())),
                    Some(Ok(())) => (true, None),
                    Some(Err(e)) => (false, Some(e.clone())),
                };
                PeerView {
                    name: slot.peer.name.clone(),
                    url: slot.peer.url.clone(),
                    local: false,
                    reachable,
                    error,
                    last_seen: s.last_seen.as_ref().map(|(t, _)| t.clone()),
                    seen_ago_s: s
                        .last_seen
                        .as_ref()
                        .map(|(_, at)| (at.elapsed().as_secs_f64() * 10.0).round() / 10.0),
                    profile: summary.as_ref().map(|x| x.profile.clone()),
                    sim: summary.as_ref().map(|x| x.sim),
                    state: summary.as_ref().map(|x| x.state),
                    active_run: summary.as_ref().and_then(|x| x.active_run.clone()),
                    queue_length: summary.as_ref().map(|x| x.queue_length),
                    faults: summary.map(|x| x.faults).unwrap_or_default(),
                }
            })
            .collect()
    }

    fn slot(&self, name: &str) -> Option<&Arc<Slot>> {
        self.slots.iter().find(|s| s.peer.name == name)
    }

    /// Sends `cmd` to the peer's active run (asking the peer which run is
    /// active first, not trusting the last poll): the peer's status and
    /// JSON body, or why there was none.
    pub async fn forward(
        &self,
        name: &str,
        cmd: PeerCommand,
    ) -> Result<(StatusCode, Bytes), ForwardError> {
        let slot = self
            .slot(name)
            .ok_or_else(|| ForwardError::UnknownPeer(name.chars().take(64).collect()))?;
        let peer = &slot.peer;
        let failed = |error: CallError| match error {
            CallError::Timeout => ForwardError::Timeout {
                name: peer.name.clone(),
                url: peer.url.clone(),
                error,
            },
            CallError::Unreachable(why) => ForwardError::BadGateway {
                name: peer.name.clone(),
                url: peer.url.clone(),
                why,
            },
        };
        let bad = |why: String| ForwardError::BadGateway {
            name: peer.name.clone(),
            url: peer.url.clone(),
            why,
        };
        let rig: RemoteRig =
            get_json(&self.client, peer, "/api/v1/rig")
                .await
                .map_err(|e| match e {
                    Answer::Call(c) => failed(c),
                    Answer::Bad(why) => bad(why),
                })?;
        let id = rig
            .active_run
            .ok_or_else(|| ForwardError::NoActiveRun(peer.name.clone()))?;
        let path = format!("/api/v1/runs/{}/{}", path_segment(&id), cmd.word());
        let (status, body) = call(&self.client, peer, Method::POST, &path)
            .await
            .map_err(failed)?;
        slot.wake.notify_one();
        if status == StatusCode::UNAUTHORIZED || status == StatusCode::FORBIDDEN {
            return Err(bad(refused_token(status)));
        }
        if serde_json::from_slice::<serde_json::Value>(&body).is_err() {
            return Err(bad(format!(
                "POST {path} answered {status} without JSON: is this a rigd daemon?"
            )));
        }
        tracing::info!(peer = %peer.name, run = %id, command = cmd.word(), %status, "forwarded to a peer");
        Ok((status, body))
    }
}

/// Starts one poll task per peer; each ends when the daemon shuts down
/// (or is dropped).
pub fn start(peers: &Arc<Peers>, stop: watch::Receiver<bool>) {
    for slot in &peers.slots {
        let slot = slot.clone();
        let client = peers.client.clone();
        let mut stop = stop.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(POLL_EVERY);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    _ = tick.tick() => {}
                    _ = slot.wake.notified() => {}
                    _ = stop.wait_for(|s| *s) => return,
                }
                tokio::select! {
                    polled = poll(&client, &slot.peer) => record(&slot, polled),
                    _ = stop.wait_for(|s| *s) => return,
                }
            }
        });
    }
}

fn record(slot: &Slot, polled: Result<RigSummary, String>) {
    let mut s = lock(&slot.status);
    let was = s.outcome.clone();
    match polled {
        Ok(summary) => {
            if !matches!(was, Some(Ok(()))) {
                tracing::info!(peer = %slot.peer.name, url = %slot.peer.url, "peer reachable");
            }
            s.outcome = Some(Ok(()));
            s.last_seen = Some((crate::store::now_rfc3339(), Instant::now()));
            s.summary = Some(summary);
        }
        Err(e) => {
            if !matches!(&was, Some(Err(old)) if *old == e) {
                tracing::warn!(peer = %slot.peer.name, url = %slot.peer.url, "peer unreachable: {e}");
            }
            s.outcome = Some(Err(e));
        }
    }
}

/// `GET /api/v1/rig` (and the queue, and the active run) of a peer.
async fn poll(client: &HttpClient, peer: &Peer) -> Result<RigSummary, String> {
    let (rig, queue) = tokio::join!(
        get_json::<RemoteRig>(client, peer, "/api/v1/rig"),
        get_json::<RemoteQueue>(client, peer, "/api/v1/queue"),
    );
    let rig = rig.map_err(|e| e.to_string())?;
    let queue = queue.map_err(|e| e.to_string())?;
    let active_run = match &rig.active_run {
        None => None,
        Some(id) => {
            let path = format!("/api/v1/runs/{}", path_segment(id));
            Some(
                get_json::<PeerRun>(client, peer, &path)
                    .await
                    .map_err(|e| e.to_string())?,
            )
        }
    };
    Ok(RigSummary {
        profile: rig.profile,
        sim: rig.sim,
        state: rig.state,
        active_run,
        queue_length: queue.items.len(),
        faults: distinct_faults(rig.devices.iter().filter_map(|d| d.fault.as_deref())),
    })
}

/// What this daemon reads of a peer's `GET /api/v1/rig` (other fields, of
/// this or a later version, are ignored).
#[derive(Deserialize)]
struct RemoteRig {
    profile: String,
    #[serde(default)]
    sim: bool,
    active_run: Option<String>,
    state: RunState,
    #[serde(default)]
    devices: Vec<RemoteDevice>,
}

#[derive(Deserialize)]
struct RemoteDevice {
    #[serde(default)]
    fault: Option<String>,
}

#[derive(Deserialize)]
struct RemoteQueue {
    items: Vec<serde::de::IgnoredAny>,
}

/// A failed read: no answer, or not the answer expected.
#[derive(Debug, thiserror::Error)]
enum Answer {
    #[error(transparent)]
    Call(#[from] CallError),
    #[error("{0}")]
    Bad(String),
}

async fn get_json<T: serde::de::DeserializeOwned>(
    client: &HttpClient,
    peer: &Peer,
    path: &str,
) -> Result<T, Answer> {
    let (status, body) = call(client, peer, Method::GET, path).await?;
    if status == StatusCode::UNAUTHORIZED || status == StatusCode::FORBIDDEN {
        return Err(Answer::Bad(refused_token(status)));
    }
    if !status.is_success() {
        let detail = serde_json::from_slice::<crate::server::error::ErrorBody>(&body)
            .map(|b| format!(": {}", b.detail))
            .unwrap_or_default();
        return Err(Answer::Bad(format!("GET {path} answered {status}{detail}")));
    }
    serde_json::from_slice(&body)
        .map_err(|e| Answer::Bad(format!("GET {path}: not the answer of a rigd daemon ({e})")))
}

fn refused_token(status: StatusCode) -> String {
    format!(
        "it refused the token of the peers file ({status}): check this peer's `token` or `token_file`"
    )
}

/// One request with the peer's token, bounded by [`REQUEST_TIMEOUT`]:
/// its status and body.
async fn call(
    client: &HttpClient,
    peer: &Peer,
    method: Method,
    path: &str,
) -> Result<(StatusCode, Bytes), CallError> {
    let request = client
        .request(method, format!("{}{path}", peer.url))
        .header(header::AUTHORIZATION, format!("Bearer {}", peer.token()))
        .header(header::ACCEPT, "application/json")
        .header(
            header::USER_AGENT,
            concat!("rigd/", env!("CARGO_PKG_VERSION")),
        );
    let exchange = async {
        let mut response = request.send().await.map_err(|e| {
            let root = root_cause(&e);
            CallError::Unreachable(if e.is_builder() {
                format!("cannot make the request: {root}")
            } else if e.is_connect() {
                format!("cannot connect: {root}")
            } else {
                format!("the connection failed: {root}")
            })
        })?;
        let status = response.status();
        let mut body = Vec::new();
        while let Some(chunk) = response.chunk().await.map_err(|e| {
            CallError::Unreachable(format!("the answer broke off: {}", root_cause(&e)))
        })? {
            if body.len() + chunk.len() > MAX_ANSWER {
                return Err(CallError::Unreachable(format!(
                    "the answer broke off: longer than {MAX_ANSWER} bytes"
                )));
            }
            body.extend_from_slice(&chunk);
        }
        Ok((status, Bytes::from(body)))
    };
    tokio::time::timeout(REQUEST_TIMEOUT, exchange)
        .await
        .map_err(|_| CallError::Timeout)?
}

/// The innermost cause of an error: the operating system's words.
fn root_cause(e: &(dyn std::error::Error + 'static)) -> String {
    let mut cur = e;
    while let Some(next) = cur.source() {
        cur = next;
    }
    cur.to_string()
}

/// A run id as one path segment (ids are made of letters, digits, `-` and
/// `_`; anything else is percent-encoded).
fn path_segment(id: &str) -> String {
    let mut out = String::with_capacity(id.len());
    for b in id.bytes() {
        if b.is_ascii_alphanumeric() || b == b'-' || b == b'_' || b == b'.' {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faults_are_listed_once_and_ids_stay_one_segment() {
        assert_eq!(
            distinct_faults(["camera: timeout", "camera: timeout", "rail: alarm"]),
            vec!["camera: timeout".to_string(), "rail: alarm".to_string()]
        );
        assert_eq!(
            path_segment("20250101T000000Z-a_b-h1"),
            "20250101T000000Z-a_b-h1"
        );
        assert_eq!(path_segment("a/../b c"), "a%2F..%2Fb%20c");
    }

    #[tokio::test]
    async fn a_closed_port_is_unreachable_at_once() {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        let peer = Peer::new(
            "gone",
            &format!("http://127.0.0.1:{port}"),
            "0123456789abcdef",
        )
        .expect("peer");
        let peers = Peers::new(std::slice::from_ref(&peer));
        let started = Instant::now();
        let polled = poll(&peers.client, &peer).await;
        let err = polled.expect_err("nothing listens there");
        assert!(err.starts_with("cannot connect: "), "{err}");
        assert!(
            started.elapsed() < REQUEST_TIMEOUT,
            "{:?}",
            started.elapsed()
        );
        record(&peers.slots[0], Err(err.clone()));
        let v = &peers.views()[0];
        assert!(!v.reachable);
        assert_eq!(v.error.as_deref(), Some(err.as_str()));
        assert_eq!(v.last_seen, None);
        let fwd = peers.forward("gone", PeerCommand::Pause).await;
        assert!(
            matches!(fwd, Err(ForwardError::BadGateway { .. })),
            "{fwd:?}"
        );
        assert_eq!(
            peers.forward("nope", PeerCommand::Abort).await,
            Err(ForwardError::UnknownPeer("nope".into()))
        );
    }

    /// A peer on a loopback port whose every connection gets `answer`
    /// once the request is read, then, if `endless`, bytes without end, and
    /// is held open.
    async fn hostile_peer(answer: &'static [u8], endless: bool) -> Peer {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let port = listener.local_addr().expect("addr").port();
        tokio::spawn(async move {
            while let Ok((mut conn, _)) = listener.accept().await {
                tokio::spawn(async move {
                    let mut buf = [0u8; 4096];
                    let _ = conn.read(&mut buf).await;
                    if conn.write_all(answer).await.is_err() {
                        return;
                    }
                    let chunk = [b'x'; 64 * 1024];
                    while endless && conn.write_all(&chunk).await.is_ok() {}
                    // A silent peer holds the connection open.
                    tokio::time::sleep(Duration::from_secs(30)).await;
                });
            }
        });
        Peer::new(
            "hostile",
            &format!("http://127.0.0.1:{port}"),
            "0123456789abcdef",
        )
        .expect("peer")
    }

    #[tokio::test]
    async fn an_endless_answer_is_cut_at_its_bound_and_a_silent_peer_at_the_deadline() {
        let peer = hostile_peer(
            b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\n\r\n",
            true,
        )
        .await;
        let peers = Peers::new(std::slice::from_ref(&peer));
        let err = call(&peers.client, &peer, Method::GET, "/api/v1/rig")
            .await
            .expect_err("an answer without end");
        assert_eq!(
            err,
            CallError::Unreachable(format!(
                "the answer broke off: longer than {MAX_ANSWER} bytes"
            ))
        );

        let silent = hostile_peer(b"", false).await;
        let started = Instant::now();
        let err = call(&peers.client, &silent, Method::GET, "/api/v1/rig")
            .await
            .expect_err("no answer");
        assert_eq!(err, CallError::Timeout);
        let took = started.elapsed();
        assert!(
            took >= REQUEST_TIMEOUT && took < REQUEST_TIMEOUT + Duration::from_secs(2),
            "{took:?}"
        );
    }
}
