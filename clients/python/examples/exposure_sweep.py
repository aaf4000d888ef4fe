#!/usr/bin/env python3
"""An exposure sweep on one sample: what a longer exposure buys in signal and
costs in capture time.

For each exposure it takes a test frame (manual control: the frame's mean,
maximum and saturated fraction) and captures the plan at that exposure, then
prints the physical capture time per image, what a whole built-in plan
(default h1) would take at that pace, and, when the daemon has a trade-off
report, the most accurate plan that fits in that time.

    python exposure_sweep.py --data rigd-data --sample felt-3 --exposures 0.05,0.25,1

Exit status: 0 when every run completed, 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, Dict, List, Optional

import httpx
from _common import add_connection_args, connect, parse_directions, parse_size

from rigd_client import Client, RigdError, RigdTimeout, inline_plan


def hours(s: float) -> str:
    """Seconds as ``3h25m``."""
    m = int(round(s / 60))
    return f"{m // 60}h{m % 60:02d}m"


def full_plan(rigd: Client, name: str) -> Optional[Dict[str, Any]]:
    """The built-in plan's summary from ``GET /plans`` if it is solved and fits."""
    for p in rigd.plans()["plans"]:
        if p["name"] == name and p["ready"] and p["fits"]:
            return p
    return None


def camera_exposure(rigd: Client, camera: Optional[str]) -> float:
    """The profile's exposure of the camera (the first camera when None), from ``GET /rig``."""
    for d in rigd.rig()["devices"]:
        if d["kind"] == "camera" and (camera is None or d["name"] == camera):
            return float(d["camera"]["exposure_s"])
    raise SystemExit(f"exposure_sweep: no camera {camera!r} on this rig")


def pose_for_test_frames(rigd: Client, light: Any, view: Any) -> str:
    """Homes every axis and the arm, takes the (light, view) pose, returns its lamp.

    The test frames are then lit like the run's images (a frame with the lamp
    off shows only the sensor's dark level).
    """
    for d in rigd.rig()["devices"]:
        if d["kind"] in ("axis", "arm") and d.get("homing") is not False:
            rigd.manual_home(d["name"])
    return str(rigd.manual_pose(light, view)["lamp"])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_connection_args(p)
    p.add_argument("--sample", default="exposure-sweep")
    p.add_argument("--exposures", default="0.05,0.25,1", help="seconds, comma-separated (default %(default)s)")
    p.add_argument("--directions", default="0,0;45,90", help="inline plan θ,φ;… all paired with all (default %(default)s)")
    p.add_argument("--frame-size", default="64x48", help="simulated frame size WxH (default %(default)s)")
    p.add_argument("--camera", default=None, help="the camera for test frames (default: the profile's first)")
    p.add_argument("--full-plan", default="h1", help="the plan to extrapolate to (default %(default)s)")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for each run")
    args = p.parse_args()
    exposures = [float(x) for x in args.exposures.split(",") if x.strip()]
    plan = inline_plan(parse_directions(args.directions), name="exposure")
    if not exposures:
        p.error("no exposures")

    rows: List[Dict[str, Any]] = []
    with connect(args) as rigd:
        directions = parse_directions(args.directions)
        lamp = pose_for_test_frames(rigd, directions[-1], directions[0])
        # Every test frame before the first run: a run releases the manual rig,
        # which then has to home and take the pose again.
        tests = {}
        rigd.manual_lamp(lamp, True)
        try:
            for e in exposures:
                tests[e] = rigd.manual_frame(camera=args.camera, exposure_s=e)
        finally:
            rigd.manual_lamp(lamp, False)
        for e in exposures:
            test = tests[e]
            run = rigd.start_run(args.sample, plan, exposure_s=e, frame_size=parse_size(args.frame_size),
                                 notes=f"exposure sweep: {e:g} s")
            view = rigd.wait(run, timeout=args.timeout)
            rows.append({"exposure": e, "run": view, "test": test})
            print(f"{e:g} s: {view['id']} {view['state']}", flush=True)
        full = full_plan(rigd, args.full_plan)
        try:
            rigd.tradeoff()
            have_report = True
        except RigdError as err:
            if err.status != 404:
                raise
            have_report = False

        # The capture time a whole plan would take: the daemon's estimate at the
        # profile's exposure, plus the measured extra physical seconds per image
        # per second of exposure (slope over the sweep; 1 with a single exposure).
        slope = 1.0
        if len(rows) > 1 and rows[-1]["exposure"] != rows[0]["exposure"]:
            per = [r["run"]["physical_s"] / max(1, r["run"]["steps_done"]) for r in (rows[0], rows[-1])]
            slope = (per[1] - per[0]) / (rows[-1]["exposure"] - rows[0]["exposure"])
        profile_exposure = camera_exposure(rigd, args.camera)

        def full_estimate(e: float) -> float:
            assert full is not None
            return full["estimated_physical_s"] + full["steps_total"] * slope * (e - profile_exposure)

        print()
        bits = rows[0]["test"]["bit_depth"]
        print(f"{'exposure':>9} {'images':>6} {'physical':>9} {'s/image':>8} {'mean':>8} {'max':>6} {'satur.':>7}"
              + (f" {args.full_plan + ' (est.)':>12}" if full else ""))
        for row in rows:
            v, t = row["run"], row["test"]
            per_image = v["physical_s"] / max(1, v["steps_done"])
            line = (f"{row['exposure']:>8g}s {v['steps_done']:>6} {v['physical_s']:>8.1f}s {per_image:>8.2f}"
                    f" {t['mean']:>8.1f} {t['max']:>6} {100 * t['saturated']:>6.2f}%")
            if full:
                line += f" {hours(full_estimate(row['exposure'])):>12}"
            print(line)
        print(f"test frames: {bits}-bit (full scale {2 ** bits - 1}), lamp {lamp} on, at the pose of the plan's first pair")
        if len(rows) > 1:
            print(f"each extra second of exposure costs {slope:.2f} s of physical time per image"
                  + (f", {hours(slope * full['steps_total'])} over {args.full_plan} ({full['steps_total']} images;"
                     f" {hours(full['estimated_physical_s'])} at the profile's {profile_exposure:g} s)" if full else "")
                  + f"; the signal above the dark level grows {_gain(rows[0]['test'], rows[-1]['test']):.1f}x"
                  + f" from {rows[0]['exposure']:g} s to {rows[-1]['exposure']:g} s")
        if have_report and full:
            for row in rows:
                budget = full_estimate(row["exposure"])
                try:
                    choice = rigd.tradeoff_choice(budget=f"{budget:.0f}")
                    print(f"{row['exposure']:g} s, a {hours(budget)} budget: {choice['answer']}")
                except RigdError as err:
                    print(f"{row['exposure']:g} s, a {hours(budget)} budget: {err.detail}")
        elif not have_report:
            print("no trade-off report on the daemon (POST /api/v1/tradeoff makes one): plan choices skipped")
    return 0 if all(r["run"]["state"] == "completed" for r in rows) else 1


def _gain(a: Dict[str, Any], b: Dict[str, Any]) -> float:
    """How much brighter b's test frame is than a's, above each frame's darkest sample."""
    sa = max(1e-9, a["mean"] - a["min"])
    sb = max(1e-9, b["mean"] - b["min"])
    return sb / sa


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (RigdError, RigdTimeout, httpx.HTTPError) as e:
        print(f"exposure_sweep: {e}", file=sys.stderr)
        sys.exit(1)
