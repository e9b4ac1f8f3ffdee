"""Numba CPU kernel: exclusive cumulative sums restarted at every ray of a packed batch.

Each ray's sum runs over its own samples only, so its rounding error does not depend on the
rays packed before it (a single global cumsum minus per-ray offsets would).
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def segment_exclusive_cumsum(values, ray_indices, out):
    """out[i] = sum of values[j] for j < i on the same ray (samples sorted by ray).

    Args:
        values: (M,) float64; ray_indices: (M,) int64 sorted; out: (M,) float64.
    """
    acc = 0.0
    for i in range(values.shape[0]):
        if i == 0 or ray_indices[i] != ray_indices[i - 1]:
            acc = 0.0
        out[i] = acc
        acc += values[i]


@njit(cache=True, nogil=True)
def segment_reverse_exclusive_cumsum(values, ray_indices, out):
    """out[i] = sum of values[j] for j > i on the same ray: the adjoint of the forward scan."""
    acc = 0.0
    n = values.shape[0]
    for k in range(n):
        i = n - 1 - k
        if i == n - 1 or ray_indices[i] != ray_indices[i + 1]:
            acc = 0.0
        out[i] = acc
        acc += values[i]
