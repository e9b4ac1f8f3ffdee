"""Volume-rendering arithmetic over packed ray samples.

Samples of R rays are stored *packed*: flat arrays of M samples sorted by ray, with
``ray_indices`` (M,) naming each sample's ray (nerfacc's layout). A dense (R, S) batch is the
special case ``ray_indices = arange(R).repeat_interleave(S)``.

For a ray with samples i = 0..n-1, densities sigma_i >= 0 (1/m) and intervals
[t_i, t_i + delta_i] (m):

    tau_i = sigma_i * delta_i                  optical thickness of sample i
    T_i   = exp(-sum_{j<i} tau_j)              transmittance before it (exclusive cumsum)
    alpha_i = 1 - exp(-tau_i)
    w_i   = T_i * alpha_i                      its weight; sum_i w_i = 1 - exp(-sum_i tau_i) <= 1

The cumulative sum runs in float64 per ray whatever the input precision, and the weights never
come from a product of (1 - alpha) terms, so long rays and alpha = 1 stay accurate and
differentiable.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from nerfbot.kernels import use_kernels
from nerfbot.kernels import scan as _scan

#: Opacity below which a ray counts as empty: its depth is the far bound, not 0 / 0.
EMPTY_OPACITY = 1e-6

#: Half-precision types: rendering arithmetic on them runs in float32 (see :func:`work_dtype`).
HALF_DTYPES = (torch.float16, torch.bfloat16)

#: Largest optical thickness of one sample. exp(-1e4) is 0 in every float type, so clamping there
#: changes no result, and it keeps the packed float64 cumsum finite (inf - inf would be NaN).
MAX_THICKNESS = 1e4


def work_dtype(*tensors: torch.Tensor) -> torch.dtype:
    """The dtype rendering arithmetic runs in for these inputs: their promoted type, at least
    float32. Half-precision sums and products are not accurate enough here: a bfloat16 running
    sum stalls once its spacing exceeds the addends (0.5 + 0.001 == 0.5), float16 overflows at
    65504 (sigma * delta, t_start + t_end), and both round thickness to 3 digits or fewer."""
    dtype = torch.float32
    for t in tensors:
        dtype = torch.promote_types(dtype, t.dtype)
    return dtype


def ray_starts(ray_indices: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """First packed index and sample count of every ray: (R,) int64 each (empty rays: count 0)."""
    counts = torch.bincount(ray_indices, minlength=n_rays) if ray_indices.numel() else \
        torch.zeros(n_rays, dtype=torch.long, device=ray_indices.device)
    starts = torch.cumsum(counts, 0) - counts
    return starts, counts


class _SegmentScan(torch.autograd.Function):
    """Per-ray exclusive cumsum in float64 (numba); its gradient is the reverse scan."""

    @staticmethod
    def forward(ctx, values, ray_indices):
        idx = ray_indices.contiguous()
        out = torch.empty_like(values)
        _scan.segment_exclusive_cumsum(values.detach().contiguous().numpy(), idx.numpy(),
                                       out.numpy())
        ctx.save_for_backward(idx)
        return out

    @staticmethod
    def backward(ctx, grad):
        (idx,) = ctx.saved_tensors
        out = torch.empty_like(grad)
        _scan.segment_reverse_exclusive_cumsum(grad.contiguous().numpy(), idx.numpy(), out.numpy())
        return out, None


def segment_exclusive_cumsum(values: torch.Tensor, ray_indices: torch.Tensor,
                             starts: torch.Tensor) -> torch.Tensor:
    """Exclusive cumulative sum of ``values`` (M,) restarted at each ray, in float64.

    On CPU a sequential per-ray scan (numba), so each ray's precision is independent of the
    others; on other devices a global float64 cumsum minus each ray's offset (``starts``: (R,)
    first packed index of every ray), whose error grows with the thickness packed before a ray.
    """
    v = values.double()
    if not v.numel():
        return v
    if use_kernels(v, dtype=None):
        return _SegmentScan.apply(v, ray_indices)
    return segment_exclusive_cumsum_reference(v, ray_indices, starts)


def segment_exclusive_cumsum_reference(values: torch.Tensor, ray_indices: torch.Tensor,
                                       starts: torch.Tensor) -> torch.Tensor:
    """Plain-torch twin of the per-ray scan (:mod:`nerfbot.kernels.scan`; any device,
    differentiable): a global float64 cumsum of ``values`` (M,) minus each ray's offset
    (``starts``: (R,) first packed index of every ray); (M,) float64."""
    v = values.double()
    exclusive = torch.cumsum(v, 0) - v
    return exclusive - exclusive[starts[ray_indices]]


def render_weights(sigmas: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                   ray_indices: torch.Tensor, n_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights and transmittance of packed samples.

    Args:
        sigmas: (M,) densities >= 0, 1/m (any float dtype; +inf allowed).
        t_starts, t_ends: (M,) sample interval bounds along the ray, metres.
        ray_indices: (M,) int64, sorted.
        n_rays: R.
    Returns:
        weights (M,) and transmittance before each sample (M,), in the dtype of ``sigmas``
        (half-precision inputs are computed in float32, see :func:`work_dtype`).
    """
    starts, _ = ray_starts(ray_indices, n_rays)
    work = work_dtype(sigmas, t_starts, t_ends)
    sig = sigmas.to(work)
    deltas = (t_ends.to(work) - t_starts.to(work)).clamp_min(0.0)
    # inf * 0 would be NaN: an infinitely dense but zero-length sample has zero thickness
    tau = torch.where(deltas > 0, sig * deltas, torch.zeros_like(sig)).clamp_max(MAX_THICKNESS)
    tau_before = segment_exclusive_cumsum(tau, ray_indices, starts)
    trans = torch.exp(-tau_before)
    alpha = -torch.expm1(-tau.double())
    return (trans * alpha).to(sigmas.dtype), trans.to(sigmas.dtype)


def accumulate(weights: torch.Tensor, values: Optional[torch.Tensor], ray_indices: torch.Tensor,
               n_rays: int) -> torch.Tensor:
    """Per-ray sums of ``weights * values``: (R,) for values None or (M,), (R, C) for (M, C).

    The sums run in float32 at least (in bfloat16 the opacity of 1000 samples of thickness 1e-3
    came out 0.69 instead of 0.63); the result has the promoted dtype of the inputs.
    """
    inputs = (weights,) if values is None else (weights, values)
    out_dtype = torch.promote_types(inputs[0].dtype, inputs[-1].dtype)
    work = work_dtype(*inputs)
    w = weights.to(work)
    if values is None:
        src = w
    elif values.dim() == 1:
        src = w * values.to(work)
    else:
        src = w[:, None] * values.to(work)
    out = torch.zeros((n_rays,) + tuple(src.shape[1:]), dtype=work, device=src.device)
    return out.index_add(0, ray_indices, src).to(out_dtype)


def median_depth(weights: torch.Tensor, t_mid: torch.Tensor, ray_indices: torch.Tensor,
                 n_rays: int, opacity: torch.Tensor, far: torch.Tensor) -> torch.Tensor:
    """Distance at which a ray's accumulated weight first reaches half its opacity: (R,).

    Rays whose opacity is below :data:`EMPTY_OPACITY` get ``far``.
    """
    starts, _ = ray_starts(ray_indices, n_rays)
    cum = segment_exclusive_cumsum(weights, ray_indices, starts) + weights.double()
    crossed = cum >= 0.5 * opacity.double()[ray_indices]
    big = torch.full((n_rays,), float("inf"), dtype=t_mid.dtype, device=t_mid.device)
    cand = torch.where(crossed, t_mid.detach(), torch.full_like(t_mid, float("inf")))
    med = big.scatter_reduce(0, ray_indices, cand, reduce="amin", include_self=True)
    return torch.where((opacity > EMPTY_OPACITY) & torch.isfinite(med), med, far)


def depth_spread(weights: torch.Tensor, t_mid: torch.Tensor, ray_indices: torch.Tensor,
                 n_rays: int, opacity: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """How thick the surface a ray meets is: the standard deviation of its termination
    distance, sqrt(sum_i w_i (t_i - depth)^2 / opacity), (R,) metres, with ``depth`` (R,) the
    expected distance (a sharp surface gives about a marching step, fog tens of them). Summed
    about ``depth`` rather than as E[t^2] - E[t]^2, which loses centimetres to rounding at
    metres of distance in float32. Rays whose opacity is below :data:`EMPTY_OPACITY` get 0."""
    var = torch.zeros(n_rays, dtype=torch.float64, device=weights.device)
    if ray_indices.numel():
        d = (t_mid.detach() - depth.detach()[ray_indices]).double()
        var.index_add_(0, ray_indices, weights.detach().double() * d * d)
    full = opacity.detach() > EMPTY_OPACITY
    var = torch.where(full, var / opacity.detach().double().clamp_min(EMPTY_OPACITY), 0.0)
    return var.clamp_min(0.0).sqrt().to(t_mid.dtype)


@dataclass
class RenderOutput:
    """What rendering R rays returns.

    Attributes:
        rgb: (R, 3) colour composited over the background.
        opacity: (R,) accumulated weight sum_i w_i in [0, 1].
        depth: (R,) expected ray distance sum_i w_i t_i / opacity, metres; ``far`` for empty rays.
        z_depth: (R,) the same as z-depth (along the optical axis), metres.
        median_depth: (R,) median ray distance (see :func:`median_depth`), metres.
        weights: (M,) per-sample weights (packed), for losses and depth queries.
        num_samples: M.
        ray_indices, t_starts, t_ends, sigmas: (M,) the packed samples themselves (sorted by
            ray), for losses and threshold-depth queries.
        positions, features: (M, 3) the samples' world points (metres) and (M, C) geometry
            features, kept by renderers of models with a label head
            (:mod:`nerfbot.models.labels`), else None.
    """

    rgb: torch.Tensor
    opacity: torch.Tensor
    depth: torch.Tensor
    z_depth: torch.Tensor
    median_depth: torch.Tensor
    weights: torch.Tensor
    num_samples: int
    ray_indices: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    sigmas: torch.Tensor
    positions: Optional[torch.Tensor] = None
    features: Optional[torch.Tensor] = None


def composite(sigmas: torch.Tensor, rgbs: torch.Tensor, t_starts: torch.Tensor,
              t_ends: torch.Tensor, ray_indices: torch.Tensor, n_rays: int,
              background: torch.Tensor, far: torch.Tensor, z_per_t: torch.Tensor,
              with_median: bool = True) -> RenderOutput:
    """Volume-render packed samples.

    Args:
        sigmas: (M,) densities; rgbs: (M, 3) colours in [0, 1].
        t_starts, t_ends: (M,) metres; ray_indices: (M,) sorted int64.
        background: (R, 3) or (3,) colour behind each ray.
        far: (R,) the depth reported for empty rays (finite), metres.
        z_per_t: (R,) cosine between ray and optical axis (z-depth = t * z_per_t).

    Half-precision inputs are upcast to float32 for the arithmetic (:func:`work_dtype`; e.g.
    float16 ``t_start + t_end`` overflows beyond 32752 m) and the outputs cast back to the
    promoted dtype of ``sigmas, rgbs, t_starts, t_ends``: they carry its output rounding only.
    """
    inputs = (sigmas, rgbs, t_starts, t_ends)
    if any(t.dtype in HALF_DTYPES for t in inputs):
        work = work_dtype(*inputs)
        out = composite(*(t.to(work) for t in inputs), ray_indices, n_rays, background.to(work),
                        far.to(work), z_per_t.to(work), with_median)
        dtype = torch.promote_types(torch.promote_types(sigmas.dtype, rgbs.dtype),
                                    torch.promote_types(t_starts.dtype, t_ends.dtype))
        return RenderOutput(rgb=out.rgb.to(dtype), opacity=out.opacity.to(dtype),
                            depth=out.depth.to(dtype), z_depth=out.z_depth.to(dtype),
                            median_depth=out.median_depth.to(dtype), weights=out.weights.to(dtype),
                            num_samples=out.num_samples, ray_indices=ray_indices,
                            t_starts=t_starts, t_ends=t_ends, sigmas=sigmas)
    weights, _ = render_weights(sigmas, t_starts, t_ends, ray_indices, n_rays)
    t_mid = 0.5 * (t_starts + t_ends)
    opacity = accumulate(weights, None, ray_indices, n_rays)
    rgb = accumulate(weights, rgbs, ray_indices, n_rays)
    rgb = rgb + (1.0 - opacity)[:, None] * background
    depth_sum = accumulate(weights, t_mid, ray_indices, n_rays)
    empty = opacity <= EMPTY_OPACITY
    depth = torch.where(empty, far.to(depth_sum.dtype),
                        depth_sum / opacity.clamp_min(EMPTY_OPACITY))
    med = median_depth(weights.detach(), t_mid, ray_indices, n_rays, opacity.detach(), far) \
        if with_median else depth.detach()
    return RenderOutput(rgb=rgb, opacity=opacity, depth=depth, z_depth=depth * z_per_t,
                        median_depth=med, weights=weights, num_samples=int(sigmas.shape[0]),
                        ray_indices=ray_indices, t_starts=t_starts, t_ends=t_ends, sigmas=sigmas)


def threshold_depth(sigmas: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_indices: torch.Tensor, n_rays: int, threshold: float
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Dex-NeRF depth: where a ray's density first reaches ``threshold`` (1/m).

    Densities are taken at sample midpoints and interpolated linearly between the last sample
    below the threshold and the first at or above it. A ray whose first sample already crosses
    gets that sample's start. Rays that never cross are *invalid* (not the near plane, the
    pitfall of ``argmax(sigma > m)``).

    Args:
        sigmas, t_starts, t_ends, ray_indices: (M,) packed samples sorted by ray and distance.
        n_rays: R. threshold: density m, 1/m.
    Returns:
        depth (R,) ray distance in metres (NaN where invalid) and valid (R,) bool.
    """
    idx = torch.arange(sigmas.shape[0], device=sigmas.device)
    crossed = sigmas >= threshold
    big = torch.full((n_rays,), sigmas.shape[0], dtype=torch.long, device=sigmas.device)
    first = big.scatter_reduce(0, ray_indices[crossed], idx[crossed], reduce="amin",
                               include_self=True)
    valid = first < sigmas.shape[0]
    depth = torch.full((n_rays,), float("nan"), dtype=t_starts.dtype, device=t_starts.device)
    if not bool(valid.any()):
        return depth, valid
    rays = torch.nonzero(valid).squeeze(-1)
    i = first[rays]
    starts, _ = ray_starts(ray_indices, n_rays)
    has_prev = i > starts[rays]
    prev = torch.where(has_prev, i - 1, i)
    t_mid = 0.5 * (t_starts.double() + t_ends.double())  # float16 t_start + t_end overflows
    s0, s1 = sigmas[prev].double(), sigmas[i].double()
    frac = ((threshold - s0) / (s1 - s0).clamp_min(1e-30)).clamp(0.0, 1.0)
    interp = t_mid[prev] + frac * (t_mid[i] - t_mid[prev])
    depth[rays] = torch.where(has_prev, interp, t_starts[i].double()).to(depth.dtype)
    return depth, valid
