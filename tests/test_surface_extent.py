"""The camera bounds grow over the surface the training images agree on
(:mod:`nerfbot.data.surface_extent`): analytic renders of a table top at z = 0 under a sky,
seen from a hemisphere of cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nerfbot.data.bounds import GROUND_MARGIN, estimate_bounds_with_rule
from nerfbot.data.surface_extent import LEVEL_HEIGHTS, ground_level, probe_views
from nerfbot.ops.cameras import look_at

SIZE = 48
FOV = 40.0
RADIUS = 2.0


def _cameras(n: int = 40, below: bool = False):
    """(n, 4, 4) poses on a hemisphere of RADIUS around the origin at 25-65 degrees
    elevation (below the origin with ``below``), (n, 4) intrinsics, (n, 2) sizes."""
    elevations = np.radians([25.0, 38.0, 52.0, 65.0]) * (-1.0 if below else 1.0)
    eyes = [RADIUS * np.array([math.cos(elevations[k % 4]) * math.cos(2 * math.pi * k / n),
                               math.cos(elevations[k % 4]) * math.sin(2 * math.pi * k / n),
                               math.sin(elevations[k % 4])]) for k in range(n)]
    poses = np.stack([look_at(e, np.zeros(3)) for e in eyes])
    f = 0.5 * SIZE / math.tan(math.radians(FOV) / 2)
    return poses, np.tile([f, f, SIZE / 2, SIZE / 2], (n, 1)), np.tile([SIZE, SIZE], (n, 1))


def _render(pose: np.ndarray, f: float, half: float, textured: bool,
            table_z: float = 0.0, hole: tuple[float, float] | None = None) -> np.ndarray:
    """(SIZE, SIZE, 3) uint8 view of a table top |x|, |y| <= half at z = ``table_z`` (a random
    10 cm tile texture, or plain grey) under a sky whose colour follows the ray's elevation.
    ``hole`` (h, depth): the table has a hole |x|, |y| < h through which a floor of the same
    texture shows, ``depth`` metres below the table."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d_cam = np.stack([(u - SIZE / 2) / f, -(v - SIZE / 2) / f, -np.ones_like(u)], axis=-1)
    d = d_cam @ pose[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = pose[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (table_z - o[2]) / d[..., 2]
    hit = (t > 0) & np.isfinite(t)
    p = o + np.where(hit, t, 0.0)[..., None] * d
    hit &= (np.abs(p[..., 0]) <= half) & (np.abs(p[..., 1]) <= half)
    if hole is not None:
        through = hit & (np.abs(p[..., 0]) < hole[0]) & (np.abs(p[..., 1]) < hole[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = (table_z - hole[1] - o[2]) / d[..., 2]
        p = np.where(through[..., None], o + t_floor[..., None] * d, p)
    sky = np.stack([0.6 + 0.05 * d[..., 2], 0.75 + 0.03 * d[..., 2], np.full(d.shape[:2], 0.95)],
                   axis=-1)
    if textured:
        tiles = np.random.default_rng(7).uniform(0.1, 0.9, (80, 80, 3))
        ij = np.clip(np.floor((p[..., :2] + 4.0) / 0.1).astype(int), 0, 79)
        table = tiles[ij[..., 0], ij[..., 1]]
    else:
        table = np.full(d.shape[:2] + (3,), 0.6)
    return (255 * np.where(hit[..., None], table, sky)).astype(np.uint8)


def _bounds(half: float, textured: bool = True):
    poses, intr, sizes = _cameras()
    images = [_render(p, intr[0, 0], half, textured) for p in poses]
    return estimate_bounds_with_rule(poses, intr, sizes, images)


def test_bounds_grow_to_a_textured_table_beyond_the_cube():
    poses, intr, sizes = _cameras()
    cube, rule = estimate_bounds_with_rule(poses, intr, sizes, [None] * len(poses))
    assert rule == "axes"                       # no image takes part: the axes' cube
    box, rule = _bounds(half=1.4)
    assert rule == "surface"
    cube_half = float(cube[1, 0])
    assert cube_half < 1.0                      # the table reaches beyond the cube ...
    assert np.all(box[1, :2] >= 1.1) and np.all(box[0, :2] <= -1.1)   # ... and the box holds it
    assert np.all(box[1, :2] <= 1.4 + 0.2) and np.all(box[0, :2] >= -1.4 - 0.2)  # not the sky
    # The table fills the views: the box's bottom rises to it, less the margin; its top stays.
    edge = float(cube[1, 2] - cube[0, 2])
    step = edge / (LEVEL_HEIGHTS - 1)
    assert cube[0, 2] < -0.5
    assert -GROUND_MARGIN * edge - step <= box[0, 2] <= -GROUND_MARGIN * edge + step
    assert box[1, 2] == pytest.approx(cube[1, 2])


def test_cameras_below_a_surface_bring_the_box_top_down_to_it():
    """A ceiling seen from below: the box's side away from the cameras is its top."""
    poses, intr, sizes = _cameras(below=True)
    cube, _ = estimate_bounds_with_rule(poses, intr, sizes, [None] * len(poses))
    images = [_render(p, intr[0, 0], 1.4, True) for p in poses]
    box, rule = estimate_bounds_with_rule(poses, intr, sizes, images)
    assert rule == "surface"
    edge = float(cube[1, 2] - cube[0, 2])
    step = edge / (LEVEL_HEIGHTS - 1)
    assert cube[1, 2] > 0.5
    assert GROUND_MARGIN * edge - step <= box[1, 2] <= GROUND_MARGIN * edge + step
    assert box[0, 2] == pytest.approx(cube[0, 2])


def test_ground_level_keeps_a_floor_seen_through_a_hole_in_the_table():
    """A lower surface covering a third of the footprint (a floor under a hole, a recessed
    bin) sets the level: nothing the cameras see is cut away."""
    poses, intr, sizes = _cameras()
    images = [_render(p, intr[0, 0], 1.4, True, hole=(0.45, 0.3)) for p in poses]
    cube = np.array([[-0.8, -0.8, -0.8], [0.8, 0.8, 0.8]])
    level = ground_level(cube, np.array([0.0, 0.0, 1.0]), probe_views(poses, intr, images))
    assert level is not None
    assert abs(level + 0.3) <= 1.6 / (LEVEL_HEIGHTS - 1) + 1e-9
    box, rule = estimate_bounds_with_rule(poses, intr, sizes, images)
    assert rule == "surface" and box[0, 2] < -0.3


@pytest.mark.parametrize("table_z", [0.0, 0.25])
def test_ground_level_finds_the_table_under_the_cube(table_z):
    poses, intr, _ = _cameras()
    images = [_render(p, intr[0, 0], 1.4, True, table_z) for p in poses]
    cube = np.array([[-0.8, -0.8, -0.8], [0.8, 0.8, 0.8]])
    views = probe_views(poses, intr, images)
    level = ground_level(cube, np.array([0.0, 0.0, 1.0]), views)
    assert level is not None
    assert abs(level - table_z) <= 1.6 / (LEVEL_HEIGHTS - 1) + 1e-9   # within one step
    plain = [_render(p, intr[0, 0], 1.4, False, table_z) for p in poses]
    assert ground_level(cube, np.array([0.0, 0.0, 1.0]), probe_views(poses, intr, plain)) is None


@pytest.mark.parametrize("half, textured", [(0.5, True), (1.4, False)])
def test_bounds_stay_near_the_cube_where_the_images_agree_on_no_surface_beyond_it(half,
                                                                                  textured):
    """A table that ends inside the cube (sky beyond it), or a plain one: the cube, grown by
    at most a few probe rings at the table's edge (and its bottom raised to the table when
    those rings show it)."""
    poses, intr, sizes = _cameras()
    cube, _ = estimate_bounds_with_rule(poses, intr, sizes, [None] * len(poses))
    box, rule = _bounds(half, textured)
    assert rule in ("axes", "surface")
    if box[0, 2] > cube[0, 2]:
        assert rule == "surface" and -0.2 <= box[0, 2] <= 0.0
        box[0, 2] = cube[0, 2]
    assert np.all(box[0] <= cube[0]) and np.all(box[1] >= cube[1])
    assert np.all(box[0] >= cube[0] - 0.2) and np.all(box[1] <= cube[1] + 0.2)
    if not textured:
        assert rule == "axes"
        np.testing.assert_allclose(box, cube)
