"""Packing the per-sample scratch of the fused renderers (FastNeRF cache, KiloNeRF) into the
sorted packed arrays of :class:`nerfbot.ops.rendering.RenderOutput`, with the median depth."""

from __future__ import annotations

from numba import njit, prange


@njit(parallel=True, cache=True)
def pack(counts, src_start, starts, opacity, far, s_ts, s_te, s_sigma, s_w,
         ray_indices, t_starts, t_ends, sigmas, weights, median):
    """Copy each ray's samples from its scratch slot (``src_start``) to the packed arrays at
    ``starts``, and compute the median depth: the midpoint of the first sample where the
    accumulated weight reaches half the opacity (``far`` for rays with opacity <= 1e-6)."""
    for r in prange(counts.shape[0]):
        half = 0.5 * opacity[r]
        cum = 0.0
        med = far[r]
        found = opacity[r] <= 1e-6
        for j in range(counts[r]):
            a = src_start[r] + j
            b = starts[r] + j
            ray_indices[b] = r
            t_starts[b] = s_ts[a]
            t_ends[b] = s_te[a]
            sigmas[b] = s_sigma[a]
            weights[b] = s_w[a]
            cum += s_w[a]
            if not found and cum >= half:
                med = 0.5 * (s_ts[a] + s_te[a])
                found = True
        median[r] = med
