"""How far a surface around the scene reaches, from where the training images agree on it.

Cameras on one side of what they look at (a hemisphere over a table, an arc) see a ground
around it, a table, a bench, which may reach beyond the cube their optical axes meet in
(:mod:`nerfbot.data.bounds`). The poses alone cannot say how far: a table that ends inside the
cube and one that fills every view give the same cameras. The images can. A point on a
textured surface looks the same from every camera that sees it, though each sees it inside
texture that varies from pixel to pixel; a point above or below the surface is seen on
different parts of the texture. Sky, a plain wall or a background composited on white hold
no texture and say nothing either way.

The probe: the plane through the cube's centre facing the cameras (the mean direction to them)
on a polar grid out to :data:`REACH` times the cameras' median distance, each grid point swept
along the normal over the cube's height. At each swept point the cameras that see it (at least
:data:`MIN_VIEWS`) give a colour (images blurred by one pixel, at most :data:`MAX_SIDE` pixels
wide); their disagreement is the median over the cameras of the L1 distance (RGB in [0, 1],
summed over channels) to the per-channel median colour, and the texture there the median of
the images' local contrast (:func:`_local_contrast`). A grid point shows a surface when, at
the height where the cameras disagree least, the texture is at least :data:`MIN_TEXTURE` and
the disagreement at most :data:`RATIO` times the texture. Walking outward from the cube along
each direction, the surface's points are kept until :data:`GAP` grid rings in a row show none.

The same test, swept finer over the cube's own footprint (:func:`ground_level`), finds the
level of that surface under the cube: the lowest height at which many of the footprint's
columns show a surface. Cameras that look down on a surface filling their views see nothing
below it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

#: Polar grid of the probe: rings out to REACH times the cameras' median distance from the
#: cube's centre, directions, and the heights each grid point is swept over (across the
#: cube's height along the normal).
REACH = 1.0
RINGS = 40
AZIMUTHS = 48
HEIGHTS = 17
#: Fewest cameras that must see a swept point for its disagreement to count.
MIN_VIEWS = 4
#: A surface: where the cameras see the point at its best height, the images' local contrast
#: (:func:`_local_contrast`, median over the cameras) is at least MIN_TEXTURE, and the cameras'
#: disagreement at most RATIO times that contrast. A MuJoCo sky's contrast at 128 px is about
#: 0.002, a faintly textured bench's or a wood grain's seen from afar 0.02.
RATIO = 0.6
MIN_TEXTURE = 0.01
#: Rings in a row without a surface that end the outward walk along a direction.
GAP = 2
#: The ground's sweep over the cube's footprint: a square grid of LEVEL_COLUMNS x
#: LEVEL_COLUMNS columns, each swept at LEVEL_HEIGHTS heights across the cube's height.
LEVEL_COLUMNS = 24
LEVEL_HEIGHTS = 48
#: A surface fills the footprint when the columns within one height step of the most common
#: height are at least LEVEL_COVERAGE of all columns (as a table that fills the views does:
#: 32-65 % on the zoo's frame-filling seeds, 22 % on one under a camera-following headlight;
#: 2 % on the tabletop, whose table ends inside the cube). The ground is then the lowest
#: height at which at least LEVEL_PEAK times as many columns show a surface as at the most
#: common one: a floor seen through a hole, a recessed bin's bottom, forms such a peak when
#: it covers about a quarter of the footprint or more (a smaller one is cut away).
LEVEL_PEAK = 0.3
LEVEL_COVERAGE = 0.2
#: Images are resized so their larger side is at most this many pixels before probing.
MAX_SIDE = 256
#: At most this many cameras (evenly spaced in the list) take part.
MAX_CAMERAS = 120


def _prepared(images, intrinsics: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Blurred float32 RGB images in [0, 1], resized to :data:`MAX_SIDE`, and (N, 4)
    intrinsics scaled with them."""
    out, scaled = [], np.array(intrinsics, dtype=np.float64)
    for i, image in enumerate(images):
        rgb = np.asarray(image)[..., :3].astype(np.float32) / 255.0
        scale = min(1.0, MAX_SIDE / max(rgb.shape[:2]))
        if scale < 1.0:
            rgb = cv2.resize(rgb, (round(rgb.shape[1] * scale), round(rgb.shape[0] * scale)),
                             interpolation=cv2.INTER_AREA)
            scaled[i] *= np.array([rgb.shape[1] / image.shape[1], rgb.shape[0] / image.shape[0],
                                   rgb.shape[1] / image.shape[1], rgb.shape[0] / image.shape[0]])
        out.append(cv2.GaussianBlur(rgb, (0, 0), 1.0))
    return out, scaled


def _local_contrast(image: np.ndarray) -> np.ndarray:
    """(H, W) standard deviation of each colour channel over a 5 x 5 window, summed over the
    channels: how much texture a pixel's neighbourhood holds."""
    mean = cv2.blur(image, (5, 5))
    square = cv2.blur(image * image, (5, 5))
    return np.sqrt(np.maximum(square - mean * mean, 0.0)).sum(axis=-1)


def _disagreement(points: np.ndarray, c2w: np.ndarray, intrinsics: np.ndarray,
                  images: list[np.ndarray],
                  contrasts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """For points (M, 3): (M,) median L1 distance of the cameras' colours to their median
    colour, and (M,) median over the cameras of the local contrast where they see the point;
    NaN where fewer than :data:`MIN_VIEWS` cameras see it."""
    colours = np.full((len(images), len(points), 3), np.nan, dtype=np.float32)
    texture = np.full((len(images), len(points)), np.nan, dtype=np.float32)
    for n, image in enumerate(images):
        cam = (points - c2w[n, :3, 3]) @ c2w[n, :3, :3]              # (M, 3) camera frame
        depth = -cam[:, 2]
        h, w = image.shape[:2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = cam[:, 0] / depth * intrinsics[n, 0] + intrinsics[n, 2]
            v = -cam[:, 1] / depth * intrinsics[n, 1] + intrinsics[n, 3]
        seen = (depth > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        row, col = v[seen].astype(np.int64), u[seen].astype(np.int64)
        colours[n, seen] = image[row, col]
        texture[n, seen] = contrasts[n][row, col]
    views = np.isfinite(colours[..., 0]).sum(axis=0)
    cost = np.full(len(points), np.nan)
    local = np.full(len(points), np.nan)
    ok = views >= MIN_VIEWS
    if ok.any():
        c = colours[:, ok]
        median = np.nanmedian(c, axis=0)
        cost[ok] = np.nanmedian(np.abs(c - median[None]).sum(axis=-1), axis=0)
        local[ok] = np.nanmedian(texture[:, ok], axis=0)
    return cost, local


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (3,) unit vectors that span the plane orthogonal to the unit ``normal`` (3,)."""
    e1 = np.cross(normal, np.eye(3)[int(np.argmin(np.abs(normal)))])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(normal, e1)


def polar_grid(centre: np.ndarray, normal: np.ndarray, radius: float, rings: int,
               azimuths: int) -> np.ndarray:
    """(rings, azimuths, 3) points, metres, of the plane through ``centre`` (3,) with unit
    ``normal`` (3,): ``rings`` radii evenly out to ``radius`` (0 excluded) x ``azimuths``
    directions."""
    e1, e2 = _plane_basis(normal)
    radii = np.linspace(0.0, radius, rings + 1)[1:]
    az = np.linspace(0.0, 2.0 * math.pi, azimuths, endpoint=False)
    return centre + radii[:, None, None] * (np.cos(az)[None, :, None] * e1
                                            + np.sin(az)[None, :, None] * e2)


@dataclass(frozen=True)
class ProbeViews:
    """The cameras that take part in a probe (at most :data:`MAX_CAMERAS`, evenly spaced in
    the list): (N, 4, 4) poses, (N, 4) intrinsics of the prepared images, the N blurred
    float32 images (:func:`_prepared`) and their (H, W) local contrasts."""

    c2w: np.ndarray
    intrinsics: np.ndarray
    images: list
    contrasts: list


def probe_views(c2w: np.ndarray, intrinsics: np.ndarray, images) -> ProbeViews:
    """:class:`ProbeViews` of cameras with (N, 4, 4) OpenGL ``c2w`` poses, (N, 4) ``intrinsics``
    (fx, fy, cx, cy in pixels of ``images``) and N uint8 (H, W, 3) RGB ``images``."""
    c2w = np.asarray(c2w, dtype=np.float64)
    keep = np.unique(np.linspace(0, len(c2w) - 1, min(len(c2w), MAX_CAMERAS)).round()
                     .astype(np.int64))
    prepared, scaled = _prepared([images[i] for i in keep], np.asarray(intrinsics)[keep])
    return ProbeViews(c2w[keep], scaled, prepared, [_local_contrast(im) for im in prepared])


def _sweep(points: np.ndarray, views: ProbeViews) -> tuple[np.ndarray, np.ndarray]:
    """For columns of points (..., H, 3), each swept over H heights: (...) index of the height
    where the cameras disagree least, and (...) whether it shows a surface there (texture at
    least :data:`MIN_TEXTURE`, disagreement at most :data:`RATIO` times it)."""
    cost, local = _disagreement(points.reshape(-1, 3), views.c2w, views.intrinsics,
                                views.images, views.contrasts)
    cost = cost.reshape(points.shape[:-1])
    local = local.reshape(points.shape[:-1])
    best_h = np.argmin(np.where(np.isfinite(cost), cost, np.inf), axis=-1)
    best = np.take_along_axis(cost, best_h[..., None], axis=-1)[..., 0]
    texture = np.take_along_axis(local, best_h[..., None], axis=-1)[..., 0]
    with np.errstate(invalid="ignore"):
        surface = np.isfinite(best) & (texture >= MIN_TEXTURE) & (best <= RATIO * texture)
    return best_h, surface


def surface_points(cube: np.ndarray, normal: np.ndarray,
                   views: ProbeViews) -> np.ndarray | None:
    """(K, 3) points, metres, of a surface the images agree on outside ``cube``, reached from
    it without a gap (see the module docstring), or None when there are none.

    Args:
        cube: (2, 3) min / max corners of the cube the cameras' axes meet in.
        normal: (3,) unit normal of the probed plane, toward the cameras.
        views: the cameras and their images (:func:`probe_views`).
    """
    centre = 0.5 * (cube[0] + cube[1])
    half = 0.5 * float(np.max(cube[1] - cube[0]))
    dist = np.linalg.norm(views.c2w[:, :3, 3] - centre, axis=1)
    level = polar_grid(centre, normal, REACH * float(np.median(dist)), RINGS, AZIMUTHS)
    heights = np.linspace(-half, half, HEIGHTS)
    points = level[:, :, None] + heights[None, None, :, None] * normal       # (R, A, H, 3)
    best_h, surface = _sweep(points, views)                                  # (R, A)
    inside = np.all((level >= cube[0]) & (level <= cube[1]), axis=-1)         # (R, A)
    kept = []
    for a in range(AZIMUTHS):
        misses = 0
        for r in range(RINGS):
            if inside[r, a]:
                continue
            if surface[r, a]:
                misses = 0
                kept.append(points[r, a, best_h[r, a]])
            else:
                misses += 1
                if misses >= GAP:
                    break
    return np.array(kept) if kept else None


def ground_level(cube: np.ndarray, axis: np.ndarray, views: ProbeViews) -> float | None:
    """Where the lowest surface under the cube lies, in metres along ``axis`` from the cube's
    centre, or None when no surface fills the cube's footprint (:data:`LEVEL_COVERAGE`,
    :data:`LEVEL_PEAK`).

    The footprint's columns (:data:`LEVEL_COLUMNS` squared) are swept along ``axis`` (3,),
    the unit direction the surface faces, at :data:`LEVEL_HEIGHTS` heights across the cube's
    edge; the level is one of those heights, so within one step (edge / 47) of the surface.
    ``cube`` and ``views`` as for :func:`surface_points`.
    """
    centre = 0.5 * (cube[0] + cube[1])
    half = 0.5 * float(np.max(cube[1] - cube[0]))
    e1, e2 = _plane_basis(axis)
    across = np.linspace(-half, half, LEVEL_COLUMNS)
    heights = np.linspace(-half, half, LEVEL_HEIGHTS)
    points = (centre + across[:, None, None, None] * e1 + across[None, :, None, None] * e2
              + heights[None, None, :, None] * axis)                        # (C, C, H, 3)
    best_h, surface = _sweep(points, views)                                  # (C, C)
    counts = np.bincount(best_h[surface], minlength=LEVEL_HEIGHTS)
    mode = int(np.argmax(counts))
    if counts[max(mode - 1, 0):mode + 2].sum() < LEVEL_COVERAGE * best_h.size:
        return None
    return float(heights[int(np.flatnonzero(counts >= LEVEL_PEAK * counts[mode])[0])])
