"""Render time and test PSNR of one trained run under several values of a render-time option.

The option is set on the loaded model (``config.NAME`` or ``kilo_config.NAME``) without
retraining or re-baking. Values are timed in alternating blocks (all test images with each
value in turn, ROUNDS rounds; medians), as ``speed_ratio.py`` times pairs: the machine's speed
drifts between processes. NAME ``centre_colour`` (values 0, 1) is this script's own switch:
1 renders the centre rays of a supersampled image with colour too, as a full render, to time
what the geometry-only centre pass (``Model.render_geometry``) saves.

usage: python docs/benchmarks/render_options.py DATA RUN NAME V1,V2,...
  e.g. ... bench/final/data_ns B/octree color_min_weight 0,1e-3,1e-2,3e-2
Several options at once: NAME1+NAME2 and values V1+W1,V2+W2,... (e.g.
``supersample_pattern+supersample_tolerance grid+0,corners+0,corners+0.1``).

Prints, per value, the median render ms and the test PSNR over the whole image, the non-sky
pixels and the objects (as ``nerfbot eval`` reports them).
"""
import json
import sys
import time

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

ROUNDS = 5
if len(sys.argv) != 5:
    sys.exit(__doc__)
data, run, name, values = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4].split(",")
ds = load_dataset(data)
cams = ds.cameras(ds.indices("test"))
model = load_model(run)[0].eval()


class CentreColour:
    """``centre_colour``: 1 swaps the model's geometry-only render for its full one."""

    def __init__(self):
        self.geometry = model.render_geometry
        self.centre_colour = 0

    def __setattr__(self, key, value):
        super().__setattr__(key, value)
        if key == "centre_colour":
            model.render_geometry = (lambda rays, cond=None: model.render_rays(rays, None, cond)) \
                if value else self.geometry


names = name.split("+")
holders = []
for n in names:
    if n == "centre_colour":
        holders.append(CentreColour())
        continue
    holder = next((c for c in (getattr(model, "kilo_config", None),
                               getattr(model, "config", None))
                   if c is not None and hasattr(c, n)), None)
    if holder is None:
        sys.exit(f"{run}: the model has no render option {n!r}")
    holders.append(holder)


def parsed(value: str) -> tuple:
    parts = value.split("+")
    if len(parts) != len(names):
        sys.exit(f"value {value!r}: expected {len(names)} parts joined by '+'")
    out = []
    for holder, n, v in zip(holders, names, parts):
        kind = type(getattr(holder, n))
        out.append(v if kind is str else kind(float(v)))
    return tuple(out)


def apply(value: tuple) -> None:
    for holder, n, v in zip(holders, names, value):
        setattr(holder, n, v)


values = [parsed(v) for v in values]
times = {v: [] for v in values}
render_image(model, cams, 0)
for _ in range(ROUNDS):
    for v in values:
        apply(v)
        for i in range(len(cams)):
            t0 = time.perf_counter()
            render_image(model, cams, i)
            times[v].append(time.perf_counter() - t0)
for v in values:
    apply(v)
    result = evaluate(model, ds, "test", with_ssim=False)
    shown = v[0] if len(v) == 1 else "+".join(str(x) for x in v)
    psnrs = {k: round(result[k], 3) for k in ("psnr", "psnr_non_sky", "psnr_objects")
             if result.get(k) is not None}
    print(json.dumps({name: shown, "render_ms": round(1e3 * float(np.median(times[v])), 2),
                      **psnrs}), flush=True)
