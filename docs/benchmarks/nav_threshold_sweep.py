"""A field floor map's agreement with the true one against its obstacle density threshold.

For each room (``tasks.navigate``'s capture and training, cached as the task caches them) the
field's floor map is made at every threshold and compared with the true map
(``tasks.nav_map.map_agreement``: IoU, phantom and missed cells, standable floor kept and
wrong, and the share of the transparent obstacles' cells blocked). The default threshold
(:func:`nerfbot.query.density.default_obstacle_threshold`) and the depth sensor's map are
reported beside. Writes OUT/sweep.json and OUT/sweep.png.

usage: python docs/benchmarks/nav_threshold_sweep.py OUT [--scene room_glass] [--seed 1000]
           [--scenes 1] [--thresholds 1,2,3,4,6,8,12]
"""
import argparse
import json
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from nerfbot.query.density import default_obstacle_threshold  # noqa: E402
from nerfbot.train.runs import load_model  # noqa: E402
from tasks.nav_map import map_agreement, true_floor_map  # noqa: E402
from tasks.navigate import (NavTaskConfig, World, ensure_capture, ensure_trained,  # noqa: E402
                            field_floor_map, sensor_floor_map)

KEYS = ("iou", "phantom", "missed", "standable_kept", "standable_wrong", "transparent_blocked")

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("out", type=Path)
parser.add_argument("--scene", default="room_glass")
parser.add_argument("--seed", type=int, default=1000)
parser.add_argument("--scenes", type=int, default=1)
parser.add_argument("--thresholds", default="1,2,3,4,6,8,12")
args = parser.parse_args()
thresholds = [float(t) for t in args.thresholds.split(",")]
cfg = NavTaskConfig(scene=args.scene)
args.out.mkdir(parents=True, exist_ok=True)

rows = []
for seed in range(args.seed, args.seed + args.scenes):
    name = f"{args.scene}:{seed}"
    model, _ = load_model(ensure_trained(cfg, seed), cfg.device)
    world = World(name, cfg)
    try:
        truth = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell)
        glass = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell,
                               transparent_only=True)
        glass = glass if glass.blocked.any() else None
        radius = cfg.robot.radius + cfg.margin
        default = default_obstacle_threshold(model)
        for t in sorted(set(thresholds + [default])):
            fmap = field_floor_map(model, world, replace(cfg, threshold=t))
            rows.append({"scene": name, "map": "nerf", "threshold": t, "default": t == default,
                         **map_agreement(fmap, truth, radius, glass)})
        fmap = sensor_floor_map(ensure_capture(cfg, seed), world, cfg)
        rows.append({"scene": name, "map": "sensor", "threshold": None, "default": False,
                     **map_agreement(fmap, truth, radius, glass)})
    finally:
        world.close()

print("| room | map | threshold (1/m) | " + " | ".join(KEYS) + " |")
print("|---|---|---|" + "---|" * len(KEYS))
for r in rows:
    t = "" if r["threshold"] is None else f"{r['threshold']:.1f}" + (" (default)" if r["default"] else "")
    print(f"| `{r['scene']}` | {r['map']} | {t} | "
          + " | ".join(f"{r[k]:.3f}" if k in r else "" for k in KEYS) + " |")
(args.out / "sweep.json").write_text(json.dumps(rows, indent=1))

fig, axes = plt.subplots(1, args.scenes, figsize=(5.5 * args.scenes, 3.8), squeeze=False)
for ax, seed in zip(axes[0], range(args.seed, args.seed + args.scenes)):
    name = f"{args.scene}:{seed}"
    nerf = [r for r in rows if r["scene"] == name and r["map"] == "nerf"]
    sensor = next(r for r in rows if r["scene"] == name and r["map"] == "sensor")
    for k in KEYS:
        if k not in nerf[0]:
            continue
        line, = ax.plot([r["threshold"] for r in nerf], [r[k] for r in nerf], "o-", label=k)
        ax.axhline(sensor[k], color=line.get_color(), ls=":", lw=1)
    ax.axvline(next(r["threshold"] for r in nerf if r["default"]), color="grey", ls="--", lw=1)
    ax.set_xscale("log")
    ax.set_xlabel("obstacle threshold, 1/m (dashed: default; dotted: depth sensor)")
    ax.set_title(name)
axes[0][0].legend(fontsize=7)
fig.tight_layout()
fig.savefig(args.out / "sweep.png", dpi=110)
print(f"wrote {args.out / 'sweep.json'} and {args.out / 'sweep.png'}")
