"""NeRF-SH field (PlenOctrees, Yu et al. 2021): position -> density and spherical-harmonic
colour coefficients, no direction input; the view direction enters only through the SH basis.

Because nothing but the SH basis depends on the direction, the field's outputs at a point can be
stored once (in an octree leaf, :mod:`nerfbot.models.plenoctree`) and rendered for any view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from nerfbot.fields.base import BoxNormalizer, Field, mlp, trunc_exp
from nerfbot.ops.encodings import HashGridConfig, spherical_harmonics

#: The constant degree-0 SH basis function Y_00 = 1 / (2 sqrt(pi)).
SH_C0 = 0.5 / math.sqrt(math.pi)


def sh_degree_of(n_coeffs: int) -> int:
    """SH degree whose RGB coefficients number ``n_coeffs`` = 3 (degree + 1)^2; ValueError else."""
    n_sh = n_coeffs // 3
    degree = int(round(math.sqrt(n_sh))) - 1
    if n_coeffs != 3 * n_sh or (degree + 1) ** 2 != n_sh or not 0 <= degree <= 4:
        raise ValueError(f"{n_coeffs} coefficients are not 3 * (degree + 1)^2 for a degree 0..4")
    return degree


def sh_color(coeffs: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """rgb = sigmoid(SH(d) . k) per channel.

    Args:
        coeffs: (N, 3 * n_sh) SH coefficients, channel-major (all of red, then green, then blue),
            n_sh = (degree + 1)^2.
        d: (N, 3) unit view directions.
    Returns:
        (N, 3) rgb in (0, 1).
    """
    degree = sh_degree_of(coeffs.shape[-1])
    basis = spherical_harmonics(d, degree).to(coeffs.dtype)          # (N, n_sh)
    k = coeffs.reshape(coeffs.shape[0], 3, -1)                         # (N, 3, n_sh)
    return torch.sigmoid(torch.einsum("ncs,ns->nc", k, basis))


@dataclass
class NeRFSHFieldConfig(HashGridConfig):
    hidden: int = 64
    """Width of the MLP."""
    hidden_layers: int = 2
    """Hidden layers of the MLP from the hash features to density + SH coefficients."""
    sh_degree: int = 2
    """Degree of the spherical harmonics of the colour: 3 (degree + 1)^2 coefficients per point
    (2 -> 27, the paper's choice for its speed / quality balance)."""
    initial_transmittance: float = 0.2
    """Transmittance of a ray crossing the whole cube at initialisation (as in the ngp field)."""
    mlp_lr_scale: float = 1.0
    """Learning rate of the MLP relative to the hash table's."""
    sparsity_weight: float = 1e-4
    """Weight of PlenOctrees' sparsity prior: the mean Cauchy loss log(1 + 2 sigma^2) of the
    density at ``sparsity_points`` random points of the bounds per step. It empties free space
    and concentrates density into thin surfaces, so a baked octree holds fewer leaves and rays
    cross fewer of them. 0 turns it off."""
    sparsity_points: int = 4096
    """Random points per step for the sparsity prior (drawn anew each step, seeded by the step:
    resumed runs draw the same points)."""


class NeRFSHField(Field):
    """h = MLP(hash(x)); sigma = trunc_exp(h[0] + bias); rgb = sigmoid(SH(d) . h[1:]).

    The geometry features returned by :meth:`density` *are* the SH coefficients (N, 3 n_sh),
    channel-major. Points outside the scene bounds have zero density.
    """

    def __init__(self, aabb, config: NeRFSHFieldConfig | None = None, seed: int = 0):
        super().__init__()
        self.config = cfg = config or NeRFSHFieldConfig()
        if not 0 <= cfg.sh_degree <= 4:
            raise ValueError(f"sh_degree must be 0..4, got {cfg.sh_degree}")
        if cfg.hidden_layers < 1:
            raise ValueError(f"hidden_layers must be >= 1, got {cfg.hidden_layers}")
        if not 0.0 < cfg.initial_transmittance < 1.0:
            raise ValueError(f"initial_transmittance must be in (0, 1), got {cfg.initial_transmittance}")
        self.n_sh = (cfg.sh_degree + 1) ** 2
        self.normalize = BoxNormalizer(aabb)
        self.encoding = cfg.hash_encoding(seed)
        self.mlp = mlp(self.encoding.out_dim, cfg.hidden, cfg.hidden_layers, 1 + 3 * self.n_sh)
        diagonal = math.sqrt(3.0) * float(self.normalize.cube_size)
        self.density_bias = math.log(-math.log(cfg.initial_transmittance) / diagonal)
        if cfg.sparsity_weight < 0 or cfg.sparsity_points < 1:
            raise ValueError(f"sparsity_weight must be >= 0 and sparsity_points >= 1, got "
                             f"{cfg.sparsity_weight} and {cfg.sparsity_points}")
        self.seed = seed
        self._step = 0

    @property
    def sh_degree(self) -> int:
        return self.config.sh_degree

    def param_groups(self) -> list[dict]:
        """The hash table at the method's learning rate, the MLP at ``mlp_lr_scale`` of it."""
        mlps = [p for n, p in self.named_parameters() if not n.startswith("encoding.")]
        return [{"params": [self.encoding.table], "lr_scale": 1.0},
                {"params": mlps, "lr_scale": self.config.mlp_lr_scale}]

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """Start at colour ``rgb`` (3,) in every direction: the degree-0 coefficient of each
        channel is logit(rgb) / Y_00 (Y_00 is a constant), the others start at 0 bias."""
        head = self.mlp[-1]
        with torch.no_grad():
            bias = head.bias.view(-1)
            k = bias[1:].view(3, self.n_sh)
            k.zero_()
            k[:, 0] = torch.logit(rgb.clamp(0.02, 0.98)).to(bias) / SH_C0

    def before_step(self, step: int, progress: float) -> dict:
        self._step = step
        return {}

    def regularizer(self) -> Optional[torch.Tensor]:
        """The sparsity prior (see :attr:`NeRFSHFieldConfig.sparsity_weight`), or None."""
        cfg = self.config
        if cfg.sparsity_weight <= 0:
            return None
        sigma, _ = self.density(self.prior_points())
        return cfg.sparsity_weight * torch.log1p(2.0 * sigma ** 2).mean()

    def prior_points(self) -> torch.Tensor:
        """(sparsity_points, 3) uniform points of the bounds, a function of the seed and the
        step given to :meth:`before_step` only."""
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self._step)
        lo, hi = self.normalize.aabb[0], self.normalize.aabb[1]
        u = torch.rand(self.config.sparsity_points, 3, generator=g).to(lo.device)
        return lo + u * (hi - lo)

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        h = self.mlp(self.encoding(self.normalize(x)))
        sigma = trunc_exp(h[:, 0] + self.density_bias)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, h[:, 1:]

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return sh_color(feat, d)
