"""Density along the rays through one object's pixels, around its true surface (the
veils that ``ngp``'s log-density noise turns into surfaces).

For the first three test views that show the object: the field's density (1/m) at the true
surface (from the ground-truth z-depth) plus offsets from -10 to +12 cm along each ray, for the
five pixels farthest from the object's silhouette, then the median over all its pixels. A
surface shows as a sharp rise to hundreds per metre at offset 0. A veil peaks lower and lets
the table behind show through. A fog stays at a few tens per metre over the object's depth.

usage: python docs/benchmarks/density_along_rays.py RUN DATA GEOM_NAME
"""
import sys

import cv2
import numpy as np
import torch

import sims  # noqa: F401  (headless GL before mujoco)
from nerfbot.data import load_dataset
from nerfbot.train.runs import load_model

run, data, name = sys.argv[1], sys.argv[2], sys.argv[3]
model, _ = load_model(run)
model.eval()
ds = load_dataset(data)
ids = [int(g) for g, n in ds.manifest["geoms"].items() if n == name]
if not ids:
    sys.exit(f"{data}: no geom named {name!r} in the manifest")
idx = ds.indices("test")
cams = ds.cameras(idx)
offsets = np.arange(-0.10, 0.121, 0.01)
shown = 0
for slot, i in enumerate(idx):
    seg, gt = ds.segmentations[i], ds.depths[i]
    mask = seg == ids[0]
    ys, xs = np.nonzero(mask)
    if len(ys) == 0:
        continue
    rays = cams.rays(slot)
    sel = torch.as_tensor(ys * seg.shape[1] + xs)
    o, d = rays.origins[sel], rays.directions[sel]
    t_true = torch.as_tensor(gt[ys, xs], dtype=torch.float32) / rays.z_per_t[sel]
    with torch.no_grad():
        prof = np.stack([model.field.density(o + d * (t_true + off)[:, None], None)[0].numpy()
                         for off in offsets], 1)  # (pixels, offsets)
    inner = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)[ys, xs]
    print(f"view {slot}: {len(ys)} px; density (1/m) at the true surface + offset (cm); "
          "the 5 innermost pixels (d: distance to the silhouette, px), then the median")
    print("off  " + " ".join(f"{100 * v:5.0f}" for v in offsets))
    for k in np.argsort(-inner)[:5]:
        print(f"d{inner[k]:<3.0f} " + " ".join(f"{v:5.0f}" for v in prof[k]))
    print("med  " + " ".join(f"{v:5.0f}" for v in np.median(prof, 0)))
    shown += 1
    if shown == 3:
        break
