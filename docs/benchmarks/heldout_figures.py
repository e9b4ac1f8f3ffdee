"""Figures of BENCHMARKS.md, section 4: held-out frames, ground truth beside each method's render.

    python docs/benchmarks/heldout_figures.py BENCH_DIR

BENCH_DIR holds the captures ``mono``, ``multi``, ``art`` and the runs ``run_<capture>_<method>``
made by the commands in BENCHMARKS.md. Writes ``docs/benchmarks/<capture>_heldout.png``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import sims  # noqa: F401  (MUJOCO_GL before mujoco)
from nerfbot.data import load_dataset
from nerfbot.data.conditioning import dataset_conditioning, frame_conditions
from nerfbot.ops.metrics import psnr
from nerfbot.query.export import labelled_row, save_image
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

METHODS = {"mono": ("dnerf", "tnerf", "ngp"), "multi": ("dnerf", "tnerf", "ngp"),
           "art": ("articulated", "tnerf", "ngp")}


def _label(ds, i, cond) -> str:
    if cond.kind == "time":
        return f"t = {float(ds.times[i]):.2f}"
    return ", ".join(f"{n.split('_')[0]} {v:.2f}" for n, v in ds.joints[i].items())


def heldout_sheet(bench: Path, capture: str, rows: int = 4) -> np.ndarray:
    ds = load_dataset(bench / capture)
    cond = dataset_conditioning(ds, tracks=False)
    conds = frame_conditions(ds, cond)
    models = {m: load_model(bench / f"run_{capture}_{m}")[0] for m in METHODS[capture]}
    test = ds.indices("test")
    picks = [test[k] for k in np.linspace(0, len(test) - 1, rows).round().astype(int)]
    out = []
    for i in picks:
        gt = ds.image_float(i)
        images, labels = [gt], [_label(ds, i, cond)]
        for name, model in models.items():
            rgb = render_image(model, ds.cameras([i]), 0, cond=conds[i])["rgb"]
            images.append(rgb)
            labels.append(f"{name} {psnr(rgb, gt):.1f} dB")
        out.append(labelled_row(images, labels, scale=2))
    return np.vstack(out)


def main(bench: str) -> None:
    here = Path(__file__).resolve().parent
    for capture in METHODS:
        path = save_image(here / f"{capture}_heldout.png", heldout_sheet(Path(bench), capture))
        print("wrote", path)


if __name__ == "__main__":
    main(sys.argv[1])
