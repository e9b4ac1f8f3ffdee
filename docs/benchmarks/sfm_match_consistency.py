"""How many of SfM's matches are right? (BENCHMARKS.md, section 12)

usage: python docs/benchmarks/sfm_match_consistency.py CAPTURE SFM_DATASET [--max-error PX]

CAPTURE is the dataset ``nerfbot colmap`` posed (its true poses are the reference), SFM_DATASET
the dataset it wrote (``colmap/database.db`` inside). For every image pair with matches, the
share of the matches that lie within ``--max-error`` pixels (Sampson distance, at the SfM
images' resolution) of the epipolar geometry of the two true poses: first the matches the
descriptors found (ratio test, cross check), then those geometric verification kept (the
``inlier_matches`` of the pair's two-view geometry, which the mapper uses). A texture that
repeats gives matches to the wrong copy of a pattern; if they agree with one another, the
verification keeps them and the right ones go.

Prints the medians over pairs and the share of pairs whose verified matches are mostly right,
the same by the angle between the two cameras' optical axes, and which kind of two-view
geometry verification chose (essential, fundamental or planar).
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import pycolmap

from nerfbot.ops.cameras import opengl_to_opencv
from nerfbot.sfm.dataset import dataset_input


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def sampson_px(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """(M,) Sampson distances in pixels of matched pixels x1, x2 (M, 2) under F (3, 3)."""
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    f1, f2 = h1 @ F.T, h2 @ F
    num = np.sum(h2 * f1, 1) ** 2
    return np.sqrt(num / (f1[:, 0] ** 2 + f1[:, 1] ** 2 + f2[:, 0] ** 2 + f2[:, 1] ** 2))


def true_fundamental(K: np.ndarray, c2w_a: np.ndarray, c2w_b: np.ndarray) -> np.ndarray:
    """F (3, 3) with x_b^T F x_a = 0 for two OpenGL camera-to-world poses (4, 4)."""
    wa, wb = np.linalg.inv(opengl_to_opencv(c2w_a)), np.linalg.inv(opengl_to_opencv(c2w_b))
    R = wb[:3, :3] @ wa[:3, :3].T
    t = wb[:3, 3] - R @ wa[:3, 3]
    Ki = np.linalg.inv(K)
    return Ki.T @ _skew(t) @ R @ Ki


_CONFIGS = {2: "essential", 3: "fundamental", 4: "planar", 5: "panoramic",
            6: "planar or panoramic", 7: "watermark", 8: "multiple"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", type=Path)
    parser.add_argument("sfm_dataset", type=Path)
    parser.add_argument("--max-error", type=float, default=2.0,
                        help="Sampson distance that counts as right, pixels")
    args = parser.parse_args()
    truth = dataset_input(args.capture).true_c2w
    db = pycolmap.Database.open(str(args.sfm_dataset / "colmap" / "database.db"))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        camera = db.read_all_cameras()[0]
        fx, fy, cx, cy = camera.params[:4]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        pairs, geometries = db.read_two_view_geometries()
        raw_share, verified_share, configs, angles = [], [], Counter(), []
        counts, right = [0, 0], [0, 0]
        for pair, geometry in zip(pairs, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pair)
            F = true_fundamental(K, truth[names[a]], truth[names[b]])
            ka, kb = db.read_keypoints(a)[:, :2], db.read_keypoints(b)[:, :2]
            raw = db.read_matches(a, b)
            if len(raw):
                ok = sampson_px(F, ka[raw[:, 0]], kb[raw[:, 1]]) < args.max_error
                raw_share.append(ok.mean())
                counts[0] += len(raw)
                right[0] += int(ok.sum())
            kept = geometry.inlier_matches
            if len(kept):
                ok = sampson_px(F, ka[kept[:, 0]], kb[kept[:, 1]]) < args.max_error
                verified_share.append(ok.mean())
                axes = truth[names[a]][:3, 2] @ truth[names[b]][:3, 2]
                angles.append(np.degrees(np.arccos(np.clip(axes, -1.0, 1.0))))
                configs[_CONFIGS.get(int(geometry.config), str(geometry.config))] += 1
                counts[1] += len(kept)
                right[1] += int(ok.sum())
    finally:
        db.close()
    raw_share, verified_share = np.array(raw_share), np.array(verified_share)
    print(f"{args.sfm_dataset}: {len(raw_share)} matched pairs ({counts[0]} matches), "
          f"{len(verified_share)} verified ({counts[1]} matches)")
    print(f"right within {args.max_error:g} px of the true epipolar geometry: "
          f"matches {np.median(raw_share):.2f} (median over pairs), "
          f"verified matches {np.median(verified_share):.2f}; pooled over pairs: matches "
          f"{right[0] / max(counts[0], 1):.2f}, verified {right[1] / max(counts[1], 1):.2f}")
    right_pairs = verified_share > 0.5
    print(f"verified pairs whose matches are mostly right: {right_pairs.mean():.2f} "
          f"({right_pairs.sum()} of {len(right_pairs)})")
    angles = np.array(angles)
    for lo, hi in ((0, 15), (15, 30), (30, 60), (60, 180)):
        inside = (angles >= lo) & (angles < hi)
        print(f"  cameras {lo}-{hi} deg apart: {inside.sum()} verified pairs, "
              f"{(inside & right_pairs).sum()} mostly right")
    print("two-view geometry: " + ", ".join(f"{k} {v}" for k, v in configs.most_common()))


if __name__ == "__main__":
    main()
