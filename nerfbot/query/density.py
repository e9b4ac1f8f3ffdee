"""Density where a robot asks for it: at world points (batched, optionally differentiable), on a
grid as occupancy, as the distance to the nearest occupied point, and along a rigid body's
trajectory as a collision cost (NeRF-Nav's).

Density is the rendered scene's: the field's density (1/m) where the model's occupancy grid
lets the renderer sample, zero elsewhere and outside the modelled space. Any method answers,
conditioned ones with a condition vector (time or joints) per query.

A point is an obstacle when its density reaches a threshold: Dex-NeRF's threshold depth uses
the same test along rays, so faint surfaces such as glass, which barely show in the expected
depth, count as obstacles at a low enough threshold (:func:`default_obstacle_threshold`).
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch
from scipy import ndimage



#: Marching steps along the cube diagonal that define the default density threshold (the
#: default ``render_steps`` of the occupancy marcher).
REFERENCE_STEPS = 256
#: Opacity of one reference step at the default threshold.
REFERENCE_OPACITY = 0.5


def default_density_threshold(aabb, steps: int = REFERENCE_STEPS,
                              opacity: float = REFERENCE_OPACITY) -> float:
    """Density (1/m) at which one marching step of the default occupancy marcher, the diagonal
    of the cube enclosing ``aabb`` (2, 3) divided by ``steps``, is ``opacity`` opaque:
    ``-ln(1 - opacity) / step``. About 80 /m for the tabletop (step 8.7 mm). The same for every
    method, so meshes of different methods are cut at the same density."""
    aabb = np.asarray(aabb, float)
    step = math.sqrt(3.0) * float((aabb[1] - aabb[0]).max()) / steps
    return -math.log(1.0 - opacity) / step


def grid_points(bounds, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Corners of a near-isotropic grid spanning ``bounds`` (2, 3) exactly, with ``resolution``
    cells along the longest axis. Returns (shape (3,) points per axis, spacing (3,) metres)."""
    lo, hi = np.asarray(bounds, float)
    extent = hi - lo
    if resolution < 2 or not np.all(extent > 0):
        raise ValueError(f"need resolution >= 2 and non-empty bounds, got {resolution}, {bounds}")
    cell = extent.max() / resolution
    shape = np.maximum(np.round(extent / cell).astype(int), 1) + 1
    return shape, extent / (shape - 1)


def occupancy_mask(model, x: torch.Tensor) -> Optional[torch.Tensor]:
    """(N,) bool: the model's occupancy grid (if it has one) lets the renderer sample at x."""
    grid = getattr(model, "grid", None)
    occupied = getattr(grid, "occupied", None)
    if occupied is None:
        return None
    g = occupied.shape[0]
    idx = ((grid.lookup_points(x) - grid.cube_min) / grid.cell_size).floor().long()
    idx = idx.clamp(0, g - 1)
    return occupied[idx[:, 0], idx[:, 1], idx[:, 2]].bool()


def density_at(model, points: torch.Tensor, cond: Optional[torch.Tensor] = None,
               chunk: int = 1 << 16, grad: bool = False,
               respect_occupancy: bool = True) -> torch.Tensor:
    """Density of the rendered scene at world points.

    Args:
        model: a trained model (any method); evaluated in eval mode.
        points: (N, 3) world points, metres (float32 unless the field takes another type).
        cond: (D,) one condition vector for every point, or (N, D) one per point; None for
            unconditioned methods.
        chunk: points per field call.
        grad: keep the graph so the result can be differentiated w.r.t. ``points`` (the
            field's parameters are not trained by it).
        respect_occupancy: zero where the model's occupancy grid marks cells empty (the
            renderer never samples there, so nothing there is part of the rendered scene).
    Returns:
        (N,) density, 1/m, in the field's floating type, on the model's device.
    """
    points = torch.as_tensor(points)
    if not points.is_floating_point():
        points = points.float()
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {tuple(points.shape)}")
    device = model.aabb.device
    points = points.to(device)
    if cond is not None:
        cond = torch.as_tensor(cond, dtype=points.dtype, device=device)
        cond = cond.reshape(1, -1).expand(len(points), -1) if cond.ndim == 1 else cond
    was_training = model.training
    model.eval()
    parts = []
    try:
        with torch.set_grad_enabled(grad):
            for i in range(0, len(points), chunk):
                x = points[i:i + chunk]
                c = None if cond is None else cond[i:i + chunk]
                sigma = model.field.density(x, c)[0]
                if respect_occupancy:
                    occ = occupancy_mask(model, x.detach())
                    if occ is not None:
                        sigma = torch.where(occ, sigma, torch.zeros_like(sigma))
                parts.append(sigma)
    finally:
        model.train(was_training)
    if not parts:
        return torch.zeros(0, device=device)
    return parts[0] if len(parts) == 1 else torch.cat(parts)


@torch.no_grad()
def density_grid(model, bounds, resolution: int, chunk: int = 1 << 16,
                 respect_occupancy: bool = True, cond=None) -> tuple[np.ndarray, np.ndarray]:
    """Density (1/m) of the model at the corners of :func:`grid_points` over ``bounds``
    (:func:`density_at`; with ``respect_occupancy``, 0 in cells the model's occupancy grid
    marks empty, where the renderer never samples). Returns (volume (X, Y, Z) float32,
    spacing (3,) metres)."""
    shape, spacing = grid_points(bounds, resolution)
    lo = np.asarray(bounds, float)[0]
    axes = [lo[a] + spacing[a] * np.arange(shape[a]) for a in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sigma = density_at(model, torch.as_tensor(pts, dtype=torch.float32), cond, chunk,
                       respect_occupancy=respect_occupancy)
    return sigma.float().cpu().numpy().reshape(tuple(shape)), spacing


def default_obstacle_threshold(model) -> float:
    """Density (1/m) above which a point is an obstacle by default: where one step of the
    default occupancy marcher is half opaque (:func:`default_density_threshold`), the density
    at which meshes are cut."""
    return default_density_threshold(model.aabb.detach().cpu().numpy())


class OccupancyVolume:
    """A boolean grid of obstacles over a box, with the free-space distance derived from it.

    Attributes:
        occupied: (X, Y, Z) bool, True where the density at the grid point reaches the
            threshold.
        origin: (3,) world position of grid point (0, 0, 0), metres.
        spacing: (3,) distance between neighbouring grid points per axis, metres.
        threshold: the density threshold used, 1/m.
    """

    def __init__(self, occupied: np.ndarray, origin, spacing, threshold: float):
        self.occupied = np.asarray(occupied, bool)
        self.origin = np.asarray(origin, float)
        self.spacing = np.asarray(spacing, float)
        self.threshold = float(threshold)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.occupied.shape)

    def points(self) -> np.ndarray:
        """(X, Y, Z, 3) world positions of the grid points, metres."""
        axes = [self.origin[a] + self.spacing[a] * np.arange(self.shape[a]) for a in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1)

    def index_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) int: nearest grid index of world points (N, 3), clipped to the grid."""
        idx = np.rint((np.asarray(points, float) - self.origin) / self.spacing).astype(int)
        return np.clip(idx, 0, np.asarray(self.shape) - 1)

    def distance(self) -> np.ndarray:
        """(X, Y, Z) float: Euclidean distance (metres) from each grid point to the nearest
        occupied one (0 on obstacles; inf everywhere when nothing is occupied)."""
        if not self.occupied.any():
            return np.full(self.shape, np.inf)
        return ndimage.distance_transform_edt(~self.occupied, sampling=self.spacing)


@torch.no_grad()
def occupancy_volume(model, bounds, resolution: int, threshold: Optional[float] = None,
                     cond=None, chunk: int = 1 << 16) -> OccupancyVolume:
    """Obstacles of a trained model on a near-isotropic grid over ``bounds`` (2, 3) with
    ``resolution`` cells along the longest axis: a grid point is occupied when the rendered
    scene's density there (:func:`density_at`) reaches ``threshold`` (1/m; None:
    :func:`default_obstacle_threshold`)."""
    if threshold is None:
        threshold = default_obstacle_threshold(model)
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"obstacle threshold must be finite and > 0 (1/m), got {threshold}")
    volume, spacing = density_grid(model, bounds, resolution, chunk, cond=cond)
    return OccupancyVolume(volume >= threshold, np.asarray(bounds, float)[0], spacing,
                           threshold)


def collision_cost(model, body_points: torch.Tensor, positions: torch.Tensor,
                   rotations: torch.Tensor, dt: float = 1.0, cond=None,
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """NeRF-Nav's collision cost of a rigid body moved along a trajectory, and the hard check.

    The body is a set of sample points in its own frame; pose t moves them to
    ``rotations[t] @ p + positions[t]``. The cost is the mean over poses of the mean squared
    density at the moved points times the speed at that pose (finite differences of the
    positions over ``dt`` seconds): a path through fog costs by how much of it the body sweeps,
    not by how finely the path is sampled. A single pose is weighted by 1 (its density
    alone).

    Args:
        body_points: (B, 3) sample points of the body in its frame, metres.
        positions: (T, 3) body origins in the world, metres; differentiable.
        rotations: (T, 3, 3) body orientations (body to world); differentiable.
        dt: seconds between poses.
    Returns:
        (cost, hard): a scalar tensor (differentiable w.r.t. positions and rotations, units
        1/m^2 x m/s) and (T,) the largest density at each pose's points (1/m, no gradient).
    """
    body_points = torch.as_tensor(body_points, dtype=positions.dtype, device=positions.device)
    if positions.ndim != 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions must have shape (T, 3), got {tuple(positions.shape)}")
    if rotations.shape != (len(positions), 3, 3):
        raise ValueError(f"rotations must have shape ({len(positions)}, 3, 3), got "
                         f"{tuple(rotations.shape)}")
    if dt <= 0:
        raise ValueError(f"dt must be > 0 seconds, got {dt}")
    world = torch.einsum("tij,bj->tbi", rotations, body_points) + positions[:, None, :]
    t, b = world.shape[:2]
    sigma = density_at(model, world.reshape(-1, 3), cond, grad=True).reshape(t, b)
    if t > 1:
        step = torch.linalg.vector_norm(positions[1:] - positions[:-1], dim=-1) / dt
        speed = torch.cat([step[:1], 0.5 * (step[1:] + step[:-1]), step[-1:]]) if t > 2 \
            else torch.cat([step, step])
    else:
        speed = torch.ones(1, device=positions.device)
    cost = ((sigma ** 2).mean(dim=1) * speed).mean()
    return cost, sigma.detach().max(dim=1).values
