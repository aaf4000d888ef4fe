#!/usr/bin/env bash
# Rectification throughput, frames per second, as `rigd process rectify
# --size 1024 --final 256` sustains it on a whole run: for each scene
# (corduroy, flat-calibration) and frame size (384×288, 1024×768, 3032×2008
# 12-bit), captures a 48-frame plan on the simulated Bonn rig (8 views from
# the pole to 75°, 6 lights) and times the command twice; the frames per
# second of the faster run are printed. Reading and decoding the frames,
# process start-up and the index are included. `check` is the share of that
# run's CPU time (all its threads) the SHA-256 check of every frame read
# takes: benches/frame_check.rs times the hash of the run's frames on one
# thread, and rectification hashes each frame once (the up to 32 it reads
# again for its texture-alignment check come from files it checked and that
# have not changed since, which are not hashed again). The timings are only
# meaningful on an otherwise idle machine. Takes about two minutes (the
# first run also builds the bench).
# Usage: scripts/bench-rectify.sh [WORKDIR]
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-$(mktemp -d)}"
mkdir -p "$work"
cargo build --release --bin rigd
rigd="$PWD/target/release/rigd"
# The SHA-256 timing (its first build takes minutes: the benches' own
# dependency features).
check_bench=$(cargo build --release --bench frame_check --message-format=json | python3 -c '
import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "frame_check" and m.get("executable"):
        print(m["executable"])
')
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
printf '%-18s %-10s %8s %10s %7s  %s\n' scene frame seconds frames/s check methods
for scene in corduroy flat-calibration; do
    for size in 384x288 1024x768 3032x2008; do
        run="$work/$scene-$size"
        rm -rf "$run"
        "$rigd" run --sim --plan "$plan" --scene "$scene" --frame-size "$size" \
            --progress none --sample bench --out "$run" >/dev/null 2>&1
        # The faster of two runs, timed by python3 (no bc on a fresh machine):
        # its wall seconds and the CPU seconds of all its threads.
        read -r best cpu < <(python3 - "$rigd" "$run" <<'PY'
import os, shutil, subprocess, sys, time
rigd, run = sys.argv[1], sys.argv[2]
times = []
for _ in range(2):
    shutil.rmtree(f"{run}/processed", ignore_errors=True)
    before = os.times()
    start = time.monotonic()
    subprocess.run([rigd, "process", "rectify", run, "--size", "1024", "--final", "256"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.monotonic() - start
    after = os.times()
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    times.append((wall, cpu))
print(*min(times))
PY
)
        methods=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['summary']['frames_by_method'])" \
            "$run/processed/normtextures/index.json")
        # RUN FRAMES HASH_MS_PER_FRAME IMAGE_MS_PER_FRAME
        hash_ms=$("$check_bench" "$run" | awk '{print $3}')
        check=$(python3 -c "print(f'{100 * 48 * $hash_ms / 1e3 / $cpu:.1f} %')")
        printf '%-18s %-10s %8.2f %10.1f %7s  %s\n' "$scene" "$size" "$best" "$(python3 -c "print(48 / $best)")" "$check" "$methods"
        rm -rf "$run"
    done
done
