"""Training losses over packed ray samples."""

from __future__ import annotations

import torch

from nerfbot.ops.rendering import ray_starts, segment_exclusive_cumsum, work_dtype


def distortion_loss(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_indices: torch.Tensor, n_rays: int, scale: float) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss, mean over rays, in O(M) over packed samples.

    For one ray with weights w_i on intervals [s_i, s_i + d_i] (distances divided by ``scale``
    so the loss does not depend on the scene's units) and midpoints m_i:

        L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i
          = sum_i 2 w_i (m_i W_i - M_i) + 1/3 sum_i w_i^2 d_i

    with W_i = sum_{j<i} w_j and M_i = sum_{j<i} w_j m_j (samples sorted by distance). It is
    small when a ray's weight sits in one short interval (a surface) or is zero (background),
    and large for fog spread along the ray.

    Args:
        weights: (M,) rendering weights; t_starts, t_ends: (M,) metres; ray_indices: (M,) sorted.
        scale: metres per unit of normalised distance (e.g. the scene cube's diagonal).
    Returns:
        scalar tensor (0 for an empty batch) in the dtype of ``weights``, at least float32
        (a float16 loss overflows at 65504).
    """
    if weights.numel() == 0:
        return weights.sum()
    # float64 throughout, like the scans: m_i W_i - M_i cancels when samples sit far out
    # (t / scale >> their spread): float32 inputs at t = 1e4 m with scale 0.01 were off by 6e-5
    # relative, float16 ones gave NaN (t / scale overflows at 65504).
    w = weights.double()
    s0, s1 = t_starts.double() / scale, t_ends.double() / scale
    mid, width = 0.5 * (s0 + s1), s1 - s0
    starts, _ = ray_starts(ray_indices, n_rays)
    w_before = segment_exclusive_cumsum(w, ray_indices, starts)
    wm_before = segment_exclusive_cumsum(w * mid, ray_indices, starts)
    bi = 2.0 * w * (mid * w_before - wm_before)
    uni = w ** 2 * width / 3.0
    return ((bi + uni).sum() / max(n_rays, 1)).to(work_dtype(weights))
