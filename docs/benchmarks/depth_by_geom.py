"""Where a trained run's depth error lies: z-depth error over the test views, per named geometry.

usage: python docs/benchmarks/depth_by_geom.py DATA RUN [--group NAME ...]

DATA must have depth and segmentation (a `sims` capture). Each named geometry of the capture's
manifest (``--group``, e.g. ``table_top cutting_mat``) gets its own row; every other geometry
counts as "other geometry" and sky pixels are left out. Per row: pixels over all test views,
the share of all test pixels' summed error, mean and median absolute z-depth error and the
share of its pixels more than 5 cm off.
"""
import argparse

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

#: A pixel this many metres or more off counts as "far off".
FAR_OFF_M = 0.05


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="dataset folder with depth and segmentation")
    ap.add_argument("run", help="trained run folder")
    ap.add_argument("--group", nargs="*", default=[], help="geometry names with their own row")
    args = ap.parse_args()
    ds = load_dataset(args.data)
    model = load_model(args.run)[0].eval()
    test = ds.indices("test")
    geoms = (ds.manifest or {}).get("geoms") or {}
    if not geoms or any(ds.segmentations[i] is None or ds.depths[i] is None for i in test):
        raise SystemExit(f"{args.data}: needs a manifest's geoms, depth and segmentation")
    unknown = sorted(set(args.group) - set(geoms.values()))
    if unknown:
        raise SystemExit(f"--group: {unknown} not among the geometries {sorted(geoms.values())}")
    row_of = {int(k): (v if v in args.group else "other geometry") for k, v in geoms.items()}
    errors: dict[str, list[np.ndarray]] = {}
    cams = ds.cameras(test)
    for v, i in enumerate(test):
        z = render_image(model, cams, v)["z_depth"]
        depth = np.asarray(ds.depths[i], dtype=np.float64).reshape(z.shape)
        seg = np.asarray(ds.segmentations[i]).reshape(z.shape)
        err = np.abs(z - depth)
        for g, row in row_of.items():
            mask = (seg == g) & np.isfinite(depth)
            errors.setdefault(row, []).append(err[mask])
    total = sum(float(np.concatenate(e).sum()) for e in errors.values())
    print("| geometry | pixels | share of the error | MAE mm | median mm | > 5 cm off |")
    print("|---|---|---|---|---|---|")
    for row in [*args.group, "other geometry"]:
        e = np.concatenate(errors.get(row, [np.zeros(0)]))
        if e.size == 0:
            continue
        print(f"| {row} | {e.size} | {100 * e.sum() / total:.0f} % | {1000 * e.mean():.1f} | "
              f"{1000 * np.median(e):.1f} | {100 * np.mean(e > FAR_OFF_M):.1f} % |")


if __name__ == "__main__":
    main()
