"""Few training views, RGB only against DS-NeRF sparse depth supervision.

usage: python docs/benchmarks/few_views.py WORK [--scenes tabletop,workspace:0]
                                           [--views 2,3,5,10] [--seconds 60] [--weight 0.1]

Few-view work poses a scene from one side, as a robot's camera does from where it stands: for
N training views, cameras on an arc of 60 degrees of azimuth around the scene's target (the
scene's own rig radius, 35 degrees elevation), evenly spaced; 8 test views on the same arc
between them, at 30 and 40 degrees elevation, the same for every N. For each scene and N:

1. ``nerfbot capture --rig explicit`` at 512 px, then ``nerfbot colmap CAPTURE --known-poses
   --downscale 4``: SIFT features and matches among the N training images only (the test
   images are posed by a second capture and never matched), points triangulated with the
   simulator's poses; images, depth and keypoints written at 128 px. The column "SfM alone"
   says whether ``nerfbot colmap`` without the poses registers the N views.
2. ``nerfbot train --method ngp --max-seconds S``, with and without ``--sparse-depth-weight W``.
3. ``nerfbot eval --data TESTSET --split test``: PSNR, SSIM, depth MAE on the 8 test views.

Writes WORK/few_views.json, WORK/few_views.png (PSNR and depth MAE against N) and prints a
markdown table. One thing at a time.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nerfbot.ops.cameras import spherical_eye  # noqa: E402
from sims.rigs import default_rig  # noqa: E402

NERFBOT = [sys.executable, "-m", "nerfbot.app.cli"]
#: Azimuth span of the training and test cameras, degrees (SIFT matches two tabletop views 60
#: degrees apart not at all; 30 degrees apart it does).
ARC_DEG = 60.0


def run(cmd: list) -> str:
    print("$", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], check=True, capture_output=True,
                          text=True).stdout


def arc_poses(scene: str, n: int) -> dict:
    """Explicit-rig file content: n training eyes on the arc, 8 test eyes between them."""
    rig = default_rig(scene)
    target = np.asarray(rig.target, dtype=float)

    def eye(azimuth, elevation):
        return spherical_eye(target, rig.radius, azimuth, elevation).tolist()

    train = [{"eye": eye(-ARC_DEG / 2 + ARC_DEG * (i + 0.5) / n, 35.0),
              "target": target.tolist()} for i in range(n)]
    test = [{"eye": eye(a, 30.0 if k % 2 else 40.0), "target": target.tolist()}
            for k, a in enumerate(np.linspace(-0.45 * ARC_DEG, 0.45 * ARC_DEG, 8))]
    return {"train": train, "test": test}


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
        testset = args.work / f"{tag}-test128"
        if not testset.exists():
            poses = args.work / f"{tag}-test-poses.json"
            poses.write_text(json.dumps({"train": arc_poses(scene, 8)["test"]}))
            capture = args.work / f"{tag}-test-512px"
            run(NERFBOT + ["capture", "--scene", scene, "--size", 512, "--rig", "explicit",
                           "--poses", poses, "--test-views", 0, "--out", capture,
                           "--no-progress"])
            run(NERFBOT + ["colmap", capture, "--out", testset, "--known-poses", "--downscale", 4,
                           "--no-progress"])
            meta = json.loads((testset / "transforms.json").read_text())
            meta["test_filenames"] = meta["val_filenames"] = meta.pop("train_filenames")
            meta["train_filenames"] = []
            (testset / "transforms.json").write_text(json.dumps(meta, indent=2))
        rows = {}
        for n in counts:
            capture = args.work / f"{tag}-{n}v-512px"
            if not (capture / "transforms.json").exists():
                poses = args.work / f"{tag}-{n}v-poses.json"
                poses.write_text(json.dumps({"train": arc_poses(scene, n)["train"]}))
                run(NERFBOT + ["capture", "--scene", scene, "--size", 512, "--rig", "explicit",
                               "--poses", poses, "--test-views", 0, "--out", capture,
                               "--no-progress"])
            data = args.work / f"{tag}-{n}v"
            if not (data / "transforms.json").exists():
                run(NERFBOT + ["colmap", capture, "--out", data, "--known-poses", "--downscale", 4,
                               "--no-progress"])
            report = json.loads((data / "sfm_report.json").read_text())
            files = list((data / "sparse_depth").rglob("*.npy")) \
                if (data / "sparse_depth").exists() else []
            row = {"keypoints": int(sum(len(np.load(p)) for p in files)),
                   "points": report["points"],
                   "sfm_alone": sfm_alone(capture, args.work / f"{tag}-{n}v-sfm")}
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
