"""Numba ray / box intersection, float32 operation by operation as the torch reference
:func:`nerfbot.ops.sampling.ray_aabb` (tests assert bitwise agreement), so fused renderers and the
torch paths start and end rays at the same distances."""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(inline="always")
def slab(o, d, lo, hi, t0, t1):
    """Narrow [t0, t1] to where the ray is between planes lo and hi of one axis (float32); a
    direction component below 1e-12 is parallel: everything or nothing."""
    if abs(d) < 1e-12:
        if lo <= o <= hi:
            return t0, t1
        return np.float32(np.inf), np.float32(-np.inf)
    inv = np.float32(1.0) / d
    a = (lo - o) * inv
    b = (hi - o) * inv
    return max(t0, min(a, b)), min(t1, max(a, b))


@njit(inline="always")
def ray_box(origins, dirs, r, box):
    """(t_near, t_far) of ray r in the box (2, 3) float32, both 0 when it misses (ray_aabb's
    rule with near = 0), as float64."""
    t0, t1 = np.float32(-np.inf), np.float32(np.inf)
    for a in range(3):
        t0, t1 = slab(origins[r, a], dirs[r, a], box[0, a], box[1, a], t0, t1)
    t0 = max(t0, np.float32(0.0))
    if not t1 > t0:
        return 0.0, 0.0
    return np.float64(t0), np.float64(t1)


@njit(parallel=True, cache=True, nogil=True)
def ray_aabb(origins, dirs, box, near, t_near, t_far, hit):
    """All rays: origins, dirs (R, 3) float32, box (2, 3) float32, near float32 -> t_near,
    t_far (R,) float32 and hit (R,) bool, by :func:`nerfbot.ops.sampling.ray_aabb`'s rules."""
    for r in prange(origins.shape[0]):
        t0, t1 = np.float32(-np.inf), np.float32(np.inf)
        for a in range(3):
            t0, t1 = slab(origins[r, a], dirs[r, a], box[0, a], box[1, a], t0, t1)
        t0 = max(t0, near)
        h = t1 > t0
        hit[r] = h
        t_near[r] = t0 if h else near
        t_far[r] = t1 if h else near
