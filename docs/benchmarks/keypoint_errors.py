"""How far DS-NeRF's keypoints lie from the true surface: each keypoint's depth against the
simulator's depth at its pixel.

usage: python docs/benchmarks/keypoint_errors.py DATASET [DATASET ...]

DATASET: a folder ``nerfbot colmap CAPTURE --known-poses`` wrote from a ``sims`` capture (its
frames carry ``sparse_depth_file_path`` and the capture's ``nerfbot_depth_file_path``). Prints
one markdown row per dataset: keypoints, the share more than 5 and 20 cm off, the median error.
A keypoint's pixel is the training pixel holding it, so one at an object's edge is compared with
whichever surface that pixel's centre sees.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def keypoint_errors(data: Path) -> np.ndarray:
    """(K,) metres: |keypoint z-depth - true z-depth at its pixel| over the training frames."""
    meta = json.loads((data / "transforms.json").read_text())
    frames = {f["file_path"]: f for f in meta["frames"]}
    errors = []
    for name in meta["train_filenames"]:
        frame = frames[name]
        if "sparse_depth_file_path" not in frame or "nerfbot_depth_file_path" not in frame:
            raise SystemExit(f"{data / 'transforms.json'}: frame {name} lacks "
                             "sparse_depth_file_path or nerfbot_depth_file_path")
        keys = np.load(data / frame["sparse_depth_file_path"])
        truth = np.load(data / frame["nerfbot_depth_file_path"]).astype(np.float64)
        if len(keys) == 0:
            continue
        col = np.clip(keys[:, 0].astype(int), 0, truth.shape[1] - 1)
        row = np.clip(keys[:, 1].astype(int), 0, truth.shape[0] - 1)
        errors.append(np.abs(keys[:, 2] - truth[row, col]))
    return np.concatenate(errors) if errors else np.zeros(0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", type=Path, nargs="+")
    args = ap.parse_args()
    print("| dataset | keypoints | > 5 cm off | > 20 cm off | median error |")
    print("|---|---|---|---|---|")
    for data in args.datasets:
        e = keypoint_errors(data)
        if not len(e):
            print(f"| {data.name} | 0 | - | - | - |")
            continue
        print(f"| {data.name} | {len(e)} | {100 * np.mean(e > 0.05):.1f} % | "
              f"{100 * np.mean(e > 0.2):.1f} % | {100 * np.median(e):.2f} cm |")


if __name__ == "__main__":
    main()
