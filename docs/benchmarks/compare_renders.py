"""Test views of several trained runs beside the truth, one row per view: a figure to look at.

usage: python docs/benchmarks/compare_renders.py OUT.png DATA:VIEWS RUN [RUN ...] [--names A,B]
  e.g. ... cmp.png OUT/bins2:0,4 OUT/runs/bins2-diagonal-60 OUT/runs/bins2-rays-60

VIEWS are indices into DATA's test split. Each cell is titled with the run's name and its PSNR
on that view; the first column is the captured image.
"""
import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfbot.data import load_dataset  # noqa: E402
from nerfbot.query.render import render_image  # noqa: E402
from nerfbot.train.runs import load_model  # noqa: E402


def views_and_runs(description: str):
    """Parse ``OUT.png DATA:VIEWS RUN [RUN ...] [--names A,B]`` (exits with a usage error on
    bad input). Returns (args, the dataset, its test-split indices, the VIEWS as ints, the run
    names, the loaded models in eval mode, the test cameras)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("out", help="PNG to write")
    ap.add_argument("data", metavar="DATA:VIEWS", help="dataset folder and test view indices")
    ap.add_argument("runs", nargs="+", help="trained run folders")
    ap.add_argument("--names", default=None, help="run names, comma separated")
    args = ap.parse_args()
    data, _, views = args.data.rpartition(":")
    if not data or not views:
        ap.error(f"DATA:VIEWS must name a dataset and its test views, got {args.data!r}")
    ds = load_dataset(data)
    test = ds.indices("test")
    rows = [int(v) for v in views.split(",")]
    if any(not 0 <= v < len(test) for v in rows):
        ap.error(f"{data}: test views are 0-{len(test) - 1}, got {views}")
    names = args.names.split(",") if args.names else [r.rstrip("/").split("/")[-1]
                                                       for r in args.runs]
    if len(names) != len(args.runs):
        ap.error(f"--names gives {len(names)} names for {len(args.runs)} runs")
    models = [load_model(r)[0].eval() for r in args.runs]
    return args, ds, test, rows, names, models, ds.cameras(test)


def main() -> None:
    args, ds, test, rows, names, models, cams = views_and_runs(__doc__.splitlines()[0])
    fig, axes = plt.subplots(len(rows), 1 + len(models), squeeze=False,
                             figsize=(2.6 * (1 + len(models)), 2.7 * len(rows)))
    for i, v in enumerate(rows):
        truth = ds.image_float(test[v])
        axes[i, 0].imshow(truth)
        axes[i, 0].set_title(f"truth, test view {v}", fontsize=8)
        for j, (name, model) in enumerate(zip(names, models)):
            rgb = np.clip(render_image(model, cams, v)["rgb"], 0.0, 1.0)
            psnr = -10.0 * np.log10(max(float(np.mean((rgb - truth) ** 2)), 1e-10))
            axes[i, j + 1].imshow(rgb)
            axes[i, j + 1].set_title(f"{name}: {psnr:.2f} dB", fontsize=8)
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
