"""What the fused renderers (FastNeRF cache, PlenOctree, KiloNeRF) share once a ray's samples
are composited: the float32 logistic of their colour heads, and finishing a pixel."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(inline="always")
def sigmoid32(v):
    """float32 logistic function (exp(-v) overflowing to inf gives 0, as it should)."""
    one = np.float32(1.0)
    return one / (one + np.exp(-np.float32(v)))


@njit(inline="always")
def finish_pixel(rgb, r, c0, c1, c2, w_all, w_read, rest, background):
    """rgb[r] = the ray's colour over its background.

    (c0, c1, c2) = sum of w_i rgb_i over the samples whose colour was read (of total weight
    ``w_read``); the ray's other samples, too faint to be worth a lookup, take the
    weight-averaged colour of these: the sum is scaled to the ray's whole weight ``w_all``.
    ``rest`` is the transmittance left for the background (R, 3)."""
    if w_read > 0.0:
        scale = w_all / w_read
        c0 *= scale
        c1 *= scale
        c2 *= scale
    rgb[r, 0] = c0 + rest * background[r, 0]
    rgb[r, 1] = c1 + rest * background[r, 1]
    rgb[r, 2] = c2 + rest * background[r, 2]
