"""How close do a run's exports lie to the true MuJoCo geometry?

usage: python docs/benchmarks/exports.py RUN [RUN ...] [--resolution 256] [--json OUT.json]
                                         [--depth-mode expected|median|threshold]
                                         [--threshold M]

For each run (trained on a static ``sims`` capture, whose manifest names the scene), the three
exports of ``nerfbot export`` are made through the Python API (:mod:`nerfbot.query.geometry`)
from the training cameras, with the run's default depth query (threshold depth for runs whose
``auto.json`` says so) unless ``--depth-mode`` is given, inside the capture's content bounds:

- ``pointcloud``: rendered depth back-projected, flying pixels dropped;
- ``mesh``: marching cubes on density (at the depth query's threshold when it has one);
- ``tsdf``: rendered depth fused in a TSDF (voxel = content bounds' longest side / 256).

Each is scored against the scene's true geometry (every rendered geom, in the state the capture
rendered) on the surface the training cameras see: Chamfer distance (mean of accuracy, export
-> truth, and completeness, truth -> export) in mm, and precision / recall / F-score at 1 cm
(:func:`nerfbot.query.meshing.compare_meshes`, :func:`~nerfbot.query.meshing.compare_cloud`).
Seconds per export are wall-clock on this machine. A capture moved and scaled in the world
(``docs/benchmarks/moved_capture.py``) is compared with the truth moved the same way: the frame
test.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from nerfbot.data.run_dataset import resolve_run_dataset
from nerfbot.data.spec import read_json
from nerfbot.query.geometry import DepthQuery, density_mesh, point_cloud, tsdf_mesh
from nerfbot.query.meshing import compare_cloud, compare_meshes
from nerfbot.train.runs import load_model
from sims.geometry import capture_geometry


def run_query(run: Path, mode, threshold) -> DepthQuery:
    """The run's default depth query (RUN/auto.json), overridden by the flags."""
    auto = run / "auto.json"
    defaults = (read_json(auto).get("query_defaults") or {}) if auto.exists() else {}
    mode = mode or defaults.get("depth_mode", "expected")
    threshold = threshold if threshold is not None else defaults.get("threshold")
    return DepthQuery(mode, threshold if mode == "threshold" else None)


def score_run(run: Path, resolution: int, mode=None, threshold=None) -> dict:
    model, info = load_model(run)
    ds = resolve_run_dataset(run, info["spec"].get("dataset"))[1]
    truth = capture_geometry(ds.manifest)
    if truth is None:
        raise SystemExit(f"{run}: its dataset names no static sims scene to compare against")
    gt, bounds = truth
    moved = ds.manifest.get("moved")
    if moved:   # a capture moved by docs/benchmarks/moved_capture.py: move the scene's mesh
        # with it (the bounds come from the manifest, which that script moved)
        scale, offset = float(moved["scale"]), np.asarray(moved["offset"], float)
        gt = gt.copy()
        gt.vertices = gt.vertices * scale + offset
    idx = ds.indices("train")
    seen = (ds.c2w[idx], ds.intrinsics[idx], ds.sizes[idx])
    cams = ds.cameras(idx)
    query = run_query(run, mode, threshold)
    rows = {}
    t0 = time.perf_counter()
    cloud = point_cloud(model, cams, query, bounds=bounds, progress=True)
    rows["pointcloud"] = {"seconds": time.perf_counter() - t0, "points": len(cloud.points),
                          **compare_cloud(cloud.points, gt, bounds=bounds, cameras=seen)}
    t0 = time.perf_counter()
    mesh = density_mesh(model, threshold=query.threshold, resolution=resolution, bounds=bounds)
    rows["mesh"] = {"seconds": time.perf_counter() - t0,
                    **compare_meshes(mesh, gt, bounds=bounds, cameras=seen)}
    t0 = time.perf_counter()
    tsdf = tsdf_mesh(model, cams, query, bounds=bounds, progress=True)
    rows["tsdf"] = {"seconds": time.perf_counter() - t0,
                    **compare_meshes(tsdf, gt, bounds=bounds, cameras=seen)}
    scene = ds.manifest.get("source") + (f" moved x{moved['scale']:g} + {moved['offset']}"
                                         if moved else "")
    return {"run": str(run), "scene": scene, "depth": query.describe(),
            "exports": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--resolution", type=int, default=256,
                   help="marching-cubes cells along the content bounds' longest side")
    p.add_argument("--depth-mode", default=None, choices=("expected", "median", "threshold"))
    p.add_argument("--threshold", type=float, default=None)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    results = [score_run(r, args.resolution, args.depth_mode, args.threshold) for r in args.runs]
    print("| scene | depth | export | Chamfer mm | accuracy mm | completeness mm | "
          "precision | recall | F-score @1 cm | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for res in results:
        for kind, r in res["exports"].items():
            print(f"| {res['scene']} | {res['depth']} | {kind} | {r['chamfer_mm']:.1f} | "
                  f"{r['accuracy_mm']:.1f} | {r['completeness_mm']:.1f} | {r['precision']:.3f} | "
                  f"{r['recall']:.3f} | {r['fscore']:.3f} | {r['seconds']:.1f} |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
