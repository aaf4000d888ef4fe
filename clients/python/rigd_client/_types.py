"""The main answers, typed loosely: rigd may add fields, and they stay in the dicts."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

try:  # TypedDict's total=False and NotRequired differ across 3.9 … 3.11
    from typing import TypedDict
except ImportError:  # pragma: no cover
    from typing_extensions import TypedDict  # type: ignore

#: Run states after which nothing changes by itself.
FINAL_STATES = frozenset({"completed", "failed", "aborted"})
#: Process job states after which nothing changes by itself.
JOB_FINAL_STATES = frozenset({"done", "failed"})


class Health(TypedDict):
    """``GET /health``."""

    ok: bool
    version: str
    profile: str
    sim: bool
    sim_speed: float


class StepStatus(TypedDict, total=False):
    """One step of a process job."""

    step: str
    state: str
    done: int
    total: int
    elapsed_s: float
    eta_s: Optional[float]
    summary: Optional[str]
    detail: Optional[str]


class ProcessJob(TypedDict, total=False):
    """``GET /runs/{id}/process``: ``state`` is queued, running, done or failed."""

    run: str
    options: Dict[str, Any]
    state: str
    steps: List[StepStatus]
    error: Optional[str]
    created_at: str
    updated_at: str
    resumed: int
    after_capture: bool
    streamed: int
    slots_ahead: int
    cancelling: bool


class RunView(TypedDict, total=False):
    """``GET /runs/{id}`` (the fields a sweep uses; the dict holds them all)."""

    id: str
    sample: str
    plan: str
    profile: str
    state: str
    reason: Optional[str]
    last_error: Optional[str]
    active: bool
    resumable: bool
    steps_done: int
    steps_total: int
    physical_s: float
    eta_physical_s: Optional[float]
    eta_wall_s: Optional[float]
    exposure_s: Optional[float]
    frame_size: Optional[List[int]]
    started_at: str
    updated_at: Optional[str]
    finished_at: Optional[str]
    processed: Optional[str]
    processing: Optional[ProcessJob]


class QueueItem(TypedDict):
    """One queued run; ``id`` is the queue item's, not the run's."""

    id: str
    request: Dict[str, Any]
    created_at: str


class Enqueued(TypedDict, total=False):
    """``POST /queue``: ``started_run`` is set when the rig was free."""

    item: QueueItem
    started_run: Optional[RunView]


class CommandAck(TypedDict):
    """Answer to pause, resume and abort."""

    command: str
    sent_to_engine: bool
    run: RunView


@dataclass
class RunPage:
    """One page of ``GET /runs``.

    ``next`` is the cursor of the following page (None on the last page, and
    from a daemon that does not page); ``total`` is None when the daemon does
    not say.
    """

    runs: List[RunView]
    active: Optional[str] = None
    next: Optional[str] = None
    total: Optional[int] = None
    raw: Dict[str, Any] = field(default_factory=dict, repr=False)


@dataclass
class Event:
    """One message of ``GET /events``.

    ``kind`` is rigd's (``engine``, ``run_created``, ``run_ended``,
    ``run_resumed``, ``queue_changed``, ``queue_item_failed``, ``process``,
    ``tradeoff``, ``estop``), or the SSE event name for a message that is not
    a daemon event (``lagged``). ``event`` is the payload.
    """

    id: Optional[int]
    kind: str
    run: Optional[str]
    event: Dict[str, Any]
    sse_event: str = "message"

    @classmethod
    def from_sse(cls, sse_id: Optional[str], sse_event: str, data: str) -> "Event":
        """Builds an event from one SSE message (its ``id:``, ``event:`` and ``data:``)."""
        try:
            body = json.loads(data) if data else {}
        except ValueError:
            # A message that is not JSON is still delivered, not dropped.
            body = {"data": data}
        if not isinstance(body, dict):
            body = {"data": body}
        ident: Optional[int] = body.get("id") if isinstance(body.get("id"), int) else None
        if ident is None and sse_id is not None and sse_id.isdigit():
            ident = int(sse_id)
        if sse_event != "message" or "kind" not in body:
            return cls(ident, sse_event if sse_event != "message" else "unknown", None, body, sse_event)
        payload = body.get("event")
        return cls(
            ident,
            str(body["kind"]),
            body.get("run"),
            payload if isinstance(payload, dict) else {"value": payload},
            sse_event,
        )


@dataclass
class Render:
    """``GET /sim/render``: the PNG and what the frame cost."""

    png: bytes
    effects: List[str]
    render_ms: Optional[float]
