"""Numba CPU kernel of the real spherical-harmonic basis (degree 0..4) of unit directions.

Same constants and order as :func:`nerfbot.encodings.spherical_harmonics`, its plain-torch twin
(tests assert they agree). Renderers inline :func:`sh_basis`; :func:`sh_encode` fills a whole
(N, K) table, the encoding's fast path for inputs that need no gradient.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(inline="always")
def sh_basis(x, y, z, degree, out):
    """Real SH basis up to ``degree`` (0..4) of a unit direction into ``out`` (same constants
    and order as :func:`nerfbot.encodings.spherical_harmonics`)."""
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
