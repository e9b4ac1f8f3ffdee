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

from nerfbot.data.colmap import cam_from_world_from_c2w
from nerfbot.sfm.dataset import dataset_input
from nerfbot.sfm.pipeline import epipolar_errors_px

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
        focal = camera.mean_focal_length()
        world_to_cam = {i: cam_from_world_from_c2w(truth[n])[:3] for i, n in names.items()}
        normalised = {i: np.asarray(camera.cam_from_img(
            db.read_keypoints(i)[:, :2].astype(np.float64)), np.float64) for i in names}
        pairs, geometries = db.read_two_view_geometries()
        raw_share, verified_share, configs, angles = [], [], Counter(), []
        counts, right = [0, 0], [0, 0]
        for pair, geometry in zip(pairs, geometries):
            a, b = pycolmap.pair_id_to_image_pair(pair)
            raw = db.read_matches(a, b)
            if len(raw):
                ok = epipolar_errors_px(world_to_cam[a], world_to_cam[b],
                                        normalised[a][raw[:, 0]], normalised[b][raw[:, 1]],
                                        focal) < args.max_error
                raw_share.append(ok.mean())
                counts[0] += len(raw)
                right[0] += int(ok.sum())
            kept = geometry.inlier_matches
            if len(kept):
                ok = epipolar_errors_px(world_to_cam[a], world_to_cam[b],
                                        normalised[a][kept[:, 0]], normalised[b][kept[:, 1]],
                                        focal) < args.max_error
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
