"""What each part of a ``kplanes`` run holds: the static ngp field and the moving planes.

    python docs/benchmarks/kplanes_parts.py RUN [RUN ...] [--frames 3] [--out NAME]

For a few training frames of the run's dynamic capture (evenly picked), around its moving
objects (their masks plus 10 px): the truth, the run's render, the static part alone (the
moving part's density set to zero), the moving part alone (the static part's density set to
zero) and the moving part's opacity (white: opaque). Prints the object PSNR of the render and
of the static part alone. Writes ``docs/benchmarks/<NAME>.png`` (default ``kplanes_parts``;
one block of rows per run).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

import sims  # noqa: F401  (MUJOCO_GL before mujoco)
from nerfbot.data.run_dataset import resolve_run_dataset
from nerfbot.query.export import labelled_row, save_image
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dynamic_objects import crop_box, object_mask, pooled_psnr  # noqa: E402

HERE = Path(__file__).resolve().parent


def parts(run: Path, frames: int) -> list[np.ndarray]:
    model, info = load_model(run)
    if info["spec"]["method"] != "kplanes":
        raise SystemExit(f"{run}: a {info['spec']['method']} run, not kplanes")
    _, ds = resolve_run_dataset(run, info["spec"].get("dataset"))
    field = model.field
    dynamic, static = field.dynamic_density, field.static.density
    train = ds.indices("train")
    rows = []
    for i in [train[k] for k in np.linspace(0, len(train) - 1, frames + 2)[1:-1].astype(int)]:
        t, gt, mask = [float(ds.times[i])], ds.image_float(i), object_mask(ds, i)
        cams = ds.cameras([i])
        full = render_image(model, cams, 0, cond=t)
        try:
            field.dynamic_density = lambda x, c=None: (torch.zeros(len(x)), dynamic(x, c)[1])
            still = render_image(model, cams, 0, cond=t)
            field.dynamic_density = dynamic
            field.static.density = lambda x: (torch.zeros(len(x)), static(x)[1])
            moving = render_image(model, cams, 0, cond=t)
        finally:
            field.dynamic_density, field.static.density = dynamic, static
        y0, y1, x0, x1 = crop_box(mask, 10)
        images = [gt, full["rgb"], still["rgb"], moving["rgb"],
                  np.repeat(moving["opacity"][..., None], 3, -1)]
        images = [cv2.resize(np.ascontiguousarray(im[y0:y1, x0:x1]), (128, 128),
                             interpolation=cv2.INTER_NEAREST) for im in images]
        objects = pooled_psnr([(full["rgb"], gt, mask)])
        print(f"{run.name} t = {t[0]:.2f}: objects {objects:.2f} dB, static part alone "
              f"{pooled_psnr([(still['rgb'], gt, mask)]):.2f} dB")
        rows.append(labelled_row(images, [f"{run.name} t={t[0]:.2f}", f"render {objects:.1f} dB",
                                          "static part", "moving part", "moving opacity"],
                                 scale=2))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+")
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--out", default="kplanes_parts")
    args = p.parse_args(argv)
    rows = [row for run in args.runs for row in parts(run, args.frames)]
    print("wrote", save_image(HERE / f"{args.out}.png", np.vstack(rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
