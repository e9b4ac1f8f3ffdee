"""How much a ``room_glass`` capture's glass changes its pixels: the veil a field has to learn.

For every 4th training view of ``tasks.navigate``'s capture of each room (made if missing, as
the task makes it), the view is rendered again with the transparent geoms hidden (alpha 0);
on the pixels where the glass lies in front (z-depth differs), the mean absolute RGB
difference (colours in [0, 1]) is the veil. Views where glass covers under 5 % of the image
are skipped. Prints one line per room and writes OUT/veil.json.

usage: python docs/benchmarks/glass_veil.py OUT [--scene room_glass] [--seed 1000] [--scenes 1]
"""
import argparse
import json
from pathlib import Path

import mujoco
import numpy as np

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from nerfbot.data import load_dataset
from sims.camera import CaptureCamera
from sims.capture import set_lighting
from sims.manifest import rendered_geoms, transparent_geom_ids
from sims.scene import CAPTURE_CAMERA, resolve_scene
from tasks.navigate import NavTaskConfig, ensure_capture

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("out", type=Path)
parser.add_argument("--scene", default="room_glass")
parser.add_argument("--seed", type=int, default=1000)
parser.add_argument("--scenes", type=int, default=1)
args = parser.parse_args()
args.out.mkdir(parents=True, exist_ok=True)
cfg = NavTaskConfig(scene=args.scene)

rows = []
for seed in range(args.seed, args.seed + args.scenes):
    name = f"{args.scene}:{seed}"
    ds = load_dataset(ensure_capture(cfg, seed))
    spec = mujoco.MjSpec.from_file(str(resolve_scene(name)))
    spec.worldbody.add_camera(name=CAPTURE_CAMERA, pos=[0, 0, 0], quat=[1, 0, 0, 0])
    model = spec.compile()
    set_lighting(model)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    glass = np.array(sorted(transparent_geom_ids(rendered_geoms(model, data))), int)
    if len(glass) == 0:
        raise SystemExit(f"{name} has no transparent geoms")
    cams = ds.cameras(list(ds.indices("train")))
    width, height = int(cams.width[0]), int(cams.height[0])
    fovy = float(np.degrees(2 * np.arctan(0.5 * height / float(cams.fy[0]))))
    camera = CaptureCamera(model, data, width, height, fovy)
    alpha = model.geom_rgba[glass, 3].copy()
    veil, covered = [], []
    try:
        for k in range(0, len(cams.c2w), 4):
            c2w = cams.c2w[k].numpy()
            with_glass = camera.render(c2w)
            if np.isin(with_glass.segmentation, glass).mean() < 0.05:
                continue
            model.geom_rgba[glass, 3] = 0.0
            without = camera.render(c2w)
            model.geom_rgba[glass, 3] = alpha
            mask = np.abs(with_glass.depth - without.depth) > 1e-3
            diff = np.abs(with_glass.rgb.astype(float) - without.rgb.astype(float)).mean(-1)
            veil.append(diff[mask] / 255.0)
            covered.append(float(mask.mean()))
    finally:
        camera.close()
    if not veil:
        raise SystemExit(f"{name}: no training view shows its glass on 5 % of the image")
    v = np.concatenate(veil)
    row = {"scene": name, "views": len(veil), "glass_share": float(np.mean(covered)),
           "veil_mean": float(v.mean()), "veil_median": float(np.median(v)),
           "veil_p90": float(np.quantile(v, 0.9))}
    rows.append(row)
    print(f"{name}: {row['views']} views with glass (on {row['glass_share']:.0%} of their "
          f"pixels); veil mean {row['veil_mean']:.3f}, median {row['veil_median']:.3f}, "
          f"90th percentile {row['veil_p90']:.3f}")
(args.out / "veil.json").write_text(json.dumps(rows, indent=1))
