"""``nerfbot demo``: the whole story on the built-in tabletop, in one folder.

capture (MuJoCo) -> train ngp within a time budget -> evaluate -> renders, a depth map, a
comparison sheet (ground truth | render | depth | error) and metrics.json.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.data.outputs import check_output_folder
from nerfbot.data.pixels import depth_valid_mask
from nerfbot.data.writers import write_json_atomic
from nerfbot.eval.evaluation import evaluate
from nerfbot.models.base import num_params
from nerfbot.query.export import colorize_depth, comparison_sheet, save_image
from nerfbot.query.render import render_image
from nerfbot.train.trainer import TrainConfig, Trainer
from sims.capture import capture
from sims.rigs import default_rig, make_test_rig

log = logging.getLogger(__name__)


def run_demo(out: Path, seconds: float = 60.0, size: int = 128, views: int = 60,
             test_views: int = 10, seed: int = 0, progress: bool = True,
             overwrite: bool = False) -> dict:
    """Run the demo into ``out``; returns the metrics dict (also written to metrics.json).

    ``out`` must be new, empty, or (with ``overwrite``) an earlier demo folder holding nothing
    else (:mod:`nerfbot.data.outputs`); a demo that fails removes what it wrote."""
    folder = check_output_folder(out, "demo", overwrite=overwrite)
    with folder.writing():
        return _demo_into(folder.path, seconds, size, views, test_views, seed, progress)


def _demo_into(out: Path, seconds: float, size: int, views: int, test_views: int, seed: int,
               progress: bool) -> dict:
    """The demo, written into the prepared folder ``out``."""
    data_dir = out / "data"
    rig = default_rig("tabletop", count=views, width=size, height=size, seed=seed)
    log.info("capturing the tabletop: %d train + %d test views at %dx%d", views, test_views, size, size)
    capture("tabletop", rig, make_test_rig(rig, test_views), data_dir, progress=progress)
    ds = load_dataset(data_dir)

    checkpoints = tuple(s for s in (15, 30, 60, 120, 180, 300) if s < seconds) + (seconds,)
    config = TrainConfig(method="ngp", max_seconds=seconds, seed=seed, progress=progress,
                         eval_at_seconds=checkpoints)
    run = check_output_folder(out / "run", "run").prepare()
    trainer = Trainer(ds, run, config, evaluate_fn=lambda m: {
        "psnr": evaluate(m, ds, "test", with_ssim=False)["psnr"]})
    summary = trainer.train()

    metrics = evaluate(trainer.model, ds, "test")
    metrics.update(method="ngp", num_params=num_params(trainer.model),
                   curve=trainer.curve, **summary)
    write_json_atomic(out / "metrics.json", metrics, allow_nan=True)

    test = ds.indices("test")
    cams = ds.cameras(test)
    rows = []
    for slot, i in enumerate(test):
        img = render_image(trainer.model, cams, slot)
        save_image(out / "renders" / f"test_{slot:02d}.png", img["rgb"])
        if slot < 4:
            rows.append({"gt": ds.image_float(i), "rgb": img["rgb"], "depth": img["z_depth"],
                         "depth_valid": img["opacity"] > 0.5})
        if slot == 0:
            valid = depth_valid_mask(ds, i)
            save_image(out / "depth.png", colorize_depth(img["z_depth"], img["opacity"] > 0.5))
            np.save(out / "depth.npy", img["z_depth"].astype(np.float32))
            if valid is not None:
                save_image(out / "depth_gt.png", colorize_depth(ds.depths[i], valid))
    save_image(out / "sheet.png", comparison_sheet(rows))
    log.info("demo written to %s: metrics.json, sheet.png, depth.png, renders/", out)
    return {k: v for k, v in metrics.items() if k != "curve"} | {
        "curve": [{"train_seconds": c["train_seconds"], "psnr": round(c["psnr"], 2)}
                  for c in trainer.curve]}
