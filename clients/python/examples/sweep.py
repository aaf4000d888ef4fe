#!/usr/bin/env python3
"""A sweep over samples: queue a run per sample, wait for each, process it in
the daemon, and download its frames, manifest and BTF.

    python sweep.py --url http://127.0.0.1:8080 --data rigd-data \\
        --samples felt-1,felt-2 --plan h1 --out sweep-out

Exit status: 0 when every run completed and processed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Dict, List

import httpx
from _common import add_connection_args, connect, parse_directions, parse_size

from rigd_client import Client, RigdError, RigdTimeout, inline_plan


def find_new_runs(rigd: Client, samples: List[str], before: set, timeout: float) -> Dict[str, str]:
    """The run each queued sample became.

    rigd does not link a queue item to the run it becomes, so a run is matched
    by its sample name among the runs that did not exist before the sweep.
    """
    found: Dict[str, str] = {}
    deadline = time.monotonic() + timeout
    while len(found) < len(samples):
        for run in rigd.iter_runs():
            if run["id"] not in before and run["sample"] in samples and run["sample"] not in found:
                found[run["sample"]] = run["id"]
        if len(found) == len(samples):
            break
        if time.monotonic() > deadline:
            raise RigdTimeout(f"runs of {sorted(set(samples) - set(found))} did not appear within {timeout:g} s")
        time.sleep(0.2)
    return found


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_connection_args(p)
    p.add_argument("--samples", required=True, help="comma-separated sample names")
    p.add_argument("--plan", default=None, help="a built-in plan (h1, h2, …); default: the inline --directions")
    p.add_argument("--directions", default="0,0;45,90", help="inline plan: θ,φ;θ,φ… all paired with all (default %(default)s)")
    p.add_argument("--frame-size", default=None, help="simulated frame size WxH (processing needs at least 288x216)")
    p.add_argument("--steps", default="rectify,btf", help="processing steps, comma-separated; empty: the daemon's choice (default %(default)s)")
    p.add_argument("--out", default="sweep-out", help="download directory (default %(default)s)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for each run and each job")
    args = p.parse_args()

    samples = [s.strip() for s in args.samples.split(",") if s.strip()]
    if len(set(samples)) != len(samples):
        p.error("sample names must be unique within a sweep")
    plan = args.plan or inline_plan(parse_directions(args.directions), name="sweep")
    steps = [s for s in args.steps.split(",") if s]
    out = Path(args.out)

    with connect(args) as rigd:
        before = {r["id"] for r in rigd.iter_runs()}
        for sample in samples:
            q = rigd.enqueue(sample, plan, frame_size=parse_size(args.frame_size))
            started = q.get("started_run")
            print(f"queued {sample}: item {q['item']['id']}" + (f", started as {started['id']}" if started else ""))
        runs = find_new_runs(rigd, samples, before, args.timeout)

        ok = True
        summary = []
        for sample in samples:
            run_id = runs[sample]
            view = rigd.wait(run_id, timeout=args.timeout)
            print(f"{run_id}: {view['state']} {view['steps_done']}/{view['steps_total']} images, {view['physical_s']:.0f} s physical"
                  + (f" ({view['reason']})" if view.get("reason") else ""))
            if view["state"] != "completed":
                ok = False
                summary.append({"sample": sample, "run": run_id, "state": view["state"], "reason": view.get("reason")})
                continue
            job = rigd.process(run_id, *steps, wait=True, timeout=args.timeout)
            for st in job.get("steps", []):
                print(f"  {st['step']}: {st['state']}, {st.get('summary') or ''}")
            if job["state"] != "done":
                ok = False
                print(f"  processing failed: {job.get('error')}", file=sys.stderr)
            files = rigd.download(run_id, "frames", out / run_id)
            files += rigd.download(run_id, "manifest", out / run_id)
            if job["state"] == "done":
                try:
                    files += rigd.download(run_id, "btf", out / run_id)
                except RigdError as e:
                    # A run processed to something else (e.g. photometric stereo only) may have no BTF.
                    print(f"  no BTF: {e}", file=sys.stderr)
            size = sum(f.stat().st_size for f in files)
            print(f"  downloaded {len(files)} files, {size / 1e6:.2f} MB into {out / run_id}")
            summary.append({"sample": sample, "run": run_id, "state": view["state"], "physical_s": view["physical_s"],
                            "processed": job["state"], "files": len(files), "bytes": size})
        out.mkdir(parents=True, exist_ok=True)
        (out / "sweep.json").write_text(json.dumps(summary, indent=2) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (RigdError, RigdTimeout, httpx.HTTPError) as e:
        print(f"sweep: {e}", file=sys.stderr)
        sys.exit(1)
