"""The client's own logic, without a daemon: SSE framing, reconnection with
Last-Event-ID, error bodies, the paging loop."""

from __future__ import annotations

import http.server
import threading
import time
from typing import Iterator, List, Optional

import httpx
import pytest

from rigd_client import Client, Event, RigdError, RunPage
from rigd_client._client import _parse_sse


def test_sse_framing() -> None:
    lines = [": keep-alive", "", "id: 1", 'data: {"id":1,"run":"r","kind":"engine","event":{"type":"step"}}', "",
             "event: lagged", "data: {\"skipped\": 3}", "", "id: 2", "data: {\"id\":2,", "data: \"kind\":\"estop\",\"event\":{}}", ""]
    events = list(_parse_sse(lines))
    assert [(e.id, e.kind, e.run) for e in events] == [(1, "engine", "r"), (None, "lagged", None), (2, "estop", None)]
    assert events[0].event == {"type": "step"} and events[1].event == {"skipped": 3}


def _mock(handler) -> Client:
    return Client("http://rigd.test", token="t", transport=httpx.MockTransport(handler))


def test_error_bodies() -> None:
    def handler(req: httpx.Request) -> httpx.Response:
        if req.url.path.endswith("/runs"):
            return httpx.Response(409, json={"error": "conflict", "detail": "run X is active"})
        return httpx.Response(431, content=b"")

    c = _mock(handler)
    with pytest.raises(RigdError) as e:
        c.start_run("s", "h1")
    assert (e.value.status, e.value.error, e.value.detail) == (409, "conflict", "run X is active")
    assert str(e.value) == "POST /api/v1/runs: 409 conflict: run X is active"
    with pytest.raises(RigdError) as e:
        c.rig()
    assert e.value.status == 431 and e.value.error is None


def test_paging_loop_and_parameters() -> None:
    seen: List[httpx.QueryParams] = []
    pages = {None: (["a", "b"], "c1"), "c1": (["c", "d"], "c2"), "c2": (["e"], None)}

    def handler(req: httpx.Request) -> httpx.Response:
        seen.append(req.url.params)
        ids, nxt = pages[req.url.params.get("cursor")]
        body = {"runs": [{"id": i} for i in ids], "active": None, "total": 5}
        if nxt:
            body["next"] = nxt
        return httpx.Response(200, json=body)

    c = _mock(handler)
    import datetime as dt
    page = c.runs(limit=2, sample="s", state="completed", plan="h1", profile="p",
                  from_=dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=dt.timezone.utc), to="2026-02-01T00:00:00Z")
    assert isinstance(page, RunPage) and page.next == "c1" and page.total == 5
    assert dict(seen[0]) == {"limit": "2", "sample": "s", "state": "completed", "plan": "h1", "profile": "p",
                             "from": "2026-01-02T03:04:05Z", "to": "2026-02-01T00:00:00Z"}
    assert [r["id"] for r in c.iter_runs(limit=2)] == ["a", "b", "c", "d", "e"]
    # An old daemon: no next, no total.
    old = _mock(lambda req: httpx.Response(200, json={"runs": [{"id": "x"}], "active": "x"}))
    p = old.runs(limit=1)
    assert (p.next, p.total, p.active) == (None, None, "x")
    # A cursor returned twice would loop forever: it is refused.
    loop = _mock(lambda req: httpx.Response(200, json={"runs": [], "next": "same"}))
    with pytest.raises(RuntimeError):
        list(loop.iter_runs())


class _FlakySSE(http.server.BaseHTTPRequestHandler):
    """Sends two events per connection, then drops it; records Last-Event-ID."""

    headers_seen: List[Optional[str]] = []
    next_id = 1

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        type(self).headers_seen.append(self.headers.get("Last-Event-ID"))
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.end_headers()
        for _ in range(2):
            i = type(self).next_id
            type(self).next_id += 1
            self.wfile.write(f'id: {i}\ndata: {{"id":{i},"kind":"estop","event":{{}}}}\n\n'.encode())
            self.wfile.flush()
        self.close_connection = True

    def log_message(self, *args: object) -> None:
        pass


def test_events_reconnect_with_last_event_id() -> None:
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _FlakySSE)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        c = Client(f"http://127.0.0.1:{server.server_address[1]}", token="t")
        t0 = time.monotonic()
        stream: Iterator[Event] = c.events(last_event_id=7, max_backoff=0.3)
        ids = [next(stream).id for _ in range(6)]
        stream.close()  # type: ignore[attr-defined]
        assert ids == [1, 2, 3, 4, 5, 6]
        assert _FlakySSE.headers_seen[:3] == ["7", "2", "4"]
        assert time.monotonic() - t0 < 5  # bounded backoff: 0.25 s, then 0.3 s
    finally:
        server.shutdown()
        server.server_close()


def test_events_give_up_when_unreachable() -> None:
    c = Client("http://127.0.0.1:9", token="t", timeout=1)
    t0 = time.monotonic()
    with pytest.raises(httpx.TransportError):
        next(c.events(max_backoff=0.2, give_up_after=1.0))
    assert time.monotonic() - t0 < 10
