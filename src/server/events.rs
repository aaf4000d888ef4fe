//! The daemon's event stream: engine events wrapped with their run id, and
//! daemon events (queue changes, runs created and ended, emergency stops),
//! numbered daemon-wide, kept in a ring for `Last-Event-ID` replay and
//! served as Server-Sent Events.

use std::collections::VecDeque;
use std::convert::Infallible;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::response::sse::{Event, KeepAlive, Sse};
use futures::stream::{self, Stream, StreamExt};
use serde::Serialize;
use tokio::sync::{broadcast, watch};
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use tokio_stream::wrappers::BroadcastStream;
use utoipa::ToSchema;

/// Events kept for replay.
pub const RING_CAPACITY: usize = 4096;

/// One event of the daemon's stream.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub struct DaemonEvent {
    /// Daemon-wide sequence number (also the SSE `id:`), increasing from 1
    /// at every daemon start.
    pub id: u64,
    /// The run this event is about, if any.
    pub run: Option<String>,
    /// `engine` (the run engine's own event: `event` is a RunEvent with
    /// `seq`, `t_s`, `type` = state|step|retry|refused), `run_created`,
    /// `run_ended`, `run_resumed`, `queue_changed`, `estop`.
    pub kind: String,
    /// The payload.
    #[schema(value_type = Object)]
    pub event: serde_json::Value,
}

struct Ring {
    next_id: u64,
    events: VecDeque<Arc<DaemonEvent>>,
}

/// Publishes events to every subscriber and keeps the recent ones.
pub struct EventHub {
    ring: Mutex<Ring>,
    tx: broadcast::Sender<Arc<DaemonEvent>>,
}

impl Default for EventHub {
    fn default() -> Self {
        Self::new()
    }
}

impl EventHub {
    /// An empty hub; the first event published gets id 1.
    pub fn new() -> Self {
        let (tx, _) = broadcast::channel(RING_CAPACITY);
        EventHub {
            ring: Mutex::new(Ring {
                next_id: 1,
                events: VecDeque::with_capacity(RING_CAPACITY),
            }),
            tx,
        }
    }

    fn ring(&self) -> std::sync::MutexGuard<'_, Ring> {
        rigd_core::sync::lock(&self.ring)
    }

    /// Numbers, keeps and sends one event.
    pub fn publish(&self, run: Option<&str>, kind: &str, event: serde_json::Value) -> u64 {
        let mut ring = self.ring();
        let id = ring.next_id;
        ring.next_id += 1;
        let ev = Arc::new(DaemonEvent {
            id,
            run: run.map(str::to_string),
            kind: kind.to_string(),
            event,
        });
        if ring.events.len() == RING_CAPACITY {
            ring.events.pop_front();
        }
        ring.events.push_back(ev.clone());
        // Sent under the lock, so a subscriber taken under it sees no gap
        // and no repeat between the replay and the live events.
        let _ = self.tx.send(ev);
        id
    }

    /// Kept events after `after`, and a receiver for everything later.
    pub fn subscribe_after(
        &self,
        after: Option<u64>,
    ) -> (Vec<Arc<DaemonEvent>>, broadcast::Receiver<Arc<DaemonEvent>>) {
        let ring = self.ring();
        let rx = self.tx.subscribe();
        let replay = match after {
            Some(last) => ring
                .events
                .iter()
                .filter(|e| e.id > last)
                .cloned()
                .collect(),
            None => Vec::new(),
        };
        (replay, rx)
    }
}

fn to_sse(ev: &DaemonEvent) -> Event {
    let data = serde_json::to_string(ev).unwrap_or_else(|_| "{}".into());
    Event::default().id(ev.id.to_string()).data(data)
}

/// The SSE response: replay after `last_event_id`, then live events until
/// the client goes or the daemon shuts down. A client too slow to keep up
/// gets an `event: lagged` message and continues with newer events.
pub fn sse_stream(
    hub: &EventHub,
    last_event_id: Option<u64>,
    mut shutdown: watch::Receiver<bool>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let (replay, rx) = hub.subscribe_after(last_event_id);
    let replayed_to = replay.last().map(|e| e.id).or(last_event_id).unwrap_or(0);
    let replay = stream::iter(replay.into_iter().map(|e| Ok(to_sse(&e))));
    let live = BroadcastStream::new(rx).filter_map(move |r| async move {
        match r {
            Ok(ev) if ev.id > replayed_to => Some(Ok(to_sse(&ev))),
            Ok(_) => None,
            Err(BroadcastStreamRecvError::Lagged(n)) => Some(Ok(Event::default()
                .event("lagged")
                .data(format!("{{\"missed\":{n}}}")))),
        }
    });
    let stop = async move {
        // Ends when shutdown turns true or its sender is dropped.
        let _ = shutdown.wait_for(|s| *s).await;
    };
    let stream = replay.chain(live).take_until(Box::pin(stop));
    Sse::new(stream).keep_alive(
        KeepAlive::new()
            .interval(Duration::from_secs(15))
            .text("keep-alive"),
    )
}
