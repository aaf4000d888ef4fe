#!/usr/bin/env bash
# Capture to viewer-ready BTF with processing during the capture: starts
# `rigd serve` on the simulated Bonn rig with the corduroy scene, asks for a
# run with `"process": {"rectify": {"size": 1024, "final": 256}}` (then
# `btf`), and follows it every half second. Prints the capture's wall time
# and frame rate, how far the registration during the capture fell behind
# the journal, and the wall time from the last journaled frame to the BTF
# (the job done). The figures are only meaningful on an otherwise idle
# machine. The default (a full H2 at 1024×768, 6561 frames, 3.4 GB) takes
# about 15 minutes.
# Usage: scripts/bench-stream.sh [WORKDIR]
#   PLAN (h2), SIZE (1024,768), SPEED (55: simulated seconds per wall second),
#   ORDER (unset: the daemon's choice, `slots` when it costs at most 2 %)
#   override the run; PORT (7399) the daemon's port.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-$(mktemp -d)}"
plan="${PLAN:-h2}"
size="${SIZE:-1024,768}"
speed="${SPEED:-55}"
order="${ORDER:-}"
port="${PORT:-7399}"
mkdir -p "$work"
rm -rf "$work/data"
cargo build --release --bin rigd
rigd="$PWD/target/release/rigd"
profile="$work/bonn-corduroy.toml"
sed 's/^\[sim\]$/[sim]\nscene = "corduroy"/' rig-profiles/bonn-gonioreflectometer.toml >"$profile"
"$rigd" serve --profile "$profile" --sim --listen "127.0.0.1:$port" --sim-speed "$speed" \
    --data "$work/data" >"$work/serve.log" 2>&1 &
daemon=$!
trap 'kill $daemon 2>/dev/null || true' EXIT
python3 - "$work" "$port" "$plan" "$size" "$order" <<'PY'
import json, os, sys, time, urllib.request
work, port, plan, size, order = sys.argv[1:]
base = f"http://127.0.0.1:{port}/api/v1"
for _ in range(100):
    try:
        urllib.request.urlopen(f"{base}/rig", timeout=2)
        break
    except OSError:
        time.sleep(0.1)
token = open(f"{work}/data/token").read().strip()
body = {"sample": "corduroy", "plan": plan,
        "frame_size": [int(v) for v in size.split(",")],
        "process": {"steps": ["rectify", "btf"], "rectify": {"size": 1024, "final": 256}}}
if order:
    body["order"] = order
req = urllib.request.Request(f"{base}/runs", json.dumps(body).encode(), method="POST",
                             headers={"Authorization": f"Bearer {token}",
                                      "Content-Type": "application/json"})
run = json.load(urllib.request.urlopen(req))
rid = run["id"]
root = f"{work}/data/runs/{rid}"
started = time.monotonic()
capture_end = first_frame = None
max_lag = 0
while True:
    v = json.load(urllib.request.urlopen(f"{base}/runs/{rid}"))
    now = time.monotonic()
    p = v.get("processing") or {}
    if first_frame is None and v["steps_done"] > 0:
        first_frame = now
    if v["active"] and v["state"] == "running":
        max_lag = max(max_lag, v["steps_done"] - p.get("streamed", 0))
    if capture_end is None and not v["active"]:
        capture_end = now
        # The last frame's journal line, on the same clock.
        journaled = time.time() - os.stat(f"{root}/journal.ndjson").st_mtime
        capture_end_journal = now - journaled
    if p.get("state") in ("done", "failed"):
        break
    time.sleep(0.5)
done = now
steps = {s["step"]: s for s in p["steps"]}
frames = v["steps_done"]
capture_s = capture_end_journal - (first_frame or started)
meta = json.load(open(f"{root}/run.json"))
print(f"run {rid}: {frames} frames of {size.replace(',', 'x')}, order {meta['plan']['order']}; "
      f"processing {p['state']}; {v['physical_s'] / 3600:.1f} h physical")
print(f"capture: {capture_s:.0f} s wall from the first frame, {frames / capture_s:.2f} frames/s; "
      f"registration during the capture at most {max_lag} frames behind the journal "
      f"(sampled every 0.5 s); {p.get('streamed', 0)} registered and "
      f"{p.get('slots_ahead', 0)} view slots compressed before the capture ended")
print(f"after the last frame: BTF done in {done - capture_end_journal:.1f} s wall "
      f"(rectify {steps['rectify']['elapsed_s']:.1f} s, btf {steps['btf']['elapsed_s']:.1f} s)")
print(f"rectify: {steps['rectify']['summary']}")
print(f"btf: {steps['btf']['summary']}")
PY
