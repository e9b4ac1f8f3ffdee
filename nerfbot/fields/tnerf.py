"""T-NeRF: a radiance field with the condition (time, or the joint vector) as an extra input.

The baseline of D-NeRF (Pumarola et al. 2021, "T-NeRF"): nothing models motion explicitly; the
network sees (x, c) and must represent every state of the scene at once. Built on the Instant-NGP
field so it trains at the same speed: the hash features of x and a frequency encoding of the
normalised condition c in [0, 1]^C go through the density MLP, whose geometry features carry the
condition on to the colour MLP.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.base import mlp, run_mlp, trunc_exp
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.ops.encodings import FrequencyEncoding


@dataclass
class TNeRFFieldConfig:
    cond_freqs: int = 6
    """Frequencies of the positional encoding of each normalised condition value."""
    density_layers: int = 2
    """Hidden layers of the density MLP (the NGP field has 1; time needs more capacity)."""


class TNeRFField(NGPField):
    """sigma, rgb = NGP(hash(x) ++ gamma(c)): the condition is just another input.

    ``cond`` (N, C) in scene units (see :class:`~nerfbot.data.conditioning.Conditioning`); None
    means the low end of every range (t = 0, joints at their lower limits).
    """

    def __init__(self, aabb, conditioning: Conditioning, config: NGPFieldConfig | None = None,
                 tconfig: TNeRFFieldConfig | None = None, seed: int = 0):
        super().__init__(aabb, config, seed)
        if conditioning.is_static:
            raise ValueError("tnerf needs a time- or joint-conditioned capture (frames with "
                             "'time' or 'joints'); use ngp for a static scene")
        self.conditioning = conditioning
        self.tconfig = tc = tconfig or TNeRFFieldConfig()
        self.cond_encoding = FrequencyEncoding(conditioning.dim, tc.cond_freqs)
        cfg = self.config
        self.density_mlp = mlp(self.encoding.out_dim + self.cond_encoding.out_dim, cfg.hidden,
                               tc.density_layers, 1 + cfg.geo_feat_dim)

    def _cond(self, cond: Optional[torch.Tensor], n: int, like: torch.Tensor) -> torch.Tensor:
        if cond is None:
            return like.new_zeros(n, self.conditioning.dim)
        return self.conditioning.normalize(cond.to(like.dtype))

    def density_at_scale(self, x: torch.Tensor, radius: Optional[torch.Tensor],
                         cond: Optional[torch.Tensor] = None):
        enc = self._encode(x, radius)
        c = self.cond_encoding(self._cond(cond, x.shape[0], enc))
        h = run_mlp(self.density_mlp, torch.cat([enc, c], -1), self.config.mlp_precision)
        sigma = trunc_exp(h[:, 0] + self.density_bias)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, h[:, 1:]

    def occupancy_density(self, x, generator=None):
        return self.density(x, self.conditioning.sample(x.shape[0], generator, x.device))[0]
