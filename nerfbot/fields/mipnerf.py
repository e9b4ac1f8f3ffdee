"""mip-NeRF's field (Barron et al. 2021): cones instead of rays, integrated positional encoding.

Each interval [t0, t1] of a ray is the conical frustum cut from the cone through the ray's
pixel (radius ``t * radii`` at distance t, see :class:`~nerfbot.ops.cameras.Rays`). The frustum is
replaced by a Gaussian of the same mean and (diagonal) covariance, and the field sees the
*expected* positional encoding of a point drawn from it (the IPE): every sin / cos feature of
frequency a is damped by ``exp(-a^2 var / 2)``, so features finer than the footprint fade out
and an image rendered at a lower resolution (larger pixels, wider cones) is anti-aliased. The
renderer is :class:`nerfbot.models.mipnerf.MipNeRFModel`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.fields.base import BoxNormalizer, Field
from nerfbot.ops.encodings import FrequencyEncoding


#: Samples per field query when rendering without gradients (bounds the activation memory of
#: a 256-wide MLP to ~0.3 GB per layer whatever the number of rays).
EVAL_QUERY_CHUNK = 1 << 18


def conical_frustum_gaussian(t0: torch.Tensor, t1: torch.Tensor, radii: torch.Tensor
                             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Moments of the conical frustum between distances t0 <= t1 of a cone of radius
    ``radii * t`` at distance t (a point uniform in its volume).

    Args:
        t0, t1: (...) interval bounds along the unit axis, metres, t0 >= 0.
        radii: (...) (broadcastable) cone radius per metre of distance.
    Returns:
        t_mean (...): mean distance along the axis (m); t_var (...): its variance (m^2);
        r_var (...): variance of the offset perpendicular to the axis, per perpendicular
        direction (m^2).

    Written in the interval's centre ``mu`` and half-width ``hw`` (mip-NeRF's stable form), so
    short intervals far away lose no precision to cancellation.
    """
    mu = 0.5 * (t0 + t1)
    hw = 0.5 * (t1 - t0)
    mu2, hw2 = mu * mu, hw * hw
    # 3 mu^2 + hw^2 is 0 only for an empty interval at t = 0 (a ray starting inside the
    # bounds and missing nothing); every moment is then 0 and the clamp keeps it 0 / eps
    den = (3.0 * mu2 + hw2).clamp_min(torch.finfo(mu.dtype).tiny ** 0.5)
    t_mean = mu + 2.0 * mu * hw2 / den
    t_var = (hw2 / 3.0 - (4.0 / 15.0) * hw2 * hw2 * (12.0 * mu2 - hw2) / (den * den)).clamp_min(0.0)
    r_var = radii * radii * (mu2 / 4.0 + (5.0 / 12.0) * hw2 - (4.0 / 15.0) * hw2 * hw2 / den)
    return t_mean, t_var, r_var.clamp_min(0.0)


def lift_gaussian(origins: torch.Tensor, directions: torch.Tensor, t_mean: torch.Tensor,
                  t_var: torch.Tensor, r_var: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space mean (..., 3) and diagonal covariance (..., 3) of a frustum Gaussian.

    Args:
        origins, directions: (..., 3) ray origin (m) and *unit* axis direction.
        t_mean, t_var, r_var: (...) from :func:`conical_frustum_gaussian`.
    The covariance is ``t_var d d^T + r_var (I - d d^T)``; only its diagonal is kept.
    """
    mean = origins + directions * t_mean[..., None]
    d2 = directions * directions
    var = t_var[..., None] * d2 + r_var[..., None] * (1.0 - d2)
    return mean, var.clamp_min(0.0)


def integrated_pos_enc(mean: torch.Tensor, var: Optional[torch.Tensor], n_freqs: int
                       ) -> torch.Tensor:
    """E[gamma(x)] for x ~ N(mean, diag(var)): (N, D) -> (N, D (1 + 2 n_freqs)).

    gamma is nerfbot's positional encoding (:class:`~nerfbot.ops.encodings.FrequencyEncoding`:
    ``[x, sin(a_k x), cos(a_k x)]`` with ``a_k = pi 2^k``, in that layout), and
    ``E[sin(a x)] = sin(a mean) exp(-a^2 var / 2)`` (likewise cos). ``var`` None (or 0) gives
    gamma(mean) exactly.
    """
    freqs = math.pi * 2.0 ** torch.arange(n_freqs, dtype=mean.dtype, device=mean.device)
    scaled = (mean[..., None, :] * freqs[:, None]).flatten(-2)  # (N, F*D), frequency-major
    sin, cos = torch.sin(scaled), torch.cos(scaled)
    if var is not None:
        damp = torch.exp(-0.5 * (var[..., None, :] * (freqs * freqs)[:, None]).flatten(-2))
        sin, cos = sin * damp, cos * damp
    return torch.cat([mean, sin, cos], dim=-1)


@dataclass
class MipNeRFFieldConfig:
    pos_freqs: int = 12
    """L of the integrated positional encoding (frequencies pi 2^k, k < L, over the cube mapped
    to [-1, 1]). The IPE silences levels finer than the pixel footprint, so L only needs to
    cover the finest footprint: 12 reaches ~1000 px images of this scene scale (on 128 px
    images levels above ~8 are already damped to < e^-5). Higher levels never carry a signal
    in training but are undamped in point queries (:meth:`MipNeRFField.density`)."""
    dir_freqs: int = 4
    """L of the positional encoding of the view direction."""
    width: int = 256
    """Width of the trunk."""
    depth: int = 8
    """Layers of the trunk."""
    skip: int = 4
    """The encoded input is concatenated again before this layer."""
    color_width: int = 128
    """Width of the view-dependent branch."""

    def validate(self) -> None:
        for name in ("pos_freqs", "dir_freqs", "skip", "width", "depth", "color_width"):
            value, least = getattr(self, name), 0 if name.endswith(("freqs", "skip")) else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"mipnerf option {name} must be an integer >= {least}, "
                                 f"got {value!r}")


class MipNeRFField(Field):
    """NeRF's MLP (trunk with a skip, view-dependent branch) on integrated positional encodings.

    ``density_gaussian(mean, var)`` is the model's entry point (frustum Gaussians);
    ``density(x)`` answers point queries (depth, meshes, occupancy) as a zero-variance Gaussian,
    i.e. the plain positional encoding. Points outside the scene bounds have zero density.
    """

    def __init__(self, aabb, config: MipNeRFFieldConfig | None = None):
        super().__init__()
        self.config = cfg = config or MipNeRFFieldConfig()
        cfg.validate()
        self.normalize = BoxNormalizer(aabb)
        self.dir_enc = FrequencyEncoding(3, cfg.dir_freqs)
        enc_dim = 3 * (1 + 2 * cfg.pos_freqs)
        layers = []
        for i in range(cfg.depth):
            d_in = enc_dim if i == 0 else cfg.width
            if i == cfg.skip:
                d_in += enc_dim
            layers.append(nn.Linear(d_in, cfg.width))
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(cfg.width, 1)
        self.feature = nn.Linear(cfg.width, cfg.width)
        self.branch = nn.Linear(cfg.width + self.dir_enc.out_dim, cfg.color_width)
        self.rgb_head = nn.Linear(cfg.color_width, 3)

    def density_gaussian(self, mean: torch.Tensor, var: Optional[torch.Tensor],
                         cond: Optional[torch.Tensor] = None):
        """mean (N, 3) world points (m), var (N, 3) diagonal covariance (m^2) or None ->
        sigma (N,) >= 0 in 1/m, features (N, width)."""
        scale = 2.0 / self.normalize.cube_size  # world -> [-1, 1] over the cube
        xn = self.normalize(mean) * 2.0 - 1.0
        vn = None if var is None else var * (scale * scale)
        e = integrated_pos_enc(xn, vn, self.config.pos_freqs)
        h = e
        for i, layer in enumerate(self.trunk):
            if i == self.config.skip:
                h = torch.cat([h, e], -1)
            h = F.relu(layer(h))
        sigma = F.softplus(self.sigma_head(h)[:, 0] - 1.0)
        sigma = torch.where(self.normalize.inside(mean), sigma, torch.zeros_like(sigma))
        return sigma, self.feature(h)

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return self.density_gaussian(x, None, cond)

    def color_head(self):
        return self.rgb_head

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        h = F.relu(self.branch(torch.cat([feat, self.dir_enc(d)], -1)))
        return torch.sigmoid(self.rgb_head(h))
