"""Where a labelled thing is: the occupied points of one class of a run trained with labels,
and their centre (what a task uses to pick its object by name rather than by simulator ids).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from nerfbot.models.labels import point_labels
from nerfbot.query.density import default_density_threshold, density_at, grid_points


@dataclass
class ClassLocation:
    """The occupied points of one class.

    Attributes:
        name: the class.
        points: (N, 3) world points, metres: grid corners whose density reaches the
            threshold and whose most likely class is ``name``.
        centre: (3,) the points' median x, y and their lowest z (5th percentile; where the
            thing stands), metres; NaN without points.
        size: (3,) extent of the points (5th to 95th percentile per axis), metres.
    """

    name: str
    points: np.ndarray
    centre: np.ndarray
    size: np.ndarray


@torch.no_grad()
def locate_class(model, name: str, threshold: Optional[float] = None, bounds=None,
                 resolution: int = 160, chunk: int = 1 << 16) -> ClassLocation:
    """The occupied points of class ``name`` (:class:`ClassLocation`) on a grid over ``bounds``
    ((2, 3) metres; None: the run's bounds) with ``resolution`` cells along its longest side;
    occupied: density at least ``threshold`` (1/m; None:
    :func:`~nerfbot.query.density.default_density_threshold`; give Dex-NeRF's threshold to
    count glass). ValueError for a run without labels or an unknown class."""
    head = model.label_head
    if head is None:
        raise ValueError("this run has no label head (train it with --labels)")
    k = head.classes.index(name)
    aabb = model.aabb.detach().cpu().numpy()
    box = aabb if bounds is None else np.asarray(bounds, float)
    level = default_density_threshold(aabb) if threshold is None else float(threshold)
    shape, spacing = grid_points(box, resolution)
    axes = [box[0][a] + spacing[a] * np.arange(shape[a]) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    found = []
    for part in np.array_split(grid, max(1, len(grid) // chunk)):
        x = torch.from_numpy(part)
        occupied = density_at(model, x, chunk=chunk) >= level
        if bool(occupied.any()):
            pts = x[occupied.cpu()]
            cls = point_labels(model, pts, chunk).argmax(-1).cpu()
            found.append(pts[cls == k].numpy())
    points = np.concatenate(found) if found else np.zeros((0, 3), np.float32)
    if not len(points):
        nan = np.full(3, np.nan)
        return ClassLocation(name, points, nan, nan)
    lo, hi = np.percentile(points, 5, axis=0), np.percentile(points, 95, axis=0)
    centre = np.array([*np.median(points[:, :2], axis=0), lo[2]])
    return ClassLocation(name, points, centre, hi - lo)
