"""Axis-aligned bounds of a scene: from the user, from the scene manifest, or from the cameras.

Priority in :func:`nerfbot.data.load_dataset`: the ``aabb`` argument, else the manifest's
``scene.bounds`` padded by :func:`pad_bounds`, else :func:`estimate_bounds_from_cameras`.

Camera-based rule (all distances in metres):

1. Optical axes: camera centre ``o_i`` and viewing direction ``d_i`` (the camera's -z axis).
   The centre ``p`` is the least-squares point closest to all axes, solving
   ``sum_i (I - d_i d_i^T) p = sum_i (I - d_i d_i^T) o_i``.
2. Half-size of a cube: ``h = 1.1 * median_i(|o_i - p| * tan(fov_i / 2))`` with ``fov_i`` the
   larger of camera i's horizontal and vertical fields of view, then capped at
   ``0.9 * min_i |o_i - p|_inf`` so that no camera lies inside the box.
3. Fallback, used when the axes are (nearly) parallel (smallest eigenvalue of
   ``mean_i(I - d_i d_i^T)`` below ``2e-3``, i.e. the axes spread less than about 5 degrees),
   when there is a single camera, or when ``p`` lies behind most cameras (median of
   ``(p - o_i) . d_i`` <= 0): the look distance ``D`` is the median distance of the cameras from
   their centroid, at least 1 m; look points ``l_i = o_i + D d_i``; the cube is centred on their
   mean ``c`` with half-size ``1.1 * (max_i |l_i - c|_inf + median_i(D tan(fov_i / 2)))``, and
   capped as in step 2.
   In both rules the cap is skipped only if a camera sits at the centre itself (it would give
   an empty box).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Relative margin added to manifest bounds on every side, per axis, and its floor in metres.
MANIFEST_PAD_FRACTION = 0.05
MANIFEST_PAD_MIN = 0.01
#: Smallest eigenvalue of mean(I - d d^T) below which optical axes count as parallel.
PARALLEL_EIGEN = 2e-3
#: Enlargement of the view-cone footprint, and the fraction of the nearest camera's distance
#: the half-size may reach.
SIZE_FACTOR = 1.1
CAP_FACTOR = 0.9
#: Look distance floor of the parallel-axes fallback, metres.
MIN_LOOK_DISTANCE = 1.0


def as_aabb(value: Any, where: str, *, strict: bool) -> np.ndarray:
    """Validate ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` into (2, 3) float64.

    Raises ``ValueError`` (prefixed by ``where``) on a wrong shape, non-finite values, or
    min > max (min >= max when ``strict``).
    """
    try:
        box = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected [[xmin, ymin, zmin], [xmax, ymax, zmax]], "
                         f"got {value!r}") from None
    if box.shape != (2, 3):
        raise ValueError(f"{where}: expected shape (2, 3) [[xmin, ymin, zmin], "
                         f"[xmax, ymax, zmax]], got shape {box.shape}")
    if not np.all(np.isfinite(box)):
        raise ValueError(f"{where}: bounds must be finite, got {box.tolist()}")
    bad = box[0] >= box[1] if strict else box[0] > box[1]
    if np.any(bad):
        raise ValueError(f"{where}: min corner must be below the max corner on every axis, "
                         f"got {box.tolist()}")
    return box


def pad_bounds(aabb: np.ndarray, fraction: float = MANIFEST_PAD_FRACTION,
               minimum: float = MANIFEST_PAD_MIN) -> np.ndarray:
    """Grow (2, 3) bounds on every side by ``max(fraction * extent, minimum)`` per axis."""
    aabb = np.asarray(aabb, dtype=np.float64)
    pad = np.maximum(fraction * (aabb[1] - aabb[0]), minimum)
    return np.stack([aabb[0] - pad, aabb[1] + pad])


def _tan_half_fov(intrinsics: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(N,) tangent of half the larger of each camera's horizontal and vertical fov."""
    fx, fy, cx, cy = (intrinsics[:, k] for k in range(4))
    w, h = sizes[:, 0], sizes[:, 1]
    fov_x = np.arctan(cx / fx) + np.arctan((w - cx) / fx)
    fov_y = np.arctan(cy / fy) + np.arctan((h - cy) / fy)
    return np.tan(np.clip(np.maximum(fov_x, fov_y), 1e-6, math.pi - 1e-3) / 2.0)


def _capped_cube(centre: np.ndarray, half: float, origins: np.ndarray) -> np.ndarray:
    """Cube ``centre +- half``, shrunk so every camera in ``origins`` stays outside it."""
    nearest = float(np.abs(origins - centre).max(axis=1).min())
    cap = CAP_FACTOR * nearest
    if cap > 1e-9:
        half = min(half, cap)
    else:
        log.warning("a camera sits at the estimated scene centre; bounds are not capped")
    return np.stack([centre - half, centre + half])


def estimate_bounds_with_rule(c2w, intrinsics, sizes) -> tuple[np.ndarray, str]:
    """:func:`estimate_bounds_from_cameras` plus the rule used: "axes" or "look_points"."""
    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    intrinsics = np.asarray(intrinsics, dtype=np.float64).reshape(-1, 4)
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 2)
    n = c2w.shape[0]
    if n == 0 or intrinsics.shape[0] != n or sizes.shape[0] != n:
        raise ValueError(f"estimate_bounds_from_cameras: need N >= 1 cameras with matching "
                         f"intrinsics and sizes, got {n}, {intrinsics.shape[0]}, {sizes.shape[0]}")
    origins = c2w[:, :3, 3]
    dirs = -c2w[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    tan_half = _tan_half_fov(intrinsics, sizes)

    projectors = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]      # (N, 3, 3)
    a = projectors.sum(axis=0)
    b = np.einsum("nij,nj->i", projectors, origins)
    if n >= 2 and np.linalg.eigvalsh(a / n)[0] > PARALLEL_EIGEN:
        centre = np.linalg.solve(a, b)
        if np.median(np.einsum("ni,ni->n", centre - origins, dirs)) > 0.0:
            dist = np.linalg.norm(origins - centre, axis=1)
            half = SIZE_FACTOR * float(np.median(dist * tan_half))
            return _capped_cube(centre, half, origins), "axes"

    centroid = origins.mean(axis=0)
    look = max(float(np.median(np.linalg.norm(origins - centroid, axis=1))), MIN_LOOK_DISTANCE)
    points = origins + look * dirs
    centre = points.mean(axis=0)
    spread = float(np.abs(points - centre).max())
    half = SIZE_FACTOR * (spread + float(np.median(look * tan_half)))
    return _capped_cube(centre, half, origins), "look_points"


def estimate_bounds_from_cameras(c2w, intrinsics, sizes) -> np.ndarray:
    """Estimate scene bounds from camera poses alone (see the module docstring for the rule).

    Args:
        c2w: (N, 4, 4) camera-to-world poses, OpenGL convention (cameras look along -z), metres.
        intrinsics: (N, 4) fx, fy, cx, cy in pixels.
        sizes: (N, 2) image width, height in pixels.

    Returns:
        (2, 3) float64 min / max corners of a cube, metres.
    """
    return estimate_bounds_with_rule(c2w, intrinsics, sizes)[0]
