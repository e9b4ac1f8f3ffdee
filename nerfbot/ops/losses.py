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


#: Opacities are clamped to [eps, 1 - eps] inside :func:`opacity_entropy_loss`: the entropy's
#: slope, log((1 - a) / a), stays within +-9.2 at saturated or empty rays.
OPACITY_EPS = 1e-4


def opacity_entropy_loss(opacity: torch.Tensor) -> torch.Tensor:
    """Mean binary entropy of the rays' opacities, -a log a - (1 - a) log(1 - a), in nats.

    About zero for rays that are empty (a = 0: the background shows) or opaque (a = 1;
    1e-3 nats at the clamp :data:`OPACITY_EPS`), log 2 at a = 1/2. Minimising it pushes each
    ray toward one or the other: a ray that stops on a surface inside the bounds should not
    let the learned background through, which otherwise paints dark texture (a checker's dark
    squares, grout lines) by mixing the background into a half-transparent surface.

    Args:
        opacity: (R,) accumulated weights in [0, 1].
    Returns:
        scalar in the dtype of ``opacity``, at least float32 (0 for no rays).
    """
    if opacity.numel() == 0:
        return opacity.sum()
    a = opacity.to(work_dtype(opacity)).clamp(OPACITY_EPS, 1.0 - OPACITY_EPS)
    return -(a * torch.log(a) + (1.0 - a) * torch.log1p(-a)).mean()


#: Floor of a sample's weight inside the logarithm of :func:`keypoint_depth_loss`: a ray whose
#: weights are all zero (empty space so far) still has a finite loss and gradient.
KEYPOINT_WEIGHT_FLOOR = 1e-5


def keypoint_depth_loss(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                        ray_indices: torch.Tensor, target_t: torch.Tensor,
                        sigma_t: torch.Tensor, robust: float = 0.0) -> torch.Tensor:
    """DS-NeRF's depth loss: the ray-termination distribution pushed toward a narrow Gaussian at
    each keypoint's distance, mean over the rays with a finite target.

    For a ray with weights w_k on intervals of length d_k and midpoints t_k, keypoint distance D
    and width sigma (Deng et al. 2022, eq. 7):

        L = - sum_k log(w_k + floor) exp(-(t_k - D)^2 / (2 sigma^2)) d_k

    Minimising it raises the weight where the Gaussian sits (the cross-entropy of the target
    distribution against the rendered one, up to a constant); a ray without samples contributes
    0, zero weights give log(floor) (:data:`KEYPOINT_WEIGHT_FLOOR`), never NaN.

    Args:
        weights: (M,) rendering weights; t_starts, t_ends: (M,) metres; ray_indices: (M,)
            sorted, in [0, R).
        target_t: (R,) keypoint distance along each ray, metres (NaN: no keypoint).
        sigma_t: (R,) Gaussian widths, metres (> 0 where target_t is finite).
        robust: c > 0 weighs each ray's loss by ``1 / (1 + (r / (c sigma))^2)`` (no gradient
            through the weight), r the distance from the ray's expected distance under its
            (normalised) weights to the keypoint's; a ray without weight keeps 1. 0: all 1.
    Returns:
        scalar, float32 at least (0 when no ray has a keypoint, still connected to ``weights``).
    """
    valid = torch.isfinite(target_t) & (sigma_t > 0)
    work = torch.promote_types(weights.dtype, torch.float32)
    if not bool(valid.any()) or weights.numel() == 0:
        return weights.to(work).sum() * 0.0
    w = weights.to(work)
    mid = 0.5 * (t_starts + t_ends).to(work)
    width = (t_ends - t_starts).to(work).clamp_min(0.0)
    target = torch.where(valid, target_t, torch.zeros_like(target_t)).to(work)[ray_indices]
    sigma = torch.where(valid, sigma_t, torch.ones_like(sigma_t)).to(work)[ray_indices]
    gauss = torch.exp(-0.5 * ((mid - target) / sigma) ** 2)
    per_sample = -torch.log(w + KEYPOINT_WEIGHT_FLOOR) * gauss * width
    per_sample = torch.where(valid[ray_indices], per_sample, torch.zeros_like(per_sample))
    per_ray = torch.zeros(len(target_t), dtype=work, device=w.device).index_add(
        0, ray_indices, per_sample)
    if robust > 0:
        with torch.no_grad():
            zeros = torch.zeros(len(target_t), dtype=work, device=w.device)
            mass = zeros.index_add(0, ray_indices, w)
            expected = zeros.index_add(0, ray_indices, w * mid) / mass.clamp_min(1e-12)
            tgt = torch.where(valid, target_t, torch.zeros_like(target_t)).to(work)
            sig = torch.where(valid, sigma_t, torch.ones_like(sigma_t)).to(work)
            scaled = torch.where(mass > 1e-6, (expected - tgt) / (robust * sig),
                                 torch.zeros_like(mass))
        per_ray = per_ray / (1.0 + scaled ** 2)
    return per_ray[valid].mean()
