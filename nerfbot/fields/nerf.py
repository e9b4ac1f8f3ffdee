"""Vanilla NeRF field (Mildenhall et al. 2020): positional encoding + 8x256 MLP, skip at layer 4."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.fields.base import BoxNormalizer, Field
from nerfbot.ops.encodings import FrequencyEncoding


@dataclass
class NeRFFieldConfig:
    pos_freqs: int = 10
    """L of the positional encoding of x."""
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


class NeRFField(Field):
    """sigma = softplus(trunk(gamma(x))), rgb = sigmoid(branch(trunk features, gamma(d))).

    Positions are normalised to [-1, 1] over the cube enclosing the scene bounds before the
    encoding; points outside the bounds have zero density.
    """

    def __init__(self, aabb, config: NeRFFieldConfig | None = None):
        super().__init__()
        self.config = cfg = config or NeRFFieldConfig()
        self.normalize = BoxNormalizer(aabb)
        self.pos_enc = FrequencyEncoding(3, cfg.pos_freqs)
        self.dir_enc = FrequencyEncoding(3, cfg.dir_freqs)
        layers = []
        for i in range(cfg.depth):
            d_in = self.pos_enc.out_dim if i == 0 else cfg.width
            if i == cfg.skip:
                d_in += self.pos_enc.out_dim
            layers.append(nn.Linear(d_in, cfg.width))
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = nn.Linear(cfg.width, 1)
        self.feature = nn.Linear(cfg.width, cfg.width)
        self.branch = nn.Linear(cfg.width + self.dir_enc.out_dim, cfg.color_width)
        self.rgb_head = nn.Linear(cfg.color_width, 3)

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        e = self.pos_enc(self.normalize(x) * 2.0 - 1.0)
        h = e
        for i, layer in enumerate(self.trunk):
            if i == self.config.skip:
                h = torch.cat([h, e], -1)
            h = F.relu(layer(h))
        sigma = F.softplus(self.sigma_head(h)[:, 0] - 1.0)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, self.feature(h)

    def color_head(self):
        return self.rgb_head

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        h = F.relu(self.branch(torch.cat([feat, self.dir_enc(d)], -1)))
        return torch.sigmoid(self.rgb_head(h))
