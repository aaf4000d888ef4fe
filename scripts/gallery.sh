#!/usr/bin/env bash
# Renders every built-in scene at a few poses, plus laser lines, into a
# folder (default docs/gallery): one PNG per frame and a JSON beside it
# with the live effects, render time and marker positions. Uses the MSRA
# profile's 8-bit camera, magnified so the sample fills the frame.
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-docs/gallery}
mkdir -p "$out"
# RIGD=path/to/rigd uses that binary instead of building a release one.
rigd=${RIGD:-}
if [[ -z "$rigd" ]]; then
  cargo build --release --quiet --locked
  rigd=target/release/rigd
fi
common=(--profile msra-btf-mdf --size 384x288 --zoom 2.5)
for scene in flat-calibration corduroy knitted-wool leather folded-cloth ps-target; do
  "$rigd" sim render "${common[@]}" --scene "$scene" --light 30,0 --view 0,0 --out "$out/$scene-l30-v0.png"
  "$rigd" sim render "${common[@]}" --scene "$scene" --light 80,0 --view 0,0 --exposure 3 --out "$out/$scene-l80-v0.png"
  "$rigd" sim render "${common[@]}" --scene "$scene" --light 45,90 --view 60,200 --out "$out/$scene-l45-v60.png"
done
for scene in corduroy knitted-wool leather ps-target; do
  "$rigd" sim render "${common[@]}" --scene "$scene" --lamp-off --laser 0,30 --view 45,180 --out "$out/$scene-laser.png"
done
echo "gallery in $out"
