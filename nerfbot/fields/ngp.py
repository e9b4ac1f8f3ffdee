"""Instant-NGP field: multiresolution hash encoding + tiny density and colour MLPs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from nerfbot.encodings import HashEncoding, SHEncoding
from nerfbot.fields.base import BoxNormalizer, Field, mlp, trunc_exp


@dataclass
class NGPFieldConfig:
    n_levels: int = 16
    """L, hash-grid resolution levels."""
    n_features: int = 2
    """F, features per level."""
    log2_hashmap_size: int = 17
    """log2 of the hash-table size T per level (2^17 rows x F floats = 1 MB: fits in L2)."""
    min_res: int = 16
    """Cells per axis of the coarsest level (over the cube enclosing the bounds)."""
    max_res: int = 512
    """Cells per axis of the finest level."""
    hidden: int = 64
    """Width of the density and colour MLPs."""
    geo_feat_dim: int = 15
    """Geometry features passed from the density MLP to the colour MLP."""
    color_layers: int = 2
    """Hidden layers of the colour MLP."""
    sh_degree: int = 4
    """Spherical-harmonics degree of the view-direction encoding (0 = view-independent)."""
    backend: str = "numba"
    """Hash-encoding implementation: "numba" (fast CPU) or "torch" (reference twin)."""


class NGPField(Field):
    """sigma = trunc_exp(MLP_d(hash(x))[0]); rgb = sigmoid(MLP_c(MLP_d(hash(x))[1:], SH(d))).

    Points outside the scene bounds have zero density.
    """

    def __init__(self, aabb, config: NGPFieldConfig | None = None, seed: int = 0):
        super().__init__()
        self.config = cfg = config or NGPFieldConfig()
        self.normalize = BoxNormalizer(aabb)
        self.encoding = HashEncoding(cfg.n_levels, cfg.n_features, cfg.log2_hashmap_size,
                                     cfg.min_res, cfg.max_res, backend=cfg.backend, seed=seed)
        self.density_mlp = mlp(self.encoding.out_dim, cfg.hidden, 1, 1 + cfg.geo_feat_dim)
        self.dir_encoding = SHEncoding(cfg.sh_degree)
        self.color_mlp = mlp(cfg.geo_feat_dim + self.dir_encoding.out_dim, cfg.hidden,
                             cfg.color_layers, 3)

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        h = self.density_mlp(self.encoding(self.normalize(x)))
        sigma = trunc_exp(h[:, 0] - 1.0)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, h[:, 1:]

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return torch.sigmoid(self.color_mlp(torch.cat([feat, self.dir_encoding(d)], -1)))
