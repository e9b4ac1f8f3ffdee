"""Where trained runs put their surfaces on test views: colour, depth error and opacity.

usage: python docs/benchmarks/depth_opacity.py OUT.png DATA:VIEWS RUN [RUN ...] [--names A,B]
  e.g. ... opacity.png OUT/data/bins_4-128px-60v10t-seed0:7,5 OUT/runs/plain OUT/runs/entropy

VIEWS are indices into DATA's test split, which must have depth. One row per view: the captured
image and its depth, then for each run its render (titled with the view's PSNR), its z-depth
error (0-5 cm, sky pixels left out) and its opacity (0-1; below 1 the learned background
shows through).
"""
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfbot.query.render import render_image  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_renders import views_and_runs  # noqa: E402

#: Depth errors at or above this many metres saturate the error panels.
ERROR_SCALE_M = 0.05


def main() -> None:
    args, ds, test, rows, names, models, cams = views_and_runs(__doc__.splitlines()[0])
    if any(ds.depths[test[v]] is None for v in rows):
        sys.exit(f"{args.data}: the test views have no depth")
    cols = 2 + 3 * len(models)
    fig, axes = plt.subplots(len(rows), cols, squeeze=False,
                             figsize=(1.9 * cols, 2.1 * len(rows)))
    for i, v in enumerate(rows):
        truth, depth = ds.image_float(test[v]), ds.depths[test[v]]
        depth = np.where(np.isfinite(depth), depth, np.nan)  # sky: no surface to compare
        near, far = np.nanpercentile(depth, [1, 99])
        axes[i, 0].imshow(truth)
        axes[i, 0].set_title(f"truth, test view {v}", fontsize=7)
        axes[i, 1].imshow(depth, vmin=near, vmax=far)
        axes[i, 1].set_title(f"depth {near:.2f}-{far:.2f} m", fontsize=7)
        for j, (name, model) in enumerate(zip(names, models)):
            out = render_image(model, cams, v)
            rgb = np.clip(out["rgb"], 0.0, 1.0)
            psnr = -10.0 * np.log10(max(float(np.mean((rgb - truth) ** 2)), 1e-10))
            err = np.abs(out["z_depth"] - depth)
            c = 2 + 3 * j
            axes[i, c].imshow(rgb)
            axes[i, c].set_title(f"{name}: {psnr:.2f} dB", fontsize=7)
            axes[i, c + 1].imshow(err, vmin=0.0, vmax=ERROR_SCALE_M)
            axes[i, c + 1].set_title(f"|depth error|, MAE {np.nanmean(err) * 1000:.0f} mm",
                                     fontsize=7)
            axes[i, c + 2].imshow(out["opacity"], vmin=0.0, vmax=1.0)
            axes[i, c + 2].set_title(f"opacity, mean {float(np.mean(out['opacity'])):.3f}",
                                     fontsize=7)
    for ax in axes.ravel():
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
