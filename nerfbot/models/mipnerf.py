"""mip-NeRF's renderer (Barron et al. 2021) around :class:`~nerfbot.fields.mipnerf.MipNeRFField`:
one MLP serves both passes, coarse stratified intervals, then fine intervals drawn from the
coarse weights blurred by a 2-tap max and a 2-tap mean plus a constant padding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from nerfbot.fields.mipnerf import (EVAL_QUERY_CHUNK, MipNeRFField, conical_frustum_gaussian,
                                    lift_gaussian)
from nerfbot.models.base import Model, photometric_loss
from nerfbot.ops.cameras import Rays
from nerfbot.ops.rendering import RenderOutput, composite
from nerfbot.ops.sampling import pdf_samples, ray_aabb, stratified_samples


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

    def loss(self, rays, target_rgb, generator=None, cond=None, rays_per_pixel=1,
             pixel_weights=None):
        coarse, fine = self._render_both(rays, generator, cond)
        loss = photometric_loss(fine.rgb, target_rgb, rays_per_pixel, pixel_weights)
        if self.config.coarse_loss_weight > 0:
            loss = loss + self.config.coarse_loss_weight * photometric_loss(
                coarse.rgb, target_rgb, rays_per_pixel, pixel_weights)
        return loss, fine

    def rays_for_next_batch(self, last_samples: Optional[int], n_rays: int) -> int:
        return self.config.rays_per_batch
