"""Few training views, RGB only against DS-NeRF sparse depth supervision.

usage: python docs/benchmarks/few_views.py WORK [--scenes tabletop,workspace:0]
                                           [--views 2,3,5,10] [--seconds 60] [--weight 0.1]

For each scene: one 512 px capture with 10 training and 10 test views (hemisphere rig, seed 0).
For each view count N, the N training views farthest apart (greedy farthest-point order of the
camera centres, starting from view 0) make a training set:

1. ``nerfbot colmap SUBSET --known-poses --downscale 4``: SIFT features and matches among the N
   training images only, points triangulated with the simulator's poses; images, depth and
   keypoints written at 128 px. (Poses come from the simulator: the column "SfM registers"
   says whether ``nerfbot colmap`` alone would have posed the N views, and its median rotation
   error when it did.)
2. ``nerfbot train --method ngp --max-seconds S`` with and without ``--sparse-depth-weight W``.
3. ``nerfbot eval --data TESTSET --split test`` on the 10 test views (the same capture's,
   written at 128 px the same way): PSNR, SSIM, depth MAE.

Writes WORK/few_views.json, WORK/few_views.png (PSNR and depth MAE against N) and prints a
markdown table. One thing at a time.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

NERFBOT = [sys.executable, "-m", "nerfbot.app.cli"]


def run(cmd: list) -> str:
    print("$", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], check=True, capture_output=True,
                          text=True).stdout


def farthest_order(centres: np.ndarray) -> list[int]:
    """Greedy farthest-point order of camera centres (N, 3), starting from the first."""
    order = [0]
    dist = np.linalg.norm(centres - centres[0], axis=1)
    while len(order) < len(centres):
        nxt = int(np.argmax(dist))
        order.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(centres - centres[nxt], axis=1))
    return order


def subset(capture: Path, out: Path, frames: list[dict], meta: dict) -> None:
    """A copy of ``capture`` holding only ``frames`` (all of them training frames)."""
    out.mkdir(parents=True)
    for frame in frames:
        for key in ("file_path", "depth_file_path", "segmentation_path"):
            if key in frame:
                (out / frame[key]).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(capture / frame[key], out / frame[key])
    small = {k: v for k, v in meta.items() if not k.endswith("_filenames") and k != "frames"}
    small["frames"] = frames
    small["train_filenames"] = [f["file_path"] for f in frames]
    small["val_filenames"] = small["test_filenames"] = []
    (out / "transforms.json").write_text(json.dumps(small, indent=2))


def sfm_alone(data: Path, out: Path) -> dict:
    """Would structure from motion alone pose these views? (registered, rotation error)."""
    if not (out / "sfm_report.json").exists():
        try:
            run(NERFBOT + ["colmap", data, "--out", out, "--no-progress"])
        except subprocess.CalledProcessError as e:
            return {"registered": 0, "error": e.stderr.strip().splitlines()[-1]}
    report = json.loads((out / "sfm_report.json").read_text())
    row = {"registered": report["registered"]}
    if "pose_errors" in report:
        row["rotation_deg_median"] = report["pose_errors"]["rotation_deg_median"]
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--scenes", default="tabletop,workspace:0")
    ap.add_argument("--views", default="2,3,5,10")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--weight", type=float, default=0.1)
    args = ap.parse_args()
    counts = [int(v) for v in args.views.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    results = {}
    for scene in args.scenes.split(","):
        tag = scene.replace(":", "_")
        capture = args.work / f"{tag}-512px"
        if not (capture / "transforms.json").exists():
            run(NERFBOT + ["capture", "--scene", scene, "--size", 512, "--views", max(counts),
                           "--test-views", 10, "--out", capture, "--no-progress"])
        meta = json.loads((capture / "transforms.json").read_text())
        train = [f for f in meta["frames"] if f["file_path"] in set(meta["train_filenames"])]
        testset = args.work / f"{tag}-test128"
        if not testset.exists():
            run(NERFBOT + ["colmap", capture, "--out", testset, "--known-poses", "--downscale", 4,
                           "--no-progress"])
        order = farthest_order(np.array([np.array(f["transform_matrix"])[:3, 3] for f in train]))
        rows = {}
        for n in counts:
            views = args.work / f"{tag}-{n}v-512px"
            if not views.exists():
                subset(capture, views, [train[i] for i in sorted(order[:n])], meta)
            data = args.work / f"{tag}-{n}v"
            if not (data / "transforms.json").exists():
                run(NERFBOT + ["colmap", views, "--out", data, "--known-poses", "--downscale", 4,
                               "--no-progress"])
            report = json.loads((data / "sfm_report.json").read_text())
            row = {"keypoints": int(sum(len(np.load(p)) for p in (data / "sparse_depth")
                                        .rglob("*.npy"))) if (data / "sparse_depth").exists()
                   else 0, "points": report["points"],
                   "sfm_alone": sfm_alone(views, args.work / f"{tag}-{n}v-sfm")}
            for name, extra in (("rgb", []), ("sparse_depth",
                                              ["--sparse-depth-weight", args.weight])):
                if name == "sparse_depth" and not row["keypoints"]:
                    continue
                out = args.work / "runs" / f"{tag}-{n}v-{name}"
                if not (out / "checkpoint.pt").exists():
                    run(NERFBOT + ["train", "--data", data, "--method", "ngp", "--max-seconds",
                                   args.seconds, "--out", out, "--no-progress", *extra])
                ev = json.loads(run(NERFBOT + ["eval", out, "--data", testset, "--split", "test",
                                               "--json"]))
                row[name] = {k: ev.get(k) for k in ("psnr", "ssim", "depth_mae_m", "steps")}
            rows[n] = row
            results[scene] = rows
            (args.work / "few_views.json").write_text(json.dumps(results, indent=2))

    print("| scene | views | keypoints | SfM alone registers | PSNR RGB / +sparse depth | "
          "SSIM RGB / +sparse | depth MAE cm RGB / +sparse |")
    print("|---|---|---|---|---|---|---|")
    for scene, rows in results.items():
        for n, r in rows.items():
            sd = r.get("sparse_depth") or {"psnr": float("nan"), "ssim": float("nan"),
                                           "depth_mae_m": float("nan")}
            alone = r["sfm_alone"]
            reg = f"{alone['registered']}/{n}" + (
                f" ({alone['rotation_deg_median']:.2f} deg)" if "rotation_deg_median" in alone
                else "")
            print(f"| {scene} | {n} | {r['keypoints']} | {reg} | {r['rgb']['psnr']:.2f} / "
                  f"{sd['psnr']:.2f} | {r['rgb']['ssim']:.3f} / {sd['ssim']:.3f} | "
                  f"{100 * r['rgb']['depth_mae_m']:.1f} / {100 * sd['depth_mae_m']:.1f} |")

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for scene, rows in results.items():
        ns = sorted(rows)
        for name, style in (("rgb", "o--"), ("sparse_depth", "s-")):
            ok = [n for n in ns if name in rows[n]]
            axes[0].plot(ok, [rows[n][name]["psnr"] for n in ok], style,
                         label=f"{scene} {name.replace('_', ' ')}")
            axes[1].plot(ok, [100 * rows[n][name]["depth_mae_m"] for n in ok], style)
    axes[0].set(xlabel="training views", ylabel="test PSNR (dB)")
    axes[1].set(xlabel="training views", ylabel="test depth MAE (cm)", yscale="log")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.work / "few_views.png", dpi=120)


if __name__ == "__main__":
    main()
