"""One benchmark point, measured in a process of its own: train, evaluate, mesh, compare.

A point is a plain JSON-able dict (see :func:`nerfbot.bench.sweep.expand_points`); its result is
another. Executors run :func:`run_point` in a fresh process per point: the local executor as
``python -m nerfbot.bench.point RUN_DIR`` (reads ``RUN_DIR/point.json``, writes
``RUN_DIR/result.json``), the Ray executor as a task in a worker used once.

Peak memory is the process's resident-set high-water mark (``VmHWM``) measured around training
and evaluation: it is reset just before the model is built (``/proc/self/clear_refs``, Linux),
so it covers the model, optimiser, batches and renders plus what the process already held (the
loaded dataset, libraries). Where the reset is unavailable it is the whole process's
``ru_maxrss``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch

from nerfbot.data import load_dataset
from nerfbot.data.writers import write_json_atomic
from nerfbot.eval.evaluation import evaluate
from nerfbot.methods import bake_model, bake_option_names, get_method, option_names
from nerfbot.models.base import num_params
from nerfbot.ops.runtime import keep_freed_memory
from nerfbot.query.meshing import compare_meshes, field_mesh
from nerfbot.train.auto import choose_for_dataset
from nerfbot.train.baked_runs import baked_size_mb
from nerfbot.train.checkpoints import CHECKPOINT
from nerfbot.train.trainer import TrainConfig, Trainer
from sims.articulated import DEFAULT_VIEWS_PER_CONFIG, capture_articulated
from sims.capture import capture
from sims.dynamic import capture_dynamic
from sims.geometry import capture_geometry
from sims.rigs import default_rig, make_test_rig
from sims.sequence import scene_capture_kind, sequence_rig

log = logging.getLogger(__name__)

POINT_FILE, RESULT_FILE, LOG_FILE = "point.json", "result.json", "log.txt"


# -- datasets ----------------------------------------------------------------------------------
def capture_builtin(spec: dict, out: Path, progress: bool = False) -> Path:
    """Capture built-in scene ``spec["scene"]`` at ``spec["size"]`` pixels (square) with
    ``spec["views"]`` train and ``spec["test_views"]`` test views (rig seed ``spec["seed"]``).
    Dynamic and articulated scenes are captured over time / joint configurations with their
    capture defaults (a monocular rollout; 4 views per configuration), as ``nerfbot capture``
    does; ``views`` / ``test_views`` apply to static scenes only."""
    size = int(spec["size"])
    kind = scene_capture_kind(spec["scene"])
    if kind == "dynamic":
        rig = sequence_rig(spec["scene"], "monocular", size=size, seed=int(spec["seed"]))
        return capture_dynamic(spec["scene"], rig, Path(out), progress=progress)
    if kind == "articulated":
        rig = sequence_rig(spec["scene"], "multiview", DEFAULT_VIEWS_PER_CONFIG, size=size,
                           seed=int(spec["seed"]))
        return capture_articulated(spec["scene"], rig, Path(out), progress=progress)
    rig = default_rig(spec["scene"], count=int(spec["views"]), width=size, height=size,
                      seed=int(spec["seed"]))
    test = make_test_rig(rig, int(spec["test_views"])) if spec["test_views"] > 0 else None
    return capture(spec["scene"], rig, test, Path(out), progress=progress)


def capture_cache_dir() -> Path:
    """Where a worker captures a built-in scene the driver's folder does not reach:
    ``$NERFBOT_CACHE/bench-captures`` (default ``~/.cache/nerfbot/bench-captures``)."""
    base = os.environ.get("NERFBOT_CACHE") or Path.home() / ".cache" / "nerfbot"
    return Path(base) / "bench-captures"


def ensure_dataset(point: dict) -> Path:
    """The dataset folder of ``point``: its ``data_path`` when it exists on this machine, else
    (built-in scenes, e.g. on a Ray node without the driver's disk) a capture of the same spec
    in :func:`capture_cache_dir`, made once per machine."""
    path = Path(point["data_path"])
    if path.exists():
        return path
    spec = point.get("capture")
    if spec is None:
        raise FileNotFoundError(f"{path}: dataset not found on {platform.node()}")
    cached = capture_cache_dir() / Path(point["data_path"]).name
    if not (cached / "transforms.json").exists():
        capture_builtin(spec, cached)
    return cached


def _resize(img: Optional[np.ndarray], w: int, h: int, nearest: bool):
    if img is None:
        return None
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA
    if img.dtype == bool:
        return cv2.resize(img.astype(np.uint8), (w, h), interpolation=interp).astype(bool)
    return cv2.resize(img, (w, h), interpolation=interp)


def downscale_dataset(ds, size: int):
    """``ds`` with every frame resized so its longer side is ``size`` pixels (aspect kept);
    frames already that small are kept. Colours use area averaging; depth, masks and
    segmentation use the nearest pixel (no blending across surfaces). Intrinsics and sparse-depth
    keypoints scale along."""
    intr, sizes = ds.intrinsics.copy(), ds.sizes.copy()
    lists = {k: list(getattr(ds, k)) for k in ("images", "alphas", "depths", "masks",
                                               "segmentations", "sensor_depths")}
    keypoints = list(ds.keypoints)
    for i in range(len(ds)):
        w, h = (int(v) for v in ds.sizes[i])
        scale = size / max(w, h)
        if scale >= 1.0:
            continue
        nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
        intr[i] *= [nw / w, nh / h, nw / w, nh / h]
        sizes[i] = (nw, nh)
        for key, items in lists.items():
            if i < len(items):
                items[i] = _resize(items[i], nw, nh, nearest=key not in ("images", "alphas"))
        if i < len(keypoints) and keypoints[i] is not None:
            keypoints[i] = keypoints[i] * np.array([nw / w, nh / h, 1.0, 1.0], np.float32)
    return replace(ds, intrinsics=intr, sizes=sizes, keypoints=keypoints, **lists)


# -- memory ------------------------------------------------------------------------------------
def _status_mb(field: str) -> Optional[float]:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return None


def reset_peak_rss() -> bool:
    """Reset this process's RSS high-water mark to the current RSS (Linux); False if unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return _status_mb("VmHWM") is not None
    except OSError:
        return False


def peak_rss_mb() -> float:
    """Peak resident set size of this process, MB (since the last :func:`reset_peak_rss`)."""
    hwm = _status_mb("VmHWM")
    if hwm is not None:
        return hwm
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024.0 * 1024.0) if sys.platform == "darwin" else peak / 1024.0


# -- the point ---------------------------------------------------------------------------------
def _finite(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v


def _chamfer(model, ds, settings: dict, seed: int) -> dict:
    """Chamfer distance of the field's mesh to the capture's true geometry (see the bench docs)."""
    truth = capture_geometry(ds.manifest)
    if truth is None:
        return {"chamfer_note": "no ground-truth geometry (not a static sims capture)"}
    gt, bounds = truth
    t0 = time.perf_counter()
    mesh = field_mesh(model, settings["mesh_resolution"], settings.get("mesh_threshold"),
                      bounds=bounds)
    idx = ds.indices("train")
    cams = (ds.c2w[idx], ds.intrinsics[idx], ds.sizes[idx]) if settings.get("visible_only", True) \
        else None
    cmp = compare_meshes(mesh, gt, settings["chamfer_points"], bounds, cams, seed)
    return {"chamfer_mm": _finite(cmp["chamfer_mm"]),
            "chamfer_accuracy_mm": _finite(cmp["accuracy_mm"]),
            "chamfer_completeness_mm": _finite(cmp["completeness_mm"]),
            "mesh_faces": cmp["pred_faces"], "mesh_seconds": time.perf_counter() - t0,
            **({} if cmp["pred_faces"] else {"chamfer_note": "empty mesh: no density reaches "
                                                             "the threshold"})}


def run_point(point: dict, run_dir: Path) -> dict:
    """Train, evaluate and (optionally) mesh one point in this process; returns its result."""
    keep_freed_memory()  # first: a point runs in a subprocess or Ray worker, not via the CLI

    t_start = time.perf_counter()
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    ds = load_dataset(ensure_dataset(point))
    if point.get("size"):
        ds = downscale_dataset(ds, int(point["size"]))
    budget = point["budget"]
    steps_budget = point["budget_kind"] == "steps"
    method, options, resolved = point["method"], dict(point["options"]), {}
    if method == "auto":  # what `nerfbot train --method auto` picks for this scene

        choice = choose_for_dataset(ds)
        method = choice.method
        fixed = {k: v for k, v in options.items() if k in option_names(method)}
        options = {**choice.options, **fixed}
        resolved = {"auto_method": method, "auto_options": json.dumps(options, sort_keys=True)}
    recipe = get_method(method).baked_from
    train_method = recipe.source if recipe else method
    train_options = {k: v for k, v in options.items() if k in option_names(train_method)}
    config = TrainConfig(method=train_method, seed=int(point["seed"]),
                         max_steps=int(budget) if steps_budget else None,
                         max_seconds=None if steps_budget else float(budget),
                         options=train_options, checkpoint_every_seconds=math.inf,
                         progress=False)
    scoped = reset_peak_rss()
    rss_before = _status_mb("VmRSS")
    trainer = Trainer(ds, run_dir, config)
    summary = trainer.train()
    model = trainer.model
    metrics = evaluate(model, ds, "test", max_images=point.get("eval_images"))
    if recipe:  # bake the trained source, then measure the baked renderer against it
        source_metrics = metrics
        t_bake = time.perf_counter()
        bake_options = {k: v for k, v in options.items() if k in bake_option_names(method)}
        model, _, extra = bake_model(method, model, trainer.spec, ds, bake_options,
                                     int(point["seed"]), progress=False)
        resolved["bake_seconds"] = time.perf_counter() - t_bake
        metrics = evaluate(model, ds, "test", max_images=point.get("eval_images"))
        src_ms = source_metrics["render_ms_per_image"]
        resolved.update(
            source_method=train_method, source_psnr=_finite(source_metrics["psnr"]),
            source_render_ms_per_image=src_ms,
            render_speedup_vs_source=src_ms / metrics["render_ms_per_image"],
            psnr_change_vs_source=_finite(metrics["psnr"] - source_metrics["psnr"]),
            source_size_mb=baked_size_mb(trainer.model),
            **{f"bake_{k}": v for k, v in extra.items() if isinstance(v, (int, float, str))})
    peak = peak_rss_mb()
    ms = metrics["render_ms_per_image"]
    w, h = (int(v) for v in ds.sizes[0])
    result = {
        "key": point["key"], "status": "ok",
        "steps": summary["steps"], "train_seconds": summary["train_seconds"],
        "steps_per_second": summary["steps_per_second"],
        "peak_rss_mb": peak, "rss_before_mb": rss_before,
        "memory_scope": "train+eval" if scoped else "process",
        "render_ms_per_image": ms, "render_fps": (1e3 / ms) if ms else None,
        "psnr": _finite(metrics["psnr"]), "ssim": _finite(metrics["ssim"]),
        "psnr_non_sky": _finite(metrics["psnr_non_sky"]),
        "psnr_objects": _finite(metrics["psnr_objects"]),
        "depth_mae_m": metrics["depth_mae_m"], "depth_rmse_m": metrics["depth_rmse_m"],
        "depth_mae_objects_m": metrics["depth_mae_objects_m"],
        "num_params": num_params(model), "size_mb": baked_size_mb(model),
        "image_size": f"{w}x{h}",
        "train_views": len(ds.indices("train")), "test_views": metrics["num_images"],
        "torch_threads": torch.get_num_threads(), "host": platform.node(), **resolved,
    }
    chamfer = point.get("chamfer")
    if chamfer:
        result.update(_chamfer(model, ds, chamfer, int(point["seed"])))
    if not point.get("keep_checkpoint"):
        (run_dir / CHECKPOINT).unlink(missing_ok=True)
    result["point_seconds"] = time.perf_counter() - t_start
    return result


def run_point_dir(run_dir: Path) -> dict:
    """Run the point in ``run_dir/point.json`` and write ``run_dir/result.json``."""
    run_dir = Path(run_dir)
    point = json.loads((run_dir / POINT_FILE).read_text())
    result = run_point(point, run_dir)
    write_json_atomic(run_dir / RESULT_FILE, result, allow_nan=True)
    return result


def run_point_elsewhere(point: dict, run_root: str) -> dict:
    """A Ray task's body: run ``point`` in ``run_root/point["run_name"]`` (point.json and
    result.json written as by the local executor) when this machine has ``run_root``, else in
    a temporary folder, removed afterwards."""
    root = Path(run_root)
    if root.is_dir() and os.access(root, os.W_OK):
        run_dir = root / point["run_name"]
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / POINT_FILE).write_text(json.dumps(point, indent=2))
        return run_point_dir(run_dir)
    tmp = Path(tempfile.mkdtemp(prefix="nerfbot-bench-"))
    try:
        return run_point(point, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if len(sys.argv) != 2:
        sys.exit("usage: python -m nerfbot.bench.point RUN_DIR (holding point.json)")
    run_point_dir(Path(sys.argv[1]))
