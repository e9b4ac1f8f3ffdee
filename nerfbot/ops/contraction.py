"""Scene contraction for unbounded and inside-out scenes (mip-NeRF 360's, in the L-inf norm).

Points are measured in half-sizes of an inner cube around its centre, ``y = (x - centre) /
half``. Inside the inner cube (``|y|_inf <= 1``) the map is the identity; outside it,
``y -> (2 - 1 / |y|_inf) * y / |y|_inf``, so all of space lands in the open cube ``|c|_inf < 2``
and content at distance ``n`` half-sizes is resolved ``n^2`` times more coarsely than inside.
The L-inf norm (mip-NeRF 360 uses L2) maps cubes to cubes, so an axis-aligned grid covers the
contracted space exactly. The numba marcher applies the same map
(:mod:`nerfbot.kernels.marching`).
"""

from __future__ import annotations

import torch

#: The contracted cube is [-CONTRACTED_HALF, CONTRACTED_HALF]^3 in units of the inner half-size.
CONTRACTED_HALF = 2.0


def contract(y: torch.Tensor) -> torch.Tensor:
    """(..., 3) finite points in inner half-sizes -> (..., 3) contracted points,
    ``|c|_inf < 2``; continuous, differentiable outside the inner cube's surface, the identity
    for ``|y|_inf <= 1``."""
    n = y.abs().amax(-1, keepdim=True)
    outside = n > 1.0
    safe = torch.where(outside, n, torch.ones_like(n))
    scale = torch.where(outside, (2.0 - 1.0 / safe) / safe, torch.ones_like(n))
    return y * scale


def uncontract(c: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`contract` for ``|c|_inf < 2``: (..., 3) -> (..., 3) inner half-sizes."""
    n = c.abs().amax(-1, keepdim=True)
    outside = n > 1.0
    safe = torch.where(outside, n, torch.ones_like(n)).clamp_max(2.0 - 1e-6)
    scale = torch.where(outside, 1.0 / (safe * (2.0 - safe)), torch.ones_like(n))
    return c * scale


def step_scale(y: torch.Tensor) -> torch.Tensor:
    """(...,) factor ``max(1, |y|_inf^2)`` by which a marching step at ``y`` (inner half-sizes)
    grows: ``d|c| / d|y| = 1 / |y|^2`` outside the inner cube, so the grown step has about the
    same length in contracted space as the base step inside."""
    return y.abs().amax(-1).square().clamp_min(1.0)


def disparity_distance(t: torch.Tensor, scale: float) -> torch.Tensor:
    """Distances along rays, metres -> a bounded, monotone measure: ``t`` up to ``scale``, then
    ``2 scale - scale^2 / t`` (mip-NeRF 360's disparity spacing), below ``2 scale``.

    Losses that compare distances along a ray (the distortion loss) use it so that samples far
    in the contracted region do not dominate them.
    """
    far = t > scale
    safe = torch.where(far, t, torch.full_like(t, scale))
    return torch.where(far, 2.0 * scale - scale * scale / safe, t)
