"""D-NeRF: a deformation field Psi(x, t) -> dx and a canonical field queried at x + dx.

Pumarola et al. 2021: the scene at time t is the canonical scene (the scene at t = 0) seen
through a deformation. Here the canonical field is the Instant-NGP field and the deformation is
built on fast encodings so it trains on a CPU in minutes:

- ``deform_encoding="planes"`` (default): factorised space-time feature planes (K-Planes /
  HexPlane: xy, xz, yz, xt, yt, zt, multiplied per level) and a small MLP;
- ``deform_encoding="frequency"``: the paper's form, positional encodings of x (L = 10) and t
  (L = 6) into a ReLU MLP (set ``deform_hidden=256, deform_layers=8`` for its full size).

dx = t * MLP(...) (normalised units times the cube size), so dx = 0 at t = 0 exactly, whatever the
weights (the paper sets Psi(x, 0) = 0 the same way). The last layer starts at zero, so training
begins from a static scene. View directions are not deformed, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.base import Field, mlp
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.ops.encodings import FrequencyEncoding, PlaneEncoding


@dataclass
class DNeRFFieldConfig:
    deform_encoding: str = "planes"
    """"planes" (factorised space-time planes, fast) or "frequency" (the paper's MLP form)."""
    deform_levels: int = 2
    """Plane encoding: resolution levels."""
    deform_features: int = 8
    """Plane encoding: features per plane and level."""
    deform_spatial_res: int = 64
    """Plane encoding: cells per spatial axis of the finest level (each coarser level halves)."""
    deform_time_res: int = 24
    """Plane encoding: cells along time of the finest level."""
    deform_hidden: int = 64
    """Width of the deformation MLP."""
    deform_layers: int = 2
    """Hidden layers of the deformation MLP."""
    deform_x_freqs: int = 10
    """Frequency encoding: frequencies of x."""
    deform_t_freqs: int = 6
    """Frequency encoding: frequencies of t."""
    deform_tv_weight: float = 1e-4
    """Plane encoding: weight of the total variation of the spatial planes (smooth motion)."""
    deform_time_smoothness_weight: float = 1e-3
    """Plane encoding: weight of the second differences along time (smooth trajectories)."""


class DNeRFField(Field):
    """sigma, rgb = canonical(x + dx(x, t), d); ``cond`` (N, 1) time in [0, 1], None means t = 0."""

    def __init__(self, aabb, conditioning: Conditioning, config: NGPFieldConfig | None = None,
                 dconfig: DNeRFFieldConfig | None = None, seed: int = 0):
        super().__init__()
        if conditioning.kind != "time":
            raise ValueError("dnerf needs a time-conditioned capture (frames with 'time', e.g. "
                             "`nerfbot capture --scene dynamic`)")
        self.conditioning = conditioning
        self.dconfig = dc = dconfig or DNeRFFieldConfig()
        self.canonical = NGPField(aabb, config, seed=seed)
        if dc.deform_encoding == "planes":
            spatial = [max(4, dc.deform_spatial_res >> (dc.deform_levels - 1 - l))
                       for l in range(dc.deform_levels)]
            temporal = [max(2, dc.deform_time_res >> (dc.deform_levels - 1 - l))
                        for l in range(dc.deform_levels)]
            self.deform_encoding = PlaneEncoding(4, dc.deform_levels, dc.deform_features,
                                                 spatial, temporal, seed=seed + 1)
            in_dim = self.deform_encoding.out_dim
        elif dc.deform_encoding == "frequency":
            self.x_encoding = FrequencyEncoding(3, dc.deform_x_freqs)
            self.t_encoding = FrequencyEncoding(1, dc.deform_t_freqs)
            in_dim = self.x_encoding.out_dim + self.t_encoding.out_dim
        else:
            raise ValueError(f"deform_encoding must be 'planes' or 'frequency', got "
                             f"{dc.deform_encoding!r}")
        self.deform_mlp = mlp(in_dim, dc.deform_hidden, dc.deform_layers, 3)
        nn.init.zeros_(self.deform_mlp[-1].weight)
        nn.init.zeros_(self.deform_mlp[-1].bias)

    def _time(self, cond: Optional[torch.Tensor], n: int, like: torch.Tensor) -> torch.Tensor:
        return like.new_zeros(n, 1) if cond is None else cond[:, :1].to(like.dtype)

    def deformation(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None) -> torch.Tensor:
        """dx (N, 3) metres at world points x (N, 3) and times ``cond`` (N, 1); 0 at t = 0."""
        t = self._time(cond, x.shape[0], x)
        xn = self.canonical.normalize(x)
        if self.dconfig.deform_encoding == "planes":
            enc = self.deform_encoding(torch.cat([xn.clamp(0, 1), t.clamp(0, 1)], -1))
        else:
            enc = torch.cat([self.x_encoding(2 * xn - 1), self.t_encoding(2 * t - 1)], -1)
        return t * self.deform_mlp(enc) * self.canonical.normalize.cube_size

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return self.canonical.density(x + self.deformation(x, cond))

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return self.canonical.color(feat, d)

    def occupancy_density(self, x, generator=None):
        return self.density(x, self.conditioning.sample(x.shape[0], generator, x.device))[0]

    def before_step(self, step: int, progress: float) -> dict:
        return self.canonical.before_step(step, progress)

    def regularizer(self) -> Optional[torch.Tensor]:
        dc = self.dconfig
        if dc.deform_encoding != "planes":
            return None
        return (dc.deform_tv_weight * self.deform_encoding.tv_loss()
                + dc.deform_time_smoothness_weight * self.deform_encoding.smoothness_loss())

    def color_head(self):
        return self.canonical.color_head()

    def param_groups(self) -> list[dict]:
        groups = self.canonical.param_groups()
        seen = {id(p) for g in groups for p in g["params"]}
        rest = [p for p in self.parameters() if id(p) not in seen]
        return groups + [{"params": rest, "lr_scale": 1.0}]
