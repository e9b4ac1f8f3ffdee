"""How many training rays a dynamic capture's moving objects get in a run.

From the capture: the share of the training pixels on the manifest's moving bodies (their
segmentation, not dilated) and the share of the importance weights
(:func:`nerfbot.data.importance.importance_weights`) on them. From a run trained on it
(``scalars.csv``): its steps and rays per step. With ``dynamic_rays`` R of each batch drawn by
the weights and the rest uniformly (the run's ``config.json``), the rays on object pixels
over the run are steps x rays x (R x weight share + (1 - R) x pixel share); divided by the
object pixels, the times each was trained on.

usage: python docs/benchmarks/object_ray_budget.py CAPTURE RUN [RUN ...]
"""
import argparse
import csv
import json
from pathlib import Path

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.data.importance import importance_weights
from nerfbot.eval.evaluation import object_geom_ids

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("capture", type=Path)
parser.add_argument("runs", type=Path, nargs="+")
args = parser.parse_args()

ds = load_dataset(args.capture)
idx = list(ds.indices("train"))
weights, _ = importance_weights(ds, idx)
ids = object_geom_ids(ds)
objects = np.concatenate([np.isin(ds.segmentations[i], ids).reshape(-1) for i in idx])
pixel_share = float(objects.mean())
weight_share = float(weights[objects].sum() / weights.sum()) if weights.sum() > 0 else 0.0
print(f"{args.capture}: {len(idx)} training frames, {objects.sum()} object pixels "
      f"({pixel_share:.2%} of the pixels), {weight_share:.1%} of the importance weight on them")
for run in args.runs:
    with open(run / "scalars.csv") as f:
        rows = list(csv.DictReader(f))
    rays = np.array([float(r["rays"]) for r in rows])
    config = json.loads((run / "config.json").read_text())
    share = float(config["train"].get("dynamic_rays", 0.0))
    on_objects = rays.sum() * (share * weight_share + (1 - share) * pixel_share)
    print(f"{run}: {len(rows)} steps, median {np.median(rays):.0f} rays per step, "
          f"dynamic_rays {share:g}: {on_objects:.3g} rays on object pixels, "
          f"{on_objects / objects.sum():.2f} per object pixel")
