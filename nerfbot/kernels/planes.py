"""Numba CPU kernels of the factorised plane encoding (K-Planes, Fridovich-Keil et al. 2023;
HexPlane, Cao & Johnson 2023).

The plain-torch twin lives in :func:`nerfbot.ops.encodings.plane_encode_reference`; tests assert the
two agree. Both use the same grid arithmetic:

* a point ``x`` in [0, 1]^D is projected on P axis-aligned planes, plane ``p`` spanning axes
  ``(a, b) = pairs[p]``;
* level ``l`` has ``res[l, d]`` cells and ``res[l, d] + 1`` vertices along axis ``d``; along
  axis ``a`` the point lies in cell ``i = clamp(floor(x_a * res[l, a]), 0, res[l, a] - 1)`` with
  local coordinate ``w = x_a * res[l, a] - i`` in [0, 1];
* vertex ``(i, j)`` of plane ``p`` of level ``l`` has table row
  ``offsets[l * P + p] + i + j * (res[l, a] + 1)`` of one flat table (rows, F);
* the features of level ``l`` are the Hadamard product over the P planes of their bilinear
  interpolations, and levels are concatenated: output (N, L * F).

The product is taken in the kernel: no (L, P, N, F) intermediate is stored, and the backward
pass recomputes the P plane values of a point and uses prefix/suffix products (exact where a
plane value is zero). Measured on 2 cores with 131072 points, 2 levels, 6 planes, 8 features,
this takes half the time of a kernel that returns the per-plane values and leaves the product
to torch. Unlike the hash grid (parallel over levels), both passes are parallel over points:
there are few levels, and the product needs all planes of a level at once. The forward pass
loops point-major (1.7x faster here than level-major: the tables are small); in the backward
pass each worker owns a contiguous block of points and a private gradient table, so the
scatter-add needs no atomics and the sum of the private tables is deterministic for a given
number of workers.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(inline="always")
def _corners(x, n, a, b, ra, rb, off):
    """Bilinear stencil of point ``n`` on a plane over axes (a, b) with ra x rb cells.

    Returns the rows of corners (i, j) and (i, j + 1) (add 1 for i + 1) and the weights of the
    corners (i, j), (i+1, j), (i, j+1), (i+1, j+1). Indices are clamped on both sides, so even a
    NaN coordinate (whose int conversion is undefined) stays in bounds.
    """
    pa = x[n, a] * np.float32(ra)
    pb = x[n, b] * np.float32(rb)
    ia = max(min(int(pa), ra - 1), 0)
    ib = max(min(int(pb), rb - 1), 0)
    wa = pa - np.float32(ia)
    wb = pb - np.float32(ib)
    one = np.float32(1.0)
    row0 = off + ia + ib * (ra + 1)
    return (row0, row0 + ra + 1, (one - wa) * (one - wb), wa * (one - wb), (one - wa) * wb,
            wa * wb)


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def plane_forward(x, pairs, table, offsets, res, out):
    """Encoded features of every level.

    Args:
        x: (N, D) float32 points in [0, 1]^D (the caller clamps and replaces NaN).
        pairs: (P, 2) int64 axes spanned by each plane.
        table: (rows, F) float32 features of all planes of all levels.
        offsets: (L * P + 1,) int64 first row of plane p of level l at ``offsets[l * P + p]``.
        res: (L, D) int64 cells per axis of each level.
        out: (N, L * F) float32, overwritten with the per-level products of the P planes.
    """
    n_points = x.shape[0]
    n_levels = res.shape[0]
    n_planes = pairs.shape[0]
    n_feat = table.shape[1]
    for n in prange(n_points):
        for lvl in range(n_levels):
            col = lvl * n_feat
            for f in range(n_feat):
                out[n, col + f] = np.float32(1.0)
            for p in range(n_planes):
                a = pairs[p, 0]
                b = pairs[p, 1]
                r0, r1, w00, w10, w01, w11 = _corners(x, n, a, b, res[lvl, a], res[lvl, b],
                                                      offsets[lvl * n_planes + p])
                for f in range(n_feat):
                    out[n, col + f] *= (w00 * table[r0, f] + w10 * table[r0 + 1, f]
                                        + w01 * table[r1, f] + w11 * table[r1 + 1, f])


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def plane_backward(x, pairs, table, offsets, res, grad_out, grad_tables):
    """Accumulate d(loss)/d(table), one private table per worker.

    Args:
        x, pairs, table, offsets, res: as given to :func:`plane_forward`.
        grad_out: (N, L * F) float32 gradient of the loss w.r.t. the forward output.
        grad_tables: (T, rows, F) float32, zero on entry; worker ``t`` adds the contributions of
            points ``[t * ceil(N / T), (t + 1) * ceil(N / T))`` into ``grad_tables[t]``. The
            table gradient is ``grad_tables.sum(0)``.
    """
    n_points = x.shape[0]
    n_levels = res.shape[0]
    n_planes = pairs.shape[0]
    n_feat = table.shape[1]
    n_threads = grad_tables.shape[0]
    chunk = (n_points + n_threads - 1) // n_threads
    for tid in prange(n_threads):
        gt = grad_tables[tid]
        rows = np.empty((n_planes, 2), np.int64)
        ws = np.empty((n_planes, 4), np.float32)
        vals = np.empty((n_planes, n_feat), np.float32)    # interpolated plane values
        grads = np.empty((n_planes, n_feat), np.float32)   # d loss / d plane values
        for lvl in range(n_levels):
            col = lvl * n_feat
            for n in range(tid * chunk, min(n_points, (tid + 1) * chunk)):
                for p in range(n_planes):
                    a = pairs[p, 0]
                    b = pairs[p, 1]
                    r0, r1, w00, w10, w01, w11 = _corners(x, n, a, b, res[lvl, a], res[lvl, b],
                                                          offsets[lvl * n_planes + p])
                    rows[p, 0] = r0
                    rows[p, 1] = r1
                    ws[p, 0] = w00
                    ws[p, 1] = w10
                    ws[p, 2] = w01
                    ws[p, 3] = w11
                    for f in range(n_feat):
                        vals[p, f] = (w00 * table[r0, f] + w10 * table[r0 + 1, f]
                                      + w01 * table[r1, f] + w11 * table[r1 + 1, f])
                # d out / d plane p = product of the other planes: prefix times suffix products
                for f in range(n_feat):
                    acc = grad_out[n, col + f]
                    for p in range(n_planes):
                        grads[p, f] = acc
                        acc *= vals[p, f]
                    acc = np.float32(1.0)
                    for p in range(n_planes - 1, -1, -1):
                        grads[p, f] *= acc
                        acc *= vals[p, f]
                for p in range(n_planes):
                    r0 = rows[p, 0]
                    r1 = rows[p, 1]
                    for f in range(n_feat):
                        g = grads[p, f]
                        gt[r0, f] += ws[p, 0] * g
                        gt[r0 + 1, f] += ws[p, 1] * g
                        gt[r1, f] += ws[p, 2] * g
                        gt[r1 + 1, f] += ws[p, 3] * g


def plane_layout(res: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Row offsets of every plane of every level.

    Args:
        res: (L, D) int64 cells per axis of each level; pairs: (P, 2) int64 plane axes.
    Returns:
        offsets: (L * P + 1,) int64, plane p of level l holds rows
        ``offsets[l * P + p] : offsets[l * P + p + 1]``, (res[l, a] + 1) * (res[l, b] + 1) rows.
    """
    res, pairs = np.asarray(res, np.int64), np.asarray(pairs, np.int64)
    if res.ndim != 2 or (res < 1).any() or pairs.ndim != 2 or pairs.shape[1] != 2:
        raise ValueError(f"bad plane layout: res shape {res.shape}, pairs shape {pairs.shape}")
    if (pairs < 0).any() or (pairs >= res.shape[1]).any() or (pairs[:, 0] == pairs[:, 1]).any():
        raise ValueError(f"plane axes must be two distinct axes < {res.shape[1]}: {pairs.tolist()}")
    rows = (res[:, pairs[:, 0]] + 1) * (res[:, pairs[:, 1]] + 1)   # (L, P)
    return np.concatenate([[0], np.cumsum(rows.reshape(-1))]).astype(np.int64)
