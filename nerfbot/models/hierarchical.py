"""NeRF's renderer: coarse stratified samples with one field, then fine samples drawn from the
coarse weights with a second field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from nerfbot.fields.base import Field
from nerfbot.models.base import Model, photometric_loss
from nerfbot.models.occupancy import gather_rows
from nerfbot.ops.cameras import Rays
from nerfbot.ops.rendering import RenderOutput, composite
from nerfbot.ops.sampling import pdf_samples, ray_aabb, stratified_samples


@dataclass
class HierarchicalModelConfig:
    coarse_samples: int = 64
    """Stratified samples per ray for the coarse field."""
    fine_samples: int = 128
    """Extra samples per ray drawn from the coarse weights for the fine field."""
    rays_per_batch: int = 1024
    """Rays per training batch."""


class HierarchicalModel(Model):
    """NeRF's renderer: coarse stratified samples, fine pdf samples, two fields, both trained."""

    supports_labels = True  # on the fine field's samples

    def __init__(self, coarse: Field, fine: Field, background: nn.Module, aabb,
                 config: HierarchicalModelConfig | None = None):
        super().__init__()
        self.config = config or HierarchicalModelConfig()
        self.coarse, self.field, self.background = coarse, fine, background
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).clone())

    def _render_edges(self, field: Field, rays: Rays, edges: torch.Tensor, t_far, bg, cond):
        n, s = edges.shape[0], edges.shape[1] - 1
        ray_idx = torch.arange(n, device=edges.device).repeat_interleave(s)
        ts, te = edges[:, :-1].reshape(-1), edges[:, 1:].reshape(-1)
        t_mid = 0.5 * (ts + te)
        d = rays.directions[ray_idx]
        x = rays.origins[ray_idx] + d * t_mid[:, None]
        sigma, feat = field.density(x, gather_rows(cond, ray_idx))
        rgb = field.color(feat, d, gather_rows(cond, ray_idx))
        out = composite(sigma, rgb, ts, te, ray_idx, n, bg, t_far, rays.z_per_t,
                        with_median=not self.training)
        if field is self.field and self.label_head is not None:
            out.positions, out.features = x, feat
        return out

    def _render_both(self, rays: Rays, generator=None, cond=None):
        t_near, t_far, _ = ray_aabb(rays.origins, rays.directions, self.aabb)
        bg = self.background(rays.directions)
        cfg = self.config
        edges_c = stratified_samples(t_near, t_far, cfg.coarse_samples, generator, self.training)
        coarse = self._render_edges(self.coarse, rays, edges_c, t_far, bg, cond)
        w = coarse.weights.reshape(len(rays), cfg.coarse_samples)
        t_fine = pdf_samples(edges_c, w, cfg.fine_samples, generator, self.training)
        edges_f = torch.sort(torch.cat([edges_c, t_fine], -1), -1).values
        fine = self._render_edges(self.field, rays, edges_f, t_far, bg, cond)
        return coarse, fine

    def render_rays(self, rays: Rays, generator=None, cond=None) -> RenderOutput:
        return self._render_both(rays, generator, cond)[1]

    def rays_for_next_batch(self, last_samples: Optional[int], n_rays: int) -> int:
        return self.config.rays_per_batch

    def loss(self, rays, target_rgb, generator=None, cond=None, rays_per_pixel=1,
             pixel_weights=None):
        coarse, fine = self._render_both(rays, generator, cond)
        return (photometric_loss(coarse.rgb, target_rgb, rays_per_pixel, pixel_weights)
                + photometric_loss(fine.rgb, target_rgb, rays_per_pixel, pixel_weights)), fine
