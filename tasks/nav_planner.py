"""Paths for a planar mobile robot: A* on a floor map inflated by the robot's radius (the warm
start), then trajectory optimisation through the field's density (NeRF-Nav's collision cost,
smoothness and speed limits, by gradient descent).

Start and goal must be cells where the robot can stand; when one is not, :class:`PlanningError`
says which, why, and offers the nearest cell where it can.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from nerfbot.query.density import collision_cost
from tasks.nav_map import FloorMap, RobotBody

#: The 8-connected neighbourhood: (di, dj, step length in cells).
_NEIGHBOURS = [(di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1)
               if di or dj]


class PlanningError(ValueError):
    """No path: start or goal where the robot cannot stand, or no connection between them."""


def astar(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]
          ) -> Optional[list[tuple[int, int]]]:
    """Shortest 8-connected path of free cells from ``start`` to ``goal`` (both free), Euclidean
    step costs, octile-distance heuristic (admissible and consistent). A diagonal step needs
    both cells beside it free, so paths never cut an obstacle's corner. Returns the cells from
    start to goal, or None when they are not connected."""
    free = np.asarray(free, bool)
    nx, ny = free.shape
    start, goal = tuple(int(v) for v in start), tuple(int(v) for v in goal)

    def h(c):
        dx, dy = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return max(dx, dy) + (math.sqrt(2.0) - 1.0) * min(dx, dy)

    g = {start: 0.0}
    parent = {start: None}
    heap = [(h(start), 0.0, start)]
    closed = set()
    while heap:
        _, cost, cur = heapq.heappop(heap)
        if cur in closed:
            continue
        if cur == goal:
            path = []
            while cur is not None:
                path.append(cur)
                cur = parent[cur]
            return path[::-1]
        closed.add(cur)
        ci, cj = cur
        for di, dj, step in _NEIGHBOURS:
            ni, nj = ci + di, cj + dj
            if not (0 <= ni < nx and 0 <= nj < ny) or not free[ni, nj]:
                continue
            if di and dj and not (free[ci + di, cj] and free[ci, cj + dj]):
                continue
            new = cost + step
            if new < g.get((ni, nj), math.inf):
                g[(ni, nj)] = new
                parent[(ni, nj)] = cur
                heapq.heappush(heap, (new + h((ni, nj)), new, (ni, nj)))
    return None


def nearest_free(free: np.ndarray, cell: tuple[int, int]) -> Optional[tuple[int, int]]:
    """The free cell nearest to ``cell`` (Euclidean in cells), None if none is free."""
    idx = np.argwhere(free)
    if not len(idx):
        return None
    k = int(np.argmin(((idx - np.asarray(cell)) ** 2).sum(-1)))
    return int(idx[k, 0]), int(idx[k, 1])


def _check_endpoint(fmap: FloorMap, free: np.ndarray, xy, what: str, radius: float,
                    reach: float = 0.0) -> tuple:
    """The free cell of endpoint ``xy``: its own, else (with ``reach`` > 0) the nearest free
    cell whose centre lies within ``reach`` metres of it; PlanningError otherwise."""
    cell = tuple(int(v) for v in fmap.to_cell(xy))
    where = f"({xy[0]:.2f}, {xy[1]:.2f}) m"
    if not fmap.inside(cell):
        raise PlanningError(f"{what} {where} is outside the map")
    if free[cell]:
        return cell
    near = nearest_free(free, cell)
    if near is not None and np.linalg.norm(fmap.to_world(near) - np.asarray(xy)) <= reach + 1e-9:
        return near
    offer = "no cell of the map is free" if near is None else \
        "the nearest point where it can is ({:.2f}, {:.2f}) m".format(*fmap.to_world(near))
    reason = "inside an obstacle" if fmap.blocked[cell] else \
        f"closer than the robot's radius ({radius:.2f} m) to an obstacle"
    raise PlanningError(f"{what} {where} is {reason} of the map: the robot cannot stand there; "
                        f"{offer}")


def plan_grid_path(fmap: FloorMap, body: RobotBody, start_xy, goal_xy,
                   margin: float = 0.0, goal_reach: float = 0.0) -> np.ndarray:
    """A* from ``start_xy`` to ``goal_xy`` (world x, y, metres) over the cells where the body,
    its radius grown by ``margin``, can stand. Returns (N, 2) world points from start to goal
    (the exact endpoints at both ends, cell centres between). A goal where the body cannot
    stand is replaced by the nearest cell centre where it can, if that lies within
    ``goal_reach`` metres (a goal is reached within a tolerance), which then ends the path.
    PlanningError when an endpoint is not free (naming the nearest free point) or when no path
    connects them."""
    radius = body.radius + margin
    free = fmap.free_for(radius)
    start = _check_endpoint(fmap, free, start_xy, "start", radius)
    goal = _check_endpoint(fmap, free, goal_xy, "goal", radius, goal_reach)
    cells = astar(free, start, goal)
    if cells is None:
        raise PlanningError(f"no path for a robot of radius {radius:.2f} m from "
                            f"({start_xy[0]:.2f}, {start_xy[1]:.2f}) to "
                            f"({goal_xy[0]:.2f}, {goal_xy[1]:.2f}) m on this map")
    pts = fmap.to_world(np.asarray(cells))
    pts[0] = start_xy
    if goal == tuple(int(v) for v in fmap.to_cell(goal_xy)):
        pts[-1] = goal_xy
    return pts


def shortcut(points: np.ndarray, fmap: FloorMap, radius: float, step: float = 0.5) -> np.ndarray:
    """Drop waypoints while the straight segment between the kept ones stays on cells where a
    body of ``radius`` can stand (checked every ``step`` cells): a shorter polyline with the
    same clearance."""
    free = fmap.free_for(radius)
    out = [points[0]]
    i = 0
    while i < len(points) - 1:
        j = len(points) - 1
        while j > i + 1 and not segment_free(points[i], points[j], fmap, free, step):
            j -= 1
        out.append(points[j])
        i = j
    return np.asarray(out)


def segment_free(a, b, fmap: FloorMap, free: np.ndarray, step: float = 0.5) -> bool:
    """Whether every point of segment a-b (world x, y), checked every ``step`` cells, lies on a
    free cell."""
    n = max(int(np.ceil(np.linalg.norm(np.subtract(b, a)) / (fmap.cell * step))), 1)
    pts = np.asarray(a, float) + np.linspace(0, 1, n + 1)[:, None] * np.subtract(b, a)
    cells = fmap.to_cell(pts)
    if not np.all(fmap.inside(cells)):
        return False
    return bool(free[cells[:, 0], cells[:, 1]].all())


def path_length(points: np.ndarray) -> float:
    """Length of a polyline (N, 2), metres."""
    return float(np.linalg.norm(np.diff(np.asarray(points, float), axis=0), axis=1).sum())


def resample(points: np.ndarray, spacing: float) -> np.ndarray:
    """The polyline (N, 2) resampled at equal arc-length steps of at most ``spacing`` metres,
    both ends kept."""
    points = np.asarray(points, float)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / spacing)), 1)
    t = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(t, s, points[:, k]) for k in range(2)], -1)


@dataclass(frozen=True)
class TrajectoryConfig:
    """Trajectory optimisation through the field (NeRF-Nav's costs).

    Attributes:
        spacing: distance between optimised poses, metres.
        speed: planned speed, m/s (sets the time between poses for the collision cost).
        iterations: Adam steps.
        lr: Adam learning rate, metres.
        collision_weight: weight of the collision cost.
        smoothness_weight: weight of the squared second differences (acceleration), 1/m^2 per
            pose.
        max_step_ratio: a segment longer than this many times ``spacing`` is penalised
            (the speed limit).
    """

    spacing: float = 0.1
    speed: float = 0.4
    iterations: int = 60
    lr: float = 0.01
    collision_weight: float = 1e-3
    smoothness_weight: float = 10.0
    max_step_ratio: float = 1.5


def optimise_trajectory(model, warm_start: np.ndarray, body: RobotBody, fmap: FloorMap,
                        config: TrajectoryConfig = TrajectoryConfig(), floor_z: float = 0.0,
                        margin: float = 0.0) -> tuple[np.ndarray, dict]:
    """Refine a warm-start path (N, 2) by gradient descent on collision cost (the body moved
    along the path through the field's density) + smoothness + the speed limit; start and
    goal stay fixed. The refined path is kept only if it still stays on cells where the body
    (radius grown by ``margin``) can stand and its collision cost did not grow; otherwise the
    resampled warm start is returned. Returns ((M, 2) path, info: cost before and after,
    whether the refinement was kept)."""
    path0 = resample(warm_start, config.spacing)
    device = model.aabb.device
    body_pts = torch.as_tensor(body.sample_points(), dtype=torch.float32, device=device)
    body_pts[:, 2] += floor_z
    eye = torch.eye(3, device=device).expand(len(path0), 3, 3)
    dt = config.spacing / config.speed
    fixed = torch.as_tensor(path0, dtype=torch.float32, device=device)
    inner = fixed[1:-1].clone().requires_grad_(True)
    opt = torch.optim.Adam([inner], lr=config.lr)

    def costs(xy):
        pos = torch.cat([xy, torch.zeros(len(xy), 1, device=device)], 1)
        coll, hard = collision_cost(model, body_pts, pos, eye[:len(xy)], dt)
        acc = xy[2:] - 2 * xy[1:-1] + xy[:-2]
        smooth = (acc ** 2).sum(-1).mean() / config.spacing ** 2 if len(xy) > 2 else xy.sum() * 0
        seg = torch.linalg.vector_norm(xy[1:] - xy[:-1], dim=-1)
        limit = torch.relu(seg - config.max_step_ratio * config.spacing).pow(2).mean() \
            / config.spacing ** 2
        total = config.collision_weight * coll + config.smoothness_weight * smooth + 10.0 * limit
        return total, coll, hard

    with torch.no_grad():
        _, coll0, _ = costs(fixed)
    if len(path0) > 2:
        for _ in range(config.iterations):
            opt.zero_grad()
            total, _, _ = costs(torch.cat([fixed[:1], inner, fixed[-1:]]))
            total.backward()
            opt.step()
    refined = torch.cat([fixed[:1], inner.detach(), fixed[-1:]])
    with torch.no_grad():
        _, coll1, _ = costs(refined)
    out = refined.cpu().numpy().astype(float)
    free = fmap.free_for(body.radius + margin)
    ok = all(segment_free(out[k], out[k + 1], fmap, free) for k in range(len(out) - 1))
    keep = ok and float(coll1) <= float(coll0)
    info = {"collision_cost_before": float(coll0), "collision_cost_after": float(coll1),
            "refined": keep}
    return (out if keep else path0), info
