"""Trilinear interpolation in a sparse dense-indexed voxel grid (Plenoxels), numba CPU kernels
with their plain-torch twins.

Grid arithmetic (kernels and twins alike):

* the grid has ``n_a = links.shape[a] - 1`` cells and ``links.shape[a]`` vertices along axis
  ``a``; a point ``x`` in [0, 1]^3 (box coordinates) lies in cell
  ``i = clamp(floor(x * n), 0, n - 1)`` with local coordinate ``w = x * n - i`` in [0, 1];
* vertex ``(i, j, k)`` stores its values in row ``links[i, j, k]`` of a table (rows, C), or
  nothing when ``links[i, j, k] < 0`` (a pruned vertex, whose value is zero);
* corner ``c`` of a cell is ``(i + (c & 1), j + (c >> 1 & 1), k + (c >> 2))``.

The work is split in three kernels: :func:`grid_stencil` computes each point's 8 corner rows and
weights once, :func:`grid_gather` interpolates any table with them (called for the density table
and the spherical-harmonics table of the same points) and :func:`grid_scatter` is its adjoint.
A pruned corner gets row 0 and weight 0 (later loops need no branch) and the weights of the
stored corners are renormalised to sum to one: next to pruned space, values are interpolated
from the stored vertices only (no pull towards zero), and the stencil reports the *coverage*,
the trilinear weight of the stored corners, with which the caller fades density out to exactly
zero in fully pruned cells.

The module also holds the fused spherical-harmonics colour kernels (:func:`sh_color_forward`,
:func:`sh_color_backward`: one pass instead of a dozen elementwise torch ops on (N, 3, K)) and
the total-variation kernels of the grid tables (:func:`tv_forward`, :func:`tv_backward`).

Layout, measured on 2 cores with 131072 random points, 28 channels, a 129^3 grid: points-major
tables (rows, C) gather in 40 ms, channel-major ones (C, rows) in 144 ms (a corner's 28 values
are one 112-byte run instead of 28 cache lines). The scatter gives each worker the rows of a
contiguous range (every worker reads all stencils and writes only its own rows): 83 ms and
no extra memory, against 244 ms for per-worker private gradient tables that are summed after
(zeroing and summing two extra (rows, C) tables costs more than the scatter). Writes to a row
come from one worker in point order, so the sums are deterministic.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import njit, prange

from nerfbot.kernels.sh import spherical_harmonics_reference


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def grid_stencil(x, links, rows, weights, coverage):
    """Corner rows and trilinear weights of every point, renormalised over the stored corners.

    Args:
        x: (N, 3) float32 box coordinates in [0, 1]^3 (the caller clamps and replaces NaN;
            indices are clamped on both sides here anyway, so nothing reads out of bounds).
        links: (Vx, Vy, Vz) int32 table row of every vertex, < 0 for pruned vertices.
        rows: (N, 8) int32, overwritten with the corner rows (0 for pruned corners).
        weights: (N, 8) float32, overwritten with the trilinear weights of the stored corners
            divided by their sum (0 for pruned corners; all 0 when every corner is pruned).
        coverage: (N,) float32, overwritten with the sum of the trilinear weights of the stored
            corners (1 in a cell without pruned corners, 0 in a fully pruned one).
    """
    nx = links.shape[0] - 1
    ny = links.shape[1] - 1
    nz = links.shape[2] - 1
    one = np.float32(1.0)
    zero = np.float32(0.0)
    for n in prange(x.shape[0]):
        px = x[n, 0] * np.float32(nx)
        py = x[n, 1] * np.float32(ny)
        pz = x[n, 2] * np.float32(nz)
        ix = max(min(int(px), nx - 1), 0)
        iy = max(min(int(py), ny - 1), 0)
        iz = max(min(int(pz), nz - 1), 0)
        wx = px - np.float32(ix)
        wy = py - np.float32(iy)
        wz = pz - np.float32(iz)
        ux = one - wx
        uy = one - wy
        uz = one - wz
        total = zero
        for c in range(8):
            a = c & 1
            b = (c >> 1) & 1
            d = c >> 2
            r = links[ix + a, iy + b, iz + d]
            w = (wx if a else ux) * (wy if b else uy) * (wz if d else uz)
            if r < 0:
                r = 0
                w = zero
            rows[n, c] = r
            weights[n, c] = w
            total += w
        coverage[n] = total
        if total > zero:
            inv = one / total
            for c in range(8):
                weights[n, c] *= inv


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def grid_gather(table, rows, weights, out):
    """Interpolated values ``out[n] = sum_c weights[n, c] * table[rows[n, c]]``.

    Args:
        table: (V, C) float32, V >= 1; rows, weights: (N, 8) from :func:`grid_stencil`.
        out: (N, C) float32, overwritten.
    """
    n_ch = table.shape[1]
    for n in prange(rows.shape[0]):
        for f in range(n_ch):
            out[n, f] = np.float32(0.0)
        for c in range(8):
            r = rows[n, c]
            w = weights[n, c]
            for f in range(n_ch):
                out[n, f] += w * table[r, f]


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def grid_scatter(grad_out, rows, weights, grad_table, n_threads):
    """Adjoint of :func:`grid_gather`: ``grad_table[rows[n, c]] += weights[n, c] * grad_out[n]``.

    Args:
        grad_out: (N, C) float32; rows, weights: (N, 8) from :func:`grid_stencil`.
        grad_table: (V, C) float32, accumulated into (zero it first for a plain gradient).
        n_threads: worker ``t`` owns rows ``[t * ceil(V / T), (t + 1) * ceil(V / T))``.
    """
    n_rows = grad_table.shape[0]
    n_ch = grad_table.shape[1]
    n_points = rows.shape[0]
    per = (n_rows + n_threads - 1) // n_threads
    for t in prange(n_threads):
        lo = t * per
        hi = lo + per
        for n in range(n_points):
            for c in range(8):
                r = rows[n, c]
                w = weights[n, c]
                if r >= lo and r < hi and w != np.float32(0.0):
                    for f in range(n_ch):
                        grad_table[r, f] += w * grad_out[n, f]


# Real SH constants, the basis of nerfbot.ops.encodings.spherical_harmonics (degrees 0..2; the
# tests compare the two)
_Y0 = np.float32(0.28209479177387814)
_Y1 = np.float32(0.4886025119029199)
_Y2A = np.float32(1.0925484305920792)
_Y2B = np.float32(0.31539156525252005)
_Y2C = np.float32(0.5462742152960396)


@njit(inline="always")
def _sh_basis(d, n, basis):
    """SH basis of direction ``d[n]`` into ``basis`` (K,), K = 1, 4 or 9."""
    k = basis.shape[0]
    x = d[n, 0]
    y = d[n, 1]
    z = d[n, 2]
    basis[0] = _Y0
    if k > 1:
        basis[1] = -_Y1 * y
        basis[2] = _Y1 * z
        basis[3] = -_Y1 * x
    if k > 4:
        basis[4] = _Y2A * x * y
        basis[5] = -_Y2A * y * z
        basis[6] = _Y2B * (2 * z * z - x * x - y * y)
        basis[7] = -_Y2A * x * z
        basis[8] = _Y2C * (x * x - y * y)


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def sh_color_forward(coeffs, d, rgb):
    """``rgb[n, c] = sigmoid(sum_k coeffs[n, c K + k] Y_k(d[n]))``.

    Args:
        coeffs: (N, 3 K) float32 SH coefficients, channel-major, K = 1, 4 or 9.
        d: (N, 3) float32 unit directions.
        rgb: (N, 3) float32, overwritten.
    """
    k = coeffs.shape[1] // 3
    one = np.float32(1.0)
    for n in prange(coeffs.shape[0]):
        basis = np.empty(k, np.float32)
        _sh_basis(d, n, basis)
        for c in range(3):
            acc = np.float32(0.0)
            for j in range(k):
                acc += coeffs[n, c * k + j] * basis[j]
            rgb[n, c] = one / (one + np.exp(-acc))


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def sh_color_backward(rgb, d, grad_rgb, grad_coeffs):
    """Gradient of :func:`sh_color_forward` w.r.t. the coefficients.

    Args:
        rgb: (N, 3) its output; d: (N, 3) its directions; grad_rgb: (N, 3) float32.
        grad_coeffs: (N, 3 K) float32, overwritten.
    """
    k = grad_coeffs.shape[1] // 3
    one = np.float32(1.0)
    for n in prange(rgb.shape[0]):
        basis = np.empty(k, np.float32)
        _sh_basis(d, n, basis)
        for c in range(3):
            s = rgb[n, c]
            g = grad_rgb[n, c] * s * (one - s)
            for j in range(k):
                grad_coeffs[n, c * k + j] = g * basis[j]


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def tv_forward(table, pairs, partial):
    """Squared differences of pairs of rows, summed per worker.

    Args:
        table: (V, C) float32; pairs: (2, P) int64 rows (a, b) to compare.
        partial: (T,) float64, overwritten: worker ``t``'s sum of ``|table[a] - table[b]|^2``
            over its contiguous block of pairs (the total is ``partial.sum()``, deterministic
            for a given T).
    """
    n_threads = partial.shape[0]
    n_pairs = pairs.shape[1]
    n_ch = table.shape[1]
    chunk = (n_pairs + n_threads - 1) // n_threads
    for t in prange(n_threads):
        acc = 0.0
        for p in range(t * chunk, min(n_pairs, (t + 1) * chunk)):
            a = pairs[0, p]
            b = pairs[1, p]
            for f in range(n_ch):
                diff = table[a, f] - table[b, f]
                acc += diff * diff
        partial[t] = acc


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def tv_backward(table, pairs, scale, grad_table, n_threads):
    """Gradient of ``scale * sum_p |table[a_p] - table[b_p]|^2`` accumulated into
    ``grad_table`` (V, C); worker ``t`` owns a contiguous range of rows (as in
    :func:`grid_scatter`)."""
    n_rows = grad_table.shape[0]
    n_ch = grad_table.shape[1]
    n_pairs = pairs.shape[1]
    per = (n_rows + n_threads - 1) // n_threads
    two = np.float32(2.0 * scale)
    for t in prange(n_threads):
        lo = t * per
        hi = lo + per
        for p in range(n_pairs):
            a = pairs[0, p]
            b = pairs[1, p]
            if lo <= a < hi:
                for f in range(n_ch):
                    grad_table[a, f] += two * (table[a, f] - table[b, f])
            if lo <= b < hi:
                for f in range(n_ch):
                    grad_table[b, f] += two * (table[b, f] - table[a, f])


# ------------------------------------------------------------------------------ torch twins

def stencil_reference(x: torch.Tensor, links: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Plain-torch twin of :func:`grid_stencil` (any device, differentiable w.r.t. ``x``).

    Args:
        x: (N, 3) box coordinates in [0, 1]^3; links: (Vx, Vy, Vz) integer rows (< 0: pruned).
    Returns:
        rows (N, 8) int64 (0 for pruned corners), weights (N, 8) renormalised over the stored
        corners (0 for pruned ones), coverage (N,).
    """
    n = torch.tensor(links.shape, device=x.device) - 1
    pos = x * n.to(x.dtype)
    cell = torch.minimum(pos.detach().floor().long().clamp_min(0), n - 1)
    w = pos - cell.to(pos.dtype)
    rows, weights = [], []
    for c in range(8):
        corner = torch.tensor([c & 1, (c >> 1) & 1, c >> 2], device=x.device)
        v = cell + corner
        r = links[v[:, 0], v[:, 1], v[:, 2]].long()
        wc = torch.where(corner.bool(), w, 1.0 - w).prod(-1)
        rows.append(r.clamp_min(0))
        weights.append(torch.where(r >= 0, wc, torch.zeros_like(wc)))
    weights = torch.stack(weights, -1)
    coverage = weights.sum(-1)
    safe = torch.where(coverage > 0, coverage, torch.ones_like(coverage))
    return torch.stack(rows, -1), weights / safe[:, None], coverage


def gather_reference(table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Plain-torch twin of :func:`grid_gather`: (V, C), (N, 8), (N, 8) -> (N, C), differentiable
    w.r.t. ``table`` and ``weights``."""
    return (table[rows] * weights[..., None]).sum(1)


# ----------------------------------------------------------------------- torch entry points

def _n_workers() -> int:
    return numba.get_num_threads()


def stencil(x: torch.Tensor, links: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`grid_stencil` on torch tensors: x (N, 3) float32 CPU box coordinates (NaN read as
    0, clamped to [0, 1]) -> rows (N, 8) int32, weights (N, 8) float32, coverage (N,) float32
    (no gradient)."""
    xc = torch.nan_to_num(x.detach().float(), nan=0.0).clamp(0.0, 1.0).contiguous()
    rows = torch.empty(xc.shape[0], 8, dtype=torch.int32)
    weights = torch.empty(xc.shape[0], 8, dtype=torch.float32)
    coverage = torch.empty(xc.shape[0], dtype=torch.float32)
    grid_stencil(xc.numpy(), links.contiguous().numpy(), rows.numpy(), weights.numpy(),
                 coverage.numpy())
    return rows, weights, coverage


class GatherFunction(torch.autograd.Function):
    """Interpolate ``table`` (V, C) with a stencil from :func:`stencil`: (N, C). Differentiable
    w.r.t. the table only (numba gather forward, numba scatter backward)."""

    @staticmethod
    def forward(ctx, table, rows, weights):
        out = torch.empty(rows.shape[0], table.shape[1], dtype=torch.float32)
        grid_gather(table.detach().contiguous().numpy(), rows.numpy(), weights.numpy(),
                    out.numpy())
        ctx.save_for_backward(rows, weights)
        ctx.table_shape = table.shape
        return out

    @staticmethod
    def backward(ctx, grad_out):
        rows, weights = ctx.saved_tensors
        grad = torch.zeros(ctx.table_shape, dtype=torch.float32)
        grid_scatter(grad_out.float().contiguous().numpy(), rows.numpy(), weights.numpy(),
                     grad.numpy(), _n_workers())
        return grad, None, None


def gather(table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(V, C) table, stencil (N, 8) from :func:`stencil` -> (N, C) through the numba kernels."""
    return GatherFunction.apply(table, rows, weights)


class SHColorFunction(torch.autograd.Function):
    """rgb = sigmoid(SH(d) . coeffs) per channel through the numba kernels; differentiable
    w.r.t. the coefficients only."""

    @staticmethod
    def forward(ctx, coeffs, d):
        d = d.detach().float().contiguous()
        rgb = torch.empty(coeffs.shape[0], 3, dtype=torch.float32)
        sh_color_forward(coeffs.detach().float().contiguous().numpy(), d.numpy(), rgb.numpy())
        ctx.save_for_backward(rgb, d)
        ctx.n_cols = coeffs.shape[1]
        return rgb

    @staticmethod
    def backward(ctx, grad_rgb):
        rgb, d = ctx.saved_tensors
        grad = torch.empty(rgb.shape[0], ctx.n_cols, dtype=torch.float32)
        sh_color_backward(rgb.numpy(), d.numpy(), grad_rgb.float().contiguous().numpy(),
                          grad.numpy())
        return grad, None


class TVFunction(torch.autograd.Function):
    """``mean_p |table[a_p] - table[b_p]|^2 / C`` (the mean squared difference per channel)
    through the numba kernels; its gradient is written straight into one dense (V, C) tensor
    (indexing the table in torch makes slow gathers and an index_put per index)."""

    @staticmethod
    def forward(ctx, table, pairs):
        partial = np.empty(_n_workers(), np.float64)
        pairs = pairs.contiguous()
        tv_forward(table.detach().contiguous().numpy(), pairs.numpy(), partial)
        ctx.save_for_backward(table, pairs)
        count = max(pairs.shape[1] * table.shape[1], 1)
        ctx.count = count
        return torch.tensor(partial.sum() / count, dtype=torch.float32)

    @staticmethod
    def backward(ctx, grad):
        table, pairs = ctx.saved_tensors
        out = torch.zeros(table.shape, dtype=torch.float32)
        tv_backward(table.detach().contiguous().numpy(), pairs.numpy(),
                    float(grad) / ctx.count, out.numpy(), _n_workers())
        return out, None


def tv_reference(table: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """Plain-torch twin of :class:`TVFunction`: mean over pairs and channels of the squared
    difference of rows ``pairs[0]`` and ``pairs[1]`` of ``table`` (V, C)."""
    return (table[pairs[0]] - table[pairs[1]]).square().mean()


def sh_color_reference(coeffs: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Plain-torch twin of :func:`sh_color_forward` (any device and dtype, differentiable)."""
    k = coeffs.shape[1] // 3
    degree = {1: 0, 4: 1, 9: 2}[k]
    basis = spherical_harmonics_reference(d, degree)
    return torch.sigmoid((coeffs.reshape(-1, 3, k) * basis[:, None, :]).sum(-1))


def warm_up() -> None:
    """Compile (or load from cache) the kernels, so compilation never counts as training."""
    links = np.arange(8, dtype=np.int32).reshape(2, 2, 2)
    x = np.full((2, 3), 0.5, np.float32)
    rows, weights = np.empty((2, 8), np.int32), np.empty((2, 8), np.float32)
    grid_stencil(x, links, rows, weights, np.empty(2, np.float32))
    table, out = np.zeros((8, 2), np.float32), np.empty((2, 2), np.float32)
    grid_gather(table, rows, weights, out)
    grid_scatter(out, rows, weights, table, 1)
    coeffs, rgb = np.zeros((2, 27), np.float32), np.empty((2, 3), np.float32)
    sh_color_forward(coeffs, x, rgb)
    sh_color_backward(rgb, x, rgb, coeffs)
    pairs = np.zeros((2, 1), np.int64)
    tv_forward(table, pairs, np.empty(1, np.float64))
    tv_backward(table, pairs, 1.0, table, 1)
