"""The API contract, checked by an independent tool: Schemathesis fuzzes
every operation of a live daemon's OpenAPI description (examples, coverage,
fuzzing and stateful phases, following the description's links) and checks
that no answer is a server error, that every status and body is the one the
description gives, and that every operation answered with a 2xx at least
once.

A daemon needs data for some routes to answer 2xx: a processed run (frames,
BTF, MDF texture), a trade-off report, a peer with an active run. This
script makes them first, with rigd's own commands, then starts the daemon
under test on them:

  rigd serve (A): the daemon under test, simulated Bonn rig;
  rigd serve (B): its peer, slow, with long runs queued, so that
                  A's /peers/B/pause and /abort find a run.

A broad pass covers every operation; then targeted passes take the rig
through the states the commands act on (idle, axes homed, posed for the
holder check, a long run to pause, resume and abort, a queue item, a job,
the peer's run), one pass per state, each with the ids it needs given as
explicit test data.

Usage: api_contract.py --rigd BIN --work DIR [--max-time S] [--repo DIR]
Exit 0 when the contract holds; 1 with what failed otherwise.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

# Two lights and two views: the smallest plan whose run is processed to a BTF.
TINY_PLAN = {
    "lights": [{"theta_deg": 30, "phi_deg": 0}, {"theta_deg": 45, "phi_deg": 90}],
    "views": [{"theta_deg": 20, "phi_deg": 0}, {"theta_deg": 40, "phi_deg": 180}],
}
# The peer's runs: 100 images, about a minute each at the peer's speed
# (after a lamp warm-up of seconds).
BUSY_PLAN = {"name": "busy", "directions": [{"theta_deg": 5 + 8 * i, "phi_deg": 50 * i} for i in range(10)]}
PEER_SPEED = 20.0
BTF_RUN = "seed-btf"
LASER_RUN = "seed-laser"
PEER = "rig-b"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(cmd: list[str], timeout: float) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout}{done.stderr}")


def request(url: str, token: str | None = None, body: object = None, method: str = "GET") -> tuple[int, object]:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method)
    if data is not None:
        req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(req, timeout=30) as resp:
            return resp.status, json.loads(resp.read() or b"null")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"null")


def start_daemon(rigd: str, data: Path, port: int, speed: float, extra: list[str], log: Path) -> subprocess.Popen:
    data.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(
        [rigd, "serve", "--sim", "--listen", f"127.0.0.1:{port}", "--data", str(data),
         "--sim-speed", str(speed), *extra],
        stdin=subprocess.DEVNULL, stdout=log.open("w"), stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"rigd serve exited with {proc.returncode}:\n{log.read_text()}")
        try:
            if request(f"http://127.0.0.1:{port}/api/v1/health")[0] == 200:
                return proc
        except OSError:
            pass
        time.sleep(0.1)
    proc.kill()
    raise SystemExit(f"rigd serve on port {port} never answered /health:\n{log.read_text()}")


def seed_runs(rigd: str, runs: Path, work: Path) -> None:
    """A processed BTF run and a laser run with its MDF texture, made by
    the CLI into the daemon's runs folder before it starts."""
    plan = work / "tiny.json"
    plan.write_text(json.dumps(TINY_PLAN))
    common = [rigd, "run", "--sim", "--progress", "none", "--profile", "msra-btf-mdf"]
    run([*common, "--plan", str(plan), "--frame-size", "320x240", "--sample", "felt",
         "--process", "auto", "--out", str(runs / BTF_RUN)], 300)
    run([*common, "--plan", "laser:sources=1,turns=1,step=5", "--frame-size", "160x120",
         "--sample", "felt", "--out", str(runs / LASER_RUN)], 300)
    run([rigd, "process", "mdf", str(runs / LASER_RUN)], 300)
    run([rigd, "process", "mdf-texture", str(runs / BTF_RUN), "--laser", str(runs / LASER_RUN),
         "--size", "32"], 300)


def schemathesis_config(path: Path, per_operation: dict[str, dict[str, str]], max_time: int | None) -> None:
    """Explicit test data where a route needs what exists (a run's id, a
    frame's index, the peer's name): those operations always get it."""
    lines = ["request-timeout = 60", "max-stream-events = 3", ""]
    if max_time:
        lines.insert(0, f"max-time = {max_time}")
    for op, params in per_operation.items():
        lines.append("[[operations]]")
        lines.append(f'include-operation-id = "{op}"')
        lines.append("parameters = { " + ", ".join(f'"{k}" = "{v}"' for k, v in params.items()) + " }")
        lines.append("")
    path.write_text("\n".join(lines))


class Schemathesis:
    """Runs of Schemathesis against one daemon, their outcomes collected."""

    def __init__(self, work: Path, url: str, token: str) -> None:
        self.work, self.url, self.token = work, url, token
        self.passes: list[tuple[str, int, Path, str]] = []

    def run(self, name: str, per_operation: dict[str, dict[str, str]], *, only: list[str] | None = None,
            max_time: int | None = None, max_examples: int | None = None, phases: str) -> None:
        config = self.work / f"{name}.toml"
        schemathesis_config(config, per_operation, max_time)
        events = self.work / f"{name}.ndjson"
        cmd = [str(Path(sys.executable).with_name("schemathesis")), "--config-file", str(config), "run",
               f"{self.url}/api/v1/openapi.json", "-H", f"Authorization: Bearer {self.token}",
               "--checks", "not_a_server_error,status_code_conformance,response_schema_conformance,"
                           "content_type_conformance",
               "--phases", phases, "--report", "ndjson", "--report-ndjson-path", str(events),
               # One worker: Hypothesis describes its strategies by parsing
               # source with `ast`, which CPython 3.11 does not do safely from
               # two threads at once ("AST constructor recursion depth
               # mismatch", CPython gh-106905), and the rig's own commands
               # must not race each other within a pass.
               "--seed", "1", "--no-color", "--workers", "1"]
        for op in only or []:
            cmd += ["--include-operation-id", op]
        if max_examples:
            cmd += ["--max-examples", str(max_examples)]
        print(f"== schemathesis: {name}", flush=True)
        # In the work folder: Schemathesis keeps a cache where it runs.
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=(max_time or 120) + 300,
                              cwd=self.work)
        cases = re.search(r"(\d+) generated", done.stdout)
        self.passes.append((name, done.returncode, events, cases.group(1) if cases else "?"))
        if done.returncode != 0:
            print(done.stdout[-30000:])
            print(done.stderr[-5000:], file=sys.stderr)
        else:
            print(done.stdout.strip().splitlines()[-1] if done.stdout.strip() else "", flush=True)


def make_idle(base: str, token: str) -> None:
    """Empties the queue and aborts the active run, until the rig is idle."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        for queued in request(f"{base}/queue", token)[1]["items"]:
            request(f"{base}/queue/{queued['id']}", token, method="DELETE")
        active = request(f"{base}/runs", token)[1].get("active")
        if active is None:
            return
        request(f"{base}/runs/{active}/abort", token, method="POST")
        time.sleep(0.2)
    raise SystemExit("the rig never became idle")


def wait_running(base: str, token: str) -> None:
    """Until the daemon's active run is running: a paused one is resumed,
    and a run is queued when there is none."""
    deadline = time.monotonic() + 120
    last = None
    while time.monotonic() < deadline:
        active = request(f"{base}/runs", token)[1].get("active")
        last = active and request(f"{base}/runs/{active}", token)[1]
        if active is None:
            if not request(f"{base}/queue", token)[1]["items"]:
                request(f"{base}/queue", token, {"sample": "busy", "plan": BUSY_PLAN}, "POST")
        else:
            state = request(f"{base}/runs/{active}", token)[1].get("state")
            if state == "running":
                return
            if state == "paused":
                request(f"{base}/runs/{active}/resume", token, method="POST")
        time.sleep(0.2)
    raise SystemExit(f"no run became active and running on {base}: the active run is {last}")


def operation_matchers(spec: dict) -> list[tuple[str, re.Pattern, str]]:
    out = []
    for path, item in spec["paths"].items():
        pattern = re.compile("^" + re.sub(r"\\\{[^}]+\\\}", "[^/]+", re.escape(path)) + "$")
        for method in item:
            if method in ("get", "put", "post", "delete", "patch"):
                out.append((method.upper(), pattern, f"{method.upper()} {path}"))
    # The most specific (longest literal) path first.
    out.sort(key=lambda m: -len(m[1].pattern))
    return out


def statuses_by_operation(ndjson: Path, spec: dict) -> dict[str, set[int]]:
    """Every status each operation answered, from Schemathesis's event log."""
    matchers = operation_matchers(spec)
    seen: dict[str, set[int]] = {label: set() for _, _, label in matchers}
    with ndjson.open() as f:
        for line in f:
            if '"interactions"' not in line:
                continue
            event = json.loads(line).get("ScenarioFinished", {})
            for interaction in event.get("recorder", {}).get("interactions", {}).values():
                response = interaction.get("response")
                if not response:
                    continue
                method = interaction["request"]["method"]
                path = urllib.parse.urlsplit(interaction["request"]["uri"]).path
                for m, pattern, label in matchers:
                    if m == method and pattern.match(path):
                        seen[label].add(response["status_code"])
                        break
    return seen


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rigd", required=True)
    ap.add_argument("--work", required=True, type=Path)
    ap.add_argument("--max-time", type=int, default=150, help="Schemathesis's time budget, seconds")
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[2])
    args = ap.parse_args()
    work: Path = args.work
    work.mkdir(parents=True, exist_ok=True)
    daemons: list[subprocess.Popen] = []
    try:
        # B: the peer, busy with long runs one after another.
        port_b = free_port()
        data_b = work / "rig-b"
        daemons.append(start_daemon(args.rigd, data_b, port_b, PEER_SPEED, [], work / "rig-b.log"))
        token_b = (data_b / "token").read_text().strip()
        for i in range(40):
            status, body = request(f"http://127.0.0.1:{port_b}/api/v1/queue", token_b,
                                   {"sample": f"busy-{i}", "plan": BUSY_PLAN}, "POST")
            if status != 201:
                raise SystemExit(f"queueing on the peer: {status} {body}")

        # A: the daemon under test, on seeded data.
        data_a = work / "rig-a"
        seed_runs(args.rigd, data_a / "runs", work)
        (data_a / "tradeoff").mkdir(parents=True, exist_ok=True)
        shutil.copy(args.repo / "docs/tradeoff/msra-btf-mdf-corduroy/tradeoff.json",
                    data_a / "tradeoff/tradeoff.json")
        peers = work / "peers.toml"
        peers.write_text(f'[[peer]]\nname = "{PEER}"\nurl = "http://127.0.0.1:{port_b}"\n'
                         f'token_file = "{data_b / "token"}"\n')
        port_a = free_port()
        daemons.append(start_daemon(args.rigd, data_a, port_a, 200.0, ["--peers", str(peers)],
                                    work / "rig-a.log"))
        token_a = (data_a / "token").read_text().strip()
        st = Schemathesis(work, f"http://127.0.0.1:{port_a}", token_a)
        seeded = {
            "frame_raw": {"path.id": BTF_RUN, "path.index": "0"},
            "frame_preview": {"path.id": BTF_RUN, "path.index": "0"},
            "btf_manifest": {"path.id": BTF_RUN},
            "btf_data": {"path.id": BTF_RUN},
            "btf_mesh": {"path.id": BTF_RUN, "path.kind": "flat"},
            "mdf_manifest": {"path.id": BTF_RUN},
            "mdf_data": {"path.id": BTF_RUN},
            "run_manifest": {"path.id": BTF_RUN},
            "pause_peer": {"path.name": PEER},
            "abort_peer": {"path.name": PEER},
        }
        # Every operation, every phase, the stateful one following links.
        st.run("all", seeded, max_time=args.max_time, phases="examples,coverage,fuzzing,stateful")

        # What the rig's own routes need, operation by operation, each pass
        # from a known state.
        base = f"http://127.0.0.1:{port_a}/api/v1"
        make_idle(base, token_a)
        # The rig idle: the manual-control routes and the rig check (one
        # frame taken first, so that the last frame is there to fetch).
        status, body = request(f"{base}/rig/manual/frame", token_a, {}, "POST")
        if status != 200:
            raise SystemExit(f"a manual frame: {status} {body}")
        # (And a seeded run's own routes, which the broad pass reaches only
        # through links.)
        st.run("idle-rig", {**seeded, "get_run": {"path.id": BTF_RUN}, "run_steps": {"path.id": BTF_RUN}},
               only=["take_frame", "last_frame", "btf_mesh", "get_run", "run_steps"],
               max_examples=5, phases="examples,fuzzing")
        # A rig check and a release end the manual session: after the frames.
        st.run("rig-check", {}, only=["check", "release"], max_examples=5, phases="examples,fuzzing")
        # Moves need the axes homed, in one manual session (which a rig
        # check or a release ends).
        for device in ("rail", "arm"):
            status, body = request(f"{base}/rig/manual/home", token_a, {"device": device}, "POST")
            if status != 200:
                raise SystemExit(f"homing {device}: {status} {body}")
        st.run("manual", {}, only=["home", "jog", "lamp", "pose"], max_examples=5, phases="examples,fuzzing")
        # The holder check needs the view of a pose taken in this session.
        # A pass of its own: the rig-check pass's check and release end the
        # session, and the manual pass's jogs and homings leave the pose.
        for device in ("rail", "arm"):
            status, body = request(f"{base}/rig/manual/home", token_a, {"device": device}, "POST")
            if status != 200:
                raise SystemExit(f"homing {device}: {status} {body}")
        frontal = {"light": {"theta_deg": 30, "phi_deg": 0}, "view": {"theta_deg": 0, "phi_deg": 0}}
        status, body = request(f"{base}/rig/manual/pose", token_a, frontal, "POST")
        if status != 200:
            raise SystemExit(f"a pose for the holder check: {status} {body}")
        st.run("holder-check", {}, only=["holder_check"], max_examples=5, phases="examples,fuzzing")
        make_idle(base, token_a)
        # A finished run's processing: asked for, then looked at.
        for op in ("submit", "get_job"):
            st.run(op, {op: {"path.id": BTF_RUN}}, only=[op], max_examples=5, phases="examples,fuzzing")

        # A run's commands need a run in the state each acts on: a long run
        # (minutes at the daemon's speed) with a process job waiting for
        # it, a queue item behind it; then pause, the queue item's and the
        # job's cancel, resume and abort, in that order.
        long_run = {"sample": "long", "order": "naive", "process": {},
                    "plan": {"name": "long", "directions": [
                        {"theta_deg": 5 + i, "phi_deg": 6 * i} for i in range(60)]},
                    "frame_size": [320, 240]}
        status, body = request(f"{base}/runs", token_a, long_run, "POST")
        if status != 201:
            raise SystemExit(f"starting the long run: {status} {body}")
        run_id = body["id"]
        status, body = request(f"{base}/queue", token_a, long_run, "POST")
        if status != 201 or body.get("started_run") is not None:
            raise SystemExit(f"queueing behind the long run: {status} {body}")
        item = body["item"]["id"]
        for op, params in [("pause_run", {"path.id": run_id}), ("delete_queue", {"path.item": item}),
                           ("cancel", {"path.id": run_id}), ("resume_run", {"path.id": run_id}),
                           ("abort_run", {"path.id": run_id})]:
            st.run(op, {op: params}, only=[op], max_examples=5, phases="examples,fuzzing")
        make_idle(base, token_a)

        # The peer's commands: its run running (each new one warms its lamp
        # up and homes first), then paused, then aborted through this daemon.
        base_b = f"http://127.0.0.1:{port_b}/api/v1"
        wait_running(base_b, token_b)
        for op in ("pause_peer", "abort_peer"):
            st.run(op, {op: {"path.name": PEER}}, only=[op], max_examples=5, phases="examples,fuzzing")

        # A new run, then (last: it keeps a core busy until the daemon
        # stops) a trade-off computation, each on an idle rig.
        st.run("create_run", {}, only=["create_run"], max_examples=5, phases="examples")
        make_idle(base, token_a)
        st.run("tradeoff", {}, only=["start"], max_examples=5, phases="examples")

        spec = request(f"{base}/openapi.json")[1]
        seen: dict[str, set[int]] = {}
        failed = False
        for name, rc, events, cases in st.passes:
            print(f"schemathesis pass {name}: exit {rc}, {cases} test cases")
            failed |= rc != 0
            for op, statuses in statuses_by_operation(events, spec).items():
                seen.setdefault(op, set()).update(statuses)
        for op, statuses in sorted(seen.items()):
            print(f"  {op}: {sorted(statuses)}")
        without_2xx = sorted(op for op, statuses in seen.items() if not any(200 <= s < 300 for s in statuses))
        if without_2xx:
            print("operations never answered with a 2xx:\n  " + "\n  ".join(without_2xx))
            failed = True
        log_a = (work / "rig-a.log").read_text(errors="replace")
        if "panicked" in log_a:
            print("the daemon under test panicked:\n" + log_a[-5000:])
            failed = True
        return 1 if failed else 0
    finally:
        for d in daemons:
            d.kill()
            d.wait(timeout=30)


if __name__ == "__main__":
    sys.exit(main())
