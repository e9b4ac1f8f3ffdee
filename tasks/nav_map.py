"""Top-down maps a planar mobile robot plans on: which floor cells its body would hit.

A :class:`FloorMap` is a 2D grid over the floor (x, y). A cell is *blocked* when something lies
above it within the robot's height band, from :attr:`RobotBody.floor_clearance` (lower is floor)
to :attr:`RobotBody.height`; the robot's centre may stand on a cell when every blocked cell is
farther than its radius (:meth:`FloorMap.free_for`). Maps come from

- a trained field's obstacles (:func:`floor_map_from_volume` over
  :func:`nerfbot.query.density.occupancy_volume`),
- the scene's true geometry (:func:`floor_map_from_geometry`: the MuJoCo geoms the scene
  declares as obstacles, and the room's walls), the reference a field map is judged against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy import ndimage

from nerfbot.query.density import OccupancyVolume
from sims.manifest import declared_obstacles, rendered_geoms, transparent_geom_ids


@dataclass(frozen=True)
class RobotBody:
    """A cylindrical mobile base.

    Attributes:
        radius: body radius, metres.
        height: top of the body above the floor, metres: it passes under higher obstacles.
        floor_clearance: obstacles entirely below this height (metres) are floor.
    """

    radius: float = 0.18
    height: float = 0.5
    floor_clearance: float = 0.05

    def __post_init__(self):
        if not (self.radius > 0 and self.height > self.floor_clearance >= 0):
            raise ValueError(f"robot body needs radius > 0 and height > floor_clearance >= 0, "
                             f"got {self}")

    def sample_points(self, rings: int = 3, per_ring: int = 12) -> np.ndarray:
        """(B, 3) points on the body's surface and axis in its frame (origin on the floor at
        the centre, z up), metres: what a collision cost samples."""
        pts = []
        for z in np.linspace(self.floor_clearance, self.height, rings):
            a = np.linspace(0.0, 2 * np.pi, per_ring, endpoint=False)
            pts.append(np.stack([self.radius * np.cos(a), self.radius * np.sin(a),
                                 np.full_like(a, z)], -1))
            pts.append([[0.0, 0.0, z]])
        return np.concatenate([np.asarray(p, float).reshape(-1, 3) for p in pts])


class FloorMap:
    """Blocked floor cells.

    Attributes:
        blocked: (X, Y) bool, True where an obstacle stands within the body's height band.
        origin: (2,) world (x, y) of cell (0, 0)'s centre, metres.
        cell: cell size, metres.
    """

    def __init__(self, blocked: np.ndarray, origin, cell: float):
        self.blocked = np.asarray(blocked, bool)
        self.origin = np.asarray(origin, float)
        self.cell = float(cell)

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.blocked.shape)

    def clearance(self) -> np.ndarray:
        """(X, Y) distance (metres) from each cell centre to the nearest blocked cell's centre
        (inf when nothing is blocked)."""
        if not self.blocked.any():
            return np.full(self.shape, np.inf)
        return ndimage.distance_transform_edt(~self.blocked, sampling=self.cell)

    def free_for(self, radius: float) -> np.ndarray:
        """(X, Y) bool: cells where a body of ``radius`` (metres) can stand. An obstacle point
        lies within half a cell diagonal of its blocked cell's centre, so the clearance must
        exceed the radius by that much."""
        return self.clearance() > radius + self.cell * math.sqrt(0.5)

    def cleared(self, xy, radius: float) -> "FloorMap":
        """A copy with the cells a body of ``radius`` (metres) standing at world ``xy`` fills
        unblocked: every cell whose centre lies within ``radius`` plus half a cell diagonal of
        xy's cell centre, so that :meth:`free_for` ``(radius)`` holds there. A robot knows the
        floor under itself is free (ROS costmaps clear the robot's footprint the same way)."""
        centre = self.to_cell(xy)
        ii, jj = np.indices(self.shape)
        near = np.hypot(ii - centre[0], jj - centre[1]) * self.cell \
            <= radius + self.cell * math.sqrt(0.5) + 1e-9
        return FloorMap(self.blocked & ~near, self.origin, self.cell)

    def to_cell(self, xy) -> np.ndarray:
        """(..., 2) int cell indices of world points (..., 2), unclipped."""
        return np.rint((np.asarray(xy, float) - self.origin) / self.cell).astype(int)

    def to_world(self, ij) -> np.ndarray:
        """(..., 2) world (x, y) of cell centres (..., 2), metres."""
        return self.origin + self.cell * np.asarray(ij, float)

    def inside(self, ij) -> np.ndarray:
        ij = np.asarray(ij)
        return np.all((ij >= 0) & (ij < np.asarray(self.shape)), axis=-1)


def resample_onto(fmap: FloorMap, reference: FloorMap) -> np.ndarray:
    """``fmap``'s blocked cells read at ``reference``'s cell centres, (X, Y) bool of the
    reference's shape; cells outside ``fmap`` count as blocked."""
    ij = np.argwhere(np.ones(reference.shape, bool))
    cells = fmap.to_cell(reference.to_world(ij))
    inside = fmap.inside(cells)
    out = np.ones(reference.shape, bool)
    out[ij[inside, 0], ij[inside, 1]] = fmap.blocked[cells[inside, 0], cells[inside, 1]]
    return out


def map_agreement(fmap: FloorMap, truth: FloorMap, radius: float,
                  transparent: FloorMap | None = None) -> dict:
    """How a map compares with the true one, on the true map's cells:

    - ``iou``: intersection over union of the blocked cells;
    - ``phantom``: share of the truly free cells the map blocks;
    - ``missed``: share of the truly blocked cells the map leaves free;
    - ``standable_kept``: share of the cells where a body of ``radius`` (metres) truly stands
      that the map also lets it stand on (what planning can use);
    - ``standable_wrong``: share of the cells the map lets it stand on where it truly cannot
      (what drives it into things);
    - with ``transparent`` (the true map of the transparent obstacles alone, on ``truth``'s
      cells), ``transparent_blocked``: share of their cells the map blocks."""
    b, g = resample_onto(fmap, truth), truth.blocked
    fm = FloorMap(b, truth.origin, truth.cell).free_for(radius)
    ft = truth.free_for(radius)
    share = (lambda a, n: float(a.sum() / n.sum()) if n.any() else 0.0)
    out = {"iou": share(b & g, b | g), "phantom": share(b & ~g, ~g), "missed": share(~b & g, g),
           "standable_kept": share(fm & ft, ft), "standable_wrong": share(fm & ~ft, fm)}
    if transparent is not None:
        if transparent.shape != truth.shape:
            raise ValueError(f"transparent map of shape {transparent.shape} is not on the true "
                             f"map's cells {truth.shape}")
        out["transparent_blocked"] = share(b & transparent.blocked, transparent.blocked)
    return out


def floor_map_from_volume(volume: OccupancyVolume, body: RobotBody,
                          floor_z: float = 0.0) -> FloorMap:
    """Project a 3D obstacle grid onto the floor: a column is blocked when any occupied grid
    point lies between ``floor_z + body.floor_clearance`` and ``floor_z + body.height``. The
    floor map's cells are the volume's grid points in x and y (square cells need equal x and
    y spacing)."""
    if not np.isclose(volume.spacing[0], volume.spacing[1], rtol=1e-3):
        raise ValueError(f"floor map needs equal x and y grid spacing, got {volume.spacing[:2]}")
    z = volume.origin[2] + volume.spacing[2] * np.arange(volume.shape[2])
    band = (z >= floor_z + body.floor_clearance) & (z <= floor_z + body.height)
    if not band.any():
        raise ValueError(f"the occupancy grid has no points between {floor_z + body.floor_clearance:.2f}"
                         f" and {floor_z + body.height:.2f} m: refine its resolution")
    blocked = volume.occupied[:, :, band].any(axis=2)
    return FloorMap(blocked, volume.origin[:2], float(volume.spacing[0]))


def floor_map_from_geometry(model: mujoco.MjModel, data: mujoco.MjData, geoms: list[str],
                            area, cell: float, body: RobotBody, floor_z: float = 0.0,
                            walls: bool = True) -> FloorMap:
    """The true floor map: cells over ``area`` (xmin, ymin, xmax, ymax; outside it is wall)
    blocked where the footprint of a named geom that reaches into the body's height band
    reaches into the cell. Upright boxes (their footprint grown by half a cell along their own
    axes: exact for yaws in multiples of 90 degrees, conservative otherwise), upright cylinders
    and spheres (radius grown by half a cell diagonal) have their own shapes; other geoms their
    world AABB grown by half a cell.

    Args:
        model, data: the scene after ``mj_forward`` (geom poses are read from ``data``).
        geoms: names of the obstacle geoms.
        area: the free floor's extent, metres: cells outside it are blocked.
        cell: cell size, metres.
        walls: False leaves the cells outside ``area`` free (the obstacles alone).
    """
    xmin, ymin, xmax, ymax = (float(v) for v in area)
    # one ring of cells beyond the area on every side: the walls
    nx = int(np.ceil((xmax - xmin) / cell)) + 3
    ny = int(np.ceil((ymax - ymin) / cell)) + 3
    origin = np.array([xmin - cell, ymin - cell])
    gx = origin[0] + cell * np.arange(nx)
    gy = origin[1] + cell * np.arange(ny)
    px, py = np.meshgrid(gx, gy, indexing="ij")
    blocked = (px < xmin) | (px > xmax) | (py < ymin) | (py > ymax)
    if not walls:
        blocked[:] = False
    lo_band, hi_band = floor_z + body.floor_clearance, floor_z + body.height
    for name in geoms:
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if gid < 0:
            raise ValueError(f"obstacle geom {name!r} is not in the scene")
        pos, rot = data.geom_xpos[gid], data.geom_xmat[gid].reshape(3, 3)
        size, kind = model.geom_size[gid], model.geom_type[gid]
        half_z = np.abs(rot[2]) @ _half_extent(kind, size)
        if pos[2] + half_z < lo_band or pos[2] - half_z > hi_band:
            continue
        dx, dy = px - pos[0], py - pos[1]
        upright = abs(rot[2, 2]) > 1 - 1e-6
        grow, grow_disc = 0.5 * cell, cell * math.sqrt(0.5)
        if kind == mujoco.mjtGeom.mjGEOM_BOX and upright:
            lx = dx * rot[0, 0] + dy * rot[1, 0]      # into the box's frame (yaw only)
            ly = dx * rot[0, 1] + dy * rot[1, 1]
            hit = (np.abs(lx) <= size[0] + grow) & (np.abs(ly) <= size[1] + grow)
        elif (kind in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE) and upright) \
                or kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            hit = dx * dx + dy * dy <= (size[0] + grow_disc) ** 2
        else:
            half = np.abs(rot) @ _half_extent(kind, size) + grow
            hit = (np.abs(dx) <= half[0]) & (np.abs(dy) <= half[1])
        blocked |= hit
    return FloorMap(blocked, origin, cell)


def _half_extent(kind: int, size: np.ndarray) -> np.ndarray:
    """(3,) half-extent of a geom in its own frame, metres."""
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return np.asarray(size[:3], float)
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return np.full(3, float(size[0]))
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return np.array([size[0], size[0], size[1]], float)
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return np.array([size[0], size[0], size[1] + size[0]], float)
    return np.asarray(size[:3], float)


def room_area(model: mujoco.MjModel) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of a room scene's floor inside its walls, metres, from its
    ``nerfbot_room_size`` declaration (width, depth, height; the room is centred on the
    origin). ValueError for scenes that declare no room."""
    k = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, "nerfbot_room_size")
    if k < 0:
        raise ValueError("the scene declares no room size (nerfbot_room_size): navigation needs "
                         "a room scene such as room:0")
    adr = model.numeric_adr[k]
    w, d = (float(v) for v in model.numeric_data[adr:adr + 2])
    return -w / 2, -d / 2, w / 2, d / 2


def true_floor_map(model: mujoco.MjModel, data: mujoco.MjData, body: RobotBody,
                   cell: float = 0.05, transparent_only: bool = False) -> FloorMap:
    """The floor map of a room scene's true geometry: its declared obstacle geoms
    (``nerfbot_obstacles``) inside its walls (:func:`room_area`), floor at z = 0; with
    ``transparent_only``, only the declared obstacles MuJoCo draws see-through (glass),
    without the walls (an empty map when there are none)."""
    names = list(declared_obstacles(model, data))
    if not transparent_only:
        return floor_map_from_geometry(model, data, names, room_area(model), cell, body)
    clear = {model.geom(g).name for g in transparent_geom_ids(rendered_geoms(model, data))}
    return floor_map_from_geometry(model, data, [n for n in names if n in clear],
                                   room_area(model), cell, body, walls=False)
