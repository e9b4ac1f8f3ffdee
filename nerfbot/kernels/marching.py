"""Numba CPU kernels that march rays through an occupancy grid and emit packed samples.

A ray advances from ``t_begin`` in steps ``dt(t) = clamp(t * cone, dt_min, dt_max)``; the
interval [t, t + dt] becomes a sample when the grid cell holding its midpoint is occupied. Empty
cells are crossed without emitting anything, so compute goes only where the scene is.

With a scene contraction (``chalf > 0``; :mod:`nerfbot.ops.contraction`) the grid covers
contracted space: a point ``x`` is looked up at ``ccentre + chalf * contract((x - ccentre) /
chalf)``, and each step is ``dt(t) * max(1, n^2)`` with ``n`` the L-inf norm of ``(x(t) -
ccentre) / chalf``, so steps keep about the same length in contracted space and a ray reaches
infinity in finitely many of them.

The plain-torch twin is :func:`nerfbot.ops.sampling.march_reference`; tests assert they agree.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from nerfbot.kernels.schedule import block_range

#: Rays per work item of the parallel loop, visited in the scattered order of
#: :mod:`nerfbot.kernels.schedule`.
_BLOCK = 64


@njit(inline="always")
def _occupied(px, py, pz, occ, gmin, inv_cell, g):
    ix = int(np.floor((px - gmin[0]) * inv_cell))
    iy = int(np.floor((py - gmin[1]) * inv_cell))
    iz = int(np.floor((pz - gmin[2]) * inv_cell))
    if ix < 0 or iy < 0 or iz < 0 or ix >= g or iy >= g or iz >= g:
        return False
    return occ[ix, iy, iz] != 0


@njit(inline="always")
def _step(t, dt_min, dt_max, cone):
    return min(max(t * cone, dt_min), dt_max)


@njit(inline="always")
def _norm_inf(x, y, z):
    return max(abs(x), max(abs(y), abs(z)))


@njit(inline="always")
def _contract_scale(n):
    """Factor that takes y with L-inf norm n to its contracted point (1 inside the unit cube)."""
    return 1.0 if n <= 1.0 else (2.0 - 1.0 / n) / n


@njit(parallel=True, fastmath=False, cache=True, nogil=True)
def _march(origins, dirs, t_begin, t_far, occ, gmin, cell, ccentre, chalf, dt_min, dt_max, cone,
           max_per_ray, fill, starts, ray_indices, t_starts, t_ends, counts, t_stop):
    """Both passes of the marcher: counts (``fill`` False) or writes (``fill`` True) samples."""
    g = occ.shape[0]
    inv_cell = 1.0 / cell
    contracted = chalf > 0.0
    inv_half = 1.0 / chalf if contracted else 0.0
    n_rays = origins.shape[0]
    for item in prange((n_rays + _BLOCK - 1) // _BLOCK):
        r0, r1 = block_range(item, n_rays, _BLOCK)
        for r in range(r0, r1):
            t = np.float64(t_begin[r])
            tf = np.float64(t_far[r])
            n = 0
            k = starts[r] if fill else 0
            while t < tf and n < max_per_ray:
                dt = _step(t, dt_min, dt_max, cone)
                if contracted:
                    m = _norm_inf((origins[r, 0] + t * dirs[r, 0] - ccentre[0]) * inv_half,
                                  (origins[r, 1] + t * dirs[r, 1] - ccentre[1]) * inv_half,
                                  (origins[r, 2] + t * dirs[r, 2] - ccentre[2]) * inv_half)
                    dt *= max(1.0, m * m)
                tm = t + 0.5 * dt
                px = origins[r, 0] + tm * dirs[r, 0]
                py = origins[r, 1] + tm * dirs[r, 1]
                pz = origins[r, 2] + tm * dirs[r, 2]
                if contracted:
                    yx = (px - ccentre[0]) * inv_half
                    yy = (py - ccentre[1]) * inv_half
                    yz = (pz - ccentre[2]) * inv_half
                    k_c = _contract_scale(_norm_inf(yx, yy, yz)) * chalf
                    px = ccentre[0] + yx * k_c
                    py = ccentre[1] + yy * k_c
                    pz = ccentre[2] + yz * k_c
                if _occupied(px, py, pz, occ, gmin, inv_cell, g):
                    if fill:
                        ray_indices[k] = r
                        t_starts[k] = t
                        t_ends[k] = min(t + dt, tf)
                        k += 1
                    n += 1
                t += dt
            if not fill:
                counts[r] = n
                t_stop[r] = t


_NO_I64 = np.empty(0, np.int64)
_NO_F32 = np.empty(0, np.float32)


def march_count(origins, dirs, t_begin, t_far, occ, gmin, cell, ccentre, chalf, dt_min, dt_max,
                cone, max_per_ray, counts, t_stop):
    """Count the samples each ray would emit (first pass).

    Args:
        origins, dirs: (R, 3) float32 rays (unit directions), metres.
        t_begin, t_far: (R,) float32 where marching starts / must stop.
        occ: (G, G, G) uint8 occupancy of the cube [gmin, gmin + G * cell]^3 (of contracted
            points when ``chalf > 0``).
        gmin: (3,) float64 cube corner; cell: cell edge in metres.
        ccentre: (3,) float64 centre and chalf the half-size (metres) of the cube that the scene
            contraction keeps as it is; ``chalf = 0``: no contraction.
        dt_min, dt_max, cone: step rule ``dt = clamp(t * cone, dt_min, dt_max)`` (times
            ``max(1, n^2)`` under the contraction).
        max_per_ray: stop a ray after this many samples (use a large number for "no limit").
        counts: (R,) int64 output, samples per ray.
        t_stop: (R,) float32 output, where each ray stopped (resume marching from there).
    """
    _march(origins, dirs, t_begin, t_far, occ, gmin, cell, ccentre, chalf, dt_min, dt_max, cone,
           max_per_ray, False, _NO_I64, _NO_I64, _NO_F32, _NO_F32, counts, t_stop)


def march_fill(origins, dirs, t_begin, t_far, occ, gmin, cell, ccentre, chalf, dt_min, dt_max,
               cone, max_per_ray, starts, ray_indices, t_starts, t_ends):
    """Write the samples counted by :func:`march_count` (second pass, same arguments).

    Args:
        starts: (R,) int64 index of each ray's first sample in the packed arrays.
        ray_indices: (M,) int64 output, the ray of each sample (sorted, contiguous per ray).
        t_starts, t_ends: (M,) float32 output, the sample intervals along the ray.
    """
    _march(origins, dirs, t_begin, t_far, occ, gmin, cell, ccentre, chalf, dt_min, dt_max, cone,
           max_per_ray, True, starts, ray_indices, t_starts, t_ends, _NO_I64, _NO_F32)
