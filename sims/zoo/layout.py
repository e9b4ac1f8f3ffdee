"""Seeded placement of footprints on a floor or table: discs and boxes that do not overlap.

All lengths are metres in the world x-y plane.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: Random draws per item before :func:`scatter_discs` gives up on it.
TRIES = 2000


def scatter_discs(rng: np.random.Generator, radii: Sequence[float],
                  region: tuple[float, float, float, float], gap: float,
                  keep_out: Sequence[tuple[float, float, float, float]] = (),
                  required: bool = True) -> list[tuple[float, float] | None]:
    """Centres (x, y) of discs of ``radii`` inside ``region`` (xmin, ymin, xmax, ymax), at least
    ``gap`` apart (edge to edge) and clear of the ``keep_out`` boxes (xmin, ymin, xmax, ymax)
    by ``gap``; drawn uniformly, largest disc first, each by rejection.

    A disc that finds no place after :data:`TRIES` draws raises RuntimeError when ``required``,
    else gets None (the same seed always gives the same answer).
    """
    xmin, ymin, xmax, ymax = region
    placed: list[tuple[float, float, float]] = []
    out: list[tuple[float, float] | None] = [None] * len(radii)
    for i in sorted(range(len(radii)), key=lambda k: -radii[k]):
        r = float(radii[i])
        for _ in range(TRIES):
            x = float(rng.uniform(xmin + r, xmax - r)) if xmax - xmin > 2 * r else None
            y = float(rng.uniform(ymin + r, ymax - r)) if ymax - ymin > 2 * r else None
            if x is None or y is None:
                break
            if any(np.hypot(x - px, y - py) < r + pr + gap for px, py, pr in placed):
                continue
            if any(box_disc_distance(box, x, y) < r + gap for box in keep_out):
                continue
            placed.append((x, y, r))
            out[i] = (x, y)
            break
        if out[i] is None and required:
            raise RuntimeError(f"no room for a disc of radius {r:.3g} m in {region} "
                               f"after {TRIES} draws")
    return out


def box_disc_distance(box: tuple[float, float, float, float], x: float, y: float) -> float:
    """Distance from (x, y) to the box (xmin, ymin, xmax, ymax); 0 inside it."""
    dx = max(box[0] - x, 0.0, x - box[2])
    dy = max(box[1] - y, 0.0, y - box[3])
    return float(np.hypot(dx, dy))


def box_gap(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> float:
    """Distance between boxes ``a`` and ``b`` (xmin, ymin, xmax, ymax); 0 when they overlap."""
    dx = max(a[0] - b[2], 0.0, b[0] - a[2])
    dy = max(a[1] - b[3], 0.0, b[1] - a[3])
    return float(np.hypot(dx, dy))
