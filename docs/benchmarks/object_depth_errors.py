"""Per-object depth errors of a run on a dataset's test split (BENCHMARKS.md, section 1).

For each object the manifest declares: pixels, MAE of the expected z-depth, its signed median
(positive: the field's surface lies too far), MAE of the median and of the threshold depth
(m = 5 /m), and the expected depth's MAE on interior pixels (3 x 3 eroded mask) and on the
silhouette; all in cm. Last, the median opacity of the object's pixels (about 1 for an opaque
surface placed too far, below 1 for a veil).

usage: python docs/benchmarks/object_depth_errors.py RUN DATA
"""
import sys

import cv2
import numpy as np

import sims  # noqa: F401  (headless GL before mujoco)
from nerfbot.data import load_dataset
from nerfbot.data.pixels import depth_valid_mask
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

run, data = sys.argv[1], sys.argv[2]
model, meta = load_model(run)
ds = load_dataset(data)
geoms = ds.manifest["geoms"]
objects = set(ds.manifest["objects"])
idx = ds.indices("test")
cams = ds.cameras(idx)
rows = {}
allo = {"expected": [], "median": []}
for slot, i in enumerate(idx):
    out = render_image(model, cams, slot, thresholds=[5.0])
    gt = ds.depths[i]; seg = ds.segmentations[i]; valid = depth_valid_mask(ds, i)
    for g, name in geoms.items():
        if name not in objects:
            continue
        m = valid & (seg == int(g))
        if not m.any():
            continue
        r = rows.setdefault(name, {"e": [], "m": [], "t": [], "int": [], "op": []})
        r["op"].append(out["opacity"][m])
        inner = cv2.erode((seg == int(g)).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        r["int"].append(inner[m])
        r["e"].append((out["z_depth"] - gt)[m]); r["m"].append((out["median_z_depth"] - gt)[m])
        r["t"].append((out["threshold_z_depth"][0] - gt)[m])
tot = {"e": [], "m": [], "t": []}
print(f"{'geom':18s} {'px':>5s} {'MAEexp':>7s} {'sgnmed':>7s} {'MAEmed':>7s} {'MAEthr5':>7s}")
for name, r in rows.items():
    e = np.concatenate(r["e"]); md = np.concatenate(r["m"]); t = np.concatenate(r["t"])
    tot["e"].append(e); tot["m"].append(md); tot["t"].append(t)
    tf = t[np.isfinite(t)]
    inn = np.concatenate(r["int"]); tot.setdefault("int", []).append(inn)
    print(f"{name:18s} {e.size:5d} {100*np.abs(e).mean():7.2f} {100*np.median(e):+7.2f} {100*np.abs(md).mean():7.2f} {100*np.abs(tf).mean():7.2f}   int {100*np.abs(e[inn]).mean():6.2f} edge {100*np.abs(e[~inn]).mean():6.2f} ({inn.mean():.2f} int)   opacity {np.median(np.concatenate(r['op'])):.3f}")
inn = np.concatenate(tot["int"])
e = np.concatenate(tot["e"]); md = np.concatenate(tot["m"]); t = np.concatenate(tot["t"]); tf = t[np.isfinite(t)]
print(f"{'ALL OBJECTS':18s} {e.size:5d} {100*np.abs(e).mean():7.2f} {100*np.median(e):+7.2f} {100*np.abs(md).mean():7.2f} {100*np.abs(tf).mean():7.2f}   int {100*np.abs(e[inn]).mean():6.2f} edge {100*np.abs(e[~inn]).mean():6.2f} ({inn.mean():.2f} int)")
