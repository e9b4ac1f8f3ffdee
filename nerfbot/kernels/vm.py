"""Numba CPU kernels of TensoRF's vector-matrix (VM) decomposition (Chen et al. 2022).

The plain-torch twin is :func:`nerfbot.fields.tensorf.vm_reference`; tests assert the two agree.
Both use the same grid arithmetic:

* a point ``x`` in [0, 1]^3 is looked up in three (plane, line) pairs ``m``: plane ``m`` spans
  axes ``(a, b) = VM_AXES[m][:2]`` and its line runs along the remaining axis
  ``c = VM_AXES[m][2]`` (XY plane with a Z line, XZ with Y, YZ with X);
* a plane is an array ``(n_b, n_a, C)`` of vertex features (``n`` vertices span [0, 1] along an
  axis, ``n - 1`` cells, the ends on the box faces: grid_sample's ``align_corners=True``), a
  line is ``(n_c, C)``;
* along an axis with ``n`` vertices the point lies in cell ``i = clamp(floor(u (n - 1)), 0,
  n - 2)`` with local coordinate ``w = u (n - 1) - i`` in [0, 1];
* the output is, per pair and channel, the bilinear plane value times the linear line value:
  ``out[n, m, c] = plane_m(x_a, x_b)[c] * line_m(x_c)[c]``, (N, 3, C). Density sums these over
  pairs and channels, appearance concatenates them.

The forward pass is parallel over points (channels are contiguous in memory, so a corner read
is one short vector). The backward pass is parallel over blocks of channels: every worker
walks all points but writes only its own channels of the gradient arrays, so the scatter-add
needs neither atomics nor private copies of the (large) grids, and each gradient entry is
summed in point order whatever the number of workers (deterministic).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

VM_AXES = ((0, 1, 2), (0, 2, 1), (1, 2, 0))
"""Per pair m: the plane's two axes (a, b) and the line's axis c."""


@njit(inline="always")
def _axis(u, n):
    """Cell index in [0, n - 2] and local weight of coordinate ``u`` on ``n`` >= 2 vertices."""
    p = u * np.float32(n - 1)
    i = max(min(int(p), n - 2), 0)
    return i, p - np.float32(i)


@njit(inline="always")
def _pair_forward(u, v, w, plane, line, out, n, m):
    iu, fu = _axis(u, plane.shape[1])
    iv, fv = _axis(v, plane.shape[0])
    iw, fw = _axis(w, line.shape[0])
    one = np.float32(1.0)
    w00, w10 = (one - fu) * (one - fv), fu * (one - fv)
    w01, w11 = (one - fu) * fv, fu * fv
    for c in range(out.shape[2]):
        pv = (w00 * plane[iv, iu, c] + w10 * plane[iv, iu + 1, c]
              + w01 * plane[iv + 1, iu, c] + w11 * plane[iv + 1, iu + 1, c])
        out[n, m, c] = pv * ((one - fw) * line[iw, c] + fw * line[iw + 1, c])


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def vm_forward(x, p0, p1, p2, l0, l1, l2, out):
    """Per-pair products of plane and line features.

    Args:
        x: (N, 3) float32 points in [0, 1]^3 (the caller clamps and replaces NaN).
        p0, p1, p2: planes (n_b, n_a, C) float32 of the pairs in :data:`VM_AXES` order.
        l0, l1, l2: lines (n_c, C) float32.
        out: (N, 3, C) float32, overwritten with ``plane_m * line_m`` per pair m and channel.
    """
    for n in prange(x.shape[0]):
        _pair_forward(x[n, 0], x[n, 1], x[n, 2], p0, l0, out, n, 0)
        _pair_forward(x[n, 0], x[n, 2], x[n, 1], p1, l1, out, n, 1)
        _pair_forward(x[n, 1], x[n, 2], x[n, 0], p2, l2, out, n, 2)


@njit(inline="always")
def _pair_backward(u, v, w, plane, line, grad_out, gp, gl, n, m, c0, c1):
    iu, fu = _axis(u, plane.shape[1])
    iv, fv = _axis(v, plane.shape[0])
    iw, fw = _axis(w, line.shape[0])
    one = np.float32(1.0)
    w00, w10 = (one - fu) * (one - fv), fu * (one - fv)
    w01, w11 = (one - fu) * fv, fu * fv
    for c in range(c0, c1):
        g = grad_out[n, m, c]
        pv = (w00 * plane[iv, iu, c] + w10 * plane[iv, iu + 1, c]
              + w01 * plane[iv + 1, iu, c] + w11 * plane[iv + 1, iu + 1, c])
        lv = (one - fw) * line[iw, c] + fw * line[iw + 1, c]
        g_plane = g * lv
        gp[iv, iu, c] += w00 * g_plane
        gp[iv, iu + 1, c] += w10 * g_plane
        gp[iv + 1, iu, c] += w01 * g_plane
        gp[iv + 1, iu + 1, c] += w11 * g_plane
        g_line = g * pv
        gl[iw, c] += (one - fw) * g_line
        gl[iw + 1, c] += fw * g_line


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def vm_backward(x, p0, p1, p2, l0, l1, l2, grad_out, gp0, gp1, gp2, gl0, gl1, gl2, n_blocks):
    """Accumulate d(loss)/d(planes) and d(loss)/d(lines).

    Args:
        x, p0, p1, p2, l0, l1, l2: as given to :func:`vm_forward`.
        grad_out: (N, 3, C) float32 gradient of the loss w.r.t. the forward output.
        gp0, gp1, gp2, gl0, gl1, gl2: gradients shaped like the planes and lines, zero on entry.
        n_blocks: channel blocks processed in parallel (1 <= n_blocks <= C); block ``k`` owns
            channels ``[k C // n_blocks, (k + 1) C // n_blocks)``.
    """
    n_ch = grad_out.shape[2]
    for blk in prange(n_blocks):
        c0 = blk * n_ch // n_blocks
        c1 = (blk + 1) * n_ch // n_blocks
        for n in range(x.shape[0]):
            _pair_backward(x[n, 0], x[n, 1], x[n, 2], p0, l0, grad_out, gp0, gl0, n, 0, c0, c1)
            _pair_backward(x[n, 0], x[n, 2], x[n, 1], p1, l1, grad_out, gp1, gl1, n, 1, c0, c1)
            _pair_backward(x[n, 1], x[n, 2], x[n, 0], p2, l2, grad_out, gp2, gl2, n, 2, c0, c1)


def warm_up() -> None:
    """Compile (or load from numba's cache) both kernels on a toy grid."""
    x = np.full((2, 3), 0.5, np.float32)
    planes = [np.zeros((2, 2, 1), np.float32) for _ in range(3)]
    lines = [np.zeros((2, 1), np.float32) for _ in range(3)]
    out = np.empty((2, 3, 1), np.float32)
    vm_forward(x, *planes, *lines, out)
    vm_backward(x, *planes, *lines, out, *[np.zeros_like(p) for p in planes],
                *[np.zeros_like(li) for li in lines], 1)
