"""Where each moving rigid body of a dynamic capture is at each training time step, from the
training frames' segmentation: the starting track of the ``rigid`` method's parts.

For every training frame and body, the centroid of the body's mask gives a ray through the
body. The track is the least-squares point sequence closest to those rays, with a penalty on
its second differences over time (a body moves smoothly between steps):

    min_C  sum_rays |P_i (c_step(i) - o_i)|^2  +  SMOOTHNESS sum_j |c_{j-1} - 2 c_j + c_{j+1}|^2

(``P_i = I - d_i d_i^T`` projects onto the plane across ray i). Many cameras per step
triangulate each step; a single camera that moves between steps (a monocular capture) is
resolved by the smoothness, since consecutive rays see the body from different directions.
The body's extent (half the edge of the cube a part models) is a high percentile of its masks'
radii at the track's depth, with a margin.

Only training frames are read; the segmentation of held-out frames never enters a model.
"""

from __future__ import annotations

import numpy as np

#: A mask smaller than this (pixels) gives no ray: its centroid is too uncertain.
MIN_PIXELS = 4
#: Weight of a step's squared second difference relative to one ray's squared distance.
SMOOTHNESS = 1.0
#: Weight pulling every step towards the body's mean point, so steps without any ray (and the
#: ends of a monocular track) stay defined: small against a ray's weight of 1.
ANCHOR = 1e-4
#: Percentile of the per-ray mask radii (in metres) taken as the body's radius: below 100 so a
#: mask merged with a neighbour's at one step does not size the part.
RADIUS_PERCENTILE = 90.0
#: The part's cube half-edge per body radius: the mask's radius is the body's projected
#: outline, which a rotating body exceeds in other views.
EXTENT_MARGIN = 1.5
#: Smallest half-edge of a part's cube, metres.
MIN_EXTENT = 0.02


def _mask_ray(seg: np.ndarray, geoms: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray):
    """(origin (3,), unit direction (3,), radius in pixels) of a body's mask in one frame, or
    None when the mask is too small or touches the image border (its centroid is biased)."""
    mask = np.isin(seg, geoms)
    count = int(mask.sum())
    if count < MIN_PIXELS:
        return None
    v, u = np.nonzero(mask)
    h, w = seg.shape
    if u.min() == 0 or v.min() == 0 or u.max() == w - 1 or v.max() == h - 1:
        return None
    uc, vc = u.mean() + 0.5, v.mean() + 0.5
    radius_px = float(np.sqrt(((u + 0.5 - uc) ** 2 + (v + 0.5 - vc) ** 2).max())) + 0.5
    fx, fy, cx, cy = intrinsics
    d_cam = np.array([(uc - cx) / fx, -(vc - cy) / fy, -1.0])
    d = c2w[:3, :3] @ (d_cam / np.linalg.norm(d_cam))
    return c2w[:3, 3].copy(), d, radius_px


def solve_track(steps: np.ndarray, step_of_ray: np.ndarray, origins: np.ndarray,
                directions: np.ndarray, smoothness: float = SMOOTHNESS) -> np.ndarray:
    """(J, 3) points closest to the rays of their steps, smooth over the steps.

    Args:
        steps: (J,) sorted step times (any units; their spacing weighs the second differences).
        step_of_ray: (R,) index into ``steps`` of each ray.
        origins, directions: (R, 3) rays (unit directions).
    """
    n = len(steps)
    proj = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]  # (R, 3, 3)
    a = np.zeros((n, 3, n, 3))
    b = np.zeros((n, 3))
    np.add.at(a, (step_of_ray, slice(None), step_of_ray), proj)
    np.add.at(b, step_of_ray, np.einsum("rij,rj->ri", proj, origins))
    a = a.reshape(3 * n, 3 * n)
    # the point closest to all rays anchors steps no ray constrains
    mean_point = np.linalg.lstsq(proj.sum(0), np.einsum("rij,rj->i", proj, origins),
                                 rcond=None)[0]
    a += ANCHOR * np.eye(3 * n)
    b = b.reshape(-1) + ANCHOR * np.tile(mean_point, n)
    if n >= 3 and smoothness > 0:
        gaps = np.diff(steps.astype(np.float64))
        h = np.median(gaps)
        diff = np.zeros((n - 2, n))
        for j in range(1, n - 1):
            h1, h2 = gaps[j - 1] / h, gaps[j] / h
            mid = 0.5 * (h1 + h2)
            diff[j - 1, j - 1], diff[j - 1, j], diff[j - 1, j + 1] = (
                mid / h1, -mid / h1 - mid / h2, mid / h2)
        a += smoothness * np.kron(diff.T @ diff, np.eye(3))
    return np.linalg.solve(a, b).reshape(n, 3)


def estimate_tracks(dataset, indices=None) -> list[dict]:
    """The tracks of the manifest's ``moving_bodies`` over the training frames.

    Returns a list, one dict per body seen in at least one frame: ``name``, ``geoms`` (ids),
    ``times`` (J,) the distinct training times, ``centres`` (J, 3) metres, ``extent`` metres
    (half-edge of the cube around each centre that holds the body).
    [] when the manifest names no moving bodies, the frames carry no segmentation, or (without
    ``indices``) the dataset has no training split. The manifest's ``moving_bodies`` was
    checked when it was read (:func:`nerfbot.data.spec.manifest_value`).
    """
    bodies = (dataset.manifest or {}).get("moving_bodies") or {}
    if (dataset.times is None or not bodies
            or (indices is None and "train" not in dataset.splits)):
        return []
    idx = list(dataset.indices("train") if indices is None else indices)
    idx = [i for i in idx if dataset.segmentations[i] is not None]
    if not idx:
        return []
    times = np.asarray(dataset.times, np.float64)
    steps = np.unique(times[idx])
    tracks = []
    for name, geoms in sorted(bodies.items()):
        geoms = np.asarray(geoms, np.int32)
        rays = [(np.searchsorted(steps, times[i]), i, _mask_ray(dataset.segmentations[i], geoms,
                                                               dataset.c2w[i],
                                                               dataset.intrinsics[i]))
                for i in idx]
        rays = [(j, i, r) for j, i, r in rays if r is not None]
        if not rays:
            continue
        step_of_ray = np.array([j for j, _, _ in rays])
        origins = np.stack([r[0] for _, _, r in rays])
        directions = np.stack([r[1] for _, _, r in rays])
        centres = solve_track(steps, step_of_ray, origins, directions)
        radii = []
        for (j, i, (o, _, radius_px)) in rays:
            depth = -(dataset.c2w[i][:3, :3].T @ (centres[j] - o))[2]
            if depth > 0:
                radii.append(radius_px * depth / dataset.intrinsics[i][0])
        radius = float(np.percentile(radii, RADIUS_PERCENTILE)) if radii else MIN_EXTENT
        tracks.append({"name": str(name), "geoms": [int(g) for g in geoms],
                       "times": steps.tolist(), "centres": centres.tolist(),
                       "extent": max(MIN_EXTENT, EXTENT_MARGIN * radius)})
    return tracks
