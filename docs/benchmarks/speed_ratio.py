"""Render-speed ratios of baked / distilled renderers against their sources, interleaved.

The machine's speed drifts by up to 2x between processes minutes apart, so each pair is
timed in one process, in alternating blocks: all test images by A, then all by B, for ROUNDS
rounds. The figure is the median per-image time of each, and their ratio. Blocks, not
image-by-image alternation, keep each renderer's tables in cache as in real use: rendering
image by image in turn made the octree 1.8x slower (its 10 MB of leaves evicted by the
source's hash tables).

usage: python docs/benchmarks/speed_ratio.py DATA NAME_A RUN_A NAME_B RUN_B [...more pairs]
"""
import json
import sys
import time

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

ROUNDS = 5
args = sys.argv[2:]
if len(sys.argv) < 2 or not args or len(args) % 4:
    sys.exit(__doc__)
ds = load_dataset(sys.argv[1])
idx = ds.indices("test")
cams = ds.cameras(idx)
for p in range(0, len(args), 4):
    (na, ra), (nb, rb) = (args[p], args[p + 1]), (args[p + 2], args[p + 3])
    models = {na: load_model(ra)[0].eval(), nb: load_model(rb)[0].eval()}
    for m in models.values():
        render_image(m, cams, 0)  # compile / warm caches
    times = {na: [], nb: []}
    for _ in range(ROUNDS):
        for name, m in models.items():
            for i in range(len(idx)):
                t0 = time.perf_counter()
                render_image(m, cams, i)
                times[name].append(time.perf_counter() - t0)
    ms = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
    row = {"a": na, "b": nb, "a_ms": round(ms[na], 2), "b_ms": round(ms[nb], 2),
           "speedup_b_over_a": round(ms[na] / ms[nb], 2), "images": len(idx), "rounds": ROUNDS}
    print(json.dumps(row), flush=True)
