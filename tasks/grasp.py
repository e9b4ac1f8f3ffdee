"""Depth → grasp → lift, in MuJoCo physics: how well a robot grasps glass from each depth source.

``python -m tasks.grasp --scene glassware --depth dexnerf --trials 10 --seed 0``

A trial is one randomised scene (scene seed = ``--seed`` + trial index). For each trial:

1. the scene is captured (posed RGB images, :mod:`sims.capture`) and a radiance field is trained
   on it (``ngp``), unless a cached run for the same scene seed and settings exists;
2. for every object of the scene, depth maps are taken from ``--query-views`` cameras around the
   object (a ring looking at it) from the chosen depth source:

   - ``gt``: MuJoCo's exact depth, glass opaque (the planner's own ceiling);
   - ``sensor``: a simulated RGB-D sensor (:mod:`sims.sensor`) that sees through glass;
   - ``nerf``: the field's expected depth;
   - ``dexnerf``: the field's threshold depth (Dex-NeRF) at density ``--threshold``; by default
     the threshold is calibrated on a held-out scene (the best threshold on its transparent
     pixels, :func:`nerfbot.eval.depth_eval.depth_mode_sweep`), never on the trial scenes;

3. the depth maps become one world-frame point cloud with normals (:mod:`nerfbot.ops.pointcloud`),
   the antipodal planner (:mod:`tasks.planner`) picks the best grasp near the object, and the
   gripper executes it in physics from the scene's resting state (:mod:`tasks.execute`).
   Success: the object is lifted by at least 10 cm and held for 2 s.

Outputs in ``--out``: ``log.json`` (every attempt, its grasp and outcome), ``summary.json``,
``success.png`` (success rate per object and source), and one PNG per attempt in ``trials/``
(query view | the source's depth | the scene after the hold).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import cv2
import mujoco
import numpy as np
from tqdm import tqdm

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from nerfbot.app.cli import parse_option
from nerfbot.data import load_dataset
from nerfbot.data.writers import write_json_atomic
from nerfbot.eval.depth_eval import (DEFAULT_THRESHOLDS, depth_mode_sweep, plot_threshold_sweep,
                                     pool_sweeps, sweep_from_dict)
from nerfbot.ops.cameras import Cameras, look_at
from nerfbot.ops.pointcloud import cloud_arrays, depth_to_cloud, fuse_clouds
from nerfbot.query.export import colorize_depth, save_image
from nerfbot.query.render import depth
from nerfbot.query.semantic import locate_class
from nerfbot.train.checkpoints import CHECKPOINT
from nerfbot.train.labelling import LabelTrainConfig, label_run
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer
from sims.camera import CaptureCamera
from sims.capture import capture
from sims.gripper import add_gripper
from sims.manifest import declared_objects, geom_name, rendered_geoms
from sims.rigs import default_rig, make_test_rig
from sims.scene import CAPTURE_CAMERA, resolve_scene
from sims.sensor import DepthSensorModel
from tasks.execute import ExecutionResult, execute_grasp, settle
from tasks.grasp_config import CALIBRATION_SEED, Attempt, GraspTaskConfig
from tasks.grasp_pose import Grasp
from tasks.grasp_report import format_depth_report, format_table, plot_success, summarize
from tasks.planner import plan_grasps


log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------ scene + field
def scene_name(cfg: GraspTaskConfig, scene_seed: int) -> str:
    return f"{cfg.scene}:{scene_seed}"


def scene_folder(cfg: GraspTaskConfig, scene_seed: int) -> Path:
    """Cache folder of one scene seed's capture and runs."""
    return (Path(cfg.cache) / f"{cfg.scene}-{scene_seed}" /
            f"{cfg.capture_size}px-{cfg.capture_views}v")


def ensure_capture(cfg: GraspTaskConfig, scene_seed: int) -> Path:
    """The scene's capture (RGB + depth + segmentation + sensor depth), captured if missing."""
    out = scene_folder(cfg, scene_seed) / "data"
    if (out / "transforms.json").exists():
        return out
    name = scene_name(cfg, scene_seed)
    rig = default_rig(name, count=cfg.capture_views, width=cfg.capture_size,
                      height=cfg.capture_size, seed=scene_seed)
    capture(name, rig, make_test_rig(rig, cfg.capture_test_views), out, progress=cfg.progress,
            sensor=DepthSensorModel(transparent=cfg.sensor_mode, seed=scene_seed))
    return out


def run_name(cfg: GraspTaskConfig) -> str:
    """Run folder name: method, budget and options, e.g. ``ngp-300s`` or
    ``ngp-300s-distortion_weight=0.01``."""
    opts = "".join(f"-{k}={v}" for k, v in sorted(cfg.train_options.items()))
    budget = f"{cfg.train_steps}steps" if cfg.train_steps else f"{cfg.train_seconds:g}s"
    return f"{cfg.method}-{budget}{opts}"


def ensure_trained(cfg: GraspTaskConfig, scene_seed: int) -> Path:
    """A run of ``cfg.method`` trained ``cfg.train_steps`` steps (or ``cfg.train_seconds``) on the
    scene's capture; trained (or resumed after an interruption) if it is missing or incomplete."""
    data = ensure_capture(cfg, scene_seed)
    run = scene_folder(cfg, scene_seed) / run_name(cfg)
    done = run / "done.json"
    if done.exists():
        return run
    ds = load_dataset(data)
    budget = (dict(max_steps=cfg.train_steps) if cfg.train_steps
              else dict(max_seconds=cfg.train_seconds))
    trainer = Trainer(ds, run, TrainConfig(method=cfg.method, **budget, seed=scene_seed,
                                           options=dict(cfg.train_options),
                                           device=cfg.device, progress=cfg.progress))
    if (run / CHECKPOINT).exists():
        trainer.load()
    summary = trainer.train()
    write_json_atomic(done, summary)
    return run


def ensure_labelled(cfg: GraspTaskConfig, scene_seed: int) -> Path:
    """The scene's run with a label head trained on its frozen field
    (:func:`nerfbot.train.labelling.label_run`, full label maps of the capture), made if
    missing."""
    run = ensure_trained(cfg, scene_seed)
    labelled = run.with_name(run.name + "-labels")
    if (labelled / CHECKPOINT).exists():
        return labelled
    model, info = load_model(run, cfg.device)
    data = ensure_capture(cfg, scene_seed)
    label_run(model, info, load_dataset(data), data, labelled,
              LabelTrainConfig(seed=scene_seed), progress=cfg.progress)
    return labelled


def calibrate_threshold(cfg: GraspTaskConfig) -> dict:
    """Best Dex-NeRF threshold on the transparent pixels of the held-out calibration scene
    (cached in ``calibration.json`` beside its run); returns the sweep summary."""
    run = ensure_trained(cfg, CALIBRATION_SEED)
    path = run / "calibration.json"
    if path.exists():
        return json.loads(path.read_text())
    model, _ = load_model(run, cfg.device)
    ds = load_dataset(scene_folder(cfg, CALIBRATION_SEED) / "data")
    sweep = depth_mode_sweep(model, ds, "test", progress=cfg.progress)
    best = sweep.best_threshold["transparent"]
    if best is None:
        raise RuntimeError(f"{run}: no threshold gives depth on enough transparent pixels")
    plot_threshold_sweep(sweep, run / "threshold_sweep.png",
                         title=f"{cfg.scene} seed {CALIBRATION_SEED} (calibration)")
    result = {"threshold": best, "sweep": sweep.to_dict()}
    write_json_atomic(path, result)
    return result


def depth_report(cfg: GraspTaskConfig) -> dict:
    """Depth accuracy of the trial scenes' fields on their test views, pooled over scenes:
    expected / median / threshold depth (every threshold of the default sweep plus the
    calibrated one) and the capture's simulated sensor, on transparent-object, opaque-object and
    scene pixels. Writes ``depth_report.json`` and ``depth_sweep.png`` into ``cfg.out``."""
    threshold = cfg.threshold if cfg.threshold is not None else calibrate_threshold(cfg)["threshold"]
    thresholds = sorted(set(DEFAULT_THRESHOLDS) | {float(threshold)})
    sweeps = []
    for trial in range(cfg.trials):
        seed = cfg.seed + trial
        run = ensure_trained(cfg, seed)
        cache = run / "depth_sweep.json"
        if cache.exists() and json.loads(cache.read_text())["thresholds"] == thresholds:
            sweeps.append(sweep_from_dict(json.loads(cache.read_text())))
            continue
        model, _ = load_model(run, cfg.device)
        ds = load_dataset(scene_folder(cfg, seed) / "data")
        sweep = depth_mode_sweep(model, ds, "test", thresholds, progress=cfg.progress)
        write_json_atomic(cache, sweep.to_dict())
        sweeps.append(sweep)
    pooled = pool_sweeps(sweeps)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    plot_threshold_sweep(pooled, out / "depth_sweep.png",
                         title=f"{cfg.scene} seeds {cfg.seed}-{cfg.seed + cfg.trials - 1}, test views")
    at = thresholds.index(float(threshold))
    report = {"scene": cfg.scene, "seeds": [cfg.seed, cfg.seed + cfg.trials - 1],
              "threshold": threshold, "num_images": pooled.num_images}
    for c in ("transparent", "opaque_objects", "scene"):
        report[c] = {**pooled.modes[c], f"threshold_{threshold:g}": pooled.threshold[c][at],
                     "best_threshold": pooled.best_threshold[c]}
    report["sweep"] = pooled.to_dict()
    write_json_atomic(out / "depth_report.json", report)
    return report


# ------------------------------------------------------------------------------ physics world
class World:
    """The scene with a capture camera and the gripper, compiled once; its resting state."""

    def __init__(self, scene: str, query_size: int, query_fov: float):
        path = resolve_scene(scene)
        spec = mujoco.MjSpec.from_file(str(path))
        spec.worldbody.add_camera(name=CAPTURE_CAMERA, pos=[0, 0, 0], quat=[1, 0, 0, 0])
        add_gripper(spec)
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        settle(self.model, self.data, 0.5)
        self.rest_qpos = self.data.qpos.copy()
        self.rest_qvel = self.data.qvel.copy()
        self.rest_act = self.data.act.copy()
        self.camera = CaptureCamera(self.model, self.data, query_size, query_size, query_fov)
        self.transparent = sorted({int(g.objid) for g in rendered_geoms(self.model, self.data)
                                   if g.rgba[3] < 1.0})

    def reset(self) -> None:
        """Back to the resting state (objects settled, gripper parked)."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self.rest_qpos
        self.data.qvel[:] = self.rest_qvel
        self.data.act[:] = self.rest_act
        mujoco.mj_forward(self.model, self.data)

    def object_position(self, name: str) -> np.ndarray:
        return self.data.body(name).xpos.copy()

    def close(self) -> None:
        self.camera.close()


def query_poses(center: np.ndarray, cfg: GraspTaskConfig) -> list[np.ndarray]:
    """c2w poses of a ring of ``query_views`` cameras looking at ``center`` (3,)."""
    poses = []
    el = math.radians(cfg.query_elevation)
    for k in range(cfg.query_views):
        az = 2 * math.pi * k / cfg.query_views
        eye = center + cfg.query_radius * np.array([math.cos(el) * math.cos(az),
                                                    math.cos(el) * math.sin(az), math.sin(el)])
        poses.append(look_at(eye, center))
    return poses


# ------------------------------------------------------------------------------ depth sources
@dataclass
class DepthContext:
    """What a depth source may use: the world at rest and, for field sources, a trained model."""

    world: World
    model: Optional[object] = None
    threshold: Optional[float] = None
    sensor: Optional[DepthSensorModel] = None


def _gt_depth(ctx: DepthContext, poses: Sequence[np.ndarray]) -> list[np.ndarray]:
    return [ctx.world.camera.render(p).depth for p in poses]


def _sensor_depth(ctx: DepthContext, poses: Sequence[np.ndarray]) -> list[np.ndarray]:
    cam, out = ctx.world.camera, []
    for k, p in enumerate(poses):
        frame = cam.render(p)
        behind = cam.depth_without(ctx.world.transparent) if ctx.world.transparent else frame.depth
        glass = np.isin(frame.segmentation, ctx.world.transparent)
        out.append(ctx.sensor.read(behind, glass, view_index=k))
    return out


def _field_cameras(ctx: DepthContext, poses: Sequence[np.ndarray]) -> Cameras:
    k = ctx.world.camera.intrinsics
    n = len(poses)
    return Cameras.from_numpy(np.stack(poses), [[k.fx, k.fy, k.cx, k.cy]] * n,
                              [[k.width, k.height]] * n)


def _nerf_depth(ctx: DepthContext, poses: Sequence[np.ndarray]) -> list[np.ndarray]:
    cams = _field_cameras(ctx, poses)
    return [depth(ctx.model, cams, i, mode="expected") for i in range(len(poses))]


def _dexnerf_depth(ctx: DepthContext, poses: Sequence[np.ndarray]) -> list[np.ndarray]:
    cams = _field_cameras(ctx, poses)
    return [depth(ctx.model, cams, i, mode="threshold", threshold=ctx.threshold)
            for i in range(len(poses))]


#: Depth source name -> (needs a trained field, function(context, poses) -> z-depth maps).
DEPTH_SOURCES: dict[str, tuple[bool, Callable]] = {
    "gt": (False, _gt_depth),
    "sensor": (False, _sensor_depth),
    "nerf": (True, _nerf_depth),
    "dexnerf": (True, _dexnerf_depth),
}


def cloud_from_depths(depths: Sequence[np.ndarray], poses: Sequence[np.ndarray],
                      world: World, center: np.ndarray, crop_radius: float,
                      edge_jump: Optional[float] = None):
    """Fused world-frame cloud (points, normals) of the depth maps, cropped around ``center``."""
    k = world.camera.intrinsics
    clouds = [depth_to_cloud(d, k.fx, k.fy, k.cx, k.cy, p, max_depth=3.0, normal_radius=0.012,
                             max_edge_jump=edge_jump)
              for d, p in zip(depths, poses)]
    points, normals = cloud_arrays(fuse_clouds(clouds, voxel=0.003))
    keep = np.linalg.norm(points[:, :2] - center[:2], axis=1) <= crop_radius
    return points[keep], (normals[keep] if normals is not None else None)


def attempt_object(world: World, ctx: DepthContext, source: str, name: str, trial: int,
                   scene_seed: int, cfg: GraspTaskConfig, image_path: Optional[Path],
                   located: Optional[np.ndarray] = None) -> Attempt:
    """Query depth around object ``name``, plan, execute from rest, report. ``located``: where
    the field's labels put the object ((3,) metres; None: the simulator's body position)."""
    t0 = time.perf_counter()
    world.reset()
    base = world.object_position(name) if located is None else np.asarray(located, float)
    glass = any(world.model.geom_bodyid[g] == world.model.body(name).id for g in world.transparent)
    center = base + np.array([0.0, 0.0, 0.06])
    poses = query_poses(center, cfg)
    depths = DEPTH_SOURCES[source][1](ctx, poses)
    points, normals = cloud_from_depths(depths, poses, world, center, cfg.crop_radius,
                                        cfg.edge_jump)
    grasps = plan_grasps(points, normals, target=base[:2]) if len(points) else []
    attempt = Attempt(trial, scene_seed, name, glass, source, False, "", len(points))
    if located is not None:
        attempt.located_error_m = float(np.linalg.norm(located[:2]
                                                       - world.object_position(name)[:2]))
    if not grasps:
        attempt.reason = "no grasp found"
    else:
        best: Grasp = grasps[0]
        world.reset()
        result: ExecutionResult = execute_grasp(world.model, world.data, best, name)
        attempt.success, attempt.reason = bool(result.success), result.reason
        attempt.grasp, attempt.lift_height = best.to_dict(), float(result.lift_height)
    if image_path is not None:
        _attempt_sheet(world, poses[0], depths[0], image_path, attempt)
    attempt.seconds = time.perf_counter() - t0
    return attempt


def _attempt_sheet(world: World, pose: np.ndarray, depth_map: np.ndarray, path: Path,
                   attempt: Attempt) -> None:
    """PNG: the scene at rest from the first query view | the source's depth there | the scene
    now (after the hold), gripper visible."""
    cam = world.camera
    after = cam.option.geomgroup[3]
    cam.option.geomgroup[3] = 1
    try:
        now = cam.render(pose).rgb
    finally:
        cam.option.geomgroup[3] = after
    state = world.data.qpos.copy()
    world.reset()
    rest = cam.render(pose).rgb
    world.data.qpos[:] = state
    mujoco.mj_forward(world.model, world.data)
    sheet = np.concatenate([rest, colorize_depth(depth_map), now], axis=1)
    label = f"{attempt.object} [{attempt.depth_source}] {'OK' if attempt.success else 'FAIL'}"
    sheet = np.ascontiguousarray(sheet)
    cv2.putText(sheet, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                cv2.LINE_AA)
    save_image(path, sheet)


# ------------------------------------------------------------------------------ experiment
def select_objects(world_model: mujoco.MjModel, manifest_objects: list[str],
                   transparent: set[str], which: str) -> list[str]:
    """Object names of ``which`` ("glass", "opaque", "all" or comma-separated names)."""
    if which == "all":
        return list(manifest_objects)
    if which == "glass":
        return [o for o in manifest_objects if o in transparent]
    if which == "opaque":
        return [o for o in manifest_objects if o not in transparent]
    names = [n.strip() for n in which.split(",") if n.strip()]
    unknown = [n for n in names if n not in manifest_objects]
    if unknown:
        raise ValueError(f"unknown objects {unknown}; the scene has {manifest_objects}")
    return names


def run_experiment(cfg: GraspTaskConfig, sources: Sequence[str]) -> dict:
    """Run ``cfg.trials`` trials for every depth source in ``sources``; write logs and images.

    Returns {source: summary dict} (see :func:`summarize`)."""
    for s in sources:
        if s not in DEPTH_SOURCES:
            raise ValueError(f"unknown depth source {s!r} (choose from {list(DEPTH_SOURCES)})")
    out = Path(cfg.out)
    (out / "trials").mkdir(parents=True, exist_ok=True)
    needs_field = any(DEPTH_SOURCES[s][0] for s in sources) or cfg.target is not None
    threshold, calibration = cfg.threshold, None
    if "dexnerf" in sources and threshold is None:
        calibration = calibrate_threshold(cfg)
        threshold = calibration["threshold"]
        log.info("Dex-NeRF threshold %.3g /m (calibrated on scene seed %d)", threshold,
                 CALIBRATION_SEED)
    attempts: list[Attempt] = []
    for trial in range(cfg.trials):
        scene_seed = cfg.seed + trial
        model = None
        if needs_field:
            run = ensure_labelled(cfg, scene_seed) if cfg.target else \
                ensure_trained(cfg, scene_seed)
            model, _ = load_model(run, cfg.device)
        world = World(scene_name(cfg, scene_seed), cfg.query_size, cfg.query_fov)
        try:
            transparent = {geom_name(world.model, g) for g in world.transparent}
            objects = select_objects(world.model, declared_objects(world.model), transparent,
                                     cfg.target or cfg.objects)
            located = None
            if cfg.target is not None:
                # glass counts as occupied at the Dex-NeRF threshold, when there is one
                found = locate_class(model, cfg.target, threshold)
                if not len(found.points):
                    raise ValueError(f"scene {scene_seed}: the field labels no occupied point "
                                     f"{cfg.target!r}")
                located = found.centre
                log.info("%s located by labels at %s (%d points)", cfg.target,
                         np.round(located, 3).tolist(), len(found.points))
            ctx = DepthContext(world, model, threshold,
                               DepthSensorModel(transparent=cfg.sensor_mode, seed=scene_seed))
            jobs = [(s, o) for s in sources for o in objects]
            bar = tqdm(jobs, desc=f"trial {trial + 1}/{cfg.trials} (scene {scene_seed})",
                       unit="grasp", disable=not cfg.progress)
            for source, name in bar:
                image = out / "trials" / f"{source}_seed{scene_seed}_{name}.png"
                attempts.append(attempt_object(world, ctx, source, name, trial, scene_seed, cfg,
                                               image, located))
                bar.set_postfix(ok=sum(a.success for a in attempts if a.depth_source == source))
        finally:
            world.close()
        write_json_atomic(out / "log.json", {"config": _config_dict(cfg), "threshold": threshold,
                                             "attempts": [asdict(a) for a in attempts]})
    summaries = {s: summarize([a for a in attempts if a.depth_source == s], s, cfg, threshold)
                 for s in sources}
    write_json_atomic(out / "summary.json", {"config": _config_dict(cfg), "threshold": threshold,
                                             "calibration_seed": CALIBRATION_SEED
                                             if calibration else None, "sources": summaries})
    plot_success(summaries, out / "success.png",
                 title=f"{cfg.scene}, {cfg.trials} scenes (seeds {cfg.seed}-"
                       f"{cfg.seed + cfg.trials - 1}): lifted 10 cm and held 2 s")
    return summaries


def _config_dict(cfg: GraspTaskConfig) -> dict:
    d = asdict(cfg)
    d["cache"], d["out"] = str(cfg.cache), str(cfg.out)
    return d


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tasks.grasp",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="glassware", help="scene family (default glassware)")
    parser.add_argument("--depth", default="dexnerf",
                        help=f"depth source(s), comma-separated: {', '.join(DEPTH_SOURCES)}")
    parser.add_argument("--trials", type=int, default=10, help="scenes (seeds) to try")
    parser.add_argument("--seed", type=int, default=0, help="scene seed of the first trial")
    parser.add_argument("--objects", default="all", help="glass | opaque | all | names")
    parser.add_argument("--target", default=None, metavar="NAME",
                        help="grasp object NAME, found by the field's labels (a label head "
                             "trained on each scene's run) instead of the simulator's position")
    parser.add_argument("--threshold", type=float, default=None,
                        help="Dex-NeRF density threshold, 1/m (default: calibrate on a "
                             f"held-out scene, seed {CALIBRATION_SEED})")
    parser.add_argument("--train-steps", type=int, default=GraspTaskConfig.train_steps,
                        help="training steps per scene (default %(default)s; 0 = use "
                             "--train-seconds)")
    parser.add_argument("--train-seconds", type=float, default=GraspTaskConfig.train_seconds,
                        help="training time per scene when --train-steps is 0")
    parser.add_argument("--option", action="append", default=[], type=parse_option,
                        metavar="KEY=VALUE",
                        help="method option of the training runs (repeatable)")
    parser.add_argument("--capture-size", type=int, default=GraspTaskConfig.capture_size)
    parser.add_argument("--capture-views", type=int, default=GraspTaskConfig.capture_views)
    parser.add_argument("--query-views", type=int, default=GraspTaskConfig.query_views)
    parser.add_argument("--sensor", choices=("behind", "invalid"), default="behind",
                        help="what the simulated sensor returns on glass (default behind)")
    parser.add_argument("--cache", type=Path, default=None, help="capture/run cache folder")
    parser.add_argument("--out", type=Path, default=Path("grasp_out"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--depth-report", action="store_true",
                        help="instead of grasping: depth accuracy per depth mode on the trial "
                             "scenes' test views (transparent / opaque / scene pixels)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object (a single source) or {source: object}")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.trials < 1:
        parser.error("--trials must be at least 1")
    cfg = GraspTaskConfig(scene=args.scene, depth=args.depth, trials=args.trials, seed=args.seed,
                          objects=args.objects, threshold=args.threshold, target=args.target,
                          train_steps=args.train_steps or None,
                          train_seconds=args.train_seconds, capture_size=args.capture_size,
                          train_options={**GraspTaskConfig().train_options, **dict(args.option)},
                          capture_views=args.capture_views, query_views=args.query_views,
                          sensor_mode=args.sensor, out=args.out, device=args.device,
                          progress=not args.no_progress)
    if args.cache is not None:
        cfg = replace(cfg, cache=args.cache)
    sources = [s.strip() for s in args.depth.split(",") if s.strip()]
    if args.depth_report:
        report = depth_report(cfg)
        if args.json:
            print(json.dumps({k: v for k, v in report.items() if k != "sweep"}))
        else:
            print(format_depth_report(report))
        return 0
    try:
        summaries = run_experiment(cfg, sources)
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")
    if args.json:
        print(json.dumps(summaries[sources[0]] if len(sources) == 1 else summaries))
    else:
        print(format_table(summaries))
        print(f"logs and per-attempt images in {cfg.out}")
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    raise SystemExit(main())
