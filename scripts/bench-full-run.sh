#!/usr/bin/env bash
# The end-to-end processing times of a full 81 × 81 run: captures H2 on the
# simulated Bonn rig (flat-calibration scene, 1024×768 frames), then times
# `rigd process rectify` (to 1024², ROI, 256²), `rigd process btf
# --components 16` and `rigd process fit --lobes 2`, each once, with wall
# time and peak memory. One run takes about an hour on 2 cores and ~10 GB
# of disk; criterion's per-slot benchmarks (`cargo bench -p rigd-process`)
# are the quick check. H2, not H1: H1's 85° views put the holder's markers
# beyond what registration resolves at this frame size (those frames are
# named and refused). Usage: scripts/bench-full-run.sh [WORKDIR]
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-$(mktemp -d)}"
cargo build --release --bin rigd
rigd=target/release/rigd
run="$work/h2-full"
rm -rf "$run"
stage() {
    local name="$1"
    shift
    /usr/bin/time -f "$name: %e s wall, %M KiB peak" "$@" >"$work/$name.out" 2>"$work/$name.err" \
        || { cat "$work/$name.err" >&2; exit 1; }
    tail -n 1 "$work/$name.err"
}
stage capture "$rigd" run --sim --plan h2 --frame-size 1024x768 --scene flat-calibration \
    --progress none --sample full --out "$run"
stage rectify "$rigd" process rectify "$run" --size 1024 --final 256
stage btf "$rigd" process btf "$run" --components 16
stage fit "$rigd" process fit "$run" --lobes 2
cat "$work/fit.out"
echo "run directory: $run ($(du -sh "$run" | cut -f1)); remove it when done"
