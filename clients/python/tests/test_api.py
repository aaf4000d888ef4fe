"""Every call of the client against a live daemon (tests run in file order)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from conftest import FIRST_RUN_TIMEOUT, Daemon, long_plan, settle, tiny_plan

from rigd_client import Client, RigdError, is_fault_pause

PNG = b"\x89PNG\r\n\x1a\n"

#: operationId in openapi.json → the client method that calls it.
OPERATIONS = {
    "estop": "estop", "events_sse": "events", "health": "health", "list_peers": "peers",
    "abort_peer": "abort_peer", "pause_peer": "pause_peer", "plans": "plans", "plan_detail": "plan",
    "get_queue": "queue", "post_queue": "enqueue", "delete_queue": "dequeue", "rig": "rig",
    "check": "rig_check", "last_frame": "manual_frame_png", "take_frame": "manual_frame",
    "home": "manual_home", "jog": "manual_jog", "lamp": "manual_lamp", "pose": "manual_pose",
    "holder_check": "manual_holder_check",
    "release": "manual_release", "list_runs": "runs", "create_run": "start_run", "get_run": "run",
    "abort_run": "abort", "btf_manifest": "btf", "btf_data": "btf_data", "btf_mesh": "btf_mesh",
    "frame_raw": "frame", "frame_preview": "frame_preview", "run_manifest": "manifest",
    "mdf_manifest": "mdf", "mdf_data": "mdf_data", "pause_run": "pause", "get_job": "process_job",
    "submit": "process", "cancel": "cancel_process", "resume_run": "resume", "run_steps": "steps",
    "sim_render": "sim_render", "sim_scenes": "sim_scenes", "get_report": "tradeoff",
    "start": "start_tradeoff", "get_choice": "tradeoff_choice", "get_figure": "tradeoff_figure",
    "get_plot": "tradeoff_plot",
}


def test_health_and_every_route_has_a_call(client: Client) -> None:
    h = client.health()
    assert h["ok"] is True and h["sim"] is True and h["profile"] == "bonn-gonioreflectometer"
    spec = client.openapi()
    ops = {(m.upper(), p): o["operationId"] for p, v in spec["paths"].items() for m, o in v.items()
           if m in ("get", "post", "delete", "put", "patch")}
    missing = {k: op for k, op in ops.items() if op not in OPERATIONS}
    assert not missing, f"routes without a client call: {missing}"
    for op, method in OPERATIONS.items():
        assert callable(getattr(client, method)), method


def test_errors_carry_status_code_and_detail(daemon: Daemon, client: Client) -> None:
    with pytest.raises(RigdError) as e:
        client.run("no-such-run")
    assert e.value.status == 404 and e.value.error == "not_found" and "no-such-run" in e.value.detail
    assert "GET /api/v1/runs/no-such-run: 404 not_found" in str(e.value)
    with Client(daemon.url, token="wrong-token-0123456789") as bad:
        with pytest.raises(RigdError) as e:
            bad.estop()
    assert e.value.status == 401 and e.value.error == "unauthorized"
    with pytest.raises(RigdError) as e:
        client.start_run("x", "no-such-plan")
    assert e.value.status == 422 and e.value.error == "invalid"
    with pytest.raises(RigdError) as e:
        client.frame("no-such-run", 0)
    assert e.value.status == 404


def test_token_from_env_and_data_dir(daemon: Daemon, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RIGD_TOKEN", raising=False)
    monkeypatch.delenv("RIGD_DATA", raising=False)
    assert Client(daemon.url).token is None
    with pytest.raises(RigdError) as e:
        Client(daemon.url).manual_release()
    assert e.value.status == 401 and "RIGD_TOKEN" in str(e.value)
    monkeypatch.setenv("RIGD_DATA", str(daemon.data))
    assert Client(daemon.url).token == daemon.token
    monkeypatch.setenv("RIGD_TOKEN", "from-env")
    assert Client(daemon.url, data_dir=daemon.data).token == "from-env"
    assert Client(daemon.url, token="arg").token == "arg"


def test_manual_control(client: Client) -> None:
    # Before any run: manual control answers 409 while a run is active.
    assert client.manual_home("rail")["device"] == "rail"
    arm = client.manual_home("arm")
    assert len(arm["position_deg"]) == 3
    at = client.manual_jog("rail", to_deg=90)["position_deg"][0]
    assert client.manual_jog("rail", by_deg=5)["position_deg"][0] == pytest.approx(at + 5)
    with pytest.raises(RigdError) as e:
        client.manual_jog("rail", to_deg=1000)
    assert e.value.status == 422 and "soft limits" in e.value.detail
    with pytest.raises(ValueError):
        client.manual_jog("rail")
    # The holder check needs the view: 409 until the rig takes a pose.
    with pytest.raises(RigdError) as e:
        client.manual_holder_check()
    assert e.value.status == 409 and "pose" in e.value.detail
    pose = client.manual_pose((30, 0), {"theta_deg": 0, "phi_deg": 0})
    assert pose["feasible"] is True and pose["lamp"] == "hmi"
    assert client.manual_lamp("hmi", True) == {"device": "hmi", "on": True}
    check = client.manual_holder_check(camera="camera")
    assert check["ok"] is True and check["registered"] is True and check["problems"] == []
    assert check["markers_found"] == len(check["markers"]) == 8 and check["holder"] == "standard"
    frame = client.manual_frame(exposure_s=0.05)
    assert frame["camera"] == "camera" and frame["width"] > 0 and 0 <= frame["saturated"] <= 1
    assert client.manual_frame_png().startswith(PNG)
    assert client.manual_lamp("hmi", False)["on"] is False
    with pytest.raises(RigdError) as e:
        client.manual_home("no-such-device")
    assert e.value.status == 422
    assert client.manual_release() is None


def test_rig_and_check(client: Client) -> None:
    rig = client.rig()
    assert rig["state"] == "idle" and {d["name"] for d in rig["devices"]} >= {"rail", "arm", "camera", "hmi"}
    check = client.rig_check(timeout=60)
    assert check["usable"] is True and len(check["devices"]) == len(rig["devices"])


def test_sim(client: Client) -> None:
    scenes = client.sim_scenes()
    names = [s["name"] for s in scenes]
    assert "corduroy" in names
    r = client.sim_render("corduroy", light=(30, 0), view=(0, 0), size=(32, 24), seed=1, effects="none")
    assert r.png.startswith(PNG) and r.render_ms is not None
    with pytest.raises(RigdError) as e:
        client.sim_render("no-such-scene")
    assert e.value.status == 404 and "corduroy" in e.value.detail


def test_tradeoff_reads(client: Client) -> None:
    report = client.tradeoff()
    assert any(row["family"] == "plans" for row in report["rows"])
    assert client.tradeoff_plot().lstrip().startswith("<svg")
    fig = client.tradeoff_figure()
    assert fig["panels"] and fig["points"] and fig["svg"].lstrip().startswith("<svg")
    choice = client.tradeoff_choice(budget="3h")
    assert choice["goal"] == {"budget_s": 10800.0} and choice["plan"]["physical_s"] <= 10800
    assert client.tradeoff_choice(target="15%")["plan"]["error"] <= 0.15
    with pytest.raises(RigdError) as e:
        client.tradeoff_choice()
    assert e.value.status == 422


def test_run_frames_steps_manifest_download(client: Client, tmp_path: Path) -> None:
    settle(client)
    # The first run of a fresh daemon is slow to start (README): a long timeout.
    run = Client(client.url, token=client.token, timeout=FIRST_RUN_TIMEOUT).start_run(
        "api-run", tiny_plan(), frame_size=(64, 48), operator="pytest", notes="tiny")
    assert run["state"] in ("preparing", "running", "completed") and run["steps_total"] == 4
    view = client.wait(run, timeout=60)
    assert view["state"] == "completed" and view["steps_done"] == 4 and view["operator"] == "pytest"
    steps = client.steps(run)
    assert steps["steps_done"] == 4 and all(s["done"] for s in steps["steps"])
    assert client.manifest(run)["state"] == "completed"
    # The simulated Bonn camera stores its own file (a TIFF-based DNG), byte for byte.
    raw = client.frame(run, 0)
    assert raw.startswith((PNG, b"II*\x00", b"MM\x00*"))
    assert client.frame_preview(run, 3).startswith(PNG)
    with pytest.raises(RigdError) as e:
        client.frame(run, 4)
    assert e.value.status == 404
    frames = client.download(run, "frames", tmp_path)
    assert [p.stem for p in frames] == [f"{i:06d}" for i in range(4)]
    assert frames[0].suffix in (".png", ".dng", ".tiff", ".jpg", ".bin")
    assert frames[0].read_bytes() == client.frame(run, 0)
    assert len(client.download(run, "previews", tmp_path, indices=[1])) == 1
    (m,) = client.download(run, "manifest", tmp_path)
    assert json.loads(m.read_text())["sample"] == "api-run"
    (s,) = client.download(run, "steps", tmp_path)
    assert json.loads(s.read_text())["steps_total"] == 4
    with pytest.raises(ValueError):
        client.download(run, "nothing", tmp_path)
    assert not list(tmp_path.rglob("*.part"))


def test_process_btf_viewer_data(client: Client, tmp_path: Path) -> None:
    settle(client)
    run = client.start_run("api-proc", tiny_plan())  # the profile's 320x240: rectify needs >= 288x216
    assert client.wait(run, timeout=60)["state"] == "completed"
    with pytest.raises(RigdError) as e:
        client.process_job(run)
    assert e.value.status == 404
    job = client.process(run, "rectify", "btf", btf={"components": 4})
    assert job["state"] in ("queued", "running", "done") and job["options"]["btf"]["components"] == 4
    done = client.wait_process(run, timeout=120)
    assert done["state"] == "done", done
    assert [s["step"] for s in done["steps"]] == ["rectify", "btf"]
    again = client.process(run, "rectify", "btf", btf={"components": 4}, wait=True)
    assert again["created_at"] == done["created_at"]  # the same job, not done twice
    assert client.run(run)["processed"] == "btf"
    with pytest.raises(RigdError) as e:
        client.cancel_process(run)
    assert e.value.status == 409
    manifest = client.btf(run)
    assert manifest["kind"] == "btf" and manifest["data_url"].startswith("/api/v1/runs/")
    assert len(client.btf_data(run)) == manifest["bytes"]
    one = client.btf(run, components=1)
    assert one["components"] == 1 and len(client.btf_data(run, components=1)) == one["bytes"]
    mesh = client.btf_mesh(run, "flat")
    assert mesh["kind"] == "flat" and mesh["positions"]
    assert client.btf_mesh(run, "sphere", density=2.0)["kind"] == "sphere"
    with pytest.raises(RigdError) as e:
        client.btf_mesh(run, "no-such-mesh")
    assert e.value.status == 404
    files = client.download(run, "btf", tmp_path, components=1)
    assert [p.name for p in files] == ["btf.json", "btf.bin"] and files[1].stat().st_size == one["bytes"]
    # No MDF without a laser scan: the calls answer rigd's 404 naming the commands.
    for call in (client.mdf, client.mdf_data):
        with pytest.raises(RigdError) as e:
            call(run)
        assert e.value.status == 404 and "mdf" in e.value.detail
    with pytest.raises(RigdError):
        client.download(run, "mdf", tmp_path)


def test_process_cancel(client: Client) -> None:
    settle(client)
    run = client.start_run("api-cancel", tiny_plan())
    assert client.wait(run, timeout=60)["state"] == "completed"
    client.process(run, "rectify")
    try:
        job = client.cancel_process(run)
    except RigdError as e:
        # The tiny job may have finished before the cancel arrived.
        assert e.status == 409
    else:
        assert job["cancelling"] or job["state"] == "failed"
    assert client.wait_process(run, timeout=60)["state"] in ("done", "failed")


def test_pause_resume_estop_abort(client: Client) -> None:
    settle(client)
    run = client.start_run("api-pause", long_plan(), frame_size=(64, 48))
    ack = client.pause(run)
    assert ack["command"] == "pause" and ack["sent_to_engine"] is True
    view = client.wait(run, timeout=30, stop_on_pause=True)
    assert view["state"] == "paused" and view["reason"] == "paused by operator" and not is_fault_pause(view)
    with pytest.raises(RigdError) as e:
        client.pause(run)
    assert e.value.status == 409
    assert client.resume(run)["command"] == "resume"
    stop = client.estop()
    assert stop["all_stopped"] is True
    view = client.wait(run, timeout=30)  # an emergency stop is a pause with an error
    assert view["state"] == "paused" and is_fault_pause(view) and "emergency stop" in view["reason"]
    assert client.abort(run)["command"] == "abort"
    assert client.wait(run, timeout=30, until={"aborted"})["state"] == "aborted"
    assert client.manifest(run)["state"] == "aborted"
    with pytest.raises(RigdError) as e:
        client.abort(run)
    assert e.value.status == 409


def test_queue(client: Client) -> None:
    settle(client)
    first = client.enqueue("api-q1", long_plan(), frame_size=(64, 48))
    assert first["started_run"] is not None  # the rig was free
    active = first["started_run"]["id"]
    second = client.enqueue("api-q2", tiny_plan(), frame_size=(64, 48))
    assert second["started_run"] is None
    item = second["item"]
    assert item["request"]["sample"] == "api-q2"
    assert [i["id"] for i in client.queue()] == [item["id"]]
    client.dequeue(item)
    assert client.queue() == []
    with pytest.raises(RigdError) as e:
        client.dequeue(item["id"])
    assert e.value.status == 404
    third = client.enqueue("api-q3", tiny_plan(), frame_size=(64, 48))
    client.abort(active)
    # The queue goes on by itself once the rig is free.
    deadline = time.monotonic() + 30
    while not [r for r in client.runs().runs if r["sample"] == "api-q3"]:
        assert time.monotonic() < deadline, "the queued run did not start"
        time.sleep(0.1)
    (q3,) = [r for r in client.runs().runs if r["sample"] == "api-q3"]
    assert client.wait(q3, timeout=30)["state"] == "completed"
    assert third["item"]["id"] not in [i["id"] for i in client.queue()]


def test_plans(client: Client) -> None:
    plans = client.plans()
    assert [p["name"] for p in plans["plans"]] == ["h1", "h2", "grid12x8", "lamps", "laser"]
    # The daemon solves its plans in the background after it starts; this waits for h1.
    h1 = client.plan("h1", timeout=180)
    assert h1["name"] == "h1" and len(h1["steps"]) == h1["steps_total"] == 6561
    with pytest.raises(RigdError) as e:
        client.plan("no-such-plan")
    assert e.value.status == 404
    with pytest.raises(RigdError) as e:
        client.plan("grid12x8", timeout=180)
    assert e.value.status == 422 and "does not fit" in e.value.detail


def test_runs_page_without_paging(client: Client) -> None:
    page = client.runs()
    assert page.runs and page.active is None
    ids = [r["id"] for r in page.runs]
    assert len(set(ids)) == len(ids)
    assert [r["id"] for r in client.iter_runs()] == ids  # one page or several: the same runs
