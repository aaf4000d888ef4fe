"""A daemon with an injected fault: wait() stops at the fault pause, the
follow_events example exits non-zero, and the main daemon pauses and aborts
the run through its peers."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest
from conftest import FIRST_RUN_TIMEOUT, ROOT, Daemon, settle

from rigd_client import Client, RigdError, is_fault_pause


def test_follow_events_exits_on_fault_and_wait_stops(fault_daemon: Daemon, fault_client: Client) -> None:
    settle(fault_client)
    follower = subprocess.Popen(
        [sys.executable, str(ROOT / "examples" / "follow_events.py"), "--url", fault_daemon.url,
         "--data", str(fault_daemon.data), "--timeout", str(FIRST_RUN_TIMEOUT + 30),
         # From the first kept event: a follower that connects after the run
         # has started (a busy machine) still sees its fault. This daemon has
         # run nothing before, so no earlier fault is replayed.
         "--last-event-id", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        slow = Client(fault_daemon.url, data_dir=fault_daemon.data, timeout=FIRST_RUN_TIMEOUT)
        run = slow.start_run("faulty", "lamps")  # 3 images: the 2nd transfer faults
        view = fault_client.wait(run, timeout=30)
        assert view["state"] == "paused" and is_fault_pause(view)
        assert "camera" in view["last_error"] and "disconnect" in view["last_error"]
        faults = {d["name"]: d["fault"] for d in fault_client.rig()["devices"]}
        assert faults["camera"] == view["reason"]
        out, err = follower.communicate(timeout=30)
    finally:
        if follower.poll() is None:
            follower.kill()
            follower.communicate()
    assert follower.returncode == 3, (out, err)
    assert "FAULT: run " in err and "camera" in err
    assert f"{run['id']} state: running -> paused" in out


def test_peers_pause_and_abort(client: Client, fault_client: Client) -> None:
    active = fault_client.runs().active
    assert active is not None, "test_follow_events… leaves a paused run on the fault daemon"
    deadline = time.monotonic() + 20  # generous: a busy machine slows the daemons' polls
    while True:  # the daemon polls its peers once a second
        peers = client.peers()
        faulty = [p for p in peers if p["name"] == "faulty"]
        # Its run and its faults come from the same poll, but a poll from
        # before the fault may be the one shown: wait for both.
        if faulty and faulty[0]["reachable"] and faulty[0]["active_run"] and faulty[0]["faults"]:
            break
        assert time.monotonic() < deadline, peers
        time.sleep(0.2)
    assert peers[0]["local"] is True and peers[0]["name"] == "this rig"
    assert faulty[0]["active_run"]["id"] == active and faulty[0]["faults"]
    with pytest.raises(RigdError) as e:
        client.pause_peer("faulty")  # already paused by its fault
    assert e.value.status == 409
    with pytest.raises(RigdError) as e:
        client.pause_peer("no-such-peer")
    assert e.value.status == 404
    ack = client.abort_peer("faulty")
    assert ack["command"] == "abort" and ack["run"]["id"] == active
    assert fault_client.wait(active, timeout=30, until={"aborted", "completed", "failed"})["state"] == "aborted"
    with pytest.raises(RigdError) as e:
        client.abort_peer("faulty")  # no active run now
    assert e.value.status == 409
