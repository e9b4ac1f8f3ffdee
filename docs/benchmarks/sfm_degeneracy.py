"""Are COLMAP's pose errors noise or a degenerate direction? (BENCHMARKS.md, section 12)

usage: python docs/benchmarks/sfm_degeneracy.py CAPTURE WORK

Runs structure from motion on the capture (``nerfbot colmap``'s defaults, intrinsics known),
and triangulates the same matches with the capture's true poses. If the true poses fit the
matches as well as COLMAP's (mean reprojection errors alike), the observations cannot tell the
two apart: the remaining error lies along a direction they leave free. Then, per camera after
the similarity alignment, the rotation error about the camera's x and y axes against its
centre's shift along y and x (in the camera's frame): an orbit about a point d metres ahead
pairs a turn of a with a shift of d x a.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from nerfbot.data.colmap import image_c2w
from nerfbot.ops.alignment import pose_errors
from nerfbot.sfm.dataset import dataset_input
from nerfbot.sfm.pipeline import run_sfm, triangulate_known_poses


def main() -> None:
    capture, work = Path(sys.argv[1]), Path(sys.argv[2])
    work.mkdir(parents=True, exist_ok=True)
    sfm_input = dataset_input(capture)
    known = triangulate_known_poses(sfm_input.root, sfm_input.names, work / "known",
                                    sfm_input.camera, sfm_input.true_c2w, progress=False)
    result = run_sfm(sfm_input.root, sfm_input.names, work / "sfm", sfm_input.camera,
                     progress=False)
    rec = result.reconstruction
    truth = known.reconstruction
    print(f"mean reprojection error: true poses {truth.compute_mean_reprojection_error():.3f} "
          f"px ({truth.num_points3D()} points), COLMAP's "
          f"{rec.compute_mean_reprojection_error():.3f} px ({rec.num_points3D()} points)")
    images = [im for im in rec.images.values() if im.has_pose]
    est = np.stack([image_c2w(im) for im in images])
    true = np.stack([sfm_input.true_c2w[im.name] for im in images])
    errors = pose_errors(est, true)
    sim = errors.alignment
    rows = []
    for e, t in zip(est, true):
        turn = t[:3, :3].T @ sim.rotation @ e[:3, :3]   # the error, in the camera's frame
        axis = np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0],
                         turn[1, 0] - turn[0, 1]]) / 2
        centre = sim.scale * sim.rotation @ e[:3, 3] + sim.translation
        rows.append(np.r_[axis, t[:3, :3].T @ (centre - t[:3, 3])])
    rows = np.array(rows)
    print(f"rotation error median {np.median(errors.rotation_deg):.3f} deg over {len(images)} "
          "cameras")
    for turn, shift, name in ((0, 4, "x turn vs y shift"), (1, 3, "y turn vs x shift")):
        r = np.corrcoef(rows[:, turn], rows[:, shift])[0, 1]
        ratio = np.median(np.abs(rows[:, shift]) / np.maximum(np.abs(rows[:, turn]), 1e-9))
        print(f"{name}: correlation {r:+.3f}, shift / turn {ratio:.2f} m")


if __name__ == "__main__":
    main()
