"""FastNeRF field (Garbin et al. 2021): a position network and a direction network whose outputs
factorise the colour, so both can be cached on grids
(:func:`nerfbot.bake.fastnerf_cache.bake_cache`).

* F_pos: x -> (sigma, u_1..u_D), D radiance components u_i in R^3;
* F_dir: d -> (beta_1..beta_D), D weights;
* rgb = sigmoid(sum_i beta_i u_i), sigma = trunc_exp(raw density).

The sigmoid sits *after* the weighted sum (the paper's inner product, squashed), so the cached
grids interpolate linearly and the colour stays in (0, 1) for any interpolated components.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.fields.base import BoxNormalizer, Field, mlp, trunc_exp
from nerfbot.ops.encodings import FrequencyEncoding, HashGridConfig, SHEncoding


#: Raw densities (the argument of exp) are stored clamped to this range: above 15 trunc_exp
#: saturates anyway, below -20 the density (< 2e-9 /m) renders nothing.
RAW_DENSITY_RANGE = (-20.0, 15.0)


@dataclass
class FastNeRFFieldConfig(HashGridConfig):
    """The hash grid's fields (:class:`~nerfbot.ops.encodings.HashGridConfig`) apply to the hash
    variant of F_pos."""

    components: int = 8
    """D, radiance components of F_pos and weights of F_dir."""
    position_encoding: str = "hash"
    """"hash": hash grid + small MLP (fast on CPU); "frequency": the paper's 8-layer MLP on the
    positional encoding (slow on CPU)."""
    hidden: int = 64
    """Hash variant: width of the position MLP."""
    position_layers: int = 2
    """Hash variant: hidden layers of the position MLP."""
    pos_freqs: int = 10
    """Frequency variant: frequencies of the positional encoding."""
    freq_width: int = 256
    """Frequency variant: width of the 8-layer MLP."""
    freq_depth: int = 8
    """Frequency variant: layers of the MLP (the input is concatenated again at layer 4)."""
    freq_lr_scale: float = 0.05
    """Frequency variant: learning rate relative to the method's (hash tables want 1e-2, a deep
    MLP on a positional encoding 5e-4)."""
    dir_sh_degree: int = 4
    """Spherical-harmonics degree of F_dir's input."""
    dir_hidden: int = 64
    """Width of F_dir."""
    dir_layers: int = 2
    """Hidden layers of F_dir."""
    initial_transmittance: float = 0.2
    """Transmittance of a ray crossing the whole cube at initialisation (density bias, as in
    :class:`~nerfbot.fields.ngp.NGPFieldConfig`)."""
    mlp_lr_scale: float = 1.0
    """Hash variant: learning rate of the MLPs relative to the hash table's."""


class _FrequencyMLP(nn.Module):
    """gamma(x) -> 8 ReLU layers (input concatenated again at layer ``skip``) -> out_dim."""

    def __init__(self, n_freqs: int, width: int, depth: int, out_dim: int, skip: int = 4):
        super().__init__()
        self.enc = FrequencyEncoding(3, n_freqs)
        self.skip = skip
        dims = [self.enc.out_dim] + [width] * depth
        self.layers = nn.ModuleList(
            nn.Linear(dims[i] + (self.enc.out_dim if i == skip else 0), width) for i in range(depth))
        self.head = nn.Linear(width, out_dim)

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        e = self.enc(x01 * 2.0 - 1.0)
        h = e
        for i, layer in enumerate(self.layers):
            if i == self.skip:
                h = torch.cat([h, e], -1)
            h = F.relu(layer(h))
        return self.head(h)


class FastNeRFField(Field):
    """sigma = trunc_exp(F_pos(x)[0]); rgb = sigmoid(sum_i F_dir(d)_i * F_pos(x)[1 + 3i : 4 + 3i]).

    ``feat`` of :meth:`density` are the D x 3 components u, flattened (N, 3D) as u[i, c] at
    3i + c. Points outside the scene bounds have zero density.
    """

    def __init__(self, aabb, config: FastNeRFFieldConfig | None = None, seed: int = 0):
        super().__init__()
        self.config = cfg = config or FastNeRFFieldConfig()
        if cfg.components < 1:
            raise ValueError(f"components must be >= 1, got {cfg.components}")
        if not 0.0 < cfg.initial_transmittance < 1.0:
            raise ValueError(f"initial_transmittance must be in (0, 1), got {cfg.initial_transmittance}")
        self.normalize = BoxNormalizer(aabb)
        out_dim = 1 + 3 * cfg.components
        if cfg.position_encoding == "hash":
            self.encoding = cfg.hash_encoding(seed)
            self.position_net = mlp(self.encoding.out_dim, cfg.hidden, cfg.position_layers, out_dim)
        elif cfg.position_encoding == "frequency":
            self.encoding = None
            self.position_net = _FrequencyMLP(cfg.pos_freqs, cfg.freq_width, cfg.freq_depth, out_dim)
        else:
            raise ValueError(f"position_encoding must be 'hash' or 'frequency', "
                             f"got {cfg.position_encoding!r}")
        self.dir_encoding = SHEncoding(cfg.dir_sh_degree)
        self.direction_net = mlp(self.dir_encoding.out_dim, cfg.dir_hidden, cfg.dir_layers,
                                 cfg.components)
        diagonal = math.sqrt(3.0) * float(self.normalize.cube_size)
        self.density_bias = math.log(-math.log(cfg.initial_transmittance) / diagonal)

    @property
    def components(self) -> int:
        return self.config.components

    # -- the two networks ----------------------------------------------------------------------
    def position_outputs(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """F_pos. x: (N, 3) world points -> raw density (N,) (sigma = trunc_exp(raw), before the
        bounds mask) and components u (N, 3D)."""
        x01 = self.normalize(x)
        h = self.position_net(self.encoding(x01) if self.encoding is not None else x01)
        return h[:, 0] + self.density_bias, h[:, 1:]

    def direction_weights(self, d: torch.Tensor) -> torch.Tensor:
        """F_dir. d: (N, 3) unit directions -> beta (N, D)."""
        return self.direction_net(self.dir_encoding(d))

    # -- Field interface -----------------------------------------------------------------------
    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        raw, u = self.position_outputs(x)
        sigma = trunc_exp(raw)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, u

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return combine_components(self.direction_weights(d), feat)

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """Start at colour ``rgb`` (3,) everywhere: every beta starts near 1 (F_dir's output bias)
        and every component near logit(rgb) / D (F_pos's output bias), so sum_i beta_i u_i is
        logit(rgb) while the random weights keep the components distinct."""
        d = self.components
        with torch.no_grad():
            self.direction_net[-1].bias.fill_(1.0)
            head = self.position_net[-1] if isinstance(self.position_net, nn.Sequential) \
                else self.position_net.head
            logit = torch.logit(rgb.clamp(0.02, 0.98)).to(head.bias) / d
            head.bias[1:].copy_(logit.repeat(d))

    def param_groups(self) -> list[dict]:
        """Hash variant: the table at scale 1, the MLPs at ``mlp_lr_scale``. Frequency variant:
        everything at ``freq_lr_scale``."""
        if self.encoding is None:
            return [{"params": list(self.parameters()), "lr_scale": self.config.freq_lr_scale}]
        mlps = [p for n, p in self.named_parameters() if not n.startswith("encoding.")]
        return [{"params": [self.encoding.table], "lr_scale": 1.0},
                {"params": mlps, "lr_scale": self.config.mlp_lr_scale}]


def combine_components(beta: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """rgb (N, 3) = sigmoid(sum_i beta_i u_i) from beta (N, D) and u (N, 3D) (u[i, c] at 3i + c)."""
    n, d = beta.shape
    return torch.sigmoid(torch.einsum("nd,ndc->nc", beta, u.reshape(n, d, 3)))
