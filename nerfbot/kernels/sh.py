"""Numba CPU kernel of the real spherical-harmonic basis (degree 0..4) of unit directions.

Its plain-torch twin is :func:`spherical_harmonics_reference` (same constants and order; tests
assert they agree); :func:`nerfbot.ops.encodings.spherical_harmonics` dispatches between them.
Renderers inline :func:`sh_basis`; :func:`sh_encode` fills a whole (N, K) table, the encoding's
fast path for inputs that need no gradient.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange


@njit(inline="always")
def sh_basis(x, y, z, degree, out):
    """Real SH basis up to ``degree`` (0..4) of a unit direction into ``out`` (same constants
    and order as :func:`spherical_harmonics_reference`)."""
    out[0] = 0.28209479177387814
    if degree >= 1:
        out[1] = -0.4886025119029199 * y
        out[2] = 0.4886025119029199 * z
        out[3] = -0.4886025119029199 * x
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out[4] = 1.0925484305920792 * xy
        out[5] = -1.0925484305920792 * yz
        out[6] = 0.31539156525252005 * (2 * zz - xx - yy)
        out[7] = -1.0925484305920792 * xz
        out[8] = 0.5462742152960396 * (xx - yy)
        if degree >= 3:
            out[9] = -0.5900435899266435 * y * (3 * xx - yy)
            out[10] = 2.890611442640554 * xy * z
            out[11] = -0.4570457994644658 * y * (4 * zz - xx - yy)
            out[12] = 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy)
            out[13] = -0.4570457994644658 * x * (4 * zz - xx - yy)
            out[14] = 1.445305721320277 * z * (xx - yy)
            out[15] = -0.5900435899266435 * x * (xx - 3 * yy)
        if degree >= 4:
            out[16] = 2.5033429417967046 * xy * (xx - yy)
            out[17] = -1.7701307697799304 * yz * (3 * xx - yy)
            out[18] = 0.9461746957575601 * xy * (7 * zz - 1)
            out[19] = -0.6690465435572892 * yz * (7 * zz - 3)
            out[20] = 0.10578554691520431 * (zz * (35 * zz - 30) + 3)
            out[21] = -0.6690465435572892 * xz * (7 * zz - 3)
            out[22] = 0.47308734787878004 * (xx - yy) * (7 * zz - 1)
            out[23] = -1.7701307697799304 * xz * (xx - 3 * yy)
            out[24] = 0.6258357354491761 * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))


@njit(parallel=True, fastmath=False, cache=True, nogil=True)
def sh_encode(d, degree, out):
    """SH basis of unit directions ``d`` (N, 3) float32 up to ``degree`` into ``out`` (N, K)
    float32, K = (degree + 1)^2, evaluated in float64 and rounded once."""
    for i in prange(d.shape[0]):
        b = np.empty(25, np.float64)
        sh_basis(np.float64(d[i, 0]), np.float64(d[i, 1]), np.float64(d[i, 2]), degree, b)
        for k in range(out.shape[1]):
            out[i, k] = b[k]


# Real spherical-harmonic constants (the orthonormal real basis, signs as in PlenOctrees/svox2).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
_C4 = (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892,
       0.10578554691520431, -0.6690465435572892, 0.47308734787878004, -1.7701307697799304,
       0.6258357354491761)


def check_sh_degree(degree: int) -> None:
    if not 0 <= degree <= 4:
        raise ValueError(f"spherical harmonics degree must be 0..4, got {degree}")


def spherical_harmonics_reference(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Plain-torch twin of :func:`nerfbot.kernels.sh.sh_encode` (any device, dtype and batch
    shape, differentiable): unit directions ``d`` (..., 3) -> (..., (degree+1)^2)."""
    check_sh_degree(degree)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz,
                _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    if degree >= 4:
        out += [_C4[0] * xy * (xx - yy), _C4[1] * yz * (3 * xx - yy), _C4[2] * xy * (7 * zz - 1),
                _C4[3] * yz * (7 * zz - 3), _C4[4] * (zz * (35 * zz - 30) + 3),
                _C4[5] * xz * (7 * zz - 3), _C4[6] * (xx - yy) * (7 * zz - 1),
                _C4[7] * xz * (xx - 3 * yy), _C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))]
    return torch.stack(out, dim=-1)
