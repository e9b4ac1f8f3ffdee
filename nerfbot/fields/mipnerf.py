"""mip-NeRF (Barron et al. 2021): cones instead of rays, integrated positional encoding.

Each interval [t0, t1] of a ray is the conical frustum cut from the cone through the ray's
pixel (radius ``t * radii`` at distance t, see :class:`~nerfbot.cameras.Rays`). The frustum is
replaced by a Gaussian of the same mean and (diagonal) covariance, and the field sees the
*expected* positional encoding of a point drawn from it (the IPE): every sin / cos feature of
frequency a is damped by ``exp(-a^2 var / 2)``, so features finer than the footprint fade out
and an image rendered at a lower resolution (larger pixels, wider cones) is anti-aliased.

One MLP serves both passes: coarse stratified intervals, then fine intervals drawn from the
coarse weights blurred by a 2-tap max and a 2-tap mean plus a constant padding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.cameras import Rays
from nerfbot.encodings import FrequencyEncoding
from nerfbot.fields.base import BoxNormalizer, Field
from nerfbot.models import Model, pixel_mean
from nerfbot.rendering import RenderOutput, composite
from nerfbot.sampling import pdf_samples, ray_aabb, stratified_samples

#: Samples per field query when rendering without gradients (bounds the activation memory of
#: a 256-wide MLP to ~0.3 GB per layer whatever the number of rays).
EVAL_QUERY_CHUNK = 1 << 18


# -- Gaussians of conical frustums ------------------------------------------------------------

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

    gamma is nerfbot's positional encoding (:class:`~nerfbot.encodings.FrequencyEncoding`:
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


# -- the field --------------------------------------------------------------------------------

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


# -- the model --------------------------------------------------------------------------------

@dataclass
class MipNeRFModelConfig:
    coarse_samples: int = 128
    """Stratified intervals per ray of the coarse pass."""
    fine_samples: int = 128
    """Intervals per ray of the fine pass, all drawn from the blurred coarse weights (they
    replace the coarse ones: 128 + 128 field queries per ray, as nerf's 64 + (64 + 128))."""
    rays_per_batch: int = 1024
    """Rays per training batch."""
    coarse_loss_weight: float = 0.1
    """Weight of the coarse pass's MSE in the loss (the fine pass has weight 1)."""
    pdf_padding: float = 0.01
    """Added to every blurred coarse weight before fine sampling (mip-NeRF's resample padding):
    keeps some fine samples everywhere along the ray."""

    def validate(self) -> None:
        for name in ("coarse_samples", "fine_samples", "rays_per_batch"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"mipnerf option {name} must be a positive integer, got {value!r}")
        for name in ("coarse_loss_weight", "pdf_padding"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float))
                                               and 0.0 <= value < math.inf):
                raise ValueError(f"mipnerf option {name} must be finite and >= 0, got {value!r}")


def blurred_weights(weights: torch.Tensor, padding: float) -> torch.Tensor:
    """mip-NeRF's resampling pdf from coarse weights (R, S): max over neighbouring pairs
    (S + 1 values, ends replicated), mean over neighbouring pairs again (S values), plus
    ``padding``. Widens every peak by about one interval on each side."""
    padded = torch.cat([weights[:, :1], weights, weights[:, -1:]], -1)
    pooled = torch.maximum(padded[:, :-1], padded[:, 1:])
    return 0.5 * (pooled[:, :-1] + pooled[:, 1:]) + padding


class MipNeRFModel(Model):
    """Cone tracing through one :class:`MipNeRFField`: coarse, then fine intervals."""

    def __init__(self, field: MipNeRFField, background: nn.Module, aabb,
                 config: MipNeRFModelConfig | None = None):
        super().__init__()
        self.config = config or MipNeRFModelConfig()
        self.config.validate()
        self.field, self.background = field, background
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).clone())

    def _query(self, mean, var, d, cond):
        """Field density and colour of (M,) Gaussians; chunked when no gradient is recorded."""
        if torch.is_grad_enabled() or mean.shape[0] <= EVAL_QUERY_CHUNK:
            sigma, feat = self.field.density_gaussian(mean, var, cond)
            return sigma, self.field.color(feat, d, cond)
        parts = [self._query(mean[i:i + EVAL_QUERY_CHUNK], var[i:i + EVAL_QUERY_CHUNK],
                             d[i:i + EVAL_QUERY_CHUNK],
                             None if cond is None else cond[i:i + EVAL_QUERY_CHUNK])
                 for i in range(0, mean.shape[0], EVAL_QUERY_CHUNK)]
        return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])

    def _render_edges(self, rays: Rays, radii, edges, t_far, bg, cond,
                      with_median: bool) -> RenderOutput:
        """Composite the frustums between ``edges`` (R, S + 1) of every ray."""
        n, s = edges.shape[0], edges.shape[1] - 1
        ray_idx = torch.arange(n, device=edges.device).repeat_interleave(s)
        t0, t1 = edges[:, :-1], edges[:, 1:]
        t_mean, t_var, r_var = conical_frustum_gaussian(t0, t1, radii[:, None])
        mean, var = lift_gaussian(rays.origins[:, None], rays.directions[:, None], t_mean,
                                  t_var, r_var)
        d = rays.directions[ray_idx]
        c = None if cond is None else cond[ray_idx]
        sigma, rgb = self._query(mean.reshape(-1, 3), var.reshape(-1, 3), d, c)
        return composite(sigma, rgb, t0.reshape(-1), t1.reshape(-1), ray_idx, n, bg, t_far,
                         rays.z_per_t, with_median=with_median)

    def _render_both(self, rays: Rays, generator=None, cond=None):
        cfg = self.config
        t_near, t_far, _ = ray_aabb(rays.origins, rays.directions, self.aabb)
        # rays not made from pixels have no footprint: they are traced as thin rays
        radii = rays.radii if rays.radii is not None else torch.zeros_like(t_near)
        bg = self.background(rays.directions)
        edges_c = stratified_samples(t_near, t_far, cfg.coarse_samples, generator, self.training)
        coarse = self._render_edges(rays, radii, edges_c, t_far, bg, cond, False)
        w = blurred_weights(coarse.weights.detach().reshape(len(rays), cfg.coarse_samples),
                            cfg.pdf_padding)
        edges_f = pdf_samples(edges_c, w, cfg.fine_samples + 1, generator, self.training)
        edges_f = torch.sort(edges_f, -1).values
        fine = self._render_edges(rays, radii, edges_f, t_far, bg, cond, not self.training)
        return coarse, fine

    def render_rays(self, rays: Rays, generator=None, cond=None) -> RenderOutput:
        return self._render_both(rays, generator, cond)[1]

    def loss(self, rays, target_rgb, generator=None, cond=None, rays_per_pixel=1):
        coarse, fine = self._render_both(rays, generator, cond)
        loss = F.mse_loss(pixel_mean(fine.rgb, rays_per_pixel), target_rgb)
        if self.config.coarse_loss_weight > 0:
            loss = loss + self.config.coarse_loss_weight * F.mse_loss(
                pixel_mean(coarse.rgb, rays_per_pixel), target_rgb)
        return loss, fine

    def rays_for_next_batch(self, last_samples: Optional[int], n_rays: int) -> int:
        return self.config.rays_per_batch
