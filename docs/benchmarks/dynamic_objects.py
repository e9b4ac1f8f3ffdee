"""Moving objects at held-out times (BENCHMARKS.md, section 4): each method trained on each
dynamic capture, then scored where things move.

    python docs/benchmarks/dynamic_objects.py BENCH [--seconds 300] [--methods kplanes,dnerf]
        [--captures multi12,mono] [--out NAME]

A method written ``NAME/VARIANT`` is trained into ``run_<capture>_NAME_VARIANT`` with the
variant's flags (:data:`VARIANTS`): ``uniform`` rays (``--dynamic-rays 0``), ``warmup``
(``--option dynamic_warmup=0.2``, kplanes' static part alone first), or ``errors`` (half the
rays by the training error instead of the images' change: ``--error-rays 0.5``), or, for
``rigid``, ``static`` (a static scene around the parts: ``--option moving_scene=false``) or
``increments`` (each step's rotation trained as a turn from the step before:
``--option rotation_increments=true``), ``curriculum`` (the frames that train grow forward
in time over half the budget, each joining step's turn carried on: ``--option
time_curriculum=0.5``), ``curriculum_rot10`` (the same with ten times the rotations' learning
rate), ``curriculum_still`` and ``curriculum_half`` (that, carrying none or half of the turn).

``BENCH/<capture>`` holds the captures made by the commands in BENCHMARKS.md. Each method is
trained alone (``nerfbot train --max-seconds S``) into ``BENCH/run_<capture>_<method>`` (kept
if it exists), then scored on the held-out frames, which are captured at times between training
frames:

- ``psnr``, ``psnr_objects`` (the manifest's moving bodies, their masks dilated by 2 px) and
  ``psnr_non_sky``, as ``nerfbot eval`` reports them;
- ``psnr_objects_nearest``: the same frames rendered at the nearest training time instead of
  their own (what a model that cannot interpolate in time would show);
- ``psnr_objects_train``: object PSNR on about 120 training frames (evenly picked), at their
  own times: how well the field holds the objects where it was trained;
- ``steps`` and ``render_ms``.

Writes ``BENCH/<NAME>.json`` and ``docs/benchmarks/<NAME>_<capture>.png`` (NAME default
``dynamic``; held-out
frames: the truth beside each method's render, with object PSNR, and a crop around the moving
objects).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

import sims  # noqa: F401  (MUJOCO_GL before mujoco)
from nerfbot.data import load_dataset
from nerfbot.data.conditioning import dataset_conditioning, frame_conditions
from nerfbot.eval.evaluation import OBJECT_MASK_DILATION_PX, evaluate, object_geom_ids
from nerfbot.query.export import labelled_row, save_image
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

HERE = Path(__file__).resolve().parent
#: The training flags of a method written NAME/VARIANT.
VARIANTS = {"": [], "uniform": ["--dynamic-rays", "0"],
            "warmup": ["--option", "dynamic_warmup=0.2"],
            "errors": ["--dynamic-rays", "0", "--error-rays", "0.5"],
            "static": ["--option", "moving_scene=false"],
            "increments": ["--option", "rotation_increments=true"],
            "curriculum": ["--option", "time_curriculum=0.5"],
            "curriculum_rot10": ["--option", "time_curriculum=0.5",
                                 "--option", "rotation_lr_factor=10"],
            "curriculum_still": ["--option", "time_curriculum=0.5", "--option",
                                 "rotation_lr_factor=10", "--option", "curriculum_carry=0"],
            "curriculum_half": ["--option", "time_curriculum=0.5", "--option",
                                "rotation_lr_factor=10", "--option", "curriculum_carry=0.5"]}


def object_mask(dataset, i: int) -> np.ndarray:
    """(H, W) bool: the moving objects of frame ``i``, dilated as ``nerfbot eval`` does."""
    mask = np.isin(dataset.segmentations[i], object_geom_ids(dataset)).astype(np.uint8)
    k = 2 * OBJECT_MASK_DILATION_PX + 1
    return cv2.dilate(mask, np.ones((k, k), np.uint8)).astype(bool)


def pooled_psnr(pairs) -> float:
    """PSNR of the squared errors pooled over (prediction, truth, mask) triples."""
    se = sum(float(np.square(p[m] - g[m]).sum()) for p, g, m in pairs)
    n = sum(int(m.sum()) * 3 for _, _, m in pairs)
    return float(-10.0 * np.log10(max(se / max(n, 1), 1e-10)))


def nearest_training_time(dataset, i: int, train_times: np.ndarray) -> float:
    return float(train_times[np.argmin(np.abs(train_times - float(dataset.times[i])))])


def score(run: Path, dataset) -> tuple[dict, object]:
    model, _ = load_model(run)
    result = evaluate(model, dataset, "test", with_ssim=False)
    train_times = np.unique([float(dataset.times[j]) for j in dataset.indices("train")])
    pairs = []
    for i in dataset.indices("test"):
        t = np.array([nearest_training_time(dataset, i, train_times)], np.float32)
        rgb = render_image(model, dataset.cameras([i]), 0, cond=t)["rgb"]
        pairs.append((rgb, dataset.image_float(i), object_mask(dataset, i)))
    train = dataset.indices("train")
    seen = []
    for i in train[::max(1, len(train) // 120)]:
        rgb = render_image(model, dataset.cameras([i]), 0,
                           cond=np.array([float(dataset.times[i])], np.float32))["rgb"]
        seen.append((rgb, dataset.image_float(i), object_mask(dataset, i)))
    trained = json.loads((run / "metrics.json").read_text())
    row = {k: result[k] for k in ("psnr", "psnr_objects", "psnr_non_sky")}
    row.update(psnr_objects_nearest=pooled_psnr(pairs), psnr_objects_train=pooled_psnr(seen),
               render_ms=result["render_ms_per_image"],
               steps=trained["steps"], train_seconds=trained["train_seconds"])
    return row, model


def crop_box(mask: np.ndarray, pad: int = 6) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) around the mask's pixels plus ``pad``; the whole image when empty."""
    h, w = mask.shape
    if not mask.any():
        return 0, h, 0, w
    ys, xs = np.nonzero(mask)
    return (max(0, ys.min() - pad), min(h, ys.max() + pad + 1),
            max(0, xs.min() - pad), min(w, xs.max() + pad + 1))


def sheet(dataset, models: dict, rows: int = 4) -> np.ndarray:
    conds = frame_conditions(dataset, dataset_conditioning(dataset, tracks=False))
    test = dataset.indices("test")
    picks = [test[k] for k in np.linspace(0, len(test) - 1, rows).round().astype(int)]
    out = []
    for i in picks:
        gt, mask = dataset.image_float(i), object_mask(dataset, i)
        images, labels = [gt], [f"t = {float(dataset.times[i]):.2f}"]
        for name, model in models.items():
            rgb = render_image(model, dataset.cameras([i]), 0, cond=conds[i])["rgb"]
            images.append(rgb)
            labels.append(f"{name} {pooled_psnr([(rgb, gt, mask)]):.1f} dB obj")
        y0, y1, x0, x1 = crop_box(mask)
        crops = [cv2.resize(np.ascontiguousarray(im[y0:y1, x0:x1]), (gt.shape[1], gt.shape[0]),
                            interpolation=cv2.INTER_NEAREST) for im in images]
        out.append(labelled_row(images, labels, scale=2))
        out.append(labelled_row(crops, ["objects, enlarged"] + [""] * len(models), scale=2))
    return np.vstack(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("bench", type=Path)
    parser.add_argument("--seconds", type=float, default=300.0)
    parser.add_argument("--methods", default="kplanes,dnerf")
    parser.add_argument("--captures", default="multi12,mono")
    parser.add_argument("--out", default="dynamic", help="name of the json and figures")
    args = parser.parse_args()
    results = {}
    for capture in args.captures.split(","):
        data = args.bench / capture
        dataset = load_dataset(data)
        models, results[capture] = {}, {}
        for method in args.methods.split(","):
            name, _, variant = method.partition("/")
            run = args.bench / f"run_{capture}_{method.replace('/', '_')}"
            if not (run / "checkpoint.pt").is_file():
                subprocess.run(["nerfbot", "train", "--data", str(data), "--method", name,
                                "--max-seconds", str(args.seconds), "--out", str(run),
                                "--no-progress"]
                               + VARIANTS[variant],
                               check=True)
            results[capture][method], models[method] = score(run, dataset)
            print(capture, method, results[capture][method], flush=True)
        path = save_image(HERE / f"{args.out}_{capture}.png", sheet(dataset, models))
        print("wrote", path)
    (args.bench / f"{args.out}.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    sys.exit(main())
