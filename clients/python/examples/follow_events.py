#!/usr/bin/env python3
"""Follows the daemon's event stream, one line per event, and stops at a fault.

    python follow_events.py --url http://127.0.0.1:8080
    python follow_events.py --run 20261122T081559Z-felt-3-h1 --timeout 3600

A fault is a run paused by an error (a device fault, a full disk, an
emergency stop), a failed run, or a queued run that could not start. The
stream is reconnected after a dropped connection (with Last-Event-ID).

Exit status: 0 when the followed run (--run) completed, or --timeout /
--max-events was reached; 3 at a fault; 4 when the followed run was aborted;
1 when the daemon cannot be reached.
"""

from __future__ import annotations

import argparse
import signal
import sys
from typing import Optional

import httpx
from _common import add_connection_args, connect

from rigd_client import Event, RigdError

# Pause reasons that are the operator's or the daemon's own, not faults.
CALM_PAUSES = ("paused by operator", "detached")


class _Timeout(Exception):
    """--timeout ran out."""


def describe(ev: Event) -> str:
    """One line for an event."""
    e = ev.event
    run = f" {ev.run}" if ev.run else ""
    if ev.kind == "engine":
        t = e.get("type")
        if t == "step":
            return f"#{ev.id}{run} step: {e.get('frames_done')}/{e.get('frames_total')} at {e.get('t_s', 0):.1f} s"
        if t == "state":
            why = f" ({e['reason']})" if e.get("reason") else ""
            return f"#{ev.id}{run} state: {e.get('from')} -> {e.get('to')}{why}"
        if t == "retry":
            return f"#{ev.id}{run} retry: {e.get('device')} attempt {e.get('attempt')}: {e.get('reason')}"
        return f"#{ev.id}{run} {t}: {e}"
    if ev.kind in ("run_created", "run_resumed", "run_ended"):
        return f"#{ev.id}{run} {ev.kind}: {e.get('state')} {e.get('steps_done')}/{e.get('steps_total')}"
    if ev.kind == "process":
        return f"#{ev.id}{run} process: {e.get('state')} {e.get('step') or ''} {e.get('done')}/{e.get('total')}"
    return f"#{ev.id}{run} {ev.kind}: {e}"


def fault(ev: Event) -> Optional[str]:
    """The fault an event reports, if it reports one."""
    e = ev.event
    if ev.kind == "engine" and e.get("type") == "state":
        if e.get("to") == "failed":
            return f"run {ev.run} failed: {e.get('reason')}"
        if e.get("to") == "paused" and e.get("reason") not in CALM_PAUSES:
            return f"run {ev.run} paused: {e.get('reason')}"
    if ev.kind == "queue_item_failed":
        return f"a queued run could not start: {e}"
    if ev.kind == "estop":
        return f"emergency stop: {e}"
    return None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_connection_args(p)
    p.add_argument("--run", help="follow this run only, and stop when it ends")
    p.add_argument("--last-event-id", type=int, default=None, help="replay the kept events after this id first")
    p.add_argument("--timeout", type=float, default=None, help="stop (exit 0) after this many seconds")
    p.add_argument("--max-events", type=int, default=None, help="stop (exit 0) after this many events")
    args = p.parse_args()

    rigd = connect(args)
    stream = rigd.events(last_event_id=args.last_event_id)
    if args.timeout is not None:
        # The stream blocks between events; an alarm interrupts the wait (POSIX).
        def on_alarm(signum: int, frame: object) -> None:
            raise _Timeout()

        signal.signal(signal.SIGALRM, on_alarm)
        signal.setitimer(signal.ITIMER_REAL, args.timeout)
    print(f"following {rigd.api}/events", flush=True)
    count = 0
    try:
        for ev in stream:
            if args.run and ev.run not in (None, args.run):
                continue
            print(describe(ev), flush=True)
            why = fault(ev)
            if why and (not args.run or ev.run in (None, args.run)):
                print(f"FAULT: {why}", file=sys.stderr, flush=True)
                return 3
            if args.run and ev.run == args.run and ev.kind == "run_ended":
                state = ev.event.get("state")
                return {"completed": 0, "aborted": 4}.get(str(state), 3)
            count += 1
            if args.max_events is not None and count >= args.max_events:
                return 0
    except _Timeout:
        print("timeout: no fault seen", flush=True)
        return 0
    except httpx.HTTPError as e:
        print(f"follow_events: {e}", file=sys.stderr)
        return 1
    finally:
        stream.close()
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except RigdError as e:
        print(f"follow_events: {e}", file=sys.stderr)
        sys.exit(1)
