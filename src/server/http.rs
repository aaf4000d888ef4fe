//! The daemon's HTTP connections, bounded: every client gets a fixed time
//! to send a request's head and its body, the number of connections is
//! capped well below the file descriptors the process may open, and a
//! capture never competes with clients for them.
//!
//! - A request's head (request line and headers) must arrive within
//!   [`HttpLimits::header_timeout_s`]; the same time bounds how long an
//!   idle keep-alive connection waits for its next request. Its body must
//!   arrive within [`HttpLimits::body_timeout_s`] of the head, else the
//!   answer is `408` and the connection closes. Responses are not timed:
//!   the event stream and large downloads run as long as they need.
//! - At most [`HttpLimits::max_connections`] connections are open (fewer
//!   when the descriptor limit is low: [`connection_cap`]). A new
//!   connection beyond that closes the idle connection (one with no
//!   request in progress) that has been quiet longest, so a flood of
//!   silent connections cannot keep anyone out; only when every open
//!   connection is busy is the new one refused with `503`.
//! - A connection serves at most [`HttpLimits::max_requests_per_connection`]
//!   requests (the last answer says `Connection: close`), and at most
//!   [`HttpLimits::max_event_streams`] event streams are open at once.
//! - At start the soft limit on open files is raised to the hard one, and
//!   [`FD_RESERVE`] descriptors are kept out of the clients' reach for the
//!   run (its frames, journal, ports and processing). When the process
//!   runs out of descriptors anyway, accepting backs off and sheds an idle
//!   connection instead of spinning.

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::{header, HeaderValue, Request, Response, StatusCode};
use axum::response::IntoResponse;
use axum::Router;
use hyper::body::{Bytes, Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, Notify, OwnedSemaphorePermit, Semaphore};
use tokio::task::JoinSet;

use super::error::ApiError;

/// File descriptors kept out of the clients' reach for the run and the
/// daemon itself: a capture writes frames and its journal, talks to its
/// devices and, processed during the capture, reads frames on every core.
pub const FD_RESERVE: u64 = 256;
/// The fewest connections served however low the descriptor limit is.
pub const MIN_CONNECTIONS: usize = 8;
/// The longest request head (request line and headers) read, bytes;
/// beyond it hyper answers `431`.
pub const MAX_HEADER_BYTES: usize = 32 * 1024;
/// The path of the event stream, whose connections are capped apart.
const EVENTS_PATH: &str = "/api/v1/events";
/// At most this many refusals are being written at once; beyond them a
/// connection is closed without an answer.
const MAX_REFUSING: usize = 64;
/// The longest a refusal may take to write.
const REFUSAL_WRITE: Duration = Duration::from_secs(1);
/// Back-off of the accept loop when the process is out of descriptors.
const BACKOFF_MIN: Duration = Duration::from_millis(10);
const BACKOFF_MAX: Duration = Duration::from_secs(1);

/// The limits of the daemon's HTTP server: the `[http]` table of
/// `rigd serve --config FILE` (`docs/api.md`, "Security").
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HttpLimits {
    /// Seconds a client has to send a request's head; also how long an
    /// idle keep-alive connection waits for its next request.
    pub header_timeout_s: f64,
    /// Seconds a request's body may take to arrive, from its head.
    pub body_timeout_s: f64,
    /// Most connections open at once (lowered to fit the descriptor limit).
    pub max_connections: usize,
    /// Most requests one connection serves before it is closed.
    pub max_requests_per_connection: usize,
    /// Most `/api/v1/events` streams open at once.
    pub max_event_streams: usize,
}

impl Default for HttpLimits {
    fn default() -> Self {
        HttpLimits {
            header_timeout_s: 10.0,
            body_timeout_s: 10.0,
            max_connections: 256,
            max_requests_per_connection: 1000,
            max_event_streams: 128,
        }
    }
}

impl HttpLimits {
    /// Checks every value: the key and its range when one is unusable.
    pub fn check(&self) -> Result<(), String> {
        for (key, v) in [
            ("header_timeout_s", self.header_timeout_s),
            ("body_timeout_s", self.body_timeout_s),
        ] {
            if !(v.is_finite() && (0.1..=3600.0).contains(&v)) {
                return Err(format!("{key} = {v}: expected 0.1 to 3600 seconds"));
            }
        }
        for (key, v, max) in [
            ("max_connections", self.max_connections, 100_000),
            (
                "max_requests_per_connection",
                self.max_requests_per_connection,
                1_000_000,
            ),
            ("max_event_streams", self.max_event_streams, 100_000),
        ] {
            if !(1..=max).contains(&v) {
                return Err(format!("{key} = {v}: expected 1 to {max}"));
            }
        }
        Ok(())
    }
}

/// Raises the soft limit on open files to the hard one, so the limit the
/// operator allows is the one the daemon has; returns the soft limit now
/// in force (None where it cannot be read).
pub fn raise_fd_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut lim = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes the struct it is given, nothing else.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
            return None;
        }
        // An unlimited hard limit still stops at the kernel's nr_open.
        let want = lim.rlim_max.min(1 << 20);
        if lim.rlim_cur < want {
            let raised = libc::rlimit {
                rlim_cur: want,
                rlim_max: lim.rlim_max,
            };
            // SAFETY: setrlimit reads the struct it is given.
            if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
                lim.rlim_cur = want;
            }
        }
        // rlim_t is u64 on Linux, not on every unix.
        #[allow(clippy::unnecessary_cast)]
        Some(lim.rlim_cur as u64)
    }
    #[cfg(not(unix))]
    None
}

/// The connections served at once: the configured most, lowered so that
/// they and as many again (refusals, files read for them) stay clear of
/// the [`FD_RESERVE`] under the descriptor limit `fd_limit`; never fewer
/// than [`MIN_CONNECTIONS`].
pub fn connection_cap(max_connections: usize, fd_limit: Option<u64>) -> usize {
    let fit = fd_limit.map_or(usize::MAX, |n| {
        (n.saturating_sub(FD_RESERVE) / 2).min(usize::MAX as u64) as usize
    });
    max_connections.min(fit).max(MIN_CONNECTIONS)
}

/// One open connection, as the shedding sees it.
struct Slot {
    /// Requests whose head was read and whose answer is not sent yet.
    in_flight: AtomicUsize,
    /// When it last did something (connected, began or ended a request),
    /// milliseconds since the server started.
    last_active_ms: AtomicU64,
    /// Tells its task to close it.
    shed: Notify,
}

struct Shared {
    app: Router,
    limits: HttpLimits,
    cap: usize,
    started: Instant,
    conns: Mutex<BTreeMap<u64, Arc<Slot>>>,
    next_id: AtomicU64,
    refusing: AtomicUsize,
    event_streams: Arc<Semaphore>,
    builder: hyper::server::conn::http1::Builder,
}

impl Shared {
    fn now_ms(&self) -> u64 {
        self.started.elapsed().as_millis() as u64
    }

    fn conns(&self) -> MutexGuard<'_, BTreeMap<u64, Arc<Slot>>> {
        // A poisoned map is still a map of connections.
        rigd_core::sync::lock(&self.conns)
    }

    /// Closes the idle connection quiet longest; false when none is idle.
    fn shed_idle(conns: &mut BTreeMap<u64, Arc<Slot>>) -> bool {
        let oldest = conns
            .iter()
            .filter(|(_, s)| s.in_flight.load(Ordering::SeqCst) == 0)
            .min_by_key(|(id, s)| (s.last_active_ms.load(Ordering::SeqCst), **id))
            .map(|(id, _)| *id);
        match oldest.and_then(|id| conns.remove(&id)) {
            Some(slot) => {
                slot.shed.notify_one();
                true
            }
            None => false,
        }
    }

    /// Registers a new connection, making room by shedding an idle one at
    /// the cap; None when every connection is busy.
    fn admit(&self) -> Option<(u64, Arc<Slot>)> {
        let mut conns = self.conns();
        if conns.len() >= self.cap && !Self::shed_idle(&mut conns) {
            return None;
        }
        let id = self.next_id.fetch_add(1, Ordering::SeqCst);
        let slot = Arc::new(Slot {
            in_flight: AtomicUsize::new(0),
            last_active_ms: AtomicU64::new(self.now_ms()),
            shed: Notify::new(),
        });
        conns.insert(id, slot.clone());
        Some((id, slot))
    }
}

/// Serves `app` on `listener` within `limits` until `stop` turns true:
/// then accepting stops, idle connections close and busy ones finish
/// their request first.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: HttpLimits,
    fd_limit: Option<u64>,
    mut stop: watch::Receiver<bool>,
) {
    let cap = connection_cap(limits.max_connections, fd_limit);
    if cap < limits.max_connections {
        tracing::warn!(
            cap,
            configured = limits.max_connections,
            fd_limit,
            "fewer HTTP connections than configured, to keep file descriptors for the run"
        );
    }
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(Duration::from_secs_f64(limits.header_timeout_s))
        .keep_alive(true)
        .max_buf_size(2 * MAX_HEADER_BYTES)
        .max_header_size(MAX_HEADER_BYTES);
    let shared = Arc::new(Shared {
        app,
        limits,
        cap,
        started: Instant::now(),
        conns: Mutex::new(BTreeMap::new()),
        next_id: AtomicU64::new(0),
        refusing: AtomicUsize::new(0),
        event_streams: Arc::new(Semaphore::new(limits.max_event_streams)),
        builder,
    });
    let mut tasks = JoinSet::new();
    let mut backoff = BACKOFF_MIN;
    loop {
        let accepted = tokio::select! {
            _ = stop.wait_for(|s| *s) => break,
            Some(_) = tasks.join_next(), if !tasks.is_empty() => continue,
            accepted = listener.accept() => accepted,
        };
        match accepted {
            Ok((stream, peer)) => {
                backoff = BACKOFF_MIN;
                match shared.admit() {
                    Some((id, slot)) => {
                        tasks.spawn(connection(
                            shared.clone(),
                            stream,
                            peer,
                            id,
                            slot,
                            stop.clone(),
                        ));
                    }
                    None => refuse(&shared, stream),
                }
            }
            // The client gave up before the connection was accepted.
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::ConnectionAborted | std::io::ErrorKind::ConnectionReset
                ) => {}
            Err(e) => {
                if backoff == BACKOFF_MIN {
                    tracing::warn!("accepting a connection: {e}; backing off");
                }
                // Out of descriptors: an idle client gives one back.
                Shared::shed_idle(&mut shared.conns());
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(BACKOFF_MAX);
            }
        }
    }
    drop(listener);
    while tasks.join_next().await.is_some() {}
}

/// `503` to a connection beyond the cap when every connection is busy,
/// written in the background within [`REFUSAL_WRITE`].
fn refuse(shared: &Arc<Shared>, mut stream: TcpStream) {
    if shared.refusing.fetch_add(1, Ordering::SeqCst) >= MAX_REFUSING {
        shared.refusing.fetch_sub(1, Ordering::SeqCst);
        return;
    }
    let body = serde_json::json!({
        "error": "unavailable",
        "detail": format!(
            "too many connections: all {} are busy; try again in a moment",
            shared.cap
        ),
    })
    .to_string();
    let answer = format!(
        "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n\
         retry-after: 1\r\nconnection: close\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    );
    let shared = shared.clone();
    tokio::spawn(async move {
        let _ = tokio::time::timeout(REFUSAL_WRITE, async {
            stream.write_all(answer.as_bytes()).await?;
            stream.shutdown().await
        })
        .await;
        shared.refusing.fetch_sub(1, Ordering::SeqCst);
    });
}

/// Serves one connection until it ends, is shed, or the server stops.
async fn connection(
    shared: Arc<Shared>,
    stream: TcpStream,
    peer: SocketAddr,
    id: u64,
    slot: Arc<Slot>,
    mut stop: watch::Receiver<bool>,
) {
    let served = Arc::new(AtomicUsize::new(0));
    let service = {
        let (shared, slot) = (shared.clone(), slot.clone());
        hyper::service::service_fn(move |req: Request<Incoming>| {
            let (shared, slot, served) = (shared.clone(), slot.clone(), served.clone());
            async move {
                let n = served.fetch_add(1, Ordering::SeqCst) + 1;
                Ok::<_, Infallible>(request(&shared, &slot, peer, req, n).await)
            }
        })
    };
    let conn = shared
        .builder
        .serve_connection(TokioIo::new(stream), service);
    tokio::pin!(conn);
    let mut closing = false;
    loop {
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!(%peer, "connection: {e}");
                }
                break;
            }
            _ = slot.shed.notified(), if !closing => {
                // Shed while idle: close now. A request that began
                // meanwhile is answered first.
                if slot.in_flight.load(Ordering::SeqCst) == 0 {
                    break;
                }
                conn.as_mut().graceful_shutdown();
                closing = true;
            }
            _ = stop.wait_for(|s| *s), if !closing => {
                conn.as_mut().graceful_shutdown();
                closing = true;
            }
        }
    }
    shared.conns().remove(&id);
}

/// Counts a request in flight on its connection until its answer's body
/// is sent or dropped.
struct InFlight {
    slot: Arc<Slot>,
    shared: Arc<Shared>,
}

impl InFlight {
    fn begin(shared: &Arc<Shared>, slot: &Arc<Slot>) -> InFlight {
        slot.in_flight.fetch_add(1, Ordering::SeqCst);
        slot.last_active_ms.store(shared.now_ms(), Ordering::SeqCst);
        InFlight {
            slot: slot.clone(),
            shared: shared.clone(),
        }
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.slot
            .last_active_ms
            .store(self.shared.now_ms(), Ordering::SeqCst);
        self.slot.in_flight.fetch_sub(1, Ordering::SeqCst);
    }
}

/// One request: its body timed, the client's address attached for the
/// token check, the event streams counted, the connection's last request
/// marked.
async fn request(
    shared: &Arc<Shared>,
    slot: &Arc<Slot>,
    peer: SocketAddr,
    req: Request<Incoming>,
    n: usize,
) -> Response<Body> {
    let busy = InFlight::begin(shared, slot);
    let mut permit: Option<OwnedSemaphorePermit> = None;
    if req.uri().path() == EVENTS_PATH {
        match shared.event_streams.clone().try_acquire_owned() {
            Ok(p) => permit = Some(p),
            Err(_) => {
                let refusal = ApiError::new(
                    StatusCode::SERVICE_UNAVAILABLE,
                    format!(
                        "too many event streams: {} are open; try again later",
                        shared.limits.max_event_streams
                    ),
                );
                return finish(refusal.into_response(), busy, None, n, &shared.limits);
            }
        }
    }
    let timed_out = Arc::new(AtomicBool::new(false));
    let body_timeout = Duration::from_secs_f64(shared.limits.body_timeout_s);
    let (parts, body) = req.into_parts();
    let mut req = Request::from_parts(
        parts,
        Body::new(TimedBody {
            inner: body,
            deadline: Box::pin(tokio::time::sleep(body_timeout)),
            timed_out: timed_out.clone(),
        }),
    );
    req.extensions_mut()
        .insert(axum::extract::ConnectInfo(peer));
    let service = hyper_util::service::TowerToHyperService::new(shared.app.clone());
    let resp = match hyper::service::Service::call(&service, req).await {
        Ok(resp) => resp,
        Err(never) => match never {},
    };
    let resp = if timed_out.load(Ordering::SeqCst) {
        let mut late = ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            format!(
                "the request's body did not arrive within {} s",
                shared.limits.body_timeout_s
            ),
        )
        .into_response();
        late.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
        late
    } else {
        resp
    };
    finish(resp, busy, permit, n, &shared.limits)
}

/// The answer, holding the request's in-flight mark (and its event-stream
/// permit) until its body is sent; the connection's last one says so.
fn finish(
    resp: Response<Body>,
    busy: InFlight,
    permit: Option<OwnedSemaphorePermit>,
    n: usize,
    limits: &HttpLimits,
) -> Response<Body> {
    let (mut parts, body) = resp.into_parts();
    if n >= limits.max_requests_per_connection {
        parts
            .headers
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    let body = HeldBody {
        inner: body,
        _held: (busy, permit),
    };
    Response::from_parts(parts, Body::new(body))
}

/// An answer's body that holds what its request holds until it is sent or
/// dropped.
struct HeldBody {
    inner: Body,
    _held: (InFlight, Option<OwnedSemaphorePermit>),
}

impl hyper::body::Body for HeldBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Why a request's body stopped: it did not arrive in time.
#[derive(Debug, thiserror::Error)]
#[error("the request's body did not arrive in time")]
struct BodyTimedOut;

/// A request body that fails once its deadline passes.
struct TimedBody {
    inner: Incoming,
    deadline: Pin<Box<tokio::time::Sleep>>,
    timed_out: Arc<AtomicBool>,
}

impl hyper::body::Body for TimedBody {
    type Data = Bytes;
    type Error = Box<dyn std::error::Error + Send + Sync>;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Self::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(frame) => Poll::Ready(frame.map(|f| f.map_err(Into::into))),
            Poll::Pending => match this.deadline.as_mut().poll(cx) {
                Poll::Ready(()) => {
                    this.timed_out.store(true, Ordering::SeqCst);
                    Poll::Ready(Some(Err(Box::new(BodyTimedOut))))
                }
                Poll::Pending => Poll::Pending,
            },
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_keeps_descriptors_for_the_run() {
        assert_eq!(connection_cap(256, Some(20_000)), 256);
        assert_eq!(connection_cap(256, Some(1024)), 256);
        assert_eq!(connection_cap(256, Some(512)), 128);
        assert_eq!(connection_cap(256, Some(100)), MIN_CONNECTIONS);
        assert_eq!(connection_cap(256, None), 256);
    }

    #[test]
    fn limits_are_checked_with_their_key() {
        assert_eq!(HttpLimits::default().check(), Ok(()));
        let bad = HttpLimits {
            body_timeout_s: f64::NAN,
            ..HttpLimits::default()
        };
        assert!(bad
            .check()
            .is_err_and(|e| e.starts_with("body_timeout_s = NaN")));
        let bad = HttpLimits {
            max_connections: 0,
            ..HttpLimits::default()
        };
        assert!(bad
            .check()
            .is_err_and(|e| e.starts_with("max_connections = 0")));
    }
}
