"""A field floor map's agreement with the true one against its obstacle density threshold.

For each room (``tasks.navigate``'s capture and training, cached as the task caches them) the
field's floor map is made at every threshold and compared with the true map
(``tasks.nav_map.map_agreement``: IoU, phantom and missed cells, standable floor kept and
wrong, and the share of the transparent obstacles' cells blocked), with the share of the free
floor (over 0.25 m from obstacles) whose density reaches the lowest threshold, by height. The
default threshold (:func:`nerfbot.query.density.default_obstacle_threshold`) and the depth
sensor's map are reported beside. The field's density inside the declared obstacles is
printed too (over grids of points 2 cm apart filling their boxes from 0.1 to 0.5 m above the
floor, pooled over the transparent and over the opaque ones: the median, and the share of
points at 5 /m or more, the glassware family's Dex-NeRF threshold): what threshold could find
them. With ``--glass-thresholds``, the default map is also made with each as its second,
lower threshold counted from ``--glass-clearance`` above the floor up and ``--glass-halo``
away from the default's obstacles (``NavTaskConfig.glass_threshold``). Writes OUT/sweep.json
and OUT/sweep.png.

usage: python docs/benchmarks/nav_threshold_sweep.py OUT [--scene room_glass] [--seed 1000]
           [--scenes 1] [--thresholds 1,2,3,4,6,8,12] [--glass-thresholds 0.25,0.5,1]
           [--glass-clearance 0.2] [--glass-halo 0.1] [--train-steps 2000]
           [--option KEY=VALUE ...]
"""
import argparse
import json
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from nerfbot.app.cli import parse_option  # noqa: E402
from nerfbot.query.density import default_obstacle_threshold, density_at  # noqa: E402
from nerfbot.train.runs import load_model  # noqa: E402
from sims.manifest import declared_obstacles, rendered_geoms, transparent_geom_ids  # noqa: E402
from tasks.nav_map import map_agreement  # noqa: E402
from tasks.navigate import (NAV_FIELD_OPTIONS, NavTaskConfig, World,  # noqa: E402
                            ensure_capture, ensure_trained, field_floor_map, sensor_floor_map,
                            true_maps)

DEX_THRESHOLD = 5.0   # 1/m, the glassware family's calibrated threshold (BENCHMARKS, section 3)
KEYS = ("iou", "phantom", "missed", "standable_kept", "standable_wrong", "transparent_blocked")

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("out", type=Path)
parser.add_argument("--scene", default="room_glass")
parser.add_argument("--seed", type=int, default=1000)
parser.add_argument("--scenes", type=int, default=1)
parser.add_argument("--thresholds", default="1,2,3,4,6,8,12")
parser.add_argument("--glass-thresholds", default="",
                    help="second, lower thresholds (1/m) of the default map, comma-separated")
parser.add_argument("--glass-clearance", type=float, default=NavTaskConfig.glass_clearance,
                    help="height (m) from which a glass threshold counts")
parser.add_argument("--glass-halo", type=float, default=NavTaskConfig.glass_halo,
                    help="a glass threshold ignores cells this close (m) to the default's")
parser.add_argument("--train-steps", type=int, default=NavTaskConfig.train_steps)
parser.add_argument("--option", action="append", default=[], type=parse_option,
                    help="field option of the training runs, as tasks.navigate takes it")
args = parser.parse_args()
thresholds = [float(t) for t in args.thresholds.split(",")]
glass_thresholds = [float(t) for t in args.glass_thresholds.split(",") if t]
cfg = NavTaskConfig(scene=args.scene, train_options={**NAV_FIELD_OPTIONS, **dict(args.option)},
                    glass_clearance=args.glass_clearance, glass_halo=args.glass_halo,
                    train_steps=args.train_steps)
args.out.mkdir(parents=True, exist_ok=True)


def obstacle_densities(model, world) -> list[dict]:
    """Density inside each declared obstacle between 0.1 and 0.5 m above the floor, at a grid
    of points 2 cm apart filling its world box: {geom, transparent, sigma (N,) 1/m}."""
    clear = {world.model.geom(g).name
             for g in transparent_geom_ids(rendered_geoms(world.model, world.data))}
    out = []
    for name, (lo, hi) in declared_obstacles(world.model, world.data).items():
        lo, hi = np.maximum(lo, [-np.inf, -np.inf, 0.1]), np.minimum(hi, [np.inf, np.inf, 0.5])
        if np.any(hi <= lo):
            continue
        axes = [np.linspace(a, b, max(int((b - a) / 0.02), 2)) for a, b in zip(lo, hi)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        sigma = density_at(model, torch.as_tensor(pts, dtype=torch.float32)).numpy()
        out.append({"geom": name, "transparent": name in clear, "sigma": sigma})
    return out


#: Heights (m) of the free-floor density profile, and how far from obstacles it looks.
PROFILE_HEIGHTS = np.arange(0.02, 0.31, 0.02)
PROFILE_CLEARANCE = 0.25


def free_floor_profile(model, truth, level: float) -> list[float]:
    """Share of the free floor's cells (farther than PROFILE_CLEARANCE from the true map's
    obstacles) whose density reaches ``level`` (1/m), at each of PROFILE_HEIGHTS."""
    cells = np.argwhere(truth.clearance() > PROFILE_CLEARANCE)
    xy = truth.to_world(cells)
    share = []
    for z in PROFILE_HEIGHTS:
        pts = np.concatenate([xy, np.full((len(xy), 1), z)], 1)
        sigma = density_at(model, torch.as_tensor(pts, dtype=torch.float32)).numpy()
        share.append(float((sigma >= level).mean()))
    return share


rows = []
for seed in range(args.seed, args.seed + args.scenes):
    name = f"{args.scene}:{seed}"
    model, _ = load_model(ensure_trained(cfg, seed), cfg.device)
    world = World(name, cfg)
    try:
        truth, glass = true_maps(world, cfg)
        radius = cfg.robot.radius + cfg.margin
        default = default_obstacle_threshold(model)
        inside = obstacle_densities(model, world)
        for kind, sel in (("transparent", True), ("opaque", False)):
            picked = [o for o in inside if o["transparent"] == sel]
            if picked:
                sigma = np.concatenate([o["sigma"] for o in picked])
                stats = {"median": float(np.median(sigma)),
                         "share_at_dex": float((sigma >= DEX_THRESHOLD).mean())}
                rows.append({"scene": name, "map": f"inside {kind}", **stats})
                print(f"{name}: density inside the {len(picked)} {kind} obstacles: median "
                      f"{stats['median']:.2f} /m, {stats['share_at_dex']:.1%} of the points at "
                      f"{DEX_THRESHOLD:g} /m or more")
        level = min(glass_thresholds + thresholds)
        profile = free_floor_profile(model, truth, level)
        rows.append({"scene": name, "map": "free floor profile", "level": level,
                     "heights": PROFILE_HEIGHTS.tolist(), "share": profile})
        print(f"{name}: share of the free floor (> {PROFILE_CLEARANCE} m from obstacles) at "
              f"{level:g} /m or more, by height: " + ", ".join(
                  f"{z:.2f} m {v:.0%}" for z, v in zip(PROFILE_HEIGHTS, profile)))
        for t in sorted(set(thresholds + [default])):
            fmap = field_floor_map(model, world, replace(cfg, threshold=t))
            rows.append({"scene": name, "map": "nerf", "threshold": t, "default": t == default,
                         **map_agreement(fmap, truth, radius, glass)})
        for g in glass_thresholds:
            fmap = field_floor_map(model, world, replace(cfg, glass_threshold=g))
            rows.append({"scene": name, "map": "nerf+glass", "threshold": default,
                         "glass_threshold": g, "glass_halo": args.glass_halo,
                         "default": False,
                         **map_agreement(fmap, truth, radius, glass)})
        fmap = sensor_floor_map(ensure_capture(cfg, seed), world, cfg)
        rows.append({"scene": name, "map": "sensor", "threshold": None, "default": False,
                     **map_agreement(fmap, truth, radius, glass)})
    finally:
        world.close()

print("| room | map | threshold (1/m) | " + " | ".join(KEYS) + " |")
print("|---|---|---|" + "---|" * len(KEYS))
for r in rows:
    if r["map"].startswith("inside") or r["map"] == "free floor profile":
        continue
    t = "" if r["threshold"] is None else f"{r['threshold']:.1f}" + (" (default)" if r["default"] else "")
    if "glass_threshold" in r:
        t += f" + {r['glass_threshold']:g} from {args.glass_clearance:g} m, " \
            f"{args.glass_halo:g} m from it"
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
