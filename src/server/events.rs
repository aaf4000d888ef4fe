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
    /// Daemon-wide sequence number (also the SSE `id:`), increasing, and
    /// across restarts too: a daemon numbers its events from the time it
    /// started (in microseconds since 1970), so that a client's
    /// `Last-Event-ID` from before a restart is below every new event.
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

/// One message of `GET /api/v1/events` as the Server-Sent Events stream
/// frames it (the schema of each event of the stream, as OpenAPI 3.1 reads
/// `text/event-stream`): its `id:` and a [`DaemonEvent`] as JSON in `data:`.
#[derive(Debug, Clone, ToSchema)]
pub struct SseMessage {
    /// The `id:` field: the DaemonEvent's id, as text; what a reconnect
    /// sends back in `Last-Event-ID`.
    pub id: Option<String>,
    /// The `event:` field: `message`, the default type.
    pub event: Option<String>,
    /// The `data:` field: one DaemonEvent as JSON.
    #[schema(content_media_type = "application/json")]
    pub data: String,
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
    /// An empty hub; the first event published gets the current time in
    /// microseconds since 1970 as its id (see [`DaemonEvent::id`]).
    pub fn new() -> Self {
        let (tx, _) = broadcast::channel(RING_CAPACITY);
        let now_us = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(1, |d| d.as_micros() as u64);
        EventHub {
            ring: Mutex::new(Ring {
                next_id: now_us.max(1),
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

    /// Kept events after `after`, a receiver for everything later, and the
    /// id the receiver's events must exceed to be new to the subscriber.
    pub fn subscribe_after(
        &self,
        after: Option<u64>,
    ) -> (
        Vec<Arc<DaemonEvent>>,
        broadcast::Receiver<Arc<DaemonEvent>>,
        u64,
    ) {
        let ring = self.ring();
        let rx = self.tx.subscribe();
        // An id this daemon has not given yet comes from another daemon
        // (one whose clock ran ahead): everything kept is new to it.
        let after = after.map(|last| if last >= ring.next_id { 0 } else { last });
        let replay = match after {
            Some(last) => ring
                .events
                .iter()
                .filter(|e| e.id > last)
                .cloned()
                .collect(),
            None => Vec::new(),
        };
        let seen_to = replay
            .last()
            .map(|e: &Arc<DaemonEvent>| e.id)
            .or(after)
            .unwrap_or(0);
        (replay, rx, seen_to)
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
    let (replay, rx, replayed_to) = hub.subscribe_after(last_event_id);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_client_of_an_earlier_daemon_misses_nothing_of_the_next() {
        let before = EventHub::new();
        before.publish(None, "estop", serde_json::json!({}));
        let last_seen = before.publish(None, "estop", serde_json::json!({}));
        // The daemon restarts: a new hub, numbering from its start.
        std::thread::sleep(std::time::Duration::from_millis(2));
        let after = EventHub::new();
        let first = after.publish(None, "run_created", serde_json::json!({}));
        assert!(first > last_seen, "{first} after {last_seen}");
        let (replay, _, seen_to) = after.subscribe_after(Some(last_seen));
        assert_eq!(replay.iter().map(|e| e.id).collect::<Vec<_>>(), [first]);
        assert_eq!(seen_to, first);
        // An id from the future (a daemon whose clock ran ahead): all kept
        // events are replayed, and live ones are not filtered out.
        let (replay, _, seen_to) = after.subscribe_after(Some(u64::MAX));
        assert_eq!(replay.len(), 1);
        assert_eq!(seen_to, first);
        let (replay, _, seen_to) = after.subscribe_after(None);
        assert!(replay.is_empty());
        assert_eq!(seen_to, 0);
    }
}
