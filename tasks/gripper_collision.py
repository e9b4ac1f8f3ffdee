"""Gripper collision model: are top-down parallel-jaw grasps free of scene points and the table?

Boxes in the gripper frame (see :meth:`tasks.grasp_pose.Grasp.rotation`; origin at the TCP,
x = closing axis, z = up towards the palm), all from :class:`sims.gripper.GripperGeometry`:
two finger boxes ``finger_thickness`` (x) by ``finger_width`` (y) by ``finger_length`` (z) with
inner faces at x = +-open_width/2, z from -tcp_height to finger_length - tcp_height; a palm box
x in +-(max_opening/2 + finger_thickness), y in +-palm_width/2, z from finger_length - tcp_height
up by palm_height. Approach is straight down, so every box sweeps straight up (by
``PlannerConfig.approach_height``); the fingertips must also clear the table plane.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from sims.gripper import GRIPPER, GripperGeometry
from tasks.grasp_pose import Grasp
from tasks.planner_config import PlannerConfig
from tasks.scene_cloud import TablePlane, _normalize_rows


def _gripper_extent(geometry: GripperGeometry) -> float:
    """Horizontal radius (about the TCP) of everything the gripper occupies, metres."""
    half_x = geometry.max_opening / 2 + geometry.finger_thickness
    half_y = max(geometry.finger_width, geometry.palm_width) / 2
    return math.hypot(half_x, half_y)


def sweep_check(centers, axes, open_widths, obstacles, *, table: TablePlane | None = None,
                geometry: GripperGeometry = GRIPPER, config: PlannerConfig = PlannerConfig(),
                chunk_pairs: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Collision test of top-down grasps, with the local object top between the fingers.

    Args:
        centers: (K, 3) TCP positions, metres.
        axes: (K, 3) closing axes (only the horizontal part is used: the approach is straight
            down, so the gripper's z is world z).
        open_widths: (K,) finger opening (inner faces at +-open_width/2), metres.
        obstacles: (M, 3) scene points, metres.
        table: support plane; when given, every fingertip corner must be at least
            ``max(table_clearance, table.object_height(config))`` above it.
        geometry, config: gripper boxes and ``approach_height`` / ``table_clearance``.
        chunk_pairs: memory bound on (candidate, point) pairs per step.

    Returns:
        free: (K,) bool, no obstacle point inside the finger boxes or the palm box swept from
        ``approach_height`` above the grasp down to it, and the fingertips clear the table.
        top: (K,) highest obstacle point between the open fingers (|x| < open_width/2,
        |y| <= palm_width/2, above the fingertips), as a height above the TCP, metres;
        -inf where there is none.
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    ax = np.asarray(axes, dtype=np.float64).reshape(-1, 3).copy()
    ow = np.broadcast_to(np.asarray(open_widths, dtype=np.float64), (len(c),))
    obs = np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)
    g = geometry
    ax[:, 2] = 0.0
    u = _normalize_rows(ax)
    v = np.stack([-u[:, 1], u[:, 0], np.zeros(len(u))], axis=1)  # y = z x x
    free = np.ones(len(c), dtype=bool)
    top = np.full(len(c), -np.inf)
    tip = -g.tcp_height
    finger_top = tip + g.finger_length + config.approach_height
    palm_lo = tip + g.finger_length
    palm_hi = palm_lo + g.palm_height + config.approach_height
    palm_x = g.max_opening / 2 + g.finger_thickness
    if table is not None:
        floor = max(config.table_clearance, table.object_height(config))
        for sx in (-1.0, 1.0):
            for dx in (0.0, g.finger_thickness):
                for sy in (-1.0, 1.0):
                    corner = (c + (sx * (ow / 2 + dx))[:, None] * u
                              + (sy * g.finger_width / 2) * v)
                    corner[:, 2] += tip
                    free &= table.height(corner) >= floor
    if len(obs) == 0 or len(c) == 0:
        return free, top
    tree = cKDTree(obs[:, :2])
    reach = _gripper_extent(g) + 1e-6
    lo_c, hi_c = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
    near = np.asarray(tree.query_ball_point(0.5 * (lo_c + hi_c),
                                            0.5 * float(np.linalg.norm(hi_c - lo_c)) + reach),
                      dtype=np.int64)
    if len(near) == 0:
        return free, top
    pts = obs[near]
    step = max(1, chunk_pairs // len(pts))
    for s in range(0, len(c), step):
        sl = slice(s, s + step)
        d = pts[None, :, :] - c[sl, None, :]  # (k, m, 3)
        lx = np.abs(np.einsum("kmj,kj->km", d[..., :2], u[sl, :2]))
        ly = np.abs(np.einsum("kmj,kj->km", d[..., :2], v[sl, :2]))
        lz = d[..., 2]
        half = ow[sl, None] / 2
        finger = ((lx >= half) & (lx <= half + g.finger_thickness)
                  & (ly <= g.finger_width / 2) & (lz >= tip) & (lz <= finger_top))
        palm = (lx <= palm_x) & (ly <= g.palm_width / 2) & (lz >= palm_lo) & (lz <= palm_hi)
        free[sl] &= ~(finger | palm).any(axis=1)
        between = (lx < half) & (ly <= g.palm_width / 2) & (lz >= tip)
        top[sl] = np.where(between, lz, -np.inf).max(axis=1)
    return free, top


def collision_free(centers, axes, open_widths, obstacles, *, table: TablePlane | None = None,
                   geometry: GripperGeometry = GRIPPER,
                   config: PlannerConfig = PlannerConfig()) -> np.ndarray:
    """(K,) bool: the top-down grasps are free of collisions (see :func:`sweep_check`).

    Args:
        centers: (K, 3) TCP positions, metres.
        axes: (K, 3) closing axes (horizontal part used).
        open_widths: (K,) or scalar finger opening, metres.
        obstacles: (M, 3) scene points, metres (the whole cleaned cloud, table included: table
            points lie below the fingertips when the fingertips clear the table).
        table: support plane for the fingertip clearance (None: no table test).
        geometry, config: gripper and planner parameters.
    """
    return sweep_check(centers, axes, open_widths, obstacles, table=table,
                       geometry=geometry, config=config)[0]


def grasp_collision_free(grasp: Grasp, obstacles, *, open_width: float | None = None,
                         table: TablePlane | None = None, geometry: GripperGeometry = GRIPPER,
                         config: PlannerConfig = PlannerConfig()) -> bool:
    """:func:`collision_free` for one :class:`Grasp`; the opening defaults to
    ``grasp.info["open_width"]`` or else ``width + width_margin`` (capped at max_opening)."""
    if open_width is None:
        open_width = grasp.info.get("open_width",
                                    min(grasp.width + config.width_margin, geometry.max_opening))
    return bool(collision_free(np.asarray(grasp.center)[None], np.asarray(grasp.axis)[None],
                               [open_width], obstacles, table=table, geometry=geometry,
                               config=config)[0])
