#!/usr/bin/env bash
# Computes the trade-off report for two rigs (Bonn, MSRA) and two scenes
# (corduroy, leather) with `rigd tradeoff`'s defaults and keeps each one's
# tradeoff.{json,csv,svg} in docs/tradeoff/<profile>-<scene>/ (the figures
# docs/tradeoff.md shows). About 3 minutes a report on two cores.
#
#   scripts/tradeoff-figures.sh            # compute all four
#   scripts/tradeoff-figures.sh --redraw   # only draw the figures again
#                                          # from the kept reports
set -euo pipefail
cd "$(dirname "$0")/.."
out=docs/tradeoff
# RIGD=path/to/rigd uses that binary instead of building a release one.
rigd=${RIGD:-}
if [[ -z "$rigd" ]]; then
  cargo build --release --quiet --locked
  rigd=target/release/rigd
fi
redraw=${1:-}
for profile in bonn-gonioreflectometer msra-btf-mdf; do
  for scene in corduroy leather; do
    dir="$out/$profile-$scene"
    if [[ "$redraw" == "--redraw" ]]; then
      "$rigd" tradeoff --from "$dir"
    else
      mkdir -p "$dir"
      "$rigd" tradeoff --profile "$profile" --scene "$scene" --out "$dir" > "$dir/table.txt"
      echo "wrote $dir"
    fi
  done
done
