"""pixelNeRF on unseen scenes of a family against a per-scene ngp trained on the same views.

usage: python docs/benchmarks/pixelnerf.py WORK [--family workspace] [--train-seeds 0-31]
                                           [--unseen 100-102] [--seconds 900] [--size 64]
                                           [--ngp-seconds 60]

1. ``nerfbot pixelnerf --family F --seeds TRAIN --size N --max-seconds S``: captures the
   family's training scenes (24 views + 6 test views each, the family's rig) into
   WORK/captures and trains pixelNeRF across them for S seconds into WORK/run.
2. The unseen seeds are captured the same way. For each unseen scene and K = 1, 2, 3 source
   views (the K training views whose cameras are nearest to the centre of the test cameras):
   - pixelNeRF conditioned on the K views scores the 6 test views (PSNR, SSIM); its time is
     what a new scene costs it: encoding the sources and rendering the 6 views;
   - pixelNeRF fine-tuned on the K views (``finetune_on``) for ``--ngp-seconds`` minus that
     time, so that fine-tuning and rendering together take ``--ngp-seconds``;
   - ngp trained on the same K views for pixelNeRF's time, and for ``--ngp-seconds``, scores
     the same 6 views (its rendering time not counted).

Writes WORK/pixelnerf.json, WORK/pixelnerf.png (one unseen scene: truth, pixelNeRF, pixelNeRF
fine-tuned and ngp per K) and prints a markdown table. One thing at a time: nothing else should
run meanwhile.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfbot.app.pixelnerf_cli import seed_list  # noqa: E402
from nerfbot.data import load_dataset  # noqa: E402
from nerfbot.eval.evaluation import evaluate  # noqa: E402
from nerfbot.ops.cameras import Cameras  # noqa: E402
from nerfbot.query.render import render_image  # noqa: E402
from nerfbot.train.pixelnerf import FinetuneConfig, condition_on, finetune_on  # noqa: E402
from nerfbot.train.runs import load_model  # noqa: E402
from nerfbot.train.trainer import TrainConfig, Trainer  # noqa: E402
from sims.family import capture_family  # noqa: E402

NERFBOT = [sys.executable, "-m", "nerfbot.app.cli"]
VIEWS, TEST_VIEWS = 24, 6


def nearest_sources(ds, k: int) -> list[int]:
    """The k training views whose camera centres are nearest the test cameras' mean centre."""
    train = ds.indices("train")
    centre = ds.c2w[ds.indices("test"), :3, 3].mean(0)
    dist = np.linalg.norm(ds.c2w[train, :3, 3] - centre, axis=1)
    return [int(train[i]) for i in np.argsort(dist)[:k]]


def test_images(model, ds) -> list[np.ndarray]:
    test = ds.indices("test")
    cams = Cameras.from_numpy(ds.c2w[test], ds.intrinsics[test], ds.sizes[test])
    return [render_image(model, cams, i, supersample=1)["rgb"] for i in range(len(test))]


def ngp_on(ds, sources: list[int], seconds: float, out: Path):
    """ngp trained on ``sources`` only, for ``seconds``: (model, metrics on the test views)."""
    few = load_dataset(ds.root)
    few.splits["train"] = list(sources)
    trainer = Trainer(few, out, TrainConfig(method="ngp", max_seconds=seconds, seed=0,
                                            progress=False))
    summary = trainer.train()
    metrics = evaluate(trainer.model, few, "test")
    metrics["steps"] = summary["steps"]
    return trainer.model, metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--family", default="workspace")
    ap.add_argument("--train-seeds", default="0-31")
    ap.add_argument("--unseen", default="100-102")
    ap.add_argument("--seconds", type=float, default=900.0)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--ngp-seconds", type=float, default=60.0)
    args = ap.parse_args()
    work, captures, run = args.work, args.work / "captures", args.work / "run"
    work.mkdir(parents=True, exist_ok=True)
    if not (run / "checkpoint.pt").exists():
        subprocess.run([*NERFBOT, "pixelnerf", "--family", args.family, "--seeds",
                        args.train_seeds, "--size", str(args.size), "--views", str(VIEWS),
                        "--test-views", str(TEST_VIEWS), "--steps", "10000000",
                        "--max-seconds", str(args.seconds), "--captures", str(captures),
                        "--out", str(run), "--no-progress"], check=True)
    model, info = load_model(run)
    trained = {k: v.clone() for k, v in model.state_dict().items()}
    folders = capture_family(args.family, seed_list(args.unseen), captures, VIEWS, TEST_VIEWS,
                             args.size, progress=False)
    rows, shown = [], {}
    for folder in folders:
        ds = load_dataset(folder)
        for k in (1, 2, 3):
            sources = nearest_sources(ds, k)
            t0 = time.perf_counter()
            condition_on(model, ds, sources)
            pix = evaluate(model, ds, "test")
            pix_seconds = time.perf_counter() - t0
            row = {"scene": folder.name, "views": k, "sources": sources,
                   "pixelnerf": {"psnr": pix["psnr"], "ssim": pix["ssim"],
                                 "seconds": pix_seconds}}
            if folder == folders[0]:
                shown[k] = {"pix": test_images(model, ds)}
            t0 = time.perf_counter()
            tuned = finetune_on(model, ds, sources, FinetuneConfig(
                steps=None, max_seconds=max(args.ngp_seconds - pix_seconds, 1.0),
                progress=False))
            ft = evaluate(model, ds, "test")
            row["pixelnerf_finetuned"] = {"psnr": ft["psnr"], "ssim": ft["ssim"],
                                          "seconds": time.perf_counter() - t0,
                                          "steps": tuned["steps"]}
            if folder == folders[0]:
                shown[k]["ft"] = test_images(model, ds)
            model.load_state_dict(trained)
            for name, seconds in (("ngp_same_time", pix_seconds),
                                  ("ngp", args.ngp_seconds)):
                ngp, m = ngp_on(ds, sources, seconds, work / "ngp" / f"{folder.name}-{k}-{name}")
                row[name] = {"psnr": m["psnr"], "ssim": m["ssim"], "seconds": seconds,
                             "steps": m["steps"]}
                if folder == folders[0] and name == "ngp":
                    shown[k]["ngp"] = test_images(ngp, ds)
            rows.append(row)
            print(json.dumps(row), flush=True)
    doc = {"family": args.family, "train_seeds": args.train_seeds, "unseen": args.unseen,
           "size": args.size, "train_seconds": info["train_seconds"], "steps": info["step"],
           "rows": rows}
    (work / "pixelnerf.json").write_text(json.dumps(doc, indent=2))

    ds = load_dataset(folders[0])
    truth = [ds.images[i] for i in ds.indices("test")]
    fig, axes = plt.subplots(10, 3, figsize=(7, 22))
    for j in range(3):
        axes[0, j].imshow(truth[j])
        axes[0, j].set_title(f"truth, test view {j}", fontsize=8)
    titles = {"pix": "pixelNeRF", "ft": f"pixelNeRF fine-tuned, {args.ngp_seconds:g} s in all",
              "ngp": f"ngp {args.ngp_seconds:g} s"}
    for k in (1, 2, 3):
        for r, key in enumerate(("pix", "ft", "ngp")):
            for j in range(3):
                ax = axes[3 * k - 2 + r, j]
                ax.imshow(np.clip(shown[k][key][j], 0, 1))
                ax.set_title(f"{titles[key]}, {k} view(s)", fontsize=7)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"{folders[0].name} (unseen)", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.985))  # room for the title
    fig.savefig(work / "pixelnerf.png", dpi=110)

    print(f"\npixelNeRF: {info['step']} steps in {info['train_seconds']:.0f} s on "
          f"{args.family} seeds {args.train_seeds} at {args.size} px\n")
    print("| scene | views | pixelNeRF PSNR / SSIM (s) | ngp, same time | pixelNeRF fine-tuned, "
          f"{args.ngp_seconds:g} s in all | ngp, {args.ngp_seconds:g} s |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        p, a, f, b = r["pixelnerf"], r["ngp_same_time"], r["pixelnerf_finetuned"], r["ngp"]
        print(f"| {r['scene']} | {r['views']} | {p['psnr']:.2f} / {p['ssim']:.3f} "
              f"({p['seconds']:.1f}) | {a['psnr']:.2f} / {a['ssim']:.3f} ({a['steps']} steps) "
              f"| {f['psnr']:.2f} / {f['ssim']:.3f} ({f['steps']} steps) "
              f"| {b['psnr']:.2f} / {b['ssim']:.3f} ({b['steps']} steps) |")


if __name__ == "__main__":
    main()
