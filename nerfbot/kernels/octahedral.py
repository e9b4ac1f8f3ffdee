"""Numba lookups on octahedral direction maps: tables of values at the vertices of a grid over
the octahedral square (see :func:`nerfbot.ops.octahedral.octahedral_encode`), read with bilinear
interpolation. The FastNeRF cache stores its direction network this way, and the baked renderers
their background (:class:`nerfbot.fields.background.BakedBackground`)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(inline="always")
def octahedral(dx, dy, dz):
    """Unit direction -> octahedral coordinates (u, v) in [-1, 1]^2, as
    :func:`nerfbot.ops.octahedral.octahedral_encode`."""
    inv = 1.0 / max(abs(dx) + abs(dy) + abs(dz), 1e-30)
    px, py, pz = dx * inv, dy * inv, dz * inv
    if pz >= 0:
        return px, py
    sx = 1.0 if px >= 0 else -1.0
    sy = 1.0 if py >= 0 else -1.0
    return (1.0 - abs(py)) * sx, (1.0 - abs(px)) * sy


@njit(inline="always")
def corners(nd, dx, dy, dz):
    """The bilinear stencil of direction (dx, dy, dz) on an ND x ND vertex map: (iu, iv, w00,
    w10, w01, w11), the first vertex and the weights of vertices (iu + a, iv + b) as w_ab;
    vertex (i, j) sits at (u, v) = (-1 + 2i / (ND - 1), -1 + 2j / (ND - 1))."""
    u, v = octahedral(dx, dy, dz)
    fu = (u + 1.0) * 0.5 * (nd - 1)
    fv = (v + 1.0) * 0.5 * (nd - 1)
    iu = min(max(int(math.floor(fu)), 0), nd - 2)
    iv = min(max(int(math.floor(fv)), 0), nd - 2)
    wu = fu - iu
    wv = fv - iv
    return iu, iv, (1.0 - wu) * (1.0 - wv), wu * (1.0 - wv), (1.0 - wu) * wv, wu * wv


@njit(inline="always")
def bilinear(table, dx, dy, dz, out):
    """Write the bilinear lookup of ``table`` (ND, ND, C) at direction (dx, dy, dz) into
    ``out`` (C,)."""
    iu, iv, w00, w10, w01, w11 = corners(table.shape[0], dx, dy, dz)
    for i in range(out.shape[0]):
        out[i] = (w00 * table[iu, iv, i] + w10 * table[iu + 1, iv, i]
                  + w01 * table[iu, iv + 1, i] + w11 * table[iu + 1, iv + 1, i])


@njit(parallel=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"}, cache=True)
def lookup(dirs, table, out):
    """out[r] = the bilinear lookup of ``table`` (ND, ND, C) float32 at unit direction dirs[r]
    ((R, 3) float32); out: (R, C) float32. Float32 arithmetic throughout (3x faster than
    :func:`bilinear`'s float64; the two agree to ~1e-5)."""
    nd = table.shape[0]
    one = np.float32(1.0)
    half = np.float32(0.5 * (nd - 1))
    for r in prange(dirs.shape[0]):
        dx, dy, dz = dirs[r, 0], dirs[r, 1], dirs[r, 2]
        inv = one / max(abs(dx) + abs(dy) + abs(dz), np.float32(1e-30))
        u, v = dx * inv, dy * inv
        if dz < 0:
            u, v = ((one - abs(v)) * (one if u >= 0 else -one),
                    (one - abs(u)) * (one if v >= 0 else -one))
        fu = (u + one) * half  # in [0, ND - 1]: truncation is floor
        fv = (v + one) * half
        iu = min(max(np.int64(fu), 0), nd - 2)
        iv = min(max(np.int64(fv), 0), nd - 2)
        wu = fu - np.float32(iu)
        wv = fv - np.float32(iv)
        for c in range(out.shape[1]):
            a = table[iu, iv, c] + wu * (table[iu + 1, iv, c] - table[iu, iv, c])
            b = table[iu, iv + 1, c] + wu * (table[iu + 1, iv + 1, c] - table[iu, iv + 1, c])
            out[r, c] = a + wv * (b - a)
