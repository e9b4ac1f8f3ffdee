"""Mean colour and PSNR of each geom's pixels, ground truth against a run's renders
(small objects underfit in colour show here).

usage: python docs/benchmarks/object_colours.py RUN DATA [SPLIT]   (SPLIT: test or train; the
first 10 views of it)
"""
import sys

import numpy as np

import sims  # noqa: F401  (headless GL before mujoco)
from nerfbot.data import load_dataset
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

run, data = sys.argv[1], sys.argv[2]
split = sys.argv[3] if len(sys.argv) > 3 else "test"
model, _ = load_model(run)
model.eval()
ds = load_dataset(data)
idx = ds.indices(split)[:10]
cams = ds.cameras(idx)
pixels = {}
for slot, i in enumerate(idx):
    out = render_image(model, cams, slot)
    gt, seg = ds.image_float(i), ds.segmentations[i]
    for g, name in ds.manifest["geoms"].items():
        mask = seg == int(g)
        if mask.any():
            truth, rendered = pixels.setdefault(name, ([], []))
            truth.append(gt[mask])
            rendered.append(out["rgb"][mask])
print(f"{'geom':18s} {'px':>6s}  {'truth (RGB)':20s}  {'render (RGB)':20s}  PSNR")
for name, (truth, rendered) in pixels.items():
    truth, rendered = np.concatenate(truth), np.concatenate(rendered)
    mse = float(((truth - rendered) ** 2).mean())
    fmt = lambda c: " ".join(f"{v:.3f}" for v in c.mean(0))  # noqa: E731
    print(f"{name:18s} {len(truth):6d}  {fmt(truth):20s}  {fmt(rendered):20s}  "
          f"{-10 * np.log10(max(mse, 1e-12)):.1f}")
