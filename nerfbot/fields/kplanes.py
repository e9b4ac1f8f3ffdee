"""A dynamic scene as what stays plus what moves: an Instant-NGP field of the static scene and
K-Planes space-time planes of the moving content, added as densities.

    sigma(x, t) = sigma_s(x) + sigma_d(x, t)
    colour      = colour MLP of (sigma_s g_s(x) + sigma_d g_d(x, t)) / sigma, and the view

The static part is the ngp field (hash grid, density MLP, colour MLP). The moving part is a
factorised space-time encoding (K-Planes / HexPlane, Fridovich-Keil et al. 2023: the xy, xz, yz
and xt, yt, zt planes multiplied per level) and a small MLP giving a density and geometry
features, which share the static colour MLP. A small object at (x(t), y(t), z(t)) is a product
of three time planes each peaked at one coordinate, so the planes hold fast motion at frame
resolution, where a deformation of a canonical scene (``dnerf``) has to carry each object
across the scene and a time input (``tnerf``) has to be decoded by an MLP. The moving part
starts transparent and its time planes at 1 (the K-Planes initialisation). Being as able as the
static part to hold a time-constant surface, it takes much of the table while the static part
keeps time-averaged smears of the moving objects (``docs/benchmarks/kplanes_parts.py`` shows
both parts); ``dynamic_warmup`` trains the static part alone first, which separates them.

Densities add (as in D^2-NeRF's static / dynamic decomposition), so one march over one
occupancy grid renders both; the grid counts a cell occupied when the static part or the moving
part at any of a few random times is dense there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.base import Field, mlp, trunc_exp
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.ops.encodings import PlaneEncoding


@dataclass
class KPlanesFieldConfig:
    planes_levels: int = 2
    """Resolution levels of the space-time planes (each coarser level halves both axes)."""
    planes_features: int = 8
    """Features per plane and level (a product of planes holds about one moving thing per
    feature)."""
    planes_spatial_res: int = 128
    """Cells per spatial axis of the finest level."""
    planes_time_res: int = 100
    """Cells along time of the finest level (about one per captured time step resolves fast
    motion; the time-smoothness term fills steps that were not captured)."""
    dynamic_hidden: int = 64
    """Width of the moving part's density MLP (one hidden layer)."""
    dynamic_initial_transmittance: float = 0.9
    """Transmittance of a ray crossing the whole cube through the moving part alone at
    initialisation (close to 1: it starts transparent)."""
    planes_tv_weight: float = 1e-4
    """Weight of the total variation of the spatial planes."""
    planes_time_smoothness_weight: float = 1e-3
    """Weight of the squared second differences along time of the time planes."""
    dynamic_sparsity_weight: float = 0.0
    """Weight of the moving part's mean opacity over a finest plane cell, at the training
    samples, to keep out of it what the static part can explain and the floaters few views
    of a time step allow. Off: 0.01 did not help on the dynamic scene (BENCHMARKS.md,
    section 4)."""
    occupancy_times: int = 4
    """Random times per point at which the moving part is evaluated for an occupancy update
    (the maximum counts)."""
    dynamic_warmup: float = 0.0
    """Fraction of the training budget during which only the static part trains (the moving
    part is off), so that what never changes is the static part's before the moving part can
    take it. The occupancy grid prunes nothing until half as long again after it, while the
    moving part grows where the static part left space empty. Off by default: 0.2 separates
    the parts and places the moving objects better on the 12-camera capture, but its object
    PSNR is about even there and lower on the monocular capture and the tests' toy rollout
    (BENCHMARKS.md, section 4)."""

    def __post_init__(self):
        for name in ("planes_levels", "planes_features", "planes_spatial_res", "planes_time_res",
                     "dynamic_hidden", "occupancy_times"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not 0.0 < self.dynamic_initial_transmittance < 1.0:
            raise ValueError(f"dynamic_initial_transmittance must be in (0, 1), got "
                             f"{self.dynamic_initial_transmittance}")
        if not 0.0 <= self.dynamic_warmup < 1.0:
            raise ValueError(f"dynamic_warmup must be in [0, 1), got {self.dynamic_warmup}")
        for name in ("planes_tv_weight", "planes_time_smoothness_weight",
                     "dynamic_sparsity_weight"):
            if not 0.0 <= getattr(self, name) < math.inf:
                raise ValueError(f"{name} must be >= 0 and finite, got {getattr(self, name)}")


class KPlanesField(Field):
    """Static ngp field + space-time planes; ``cond`` (N, 1) time in [0, 1] (None: t = 0)."""

    def __init__(self, aabb, conditioning: Conditioning, config: NGPFieldConfig | None = None,
                 kconfig: KPlanesFieldConfig | None = None, seed: int = 0):
        super().__init__()
        if conditioning.kind != "time":
            raise ValueError("kplanes needs a time-conditioned capture (frames with 'time', e.g. "
                             "`nerfbot capture --scene dynamic`)")
        self.conditioning = conditioning
        self.kconfig = kc = kconfig or KPlanesFieldConfig()
        self.static = NGPField(aabb, config, seed=seed)
        levels = kc.planes_levels
        spatial = [max(2, kc.planes_spatial_res >> (levels - 1 - lvl)) for lvl in range(levels)]
        temporal = [max(1, kc.planes_time_res >> (levels - 1 - lvl)) for lvl in range(levels)]
        self.planes = PlaneEncoding(4, levels, kc.planes_features, spatial, temporal,
                                    init="kplanes", seed=seed + 1)
        self.geo_feat_dim = self.static.config.geo_feat_dim
        self.dynamic_mlp = mlp(self.planes.out_dim, kc.dynamic_hidden, 1, 1 + self.geo_feat_dim)
        diagonal = math.sqrt(3.0) * self.static.normalize.extent
        self.dynamic_bias = math.log(-math.log(kc.dynamic_initial_transmittance) / diagonal)
        #: edge of a finest plane cell, metres (the length of the sparsity term's opacity)
        self.cell = self.static.normalize.extent / kc.planes_spatial_res
        self._opacity: Optional[torch.Tensor] = None
        #: False during the static warm-up (:attr:`KPlanesFieldConfig.dynamic_warmup`)
        self._dynamic_on = True
        self._prunable = True

    def _time(self, cond: Optional[torch.Tensor], n: int, like: torch.Tensor) -> torch.Tensor:
        return like.new_zeros(n, 1) if cond is None else cond[:, :1].to(like.dtype)

    def dynamic_density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """The moving part alone: x (N, 3) metres, ``cond`` (N, 1) times -> sigma_d (N,) in
        1/m, geometry features (N, geo_feat_dim)."""
        if not self._dynamic_on:
            return x.new_zeros(x.shape[0]), x.new_zeros(x.shape[0], self.geo_feat_dim)
        t = self._time(cond, x.shape[0], x)
        xn = self.static.normalize(x)
        h = self.dynamic_mlp(self.planes(torch.cat([xn, t], -1)))
        sigma = trunc_exp(h[:, 0] + self.dynamic_bias)
        sigma = torch.where(self.static.normalize.inside(x), sigma, torch.zeros_like(sigma))
        if self.kconfig.dynamic_sparsity_weight > 0 and self.training and torch.is_grad_enabled():
            # a training render: kept for the loss
            self._opacity = (1.0 - torch.exp(-sigma * self.cell)).mean()
        return sigma, h[:, 1:]

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        sigma_s, geo_s = self.static.density(x)
        sigma_d, geo_d = self.dynamic_density(x, cond)
        sigma = sigma_s + sigma_d
        share = (sigma_d / sigma.clamp_min(1e-10))[:, None]  # 0 where both are empty
        return sigma, geo_s + share * (geo_d - geo_s)

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return self.static.color(feat, d)

    def occupancy_density(self, x, generator=None):
        moving = x.new_zeros(x.shape[0])
        for _ in range(self.kconfig.occupancy_times):
            t = self.conditioning.sample(x.shape[0], generator, x.device)
            moving = torch.maximum(moving, self.dynamic_density(x, t)[0])
        return self.static.density(x)[0] + moving

    def before_step(self, step: int, progress: float) -> dict:
        warmup = self.kconfig.dynamic_warmup
        self._dynamic_on = progress >= warmup
        self._prunable = warmup == 0.0 or progress >= 1.5 * warmup
        return self.static.before_step(step, progress)

    def prunable(self) -> bool:
        return self._prunable

    def regularizer(self) -> Optional[torch.Tensor]:
        kc = self.kconfig
        reg = (kc.planes_tv_weight * self.planes.tv_loss()
               + kc.planes_time_smoothness_weight * self.planes.smoothness_loss())
        if self._opacity is not None:  # the moving part's opacity at the last render's samples
            reg = reg + kc.dynamic_sparsity_weight * self._opacity
            self._opacity = None
        return reg

    def color_head(self):
        return self.static.color_head()

    def param_groups(self) -> list[dict]:
        groups = self.static.param_groups()
        return groups + [{"params": [self.planes.table], "lr_scale": 1.0},
                         {"params": list(self.dynamic_mlp.parameters()),
                          "lr_scale": self.static.config.mlp_lr_scale}]
