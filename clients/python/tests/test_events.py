"""The event stream against a live daemon: replay, live events, and a restart."""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, List

import httpx
import pytest
from conftest import Daemon

from rigd_client import Client, Event, RigdError


def collect(stream: Iterator[Event], until: Callable[[List[Event]], bool], timeout: float) -> List[Event]:
    """Reads ``stream`` on a thread until ``until(events)`` or ``timeout`` s;
    the stream blocks between events, so the bound cannot live in the loop."""
    got: List[Event] = []
    done = threading.Event()
    q: "queue.Queue[Event]" = queue.Queue()

    def pump() -> None:
        try:
            for ev in stream:
                q.put(ev)
                if done.is_set():
                    return
        except (httpx.HTTPError, RigdError, RuntimeError):
            return  # the daemon or the client went away after the test: nothing to report

    threading.Thread(target=pump, daemon=True).start()
    deadline = time.monotonic() + timeout
    while not until(got):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        try:
            got.append(q.get(timeout=left))
        except queue.Empty:
            break
    done.set()
    return got


def test_replay_from_last_event_id(client: Client) -> None:
    for _ in range(5):  # events of our own, whatever ran before
        client.estop()
    # Last-Event-ID 0 replays every kept event, in order, without a gap
    # (ids count on from the daemon's start time, not from 1).
    events = collect(client.events(last_event_id=0), lambda e: len(e) >= 5, 20)
    assert len(events) >= 5, events
    first = events[0].id
    assert [e.id for e in events] == list(range(first, first + len(events)))
    assert all(e.kind for e in events) and any(e.kind == "engine" for e in events)
    later = collect(client.events(last_event_id=events[2].id), lambda e: len(e) >= 1, 20)
    assert later[0].id == events[3].id


def test_live_event(client: Client) -> None:
    stream = client.events()
    timer = threading.Timer(0.5, client.estop)
    timer.start()
    try:
        events = collect(stream, lambda e: any(x.kind == "estop" for x in e), 20)
    finally:
        timer.cancel()
    (stop,) = [e for e in events if e.kind == "estop"]
    # The event's payload is not the POST answer's shape (README, "Known issues").
    assert stop.id is not None and {"note", "report", "run"} <= set(stop.event)


class Pump:
    """Reads one stream on one thread for a whole test, into a queue."""

    def __init__(self, stream: Iterator[Event]) -> None:
        self.q: "queue.Queue[Event]" = queue.Queue()
        threading.Thread(target=self._run, args=(stream,), daemon=True).start()

    def _run(self, stream: Iterator[Event]) -> None:
        try:
            for ev in stream:
                self.q.put(ev)
        except (httpx.HTTPError, RigdError, RuntimeError):
            return  # the test is over and its daemon gone

    def until_estop(self, d: Daemon, timeout: float) -> List[Event]:
        """Asks for an emergency stop and returns the events up to its event."""
        Client(d.url, data_dir=d.data).estop()
        got: List[Event] = []
        deadline = time.monotonic() + timeout
        while not any(e.kind == "estop" for e in got):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            try:
                got.append(self.q.get(timeout=left))
            except queue.Empty:
                break
        return got


def test_reconnects_after_daemon_restart(tmp_path: Path) -> None:
    d = Daemon(tmp_path / "data", ["--profile", "virtex-photometric-stereo"]).start()
    try:
        pump = Pump(d.client().events(max_backoff=0.5, give_up_after=30))
        time.sleep(0.3)  # connected
        # Two events, so the client's last id (2) is above the restarted daemon's first (1).
        assert any(e.kind == "estop" for e in pump.until_estop(d, 10))
        assert any(e.kind == "estop" for e in pump.until_estop(d, 10))
        d.stop()
        d.start()  # same port, same data: the client reconnects by itself
        time.sleep(1.5)  # its backoff is at most 0.5 s
        again = pump.until_estop(d, 5)
        assert any(e.kind == "estop" for e in again), "no event after the daemon restarted"
    finally:
        d.stop()
