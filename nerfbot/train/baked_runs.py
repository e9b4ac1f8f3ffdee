"""``nerfbot bake``: turn a trained run into a faster renderer, written as a run of its own.

A baked renderer is a :class:`~nerfbot.models.base.Model` registered as a method (e.g.
``fastnerf_cache``, ``plenoctree_octree``), so ``nerfbot eval / render`` and every query load
it like any run. Its tensors have data-dependent sizes (only occupied cells are stored); the
loader resizes them from the checkpoint (:func:`nerfbot.models.base.resize_like_state_dict`).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

from nerfbot.data.outputs import check_output_folder
from nerfbot.data.run_dataset import run_data_fields
from nerfbot.data.writers import write_json_atomic
from nerfbot.models.base import Model, num_params
from nerfbot.train.checkpoints import CHECKPOINT, save_checkpoint

def baked_size_mb(model: Model) -> float:
    """Memory of every tensor (parameters and buffers) of ``model`` in MB (1e6 bytes)."""
    total = sum(t.numel() * t.element_size() for t in model.state_dict().values())
    return total / 1e6

def write_baked_run(model: Model, spec: dict, source_info: dict, out: Path,
                    data: Optional[Path] = None, extra: Optional[dict] = None,
                    overwrite: bool = False) -> Path:
    """Write ``model`` (built by ``spec``: method, aabb, background, options, seed,
    conditioning, and the ``dataset`` identity) as a run folder ``out`` with ``checkpoint.pt``
    (durable: :func:`nerfbot.train.checkpoints.save_checkpoint`), ``config.json`` and ``bake.json``
    (size, parameters, ``extra``); ``data`` is the dataset folder the source was trained on,
    stored absolute and relative to ``out`` (so ``nerfbot eval OUT`` finds it, also after both
    moved). Training time and step are the source run's: baking is not training. Returns the
    checkpoint path.

    ``out`` must be new, empty, or (with ``overwrite``) an earlier baked run
    (:mod:`nerfbot.data.outputs`); anything else is a FileExistsError, before anything is
    written."""
    folder = check_output_folder(out, "baked_run", overwrite=overwrite)
    out = folder.path
    ckpt = {"spec": spec, "model": model.state_dict(), "step": source_info.get("step", 0),
            "train_seconds": source_info.get("train_seconds", 0.0), "curve": [],
            "config": source_info.get("config", {})}
    path = out / CHECKPOINT
    data_fields = {"data": None} if data is None else run_data_fields(data, out)
    with folder.writing():
        save_checkpoint(ckpt, path)
        write_json_atomic(out / "config.json", {"spec": spec, "train": ckpt["config"],
                                                **data_fields}, allow_nan=True)
        report = {"method": spec["method"], "size_mb": round(baked_size_mb(model), 3),
                  "num_params": num_params(model), **(extra or {})}
        write_json_atomic(out / "bake.json", report, allow_nan=True)
    return path

def read_bake_report(run: Path) -> Optional[dict]:
    """``bake.json`` of a baked run, or None for a trained one."""
    path = Path(run) / "bake.json"
    return json.loads(path.read_text()) if path.exists() else None

