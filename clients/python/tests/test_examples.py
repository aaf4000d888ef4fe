"""The examples, run as scripts against the test daemon (follow_events.py is
run in test_fault.py, against the daemon with a fault)."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import Daemon, run_example, settle

from rigd_client import Client


def test_sweep(daemon: Daemon, client: Client, tmp_path: Path) -> None:
    settle(client)
    out = tmp_path / "out"
    r = run_example("sweep.py", "--url", daemon.url, "--data", str(daemon.data), "--samples", "sw-a,sw-b",
                    "--directions", "0,0;45,90", "--out", str(out), "--timeout", "120")
    assert r.returncode == 0, (r.stdout, r.stderr)
    summary = json.loads((out / "sweep.json").read_text())
    assert [s["sample"] for s in summary] == ["sw-a", "sw-b"]
    for s in summary:
        assert s["state"] == "completed" and s["processed"] == "done"
        d = out / s["run"]
        assert sorted(p.stem for p in (d / "frames").iterdir()) == [f"{i:06d}" for i in range(4)]
        assert json.loads((d / "manifest.json").read_text())["sample"] == s["sample"]
        assert json.loads((d / "btf.json").read_text())["bytes"] == (d / "btf.bin").stat().st_size


def test_exposure_sweep(daemon: Daemon, client: Client) -> None:
    settle(client)
    r = run_example("exposure_sweep.py", "--url", daemon.url, "--token", daemon.token,
                    "--sample", "exp", "--exposures", "0.05,1", "--frame-size", "64x48", "--timeout", "60")
    assert r.returncode == 0, (r.stdout, r.stderr)
    lines = r.stdout.splitlines()
    table = [l for l in lines if l.strip().startswith(("0.05s", "1s"))]
    assert len(table) == 2, r.stdout
    assert "extra second of exposure costs" in r.stdout
    # The longer exposure takes longer and collects more light.
    runs = [run for run in client.runs().runs if run["sample"] == "exp"]
    assert sorted(run["exposure_s"] for run in runs) == [0.05, 1.0]
    by = {run["exposure_s"]: run["physical_s"] for run in runs}
    assert by[1.0] > by[0.05]


def test_examples_fail_clearly_without_daemon(tmp_path: Path) -> None:
    r = run_example("exposure_sweep.py", "--url", "http://127.0.0.1:9", "--token", "x", timeout=30)
    assert r.returncode == 1 and "exposure_sweep:" in r.stderr and "Traceback" not in r.stderr
