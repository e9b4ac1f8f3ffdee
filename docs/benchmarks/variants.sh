#!/usr/bin/env bash
# The variants table of BENCHMARKS.md: every static method on the 128x128 tabletop.
#
# usage: docs/benchmarks/variants.sh OUT
#   run after `python docs/benchmarks/ngp_tabletop.py OUT`: it uses that capture (OUT/data_ns)
#   and its 180 s ngp run as kilonerf's teacher (OUT/ngp_data_ns). Run alone: budgets are
#   wall-clock seconds.
set -euo pipefail
OUT=$1
DATA=$OUT/data_ns
TEACHER=$OUT/ngp_data_ns

# the grid, baked and distilled variants at 300 s, ngp as the baseline (baked methods train
# their source on the budget, then bake it by the registry's recipe with its defaults)
nerfbot bench --data "$DATA" --budgets 300 --no-chamfer --keep-checkpoints \
    --methods ngp,plenoxels,tensorf,fastnerf_cache,plenoctree_octree,kilonerf \
    --option "teacher_run=$TEACHER" --out "$OUT/variants"

# nerf and mipnerf with their defaults (a 4x64 MLP, 16 + 32 and 32 + 32 samples per ray), on
# a step budget
C=(--max-steps 3000 --seed 0 --no-progress)
[ -f "$OUT/nerf/metrics.json" ] || nerfbot train --data "$DATA" --method nerf "${C[@]}" \
    --out "$OUT/nerf"
[ -f "$OUT/mipnerf/metrics.json" ] || nerfbot train --data "$DATA" --method mipnerf "${C[@]}" \
    --out "$OUT/mipnerf"
for run in nerf mipnerf; do
    for k in 1 2 4; do
        nerfbot eval "$OUT/$run" --downscale $k --json > "$OUT/$run/eval_downscale$k.json"
    done
done
cat "$OUT/variants/bench.md"
for run in nerf mipnerf; do
    echo "$run:"; cat "$OUT/$run/eval_downscale"{1,2,4}.json; echo
done
