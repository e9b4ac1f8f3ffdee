"""Few training views, RGB only against DS-NeRF sparse depth supervision.

usage: python docs/benchmarks/few_views.py WORK [--scenes tabletop,workspace:0]
                                           [--views 2,3,5,10] [--seconds 60] [--weight 0.1]
                                           [--repeats 1] [--size 512] [--downscale 4]
                                           [--robust C] [--until F] [--no-guided-matching]

Few-view work poses a scene from one side, as a robot's camera does from where it stands: for
N training views, cameras on an arc of 60 degrees of azimuth around the scene's target (the
scene's own rig radius, 35 degrees elevation), evenly spaced; 8 test views on the same arc
between them, at 30 and 40 degrees elevation, the same for every N. For each scene and N:

1. ``nerfbot capture --rig explicit`` at ``--size`` px, then ``nerfbot colmap CAPTURE
   --known-poses --downscale D``: SIFT features and matches among the N training images only
   (the test images are posed by a second capture and never matched), points triangulated
   with the simulator's poses; images, depth and keypoints written at size / D px. The column "SfM alone"
   says whether ``nerfbot colmap`` without the poses registers the N views.
2. ``nerfbot train --method ngp --max-seconds S --seed R``, with and without
   ``--sparse-depth-weight W`` (with ``--robust C``, also with it and
   ``--sparse-depth-robust C``; with ``--until F``, also with it, ``--sparse-depth-until F`` and
   the robust weights if given), for R = 0 .. repeats - 1.
3. ``nerfbot eval --data TESTSET --split test``: PSNR, SSIM, depth MAE on the 8 test views.

Writes WORK/few_views.json (every run), WORK/few_views.png (medians over the repeats, PSNR and
depth MAE against N) and prints a markdown table of the medians and, with repeats, of how many
seeds sparse depth won. One thing at a time.
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


def sfm_alone(data: Path, out: Path, flags: list) -> dict:
    """Would structure from motion alone pose these views? (registered, rotation error)."""
    if not (out / "sfm_report.json").exists():
        try:
            run(NERFBOT + ["colmap", data, "--out", out, "--no-progress", *flags])
        except subprocess.CalledProcessError as e:
            return {"registered": 0, "error": e.stderr.strip().splitlines()[-1]}
    report = json.loads((out / "sfm_report.json").read_text())
    row = {"registered": report["registered"]}
    if "pose_errors" in report:
        row["rotation_deg_median"] = report["pose_errors"]["rotation_deg_median"]
    return row


METRICS = ("psnr", "ssim", "depth_mae_m")


def median_of(runs: list) -> dict:
    return {k: float(np.median([r[k] for r in runs])) for k in METRICS}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--scenes", default="tabletop,workspace:0")
    ap.add_argument("--views", default="2,3,5,10")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--weight", type=float, default=0.1)
    ap.add_argument("--repeats", type=int, default=1, help="training seeds per point")
    ap.add_argument("--size", type=int, default=512, help="capture size, px (SfM runs on it)")
    ap.add_argument("--downscale", type=int, default=4, help="fields train on size / N px")
    ap.add_argument("--robust", type=float, default=0.0, metavar="C",
                    help="also train with --sparse-depth-robust C (robust keypoint weights)")
    ap.add_argument("--until", type=float, default=1.0, metavar="F",
                    help="also train with --sparse-depth-until F (and --robust's weights)")
    ap.add_argument("--no-guided-matching", action="store_true",
                    help="nerfbot colmap --no-guided-matching (fewer keypoints)")
    args = ap.parse_args()
    counts = [int(v) for v in args.views.split(",")]
    args.work.mkdir(parents=True, exist_ok=True)
    px = f"{args.size}px"
    sfm_flags = ["--no-guided-matching"] if args.no_guided_matching else []
    results = {}
    for scene in args.scenes.split(","):
        tag = scene.replace(":", "_")
        testset = args.work / f"{tag}-test{args.size // args.downscale}"
        if not testset.exists():
            poses = args.work / f"{tag}-test-poses.json"
            poses.write_text(json.dumps({"train": arc_poses(scene, 8)["test"]}))
            capture = args.work / f"{tag}-test-{px}"
            run(NERFBOT + ["capture", "--scene", scene, "--size", args.size, "--rig", "explicit",
                           "--poses", poses, "--test-views", 0, "--out", capture,
                           "--no-progress"])
            run(NERFBOT + ["colmap", capture, "--out", testset, "--known-poses", "--downscale",
                           args.downscale, "--no-progress", *sfm_flags])
            meta = json.loads((testset / "transforms.json").read_text())
            meta["test_filenames"] = meta["val_filenames"] = meta.pop("train_filenames")
            meta["train_filenames"] = []
            (testset / "transforms.json").write_text(json.dumps(meta, indent=2))
        rows = {}
        for n in counts:
            capture = args.work / f"{tag}-{n}v-{px}"
            if not (capture / "transforms.json").exists():
                poses = args.work / f"{tag}-{n}v-poses.json"
                poses.write_text(json.dumps({"train": arc_poses(scene, n)["train"]}))
                run(NERFBOT + ["capture", "--scene", scene, "--size", args.size, "--rig",
                               "explicit", "--poses", poses, "--test-views", 0, "--out", capture,
                               "--no-progress"])
            data = args.work / f"{tag}-{n}v"
            if not (data / "transforms.json").exists():
                run(NERFBOT + ["colmap", capture, "--out", data, "--known-poses", "--downscale",
                               args.downscale, "--no-progress", *sfm_flags])
            report = json.loads((data / "sfm_report.json").read_text())
            files = list((data / "sparse_depth").rglob("*.npy")) \
                if (data / "sparse_depth").exists() else []
            row = {"keypoints": int(sum(len(np.load(p)) for p in files)),
                   "points": report["points"],
                   "sfm_alone": sfm_alone(capture, args.work / f"{tag}-{n}v-sfm", sfm_flags)}
            variants = [("rgb", []), ("sparse_depth", ["--sparse-depth-weight", args.weight])]
            if args.robust > 0:
                variants.append(("robust", ["--sparse-depth-weight", args.weight,
                                            "--sparse-depth-robust", args.robust]))
            if args.until < 1:
                variants.append(("until", ["--sparse-depth-weight", args.weight,
                                           "--sparse-depth-robust", args.robust,
                                           "--sparse-depth-until", args.until]))
            for name, extra in variants:
                if name != "rgb" and not row["keypoints"]:
                    continue
                runs = []
                for seed in range(args.repeats):
                    out = args.work / "runs" / f"{tag}-{n}v-{name}-s{seed}"
                    if not (out / "checkpoint.pt").exists():
                        run(NERFBOT + ["train", "--data", data, "--method", "ngp",
                                       "--max-seconds", args.seconds, "--seed", seed, "--out", out,
                                       "--no-progress", *extra])
                    ev = json.loads(run(NERFBOT + ["eval", out, "--data", testset, "--split",
                                                   "test", "--json"]))
                    runs.append({k: ev.get(k) for k in (*METRICS, "steps")})
                row[name] = {"runs": runs, "median": median_of(runs)}
            for name in ("sparse_depth", "robust", "until"):   # paired by seed
                if name in row:
                    pairs = list(zip(row["rgb"]["runs"], row[name]["runs"]))
                    row[f"{name}_wins"] = {
                        "psnr": sum(b["psnr"] > a["psnr"] for a, b in pairs),
                        "depth_mae_m": sum(b["depth_mae_m"] < a["depth_mae_m"]
                                           for a, b in pairs)}
            rows[n] = row
            results[scene] = rows
            (args.work / "few_views.json").write_text(json.dumps(results, indent=2))

    nan = {k: float("nan") for k in METRICS}
    print(f"Medians over {args.repeats} seed(s); wins: seeds where sparse depth gave the higher "
          "PSNR / the lower depth MAE.")
    print("| scene | views | keypoints | SfM alone registers | PSNR RGB / +sparse depth | "
          "SSIM RGB / +sparse | depth MAE cm RGB / +sparse | wins PSNR, depth |")
    print("|---|---|---|---|---|---|---|---|")
    for scene, rows in results.items():
        for n, r in rows.items():
            rgb = r["rgb"]["median"]
            sd = r["sparse_depth"]["median"] if "sparse_depth" in r else nan
            wins = r.get("sparse_depth_wins")
            won = f"{wins['psnr']}/{args.repeats}, {wins['depth_mae_m']}/{args.repeats}" \
                if wins else "-"
            alone = r["sfm_alone"]
            reg = f"{alone['registered']}/{n}" + (
                f" ({alone['rotation_deg_median']:.2f} deg)" if "rotation_deg_median" in alone
                else "")
            print(f"| {scene} | {n} | {r['keypoints']} | {reg} | {rgb['psnr']:.2f} / "
                  f"{sd['psnr']:.2f} | {rgb['ssim']:.3f} / {sd['ssim']:.3f} | "
                  f"{100 * rgb['depth_mae_m']:.1f} / {100 * sd['depth_mae_m']:.1f} | {won} |")
            if "robust" in r:
                rb, rw = r["robust"]["median"], r["robust_wins"]
                print(f"|   robust (C = {args.robust}) | | | | {rb['psnr']:.2f} | "
                      f"{rb['ssim']:.3f} | {100 * rb['depth_mae_m']:.1f} | "
                      f"{rw['psnr']}/{args.repeats}, {rw['depth_mae_m']}/{args.repeats} |")
            if "until" in r:
                ut, uw = r["until"]["median"], r["until_wins"]
                print(f"|   until {args.until} | | | | {ut['psnr']:.2f} | "
                      f"{ut['ssim']:.3f} | {100 * ut['depth_mae_m']:.1f} | "
                      f"{uw['psnr']}/{args.repeats}, {uw['depth_mae_m']}/{args.repeats} |")

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for scene, rows in results.items():
        ns = sorted(rows)
        for name, style in (("rgb", "o--"), ("sparse_depth", "s-"), ("robust", "^:"), ("until", "v-.")):
            ok = [n for n in ns if name in rows[n]]
            axes[0].plot(ok, [rows[n][name]["median"]["psnr"] for n in ok], style,
                         label=f"{scene} {name.replace('_', ' ')}")
            axes[1].plot(ok, [100 * rows[n][name]["median"]["depth_mae_m"] for n in ok], style)
    axes[0].set(xlabel="training views", ylabel=f"test PSNR (dB), median of {args.repeats}")
    axes[1].set(xlabel="training views", ylabel="test depth MAE (cm)", yscale="log")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.work / "few_views.png", dpi=120)


if __name__ == "__main__":
    main()
