"""Numba CPU kernels of the multiresolution hash encoding (Instant-NGP, Mueller et al. 2022).

The plain-torch twin lives in :func:`nerfbot.ops.encodings.hash_encode_reference`; tests assert the
two agree. Both use the same grid arithmetic:

* level ``l`` has ``res[l]`` cells per axis and ``res[l] + 1`` vertices per axis;
* a point ``x`` in [0, 1]^3 lies in cell ``i = clamp(floor(x * res), 0, res - 1)`` with local
  coordinate ``w = x * res - i`` in [0, 1];
* vertex ``(i, j, k)`` has table row ``i + j (res+1) + k (res+1)^2`` on dense levels (those with
  ``(res+1)^3 <= size``) and ``(i * 1 xor j * 2654435761 xor k * 805459861) mod size`` on hashed
  ones (size is a power of two, so the modulo is a mask);
* level ``l`` owns rows ``offsets[l] : offsets[l+1]`` of one flat table (rows, F).

Loops run level-major: one level's table (a few MB at most) stays in cache while all points
are looked up in it (3x faster here than point-major loops), features are laid out (L, N, F) so
each level writes contiguously, and in the backward pass each level's rows are written by one
worker only, so the scatter-add needs no atomics and is deterministic. The gradient w.r.t. the
positions (:func:`hash_backward_input`) is parallel over blocks of points instead (each point is
written by one worker), each block still visited level by level.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

PRIME_Y = 2654435761
PRIME_Z = 805459861


@njit(inline="always")
def _level(res, offsets, lvl):
    """Cells per axis (int and float32), vertices per axis, first row, rows, dense or hashed."""
    r = res[lvl]
    res1 = r + 1
    off = offsets[lvl]
    size = offsets[lvl + 1] - off
    return r, np.float32(r), res1, off, size, res1 * res1 * res1 <= size


@njit(inline="always")
def _cell(x, n, rf, r):
    """Cell index and local coordinates of point ``n`` on a level with ``r`` cells per axis."""
    px = x[n, 0] * rf
    py = x[n, 1] * rf
    pz = x[n, 2] * rf
    ix = min(int(px), r - 1)
    iy = min(int(py), r - 1)
    iz = min(int(pz), r - 1)
    return ix, iy, iz, px - np.float32(ix), py - np.float32(iy), pz - np.float32(iz)


@njit(inline="always")
def _corner_rows(ix, iy, iz, res1, mask, dense):
    """Table rows (level-relative) of the 8 cell corners, corner c = (c & 1, c >> 1 & 1, c >> 2)."""
    a0 = ix
    a1 = ix + 1
    if dense:
        b0 = iy * res1
        b1 = b0 + res1
        c0 = iz * res1 * res1
        c1 = c0 + res1 * res1
        return (a0 + b0 + c0, a1 + b0 + c0, a0 + b1 + c0, a1 + b1 + c0,
                a0 + b0 + c1, a1 + b0 + c1, a0 + b1 + c1, a1 + b1 + c1)
    b0 = iy * PRIME_Y
    b1 = b0 + PRIME_Y
    c0 = iz * PRIME_Z
    c1 = c0 + PRIME_Z
    return ((a0 ^ b0 ^ c0) & mask, (a1 ^ b0 ^ c0) & mask, (a0 ^ b1 ^ c0) & mask,
            (a1 ^ b1 ^ c0) & mask, (a0 ^ b0 ^ c1) & mask, (a1 ^ b0 ^ c1) & mask,
            (a0 ^ b1 ^ c1) & mask, (a1 ^ b1 ^ c1) & mask)


@njit(inline="always")
def _corner_weights(wx, wy, wz):
    """Trilinear weights of the 8 corners, same order as :func:`_corner_rows`."""
    one = np.float32(1.0)
    ux = one - wx
    uy = one - wy
    uz = one - wz
    return (ux * uy * uz, wx * uy * uz, ux * wy * uz, wx * wy * uz,
            ux * uy * wz, wx * uy * wz, ux * wy * wz, wx * wy * wz)


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def hash_forward(x, table, offsets, res, out, n_threads):
    """Interpolated features of every level.

    Args:
        x: (N, 3) float32 positions in [0, 1]^3 (the caller clamps).
        table: (rows, F) float32 feature table of all levels.
        offsets: (L + 1,) int64 first row of each level.
        res: (L,) int64 cells per axis of each level.
        out: (L, N, F) float32, overwritten.
        n_threads: levels are dealt round-robin to this many workers (the cost of a level grows
            with its resolution, so contiguous blocks of levels would be unbalanced).
    """
    n_points = x.shape[0]
    n_levels = res.shape[0]
    n_feat = table.shape[1]
    for tid in prange(n_threads):
        for lvl in range(tid, n_levels, n_threads):
            r, rf, res1, off, size, dense = _level(res, offsets, lvl)
            if n_feat == 2:
                # both features of a corner's row at once: 25 % faster than the generic loop
                for n in range(n_points):
                    ix, iy, iz, wx, wy, wz = _cell(x, n, rf, r)
                    rows = _corner_rows(ix, iy, iz, res1, size - 1, dense)
                    ws = _corner_weights(wx, wy, wz)
                    acc0 = np.float32(0.0)
                    acc1 = np.float32(0.0)
                    for c in range(8):
                        row = off + rows[c]
                        acc0 += ws[c] * table[row, 0]
                        acc1 += ws[c] * table[row, 1]
                    out[lvl, n, 0] = acc0
                    out[lvl, n, 1] = acc1
                continue
            for n in range(n_points):
                ix, iy, iz, wx, wy, wz = _cell(x, n, rf, r)
                rows = _corner_rows(ix, iy, iz, res1, size - 1, dense)
                ws = _corner_weights(wx, wy, wz)
                for f in range(n_feat):
                    acc = np.float32(0.0)
                    for c in range(8):
                        acc += ws[c] * table[off + rows[c], f]
                    out[lvl, n, f] = acc


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def hash_backward(x, grad_out, offsets, res, grad_table, n_threads):
    """d(loss)/d(table) into ``grad_table`` (rows, F), overwritten (it may come uninitialised).

    Args:
        x: (N, 3) float32 positions as given to :func:`hash_forward`.
        grad_out: (L, N, F) float32 gradient of the loss w.r.t. the forward output.
    Each level's rows are written by one worker only: no atomics, deterministic sums. The worker
    zeroes a level's rows just before adding into them, so the zeroing runs in parallel and
    the rows are still in its cache when the scatter-add reaches them.
    """
    n_points = x.shape[0]
    n_levels = res.shape[0]
    n_feat = grad_table.shape[1]
    for tid in prange(n_threads):
        for lvl in range(tid, n_levels, n_threads):
            r, rf, res1, off, size, dense = _level(res, offsets, lvl)
            grad_table[off:off + size, :] = 0.0
            if n_feat == 2:
                # both features of a corner's row at once: 30 % faster than the generic loop
                for n in range(n_points):
                    ix, iy, iz, wx, wy, wz = _cell(x, n, rf, r)
                    rows = _corner_rows(ix, iy, iz, res1, size - 1, dense)
                    ws = _corner_weights(wx, wy, wz)
                    g0 = grad_out[lvl, n, 0]
                    g1 = grad_out[lvl, n, 1]
                    for c in range(8):
                        row = off + rows[c]
                        grad_table[row, 0] += ws[c] * g0
                        grad_table[row, 1] += ws[c] * g1
                continue
            for n in range(n_points):
                ix, iy, iz, wx, wy, wz = _cell(x, n, rf, r)
                rows = _corner_rows(ix, iy, iz, res1, size - 1, dense)
                ws = _corner_weights(wx, wy, wz)
                for f in range(n_feat):
                    g = grad_out[lvl, n, f]
                    for c in range(8):
                        grad_table[off + rows[c], f] += ws[c] * g


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def hash_backward_input(x, table, grad_out, offsets, res, grad_x, n_threads):
    """d(loss)/d(position) of every point into ``grad_x`` (N, 3), overwritten.

    Args:
        x: (N, 3) float32 positions as given to :func:`hash_forward` (clamped by the caller).
        table: (rows, F) float32 feature table of all levels.
        grad_out: (L, N, F) float32 gradient of the loss w.r.t. the forward output.
        grad_x: (N, 3) float32, overwritten.
        n_threads: points are split into this many contiguous blocks, one per worker; each
            worker runs its block level by level (one level's table in cache at a time).

    Per level, with ``pos = x * res`` and the weights of :func:`_corner_weights`, the derivative
    is ``res * sum_c (grad_out . table[row_c]) * d(weight_c)/d(w)``, taken inside the cell
    :func:`hash_forward` uses (``min(floor(pos), res - 1)``): on a cell face, where the
    interpolation is continuous but not differentiable, that is the one-sided derivative from
    the upper cell (from the lower one at x = 1), as in the autograd of the torch twin. This is
    the gradient w.r.t. the clamped position: the caller zeroes the coordinates the clamp
    changed. Each point is written by one worker only, levels in a fixed order: deterministic.
    """
    n_points = x.shape[0]
    n_levels = res.shape[0]
    n_feat = table.shape[1]
    one = np.float32(1.0)
    zero = np.float32(0.0)
    block = (n_points + n_threads - 1) // n_threads
    for tid in prange(n_threads):
        start = tid * block
        stop = min(start + block, n_points)
        for n in range(start, stop):
            grad_x[n, 0] = zero
            grad_x[n, 1] = zero
            grad_x[n, 2] = zero
        for lvl in range(n_levels):
            r, rf, res1, off, size, dense = _level(res, offsets, lvl)
            for n in range(start, stop):
                ix, iy, iz, wx, wy, wz = _cell(x, n, rf, r)
                rows = _corner_rows(ix, iy, iz, res1, size - 1, dense)
                # s_c = grad_out . table[row_c]: the loss's sensitivity to corner c's weight
                if n_feat == 2:
                    g0 = grad_out[lvl, n, 0]
                    g1 = grad_out[lvl, n, 1]
                    s0 = g0 * table[off + rows[0], 0] + g1 * table[off + rows[0], 1]
                    s1 = g0 * table[off + rows[1], 0] + g1 * table[off + rows[1], 1]
                    s2 = g0 * table[off + rows[2], 0] + g1 * table[off + rows[2], 1]
                    s3 = g0 * table[off + rows[3], 0] + g1 * table[off + rows[3], 1]
                    s4 = g0 * table[off + rows[4], 0] + g1 * table[off + rows[4], 1]
                    s5 = g0 * table[off + rows[5], 0] + g1 * table[off + rows[5], 1]
                    s6 = g0 * table[off + rows[6], 0] + g1 * table[off + rows[6], 1]
                    s7 = g0 * table[off + rows[7], 0] + g1 * table[off + rows[7], 1]
                else:
                    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = zero
                    for f in range(n_feat):
                        g = grad_out[lvl, n, f]
                        s0 += g * table[off + rows[0], f]
                        s1 += g * table[off + rows[1], f]
                        s2 += g * table[off + rows[2], f]
                        s3 += g * table[off + rows[3], f]
                        s4 += g * table[off + rows[4], f]
                        s5 += g * table[off + rows[5], f]
                        s6 += g * table[off + rows[6], f]
                        s7 += g * table[off + rows[7], f]
                ux = one - wx
                uy = one - wy
                uz = one - wz
                # corner c = (c & 1, c >> 1 & 1, c >> 2): pairs differing in one axis
                dx = ((s1 - s0) * uy * uz + (s3 - s2) * wy * uz
                      + (s5 - s4) * uy * wz + (s7 - s6) * wy * wz)
                dy = ((s2 - s0) * ux * uz + (s3 - s1) * wx * uz
                      + (s6 - s4) * ux * wz + (s7 - s5) * wx * wz)
                dz = ((s4 - s0) * ux * uy + (s5 - s1) * wx * uy
                      + (s6 - s2) * ux * wy + (s7 - s3) * wx * wy)
                grad_x[n, 0] += rf * dx
                grad_x[n, 1] += rf * dy
                grad_x[n, 2] += rf * dz


def level_layout(n_levels: int, log2_size: int, min_res: int, max_res: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells per axis and row offsets of each level.

    Resolutions grow geometrically from ``min_res`` to ``max_res`` (the paper's
    ``N_l = floor(N_min * b^l)``); a level holds ``min((res+1)^3, 2^log2_size)`` rows, rounded up
    to a multiple of 8.

    Returns:
        res: (L,) int64, offsets: (L + 1,) int64.
    """
    if n_levels < 1 or min_res < 1 or max_res < min_res:
        raise ValueError(f"bad hash-grid levels: L={n_levels}, min_res={min_res}, max_res={max_res}")
    growth = np.exp((np.log(max_res) - np.log(min_res)) / max(n_levels - 1, 1))
    res = np.array([int(np.floor(min_res * growth**lvl + 1e-6)) for lvl in range(n_levels)], dtype=np.int64)
    size = 2**log2_size
    rows = [min((r + 1) ** 3, size) for r in res]
    rows = [(n + 7) // 8 * 8 for n in rows]
    offsets = np.concatenate([[0], np.cumsum(rows)]).astype(np.int64)
    return res, offsets
