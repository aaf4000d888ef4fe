#!/usr/bin/env bash
# Rectification throughput, frames per second, as `rigd process rectify
# --size 1024 --final 256` sustains it on a whole run: for each scene
# (corduroy, flat-calibration) and frame size (384×288, 1024×768, 3032×2008
# 12-bit), captures a 48-frame plan on the simulated Bonn rig (8 views from
# the pole to 75°, 6 lights) and times the command twice; the frames per
# second of the faster run are printed. Reading and decoding the PNG frames,
# process start-up and the index are included. The timings are only
# meaningful on an otherwise idle machine. Takes about two minutes.
# Usage: scripts/bench-rectify.sh [WORKDIR]
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-$(mktemp -d)}"
mkdir -p "$work"
cargo build --release --bin rigd
rigd="$PWD/target/release/rigd"
plan="$work/plan48.json"
cat >"$plan" <<'JSON'
{"name": "bench48",
 "lights": [{"theta_deg": 0, "phi_deg": 0}, {"theta_deg": 30, "phi_deg": 0},
            {"theta_deg": 30, "phi_deg": 120}, {"theta_deg": 45, "phi_deg": 240},
            {"theta_deg": 60, "phi_deg": 60}, {"theta_deg": 75, "phi_deg": 300}],
 "views": [{"theta_deg": 0, "phi_deg": 0}, {"theta_deg": 30, "phi_deg": 45},
           {"theta_deg": 45, "phi_deg": 200}, {"theta_deg": 60, "phi_deg": 0},
           {"theta_deg": 60, "phi_deg": 120}, {"theta_deg": 75, "phi_deg": 90},
           {"theta_deg": 75, "phi_deg": 270}, {"theta_deg": 15, "phi_deg": 300}]}
JSON
printf '%-18s %-10s %8s %10s  %s\n' scene frame seconds frames/s methods
for scene in corduroy flat-calibration; do
    for size in 384x288 1024x768 3032x2008; do
        run="$work/$scene-$size"
        rm -rf "$run"
        "$rigd" run --sim --plan "$plan" --scene "$scene" --frame-size "$size" \
            --progress none --sample bench --out "$run" >/dev/null 2>&1
        # The faster of two runs, timed by python3 (no bc on a fresh machine).
        best=$(python3 - "$rigd" "$run" <<'PY'
import shutil, subprocess, sys, time
rigd, run = sys.argv[1], sys.argv[2]
times = []
for _ in range(2):
    shutil.rmtree(f"{run}/processed", ignore_errors=True)
    start = time.monotonic()
    subprocess.run([rigd, "process", "rectify", run, "--size", "1024", "--final", "256"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    times.append(time.monotonic() - start)
print(min(times))
PY
)
        methods=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['summary']['frames_by_method'])" \
            "$run/processed/normtextures/index.json")
        printf '%-18s %-10s %8.2f %10.1f  %s\n' "$scene" "$size" "$best" "$(python3 -c "print(48 / $best)")" "$methods"
        rm -rf "$run"
    done
done
