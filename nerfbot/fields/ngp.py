"""Instant-NGP field: multiresolution hash encoding + tiny density and colour MLPs."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from nerfbot.fields.base import (BoxNormalizer, ContractedNormalizer, Field, mlp, run_mlp,
                                 trunc_exp)
from nerfbot.ops.encodings import HashGridConfig, SHEncoding


@dataclass
class NGPFieldConfig(HashGridConfig):
    hidden: int = 64
    """Width of the density and colour MLPs."""
    geo_feat_dim: int = 15
    """Geometry features passed from the density MLP to the colour MLP."""
    color_layers: int = 2
    """Hidden layers of the colour MLP."""
    sh_degree: int = 4
    """Spherical-harmonics degree of the view-direction encoding (0 = view-independent)."""
    sh_warmup: float = 0.0
    """Fraction of the training budget over which view dependence is brought in, one SH band
    after another (as 3D Gaussian Splatting adds bands during training): band l >= 1 fades in
    with a cosine ramp over the l-th of ``sh_degree`` equal parts of the warm-up, and the colour
    MLP's weights on those bands start at zero. Early in training, view-dependent colour can
    explain away wrong geometry (the shape-radiance ambiguity) and slows short budgets down.
    0: every band from the start."""
    initial_transmittance: float = 0.2
    """Transmittance at initialisation along ``initial_transmittance_path``. Sets a density
    bias so the scene starts nearly empty and a learned background explains what it can (sky)
    before density grows; with a fixed bias, a large box starts as fog that learns to fake the
    sky."""
    initial_transmittance_path: str = "diagonal"
    """What ``initial_transmittance`` is measured along: "diagonal", the diagonal of the cube
    enclosing the bounds; "rays", the training rays' median path through the bounds (measured
    from the data before the first step, :meth:`NGPField.init_ray_length`). Bounds shaped as a
    slab (a bench top or a tray seen from above) are crossed over a few percent of their cube's
    diagonal, so a start set along the diagonal leaves every ray about 90 % transparent, and
    the learned background fits the images before any surface forms (``bins:2``: about 19.5 dB
    for 300 steps). With the contraction the path is the rays' path through the bounds
    themselves, where density is per metre. A field trained outside the trainer, which never
    measures the rays, starts along the diagonal."""
    mlp_lr_scale: float = 1.0
    """Learning rate of the MLPs relative to the hash table's."""
    footprint_scale: float = 0.0
    """Anti-aliasing by the sample's footprint (Zip-NeRF's feature down-weighting), s >= 0: the
    features of a level of n cells per axis are weighted by ``erf(1 / sqrt(8 (s r n)^2))``, r
    the radius of the pixel's cone at the sample in the grid's unit cube, so levels finer than a
    pixel fade out: a far view of fine texture fits its average on the coarse levels and leaves
    the fine ones to the near views. 0: point samples, every level at full weight (Instant-NGP);
    density queries at points (maps, meshes) always see every level."""
    level_warmup: float = 0.0
    """Coarse to fine (as BARF and Neuralangelo anneal their encodings): over the first
    ``level_warmup`` of the training budget the hash levels fade in one after another, the
    ``level_warmup_first`` coarsest ones from the start, each later level l weighted
    0.5 (1 - cos(pi r)), r = clamp(a - l, 0, 1), a rising linearly from
    ``level_warmup_first`` to L. Without fine levels a surface can only fit the images where
    the views agree on it, so weakly textured surfaces (a plain bench top) take their depth
    from the coarse levels before the fine ones paint detail. 0: every level from the start
    (Instant-NGP)."""
    level_warmup_first: int = 4
    """Hash levels at full weight from the start of ``level_warmup``."""
    mlp_precision: str = "fp32"
    """"bf16": the MLPs run under bfloat16 autocast (AMX / AVX-512 BF16 on CPU, tensor cores on
    GPU), their rows padded to a multiple of 2048 (:func:`~nerfbot.fields.base.run_mlp`),
    weights and Adam state float32; "fp32": plain float32. On a 2-core CPU with AMX, bf16's
    matmuls are 4-5x faster, but a whole step gains 6-8 % (section 7 of BENCHMARKS.md), so fp32
    is the default."""


class NGPField(Field):
    """sigma = trunc_exp(MLP_d(hash(x))[0] + bias); rgb = sigmoid(MLP_c(MLP_d(hash(x))[1:], SH(d))).

    Points outside the scene bounds have zero density; with ``contract`` the hash grid covers
    all of space through the scene contraction around the bounds' cube
    (:class:`~nerfbot.fields.base.ContractedNormalizer`).
    """

    def __init__(self, aabb, config: NGPFieldConfig | None = None, seed: int = 0,
                 contract: bool = False):
        super().__init__()
        self.config = cfg = config or NGPFieldConfig()
        self.normalize = ContractedNormalizer(aabb) if contract else BoxNormalizer(aabb)
        self.encoding = cfg.hash_encoding(seed)
        self.density_mlp = mlp(self.encoding.out_dim, cfg.hidden, 1, 1 + cfg.geo_feat_dim)
        self.dir_encoding = SHEncoding(cfg.sh_degree)
        self.color_mlp = mlp(cfg.geo_feat_dim + self.dir_encoding.out_dim, cfg.hidden,
                             cfg.color_layers, 3)
        if not 0.0 <= cfg.sh_warmup < 1.0:
            raise ValueError(f"sh_warmup must be in [0, 1), got {cfg.sh_warmup}")
        #: (out_dim,) weights of the direction encoding's components during the SH warm-up
        #: (None: all 1; not saved: :meth:`before_step` derives it from the training progress)
        self._sh_weights: Optional[torch.Tensor] = None
        if cfg.sh_warmup > 0 and cfg.sh_degree > 0:
            with torch.no_grad():
                self.color_mlp[0].weight[:, cfg.geo_feat_dim + 1:] = 0.0

        if not 0.0 < cfg.initial_transmittance < 1.0:
            raise ValueError(f"initial_transmittance must be in (0, 1), got {cfg.initial_transmittance}")
        if cfg.initial_transmittance_path not in ("diagonal", "rays"):
            raise ValueError(f"initial_transmittance_path must be 'diagonal' or 'rays', got "
                             f"{cfg.initial_transmittance_path!r}")
        diagonal = math.sqrt(3.0) * self.normalize.extent
        self.density_bias = math.log(-math.log(cfg.initial_transmittance) / diagonal)
        #: log(diagonal / path) added to the density MLP's output bias by init_ray_length
        self._path_shift = 0.0
        if cfg.footprint_scale < 0:
            raise ValueError(f"footprint_scale must be >= 0, got {cfg.footprint_scale}")
        if not 0.0 <= cfg.level_warmup < 1.0:
            raise ValueError(f"level_warmup must be in [0, 1), got {cfg.level_warmup}")
        if not 1 <= cfg.level_warmup_first <= cfg.n_levels:
            raise ValueError(f"level_warmup_first must be 1 to n_levels ({cfg.n_levels}), got "
                             f"{cfg.level_warmup_first}")
        #: (L * F,) weights of the hash features during the level warm-up (None: all 1; not
        #: saved: :meth:`before_step` derives it from the training progress)
        self._level_feature_weights: Optional[torch.Tensor] = None
        if cfg.mlp_precision not in ("bf16", "fp32"):
            raise ValueError(f"mlp_precision must be 'bf16' or 'fp32', got {cfg.mlp_precision!r}")

    def color_head(self):
        return self.color_mlp[-1]

    def init_ray_length(self, length_m: float) -> None:
        """With ``initial_transmittance_path="rays"``: start with ``initial_transmittance``
        along ``length_m`` metres instead of the cube's diagonal (the contracted cube's, with
        the contraction), by shifting the density MLP's output bias by log(diagonal /
        length_m); the shift is a parameter, so a checkpoint keeps it. Calling again replaces
        the earlier shift."""
        if self.config.initial_transmittance_path != "rays":
            return
        if not (math.isfinite(length_m) and length_m > 0):
            raise ValueError(f"ray length must be a positive number of metres, got {length_m}")
        shift = math.log(math.sqrt(3.0) * self.normalize.extent / length_m)
        with torch.no_grad():
            self.density_mlp[-1].bias[0] += shift - self._path_shift
        self._path_shift = shift

    def param_groups(self) -> list[dict]:
        """The hash table at the method's learning rate, the MLPs at ``mlp_lr_scale`` of it.

        Adam rescales every gradient to a step of about the learning rate. Where density has
        collapsed (early in a large box, where a transparent field is the best uniform fit to a
        sky), the colour MLP still gets tiny but consistent gradients, and full-size steps in
        every layer make its outputs grow multiplicatively until the sigmoid saturates and colour
        stops learning. A smaller MLP rate keeps that drift slow."""
        mlps = [p for n, p in self.named_parameters() if not n.startswith("encoding.")]
        return [{"params": [self.encoding.table], "lr_scale": 1.0},
                {"params": mlps, "lr_scale": self.config.mlp_lr_scale}]

    @property
    def uses_footprint(self) -> bool:
        return self.config.footprint_scale > 0

    def level_weights(self, x: torch.Tensor, radius: torch.Tensor) -> torch.Tensor:
        """(N, L) weights of the hash levels' features for samples at x (N, 3) of cone radius
        ``radius`` (N,) metres (:attr:`NGPFieldConfig.footprint_scale`); 1 at radius 0."""
        r = self.config.footprint_scale * radius * self.normalize.unit_scale(x)
        scaled = r[:, None] * self.encoding.res.to(r.dtype)[None, :]
        return torch.erf(torch.rsqrt((8.0 * scaled.square()).clamp_min(1e-12)))

    def _encode(self, x: torch.Tensor, radius: Optional[torch.Tensor]) -> torch.Tensor:
        """(N, L * F) hash features of world points x (N, 3), down-weighted by the footprint
        when ``radius`` (N,) is given and :attr:`uses_footprint`."""
        enc = self.encoding(self.normalize(x))
        if self._level_feature_weights is not None:
            enc = enc * self._level_feature_weights.to(enc)
        if radius is None or not self.uses_footprint:
            return enc
        w = self.level_weights(x, radius.to(enc.dtype))
        return enc * w.repeat_interleave(self.encoding.n_features, dim=1)

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return self.density_at_scale(x, None, cond)

    def density_at_scale(self, x: torch.Tensor, radius: Optional[torch.Tensor],
                         cond: Optional[torch.Tensor] = None):
        h = run_mlp(self.density_mlp, self._encode(x, radius), self.config.mlp_precision)
        sigma = trunc_exp(h[:, 0] + self.density_bias)
        if self.normalize.contracted:
            sigma = sigma * self.normalize.density_scale(x)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, h[:, 1:]

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        sh = self.dir_encoding(d)
        if self._sh_weights is not None:
            sh = sh * self._sh_weights.to(sh.device)
        return torch.sigmoid(run_mlp(self.color_mlp, torch.cat([feat, sh], -1),
                                     self.config.mlp_precision))

    def before_step(self, step: int, progress: float) -> dict:
        """During the SH warm-up (:attr:`NGPFieldConfig.sh_warmup`), weigh band l >= 1 by
        0.5 (1 - cos(pi r)), r = clamp(progress / warmup * degree - (l - 1), 0, 1); during
        the level warm-up (:attr:`NGPFieldConfig.level_warmup`), weigh the hash levels."""
        cfg = self.config
        self._sh_weights = sh_band_weights(cfg.sh_degree, cfg.sh_warmup, progress)
        levels = hash_level_weights(cfg.n_levels, cfg.level_warmup_first, cfg.level_warmup,
                                    progress)
        self._level_feature_weights = (None if levels is None
                                       else levels.repeat_interleave(cfg.n_features))
        return {}


def hash_level_weights(n_levels: int, first: int, warmup: float,
                       progress: float) -> Optional[torch.Tensor]:
    """(n_levels,) weights of the hash levels at ``progress`` in [0, 1] of training: levels
    below ``first`` at 1, level l >= first at 0.5 (1 - cos(pi r)), r = clamp(a - l, 0, 1) with
    a = first + (n_levels - first) progress / warmup; None once every level is fully in (or
    without a warm-up)."""
    if warmup <= 0 or first >= n_levels or progress >= warmup:
        return None
    a = first + (n_levels - first) * progress / warmup
    ramp = (a - torch.arange(n_levels, dtype=torch.float64)).clamp(0.0, 1.0)
    return (0.5 * (1.0 - torch.cos(math.pi * ramp))).float()


def sh_band_weights(degree: int, warmup: float, progress: float) -> Optional[torch.Tensor]:
    """((degree + 1)^2,) weights of the SH components at ``progress`` in [0, 1] of training
    (component k is in band floor(sqrt(k))); None once every band is fully in (or without a
    warm-up)."""
    if warmup <= 0 or degree == 0 or progress >= warmup:
        return None
    band = torch.arange(degree + 1, dtype=torch.float64)
    ramp = (progress / warmup * degree - (band - 1)).clamp(0.0, 1.0)
    per_band = 0.5 * (1.0 - torch.cos(math.pi * ramp))
    per_band[0] = 1.0
    return per_band.repeat_interleave(2 * band.long() + 1).float()
