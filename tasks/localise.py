"""How far off may the guess be? The basin of convergence of the localisers, in a room.

``python -m tasks.localise --scene room --scenes 3 --views 10 --estimators inerf,wide [--planar]``

For each of ``--scenes`` room seeds (``--seed`` on), with the field of :mod:`tasks.navigate`
(same cache: captured and trained if missing):

1. ``--views`` robot poses are drawn where the base stands on the true floor map, and the
   robot's camera image at each is rendered by MuJoCo (never a training image);
2. for each perturbation level (``--levels``: translation metres and rotation degrees, applied
   exactly, in random directions; with ``--planar`` horizontal moves and turns about the
   vertical, the ground robot's pose model, which the estimators then use too) each estimator
   starts from the true camera pose so perturbed: ``inerf``
   (:func:`nerfbot.query.localise.inerf`) and ``wide``
   (:func:`nerfbot.query.localise.localise_wide`);
3. success: the estimate within 2 cm and 1 degree of the truth; "loose": within 5 cm and 2
   degrees, what the drive of :mod:`tasks.navigate` tolerates.

Outputs in ``--out``: ``log.json`` (every estimate), ``summary.json`` (success rate and median
seconds per estimator and level) and ``basin.png`` (success against the perturbation).
"""

from __future__ import annotations

import argparse
import json
import logging
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm import tqdm

from nerfbot.app.cli import parse_option
from nerfbot.data.writers import write_json_atomic
from nerfbot.query.localise import (InerfConfig, WideConfig, inerf, localise_wide, perturb,
                                    pose_error)
from nerfbot.train.runs import load_model
from tasks.navigate import (NAV_FIELD_OPTIONS, NavTaskConfig, World, ensure_trained,
                            free_base_poses)

log = logging.getLogger(__name__)

#: Estimators by name: (function, its config class).
ESTIMATORS = {"inerf": (inerf, InerfConfig), "wide": (localise_wide, WideConfig)}

#: (translation m, rotation degrees) levels of the default basin sweep.
DEFAULT_LEVELS = ((0.02, 1.0), (0.05, 3.0), (0.1, 10.0), (0.2, 15.0), (0.3, 20.0), (0.5, 30.0))
#: Success: the estimate is this close to the true pose (metres, degrees).
SUCCESS_TRANSLATION = 0.02
SUCCESS_ROTATION = 1.0
#: A looser criterion, what the drive tolerates (it stops within 5 cm of a waypoint).
LOOSE_TRANSLATION = 0.05
LOOSE_ROTATION = 2.0


def robot_views(world: World, cfg: NavTaskConfig, count: int, seed: int) -> list[np.ndarray]:
    """``count`` base poses (x, y, yaw) where the base stands on the true floor map, seeded."""
    return free_base_poses(world, cfg, count, np.random.default_rng(seed))


def estimator_config(name: str, planar: bool, options: dict | None = None):
    """The config of estimator ``name`` with the pose model ``planar`` and ``options``, fields
    of its config class (:class:`~nerfbot.query.localise.InerfConfig` or
    :class:`~nerfbot.query.localise.WideConfig`); ValueError naming an unknown field."""
    options = dict(options or {})
    config_class = ESTIMATORS[name][1]
    known = {f.name for f in fields(config_class)} - {"planar"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"--estimator-option: {name} has no {unknown}; choose from "
                         f"{', '.join(sorted(known))}")
    return config_class(planar=planar, **options)


def split_estimator_options(items, estimators) -> dict:
    """``[(key, value)]`` of ``--estimator-option`` -> {estimator: {field: value}}: a key
    ``NAME.FIELD`` goes to estimator NAME, a plain ``FIELD`` to every selected estimator whose
    config has it; ValueError for a key no selected estimator takes."""
    out: dict[str, dict] = {name: {} for name in estimators}
    for key, value in items:
        name, _, field_name = key.rpartition(".")
        names = [name] if name else [e for e in estimators if field_name in
                                     {f.name for f in fields(ESTIMATORS[e][1])}]
        if not names or any(n not in out for n in names):
            raise ValueError(f"--estimator-option {key}: no selected estimator "
                             f"({', '.join(estimators)}) takes it")
        for n in names:
            out[n][field_name] = value
    return out


def run_basin(cfg: NavTaskConfig, views: int, levels, estimators, out: Path,
              planar: bool = False, estimator_options: dict | None = None) -> dict:
    """Every scene, view, level and estimator; returns the summary (also written to ``out``).
    ``estimator_options`` maps an estimator's name to settings of its config
    (:func:`estimator_config`)."""
    configs = {name: estimator_config(name, planar, (estimator_options or {}).get(name))
               for name in estimators}
    records = []
    for s in range(cfg.scenes):
        seed = cfg.seed + s
        name = f"{cfg.scene}:{seed}"
        model, _ = load_model(ensure_trained(cfg, seed), cfg.device)
        world = World(name, cfg)
        try:
            poses = robot_views(world, cfg, views, seed)
            rng = np.random.default_rng(seed + 1000)
            total = len(poses) * len(levels) * len(estimators)
            bar = tqdm(total=total, desc=f"scene {s + 1}/{cfg.scenes} ({name})", unit="estimate",
                       disable=not cfg.progress)
            for k, pose in enumerate(poses):
                world.reset(*pose)
                image = world.observe()
                truth = world.camera_pose(pose)
                for t, r in levels:
                    start = perturb(truth, t, r, rng, planar=planar)
                    for est_name in estimators:
                        estimate = ESTIMATORS[est_name][0]
                        est = estimate(model, image, world.intrinsics, start, configs[est_name])
                        dt, dr = pose_error(est.c2w, truth)
                        records.append({
                            "scene": name, "view": k, "translation": t, "rotation": r,
                            "estimator": est_name, "error_m": dt, "error_deg": dr,
                            "seconds": est.seconds,
                            "success": bool(dt < SUCCESS_TRANSLATION and dr < SUCCESS_ROTATION),
                            "loose": bool(dt < LOOSE_TRANSLATION and dr < LOOSE_ROTATION)})
                        bar.update()
                        bar.set_postfix(ok=sum(x["success"] for x in records), refresh=False)
                write_json_atomic(out / "log.json", {"records": records})
            bar.close()
        finally:
            world.close()
    summary = summarize(records, levels, estimators)
    summary["pose_model"] = "planar" if planar else "6-DoF"
    write_json_atomic(out / "summary.json", summary)
    plot_basin(summary, out / "basin.png")
    return summary


def summarize(records: list[dict], levels, estimators) -> dict:
    rows = []
    for est in estimators:
        for t, r in levels:
            sel = [x for x in records if x["estimator"] == est and x["translation"] == t
                   and x["rotation"] == r]
            if not sel:
                continue
            rows.append({"estimator": est, "translation": t, "rotation": r, "n": len(sel),
                         "success_rate": sum(x["success"] for x in sel) / len(sel),
                         "loose_rate": sum(x["loose"] for x in sel) / len(sel),
                         "median_error_m": float(np.median([x["error_m"] for x in sel])),
                         "median_error_deg": float(np.median([x["error_deg"] for x in sel])),
                         "median_seconds": float(np.median([x["seconds"] for x in sel]))})
    return {"success": {"translation_m": SUCCESS_TRANSLATION, "rotation_deg": SUCCESS_ROTATION},
            "loose": {"translation_m": LOOSE_TRANSLATION, "rotation_deg": LOOSE_ROTATION},
            "rows": rows}


def plot_basin(summary: dict, path: Path) -> None:
    """Success rate against the perturbation level, one colour per estimator (solid: the
    success criterion, dashed: the loose one), seconds per estimate in the legend."""
    fig = Figure(figsize=(6.4, 4.0), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    by_est: dict[str, list] = {}
    for row in summary["rows"]:
        by_est.setdefault(row["estimator"], []).append(row)
    for i, (est, rows) in enumerate(by_est.items()):
        x = np.arange(len(rows))
        secs = np.median([r["median_seconds"] for r in rows])
        ax.plot(x, [100 * r["success_rate"] for r in rows], "o-", color=f"C{i}",
                label=f"{est} ({secs:.1f} s per estimate)")
        ax.plot(x, [100 * r.get("loose_rate", np.nan) for r in rows], "o--", color=f"C{i}",
                alpha=0.6, label=f"{est}, < 5 cm and < 2°")
        ax.set_xticks(x, [f"{100 * r['translation']:g} cm\n{r['rotation']:g}°" for r in rows])
    ax.set_ylim(-3, 103)
    ax.set_ylabel("success (< 2 cm and < 1°), %")
    ax.set_xlabel("initial error: translation, rotation")
    ax.set_title(f"pose model: {summary.get('pose_model', '6-DoF')}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def format_summary(summary: dict) -> str:
    lines = [f"{'estimator':<11} {'t cm':>5} {'r deg':>6} {'n':>4} {'success':>8} {'loose':>6} "
             f"{'err cm':>7} {'err deg':>8} {'s':>6}"]
    for r in summary["rows"]:
        lines.append(f"{r['estimator']:<11} {100 * r['translation']:>5g} {r['rotation']:>6g} "
                     f"{r['n']:>4} {r['success_rate']:>8.0%} {r['loose_rate']:>6.0%} "
                     f"{100 * r['median_error_m']:>7.2f} "
                     f"{r['median_error_deg']:>8.2f} {r['median_seconds']:>6.2f}")
    return "\n".join(lines)


def _levels(text: str):
    try:
        levels = [tuple(float(v) for v in item.split(",")) for item in text.split(";") if item]
    except ValueError:
        levels = []
    if not levels or any(len(lv) != 2 or lv[0] < 0 or lv[1] < 0 for lv in levels):
        raise argparse.ArgumentTypeError(
            f"--levels: expected 'metres,degrees;metres,degrees;...', got {text!r}")
    return levels


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tasks.localise",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="room")
    parser.add_argument("--scenes", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--views", type=int, default=10, help="robot camera views per room")
    parser.add_argument("--estimators", default="inerf,wide",
                        help=f"comma-separated, of {', '.join(ESTIMATORS)}")
    parser.add_argument("--levels", type=_levels,
                        default=list(DEFAULT_LEVELS),
                        help="perturbations 'metres,degrees;...' (default "
                             + ";".join(f"{t:g},{r:g}" for t, r in DEFAULT_LEVELS) + ")")
    parser.add_argument("--planar", action="store_true",
                        help="perturb and estimate (x, y, yaw) only, as a ground robot's pose")
    parser.add_argument("--train-steps", type=int, default=NavTaskConfig.train_steps)
    parser.add_argument("--capture-robot-views", type=float,
                        default=NavTaskConfig.capture_robot_views,
                        help="share of the capture's training views taken by the robot's camera "
                             "(0-1; the rest from the room's rig)")
    parser.add_argument("--option", action="append", default=[], type=parse_option,
                        metavar="KEY=VALUE",
                        help="field option of the training runs (repeatable), added to "
                        + ", ".join(f"{k}={v}" for k, v in NAV_FIELD_OPTIONS.items()))
    parser.add_argument("--sensor-depth-weight", type=float, default=0.0, metavar="W",
                        help="train the fields with depth supervision from the capture's "
                             "simulated depth sensor, weight W (an RGB-D robot's map; default "
                             "0: images only)")
    parser.add_argument("--estimator-option", action="append", default=[], type=parse_option,
                        metavar="[NAME.]KEY=VALUE",
                        help="setting of the estimators' configs (repeatable): NAME.KEY for one "
                             "estimator (inerf: InerfConfig, wide: WideConfig), KEY for every "
                             "selected one that has it; e.g. inerf.rays=1024, keep=6")
    parser.add_argument("--cache", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=Path("localise_out"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    estimators = [e for e in args.estimators.split(",") if e]
    unknown = [e for e in estimators if e not in ESTIMATORS]
    if unknown or not estimators:
        parser.error(f"--estimators: unknown {unknown}; choose from {', '.join(ESTIMATORS)}")
    for name in ("scenes", "views", "train_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    if not 0.0 <= args.capture_robot_views <= 1.0:
        parser.error(f"--capture-robot-views must be in [0, 1], got {args.capture_robot_views}")
    if not 0.0 <= args.sensor_depth_weight < float("inf"):
        parser.error(f"--sensor-depth-weight must be at least 0, got {args.sensor_depth_weight}")
    if args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out {args.out} is not empty: choose a new folder")
    cfg = NavTaskConfig(scene=args.scene, scenes=args.scenes, seed=args.seed,
                        train_steps=args.train_steps, device=args.device,
                        capture_robot_views=args.capture_robot_views,
                        train_options={**NAV_FIELD_OPTIONS, **dict(args.option)},
                        sensor_depth_weight=args.sensor_depth_weight,
                        progress=not args.no_progress)
    if args.cache is not None:
        cfg = replace(cfg, cache=args.cache)
    try:
        options = split_estimator_options(args.estimator_option, estimators)
        summary = run_basin(cfg, args.views, args.levels, estimators, args.out, args.planar,
                            options)
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")
    print(json.dumps(summary) if args.json else format_summary(summary))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    raise SystemExit(main())
