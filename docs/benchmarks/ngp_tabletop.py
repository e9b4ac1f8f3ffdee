"""The `ngp` headline: the README's command on the built-in tabletop, in three dataset forms.

Captures the tabletop (128x128, 60 train / 10 test views) as nerfstudio, as Blender and as
Blender without a manifest (bounds from the cameras), trains `ngp` for SECONDS on each with the
test PSNR measured at four points of the budget, one run after another, and prints the markdown
table of BENCHMARKS.md. Every step is a `nerfbot` command; the captures and runs stay in OUT.

usage: python docs/benchmarks/ngp_tabletop.py OUT [--seconds 180]
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

DATASETS = (  # (label, folder name, extra capture flags)
    ("nerfstudio `transforms.json`", "data_ns", []),
    ("Blender `transforms_{train,test}.json`", "data_bl", ["--format", "blender"]),
    ("Blender, no manifest", "data_bl_nomf", ["--format", "blender", "--no-manifest"]),
)


def nerfbot(*args: str) -> None:
    print("$ nerfbot", " ".join(args), flush=True)
    subprocess.run(["nerfbot", *args], check=True)


def cm(value) -> str:
    return "-" if value is None or value != value else f"{100 * value:.2f} cm"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seconds", type=float, default=180.0)
    args = parser.parse_args()
    out, seconds = args.out, args.seconds
    marks = [seconds * f for f in (1 / 6, 1 / 3, 2 / 3, 1)]
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for label, name, flags in DATASETS:
        data, run = out / name, out / f"ngp_{name}"
        if not (data / ".nerfbot.json").exists():
            nerfbot("capture", "--scene", "tabletop", "--views", "60", "--test-views", "10",
                    "--size", "128", *flags, "--out", str(data))
        if not (run / "metrics.json").exists():
            nerfbot("train", "--data", str(data), "--method", "ngp", "--max-seconds",
                    f"{seconds:g}", "--eval-at", ",".join(f"{m:g}" for m in marks),
                    "--no-progress", "--out", str(run))
        metrics = json.loads((run / "metrics.json").read_text())
        curve = json.loads((run / "curve.json").read_text())
        at = [min(curve, key=lambda p: abs(p["train_seconds"] - m))["psnr"] for m in marks]
        steps = metrics["steps"]
        rows.append(
            f"| {label} | " + " | ".join(f"{p:.2f}" for p in at[:-1]) + f" | **{at[-1]:.2f}** | "
            f"{metrics.get('psnr_non_sky', float('nan')):.2f} | {metrics['ssim']:.3f} | "
            f"{steps} ({steps / metrics['train_seconds']:.2f}) | {cm(metrics['depth_mae_m'])} | "
            f"{cm(metrics.get('depth_mae_objects_m'))} / "
            f"{cm(metrics.get('median_depth_mae_objects_m'))} | "
            f"{metrics['render_ms_per_image']:.0f} |")
    head = " | ".join(f"@{m:g} s" for m in marks)
    print(f"\n| dataset | PSNR {head} | non-sky PSNR | SSIM | steps (steps/s) | depth MAE, all "
          "| objects: expected / median | render ms |")
    print("|---|" + "---|" * 10)
    print("\n".join(rows))


if __name__ == "__main__":
    sys.exit(main())
