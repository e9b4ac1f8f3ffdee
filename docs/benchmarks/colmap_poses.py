"""Poses from images: pycolmap on sims captures, against the true poses and in a trained field.

usage: python docs/benchmarks/colmap_poses.py WORK [--scenes tabletop,glassware] [--size 1024]
                                              [--downscale 8] [--seconds 180] [--method ngp]
                                              [--colmap-args="--no-refine-all-features"]

For each scene:

1. ``nerfbot capture --scene S --size 1024`` (60 train + 10 test views; skipped when WORK holds
   it already);
2. ``nerfbot colmap`` on all 70 images at 1024 px, intrinsics known and fixed, written at 128 px
   (``--downscale 8``): registered images, seconds, and the rotation (degrees) and centre (% of
   the diagonal of the true camera centres' box) errors after the similarity alignment;
3. the same frames with their true poses (a copy of the written dataset whose poses are
   replaced), so the two datasets differ only in their poses;
4. ``nerfbot train --method ngp --max-seconds 180`` on each, then ``nerfbot eval`` on the test
   frames both share: test PSNR on COLMAP poses against true poses.

Writes WORK/colmap_poses.json and prints a markdown table. Runs one thing at a time.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

NERFBOT = [sys.executable, "-m", "nerfbot.app.cli"]


def run(cmd: list, **kwargs) -> str:
    print("$", " ".join(str(c) for c in cmd), flush=True)
    done = subprocess.run([str(c) for c in cmd], check=True, capture_output=True, text=True,
                          **kwargs)
    return done.stdout


def true_pose_twin(sfm: Path, capture: Path, twin: Path) -> None:
    """A copy of the SfM dataset ``sfm`` whose poses are the capture's true ones."""
    truth = {f["file_path"]: f["transform_matrix"]
             for f in json.loads((capture / "transforms.json").read_text())["frames"]}
    meta = json.loads((sfm / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["transform_matrix"] = truth[frame["file_path"]]
    meta.pop("ply_file_path", None)
    twin.mkdir(parents=True)
    for folder in sfm.iterdir():   # images, depth, segmentation, sparse depth (not colmap/)
        if folder.is_dir() and folder.name != "colmap":
            shutil.copytree(folder, twin / folder.name)
    (twin / "transforms.json").write_text(json.dumps(meta, indent=2))


def train_and_eval(data: Path, out: Path, method: str, seconds: float) -> dict:
    if not (out / "checkpoint.pt").exists():
        run(NERFBOT + ["train", "--data", data, "--method", method, "--max-seconds", seconds,
                       "--out", out, "--no-progress"])
    return json.loads(run(NERFBOT + ["eval", out, "--split", "test", "--json"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--scenes", default="tabletop,glassware")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=180.0)
    ap.add_argument("--method", default="ngp")
    ap.add_argument("--colmap-args", default="",
                    help="more options of nerfbot colmap, one string after '=', e.g. "
                         "--colmap-args=\"--drop-repeated 0\"")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = {}
    for scene in args.scenes.split(","):
        capture = args.work / f"{scene}-{args.size}px"
        if not (capture / "transforms.json").exists():
            run(NERFBOT + ["capture", "--scene", scene, "--size", args.size, "--out", capture,
                           "--no-progress"])
        sfm = args.work / f"{scene}-sfm"
        if not (sfm / "sfm_report.json").exists():
            run(NERFBOT + ["colmap", capture, "--out", sfm, "--downscale", args.downscale,
                           "--no-progress", *args.colmap_args.split()])
        report = json.loads((sfm / "sfm_report.json").read_text())
        twin = args.work / f"{scene}-true"
        if not twin.exists():
            true_pose_twin(sfm, capture, twin)
        row = {"sfm": {k: report[k] for k in ("images", "registered", "deregistered", "points",
                                               "mean_reprojection_error_px", "seconds")},
               "pose_errors": report["pose_errors"],
               "flipped": sum(v["rotation_deg"] > 10.0
                              for v in report["pose_errors_per_image"].values())}
        for name, data in (("colmap_poses", sfm), ("true_poses", twin)):
            ev = train_and_eval(data, args.work / "runs" / f"{scene}-{name}", args.method,
                                args.seconds)
            row[name] = {"psnr": ev["psnr"], "ssim": ev.get("ssim"), "images": ev.get("num_images")}
        row["psnr_gap_db"] = row["true_poses"]["psnr"] - row["colmap_poses"]["psnr"]
        results[scene] = row
        (args.work / "colmap_poses.json").write_text(json.dumps(results, indent=2))

    print("| scene | registered | SfM s | rotation median / max deg | centre median / max % | "
          f"{args.method} PSNR COLMAP / true poses | gap dB |")
    print("|---|---|---|---|---|---|---|")
    for scene, r in results.items():
        e = r["pose_errors"]
        print(f"| {scene} | {r['sfm']['registered']}/{r['sfm']['images']} | "
              f"{r['sfm']['seconds']['total']:.0f} | {e['rotation_deg_median']:.2f} / "
              f"{e['rotation_deg_max']:.1f} | {e['translation_percent_median']:.2f} / "
              f"{e['translation_percent_max']:.1f} | {r['colmap_poses']['psnr']:.2f} / "
              f"{r['true_poses']['psnr']:.2f} | {r['psnr_gap_db']:.2f} |")


if __name__ == "__main__":
    main()
