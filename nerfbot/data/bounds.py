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
4. The ground around it, after step 2: when the cameras stand on one side of ``p`` (a
   hemisphere or an arc over a table: the mean unit vector from ``p`` to them is at least
   :data:`ONE_SIDED` long), their oblique views see a ground (the table, a bench, a floor)
   that may reach beyond the cube. With the training images (as :func:`load_dataset` gives
   them), the cube grows over the surface the images agree on around it
   (:mod:`nerfbot.data.surface_extent`, rule "surface"; the cube alone, "axes", when they
   agree on none). Such a surface fills the views, and the cameras see nothing below it: when
   it also fills the cube's footprint at one level, the box's side away from the cameras
   moves up to that level, less :data:`GROUND_MARGIN` of the cube's edge
   (:func:`_on_ground`). From poses alone, it grows to hold the points of the plane through
   ``p`` facing the cameras, out to their median distance from ``p``, that at least
   :data:`GROUND_COVERAGE` of the cameras see (:func:`_ground_footprint`, rule
   "footprint"). Either box is then no longer a cube.

Whether the bounds are enough (:func:`choose_space`, used by the reader): a box models only
what lies inside it. Outdoors the content reaches far beyond the cameras: such a scene is
unbounded, bounded by the cameras' region (:func:`camera_region`) and modelled with the scene
contraction around it. Seen from inside a room the cameras' axes meet nowhere: the box is the
cameras' region.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from nerfbot.data.surface_extent import ground_level, polar_grid, probe_views, surface_points

log = logging.getLogger(__name__)

#: Length of the mean unit vector from the scene centre to the cameras above which the cameras
#: stand on one side of the scene (a hemisphere: about 0.5-0.9; a full sphere: about 0), so
#: the bounds hold the ground their oblique views see (:func:`_ground_footprint`).
ONE_SIDED = 0.5
#: Share of the cameras that must see a point of that ground for the bounds to hold it, and
#: the polar grid the ground is probed on (radii out to the cameras' median distance).
GROUND_COVERAGE = 0.15
GROUND_RINGS = 40
GROUND_AZIMUTHS = 48
#: The ground under the cube (rule "surface"): looked for along the axis nearest the cameras'
#: facing direction when that is within GROUND_MAX_TILT degrees of it; the box's far side is
#: put GROUND_MARGIN of the cube's edge below it.
GROUND_MAX_TILT = 30.0
GROUND_MARGIN = 0.1
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
#: Manifest bounds whose largest edge exceeds this many times the cameras' region hold content
#: far beyond the cameras (outdoors): the scene is unbounded for a box model.
UNBOUNDED_RATIO = 8.0
#: Cameras whose optical axes miss the point closest to all of them by more than this (median
#: angle, degrees) do not look at one object: they see the scene from inside it.
CONVERGENCE_ANGLE = 30.0
#: Margin of the cameras' region on every side, as a fraction of its largest edge, and its
#: floor in metres.
REGION_PAD_FRACTION = 0.1
REGION_PAD_MIN = 0.25


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


def _ground_footprint(centre: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray,
                      sizes: np.ndarray) -> np.ndarray | None:
    """(M, 3) points of the plane through ``centre`` facing the cameras that at least
    :data:`GROUND_COVERAGE` of the cameras see (metres), or None when the cameras do not
    stand on one side of it.

    Cameras on one side of what they look at (a hemisphere over a table, an arc) see a
    ground around it, a table, a bench or a floor, which may reach beyond the cube their
    axes meet in. The plane's normal is the mean direction from ``centre`` to the cameras;
    it counts when that mean is at least :data:`ONE_SIDED` long (a full sphere of cameras
    has none). The plane is probed on a polar grid out to the cameras' median distance from
    ``centre`` (:data:`GROUND_RINGS` radii x :data:`GROUND_AZIMUTHS` directions); a point
    counts when it lies in front of and inside the image of enough cameras.
    """
    origins = c2w[:, :3, 3]
    up = _facing_normal(centre, origins)
    if up is None:
        return None
    radius = float(np.median(np.linalg.norm(origins - centre, axis=1)))
    points = polar_grid(centre, up, radius, GROUND_RINGS, GROUND_AZIMUTHS).reshape(-1, 3)
    rot = c2w[:, :3, :3]
    cam = np.einsum("nji,nmj->nmi", rot, points[None] - origins[:, None])   # (N, M, 3)
    depth = -cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam[..., 0] / depth * intrinsics[:, None, 0] + intrinsics[:, None, 2]
        v = -cam[..., 1] / depth * intrinsics[:, None, 1] + intrinsics[:, None, 3]
    seen = ((depth > 0) & (u >= 0) & (u <= sizes[:, None, 0]) & (v >= 0)
            & (v <= sizes[:, None, 1]))
    kept = points[seen.mean(axis=0) >= GROUND_COVERAGE]
    return kept if len(kept) else None


def _facing_normal(centre: np.ndarray, origins: np.ndarray) -> np.ndarray | None:
    """(3,) unit mean direction from ``centre`` to the cameras at ``origins`` (N, 3), or None
    when they do not stand on one side of it (that mean is shorter than :data:`ONE_SIDED`,
    or a camera sits at ``centre``)."""
    to_cams = origins - centre
    dist = np.linalg.norm(to_cams, axis=1)
    if np.any(dist <= 1e-9):
        return None
    mean = (to_cams / dist[:, None]).mean(axis=0)
    length = float(np.linalg.norm(mean))
    return mean / length if length >= ONE_SIDED else None


def _grown(box: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(2, 3) ``box`` grown to hold ``points`` (K, 3)."""
    return np.stack([np.minimum(box[0], points.min(axis=0)),
                     np.maximum(box[1], points.max(axis=0))])


def _on_ground(box: np.ndarray, cube: np.ndarray, normal: np.ndarray, views) -> np.ndarray:
    """(2, 3) ``box`` with its side away from the cameras moved up to the ground the images
    agree on under ``cube`` (:func:`~nerfbot.data.surface_extent.ground_level`), less
    :data:`GROUND_MARGIN` of the cube's edge; ``box`` unchanged when the facing ``normal`` (3,)
    is more than :data:`GROUND_MAX_TILT` degrees from every axis or no ground fills the
    cube's footprint."""
    k = int(np.argmax(np.abs(normal)))
    if abs(normal[k]) < math.cos(math.radians(GROUND_MAX_TILT)):
        return box
    sign = 1.0 if normal[k] > 0 else -1.0
    level = ground_level(cube, sign * np.eye(3)[k], views)
    if level is None:
        return box
    ground = 0.5 * (cube[0, k] + cube[1, k]) + sign * level
    margin = GROUND_MARGIN * float(np.max(cube[1] - cube[0]))
    box = box.copy()
    if sign > 0:
        box[0, k] = max(box[0, k], ground - margin)
    else:
        box[1, k] = min(box[1, k], ground + margin)
    log.info("the images agree on a surface at %s = %.3g m filling the views: the bounds end "
             "%.3g m beyond it", "xyz"[k], ground, margin)
    return box


def estimate_bounds_with_rule(c2w, intrinsics, sizes, images=None) -> tuple[np.ndarray, str]:
    """:func:`estimate_bounds_from_cameras` plus the rule used: "axes", "surface",
    "footprint" or "look_points"."""
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
            cube = _capped_cube(centre, half, origins)
            if images is not None:
                used = [i for i, image in enumerate(images) if image is not None]
                normal = _facing_normal(centre, origins[used]) if len(used) >= 2 else None
                if normal is not None:
                    views = probe_views(c2w[used], intrinsics[used], [images[i] for i in used])
                    surface = surface_points(cube, normal, views)
                    if surface is not None:
                        return _on_ground(_grown(cube, surface), cube, normal, views), "surface"
                return cube, "axes"
            ground = _ground_footprint(centre, c2w, intrinsics, sizes)
            if ground is None:
                return cube, "axes"
            return _grown(cube, ground), "footprint"

    centroid = origins.mean(axis=0)
    look = max(float(np.median(np.linalg.norm(origins - centroid, axis=1))), MIN_LOOK_DISTANCE)
    points = origins + look * dirs
    centre = points.mean(axis=0)
    spread = float(np.abs(points - centre).max())
    half = SIZE_FACTOR * (spread + float(np.median(look * tan_half)))
    return _capped_cube(centre, half, origins), "look_points"


def estimate_bounds_from_cameras(c2w, intrinsics, sizes, images=None) -> np.ndarray:
    """Estimate scene bounds from the cameras (see the module docstring for the rule).

    Args:
        c2w: (N, 4, 4) camera-to-world poses, OpenGL convention (cameras look along -z), metres.
        intrinsics: (N, 4) fx, fy, cx, cy in pixels.
        sizes: (N, 2) image width, height in pixels.
        images: optional N uint8 (H, W, 3) RGB images, None for a camera whose image should
            not take part (a test view): with them the box grows over the surface the images
            agree on (rule "surface"), without them over the ground the cameras see
            ("footprint").

    Returns:
        (2, 3) float64 min / max corners of a box (a cube unless the surface or the ground
        footprint grew it, or the surface's level raised its side away from the cameras),
        metres.
    """
    return estimate_bounds_with_rule(c2w, intrinsics, sizes, images)[0]


def camera_region(c2w) -> np.ndarray:
    """(2, 3) cube enclosing the camera centres, grown on every side by
    ``max(REGION_PAD_FRACTION * edge, REGION_PAD_MIN)`` metres: the inner cube of a contracted
    model of a scene seen from within."""
    origins = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)[:, :3, 3]
    lo, hi = origins.min(axis=0), origins.max(axis=0)
    centre = 0.5 * (lo + hi)
    edge = float((hi - lo).max())
    half = 0.5 * edge + max(REGION_PAD_FRACTION * edge, REGION_PAD_MIN)
    return np.stack([centre - half, centre + half])


def axes_miss_angle(c2w) -> float:
    """Median angle (degrees) between each camera's optical axis and the direction from it to
    the point closest to all axes (180 when the axes are parallel or meet behind the cameras)."""
    c2w = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
    origins, dirs = c2w[:, :3, 3], -c2w[:, :3, 2]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    a = projectors.sum(axis=0)
    if len(c2w) < 2 or np.linalg.eigvalsh(a / len(c2w))[0] <= PARALLEL_EIGEN:
        return 180.0
    centre = np.linalg.solve(a, np.einsum("nij,nj->i", projectors, origins))
    to_centre = centre - origins
    norms = np.linalg.norm(to_centre, axis=1)
    cos = np.einsum("ni,ni->n", to_centre, dirs) / np.maximum(norms, 1e-12)
    return float(np.degrees(np.arccos(np.clip(np.median(cos), -1.0, 1.0))))


@dataclass(frozen=True)
class SpaceChoice:
    """How to model a scene's space: a box (``contraction`` False) or the scene contraction
    around the cube of ``aabb`` (2, 3) metres; ``reason`` says why, in one line."""

    contraction: bool
    aabb: np.ndarray
    reason: str


def choose_space(aabb, aabb_source: str, c2w) -> SpaceChoice:
    """Box or contraction, from the bounds, where they came from, and the (N, 4, 4) camera
    poses.

    - Bounds the user gave are kept as a box.
    - Manifest bounds: when their largest edge exceeds :data:`UNBOUNDED_RATIO` times the
      cameras' region (:func:`camera_region`), the content reaches far beyond the cameras:
      contraction around that region. Otherwise the box.
    - Bounds estimated from the cameras: cameras that look at one point (median miss angle
      under :data:`CONVERGENCE_ANGLE`) keep the estimated box; cameras that do not (a room
      seen from inside) get the box around their region, which holds what they stand in
      (the estimate from their axes shrinks to a small cube between them). The contraction
      did not help there: on `room:3` captured without a manifest it scored 24.4 dB against
      the box's 24.8 dB after 120 s (BENCHMARKS.md, section 8).
    """
    aabb = np.asarray(aabb, dtype=np.float64)
    region = camera_region(c2w)
    region_edge = float(region[1, 0] - region[0, 0])
    edge = float((aabb[1] - aabb[0]).max())
    if aabb_source == "user":
        return SpaceChoice(False, aabb, "bounds given by the user: a box")
    if aabb_source == "manifest":
        if edge > UNBOUNDED_RATIO * region_edge:
            return SpaceChoice(True, region, (
                f"unbounded: the manifest's bounds ({edge:.3g} m) exceed {UNBOUNDED_RATIO:g}x "
                f"the cameras' region ({region_edge:.3g} m); scene contraction around it"))
        return SpaceChoice(False, aabb, "bounds from the manifest: a box")
    miss = axes_miss_angle(c2w)
    if miss > CONVERGENCE_ANGLE:
        return SpaceChoice(False, region, (
            f"seen from inside: the cameras' axes miss their common point by {miss:.0f} degrees "
            f"(median, > {CONVERGENCE_ANGLE:g}); a box around the cameras' region "
            f"({region_edge:.3g} m)"))
    return SpaceChoice(False, aabb, (f"bounds from the cameras (axes meet within {miss:.0f} "
                                     "degrees): a box"))
