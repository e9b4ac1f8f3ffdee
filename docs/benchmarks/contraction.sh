#!/usr/bin/env bash
# The contracted model against the box at equal time: a room seen from inside (with its
# manifest, and captured without one, so the bounds come from the cameras) and the unbounded
# yard. Run alone: budgets are wall-clock seconds.
#
# usage: docs/benchmarks/contraction.sh OUT [SECONDS]
set -euo pipefail
OUT=$1
SECONDS_BUDGET=${2:-120}
[ -d "$OUT/room_no_manifest" ] || nerfbot capture --scene room:3 --no-manifest --no-progress \
    --out "$OUT/room_no_manifest"
nerfbot bench --data room:3,yard:3,"$OUT/room_no_manifest" --methods ngp \
    --option contraction=false,true --budgets "$SECONDS_BUDGET" --no-chamfer \
    --out "$OUT/contraction"
cat "$OUT/contraction/bench.md"
