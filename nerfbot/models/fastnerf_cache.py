"""The baked FastNeRF cache as a renderer of its own (method ``fastnerf_cache``).

:class:`CachedField` holds the cache (sparse F_pos grid, F_dir grid, coarse occupancy) and
answers the :class:`~nerfbot.fields.base.Field` interface by plain-torch lookups, so meshing and
density queries work on a baked run. :class:`FastNeRFCacheModel` renders rays with the fused
numba kernel (:func:`nerfbot.kernels.fastnerf_cache.render`) on CPU, and with
:meth:`FastNeRFCacheModel.render_reference` (the torch twin) elsewhere. Every size derives from
the tensors' shapes, so a model built with empty tensors loads any baked checkpoint through
:func:`nerfbot.models.base.resize_like_state_dict`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import nn

from nerfbot.fields.base import BoxNormalizer, Field
from nerfbot.fields.fastnerf import combine_components
from nerfbot.kernels import fastnerf_cache as _kc
from nerfbot.kernels import use_kernels
from nerfbot.models.base import Model
from nerfbot.ops.block_render import ScratchArrays, render_blocks
from nerfbot.ops.cameras import Rays
from nerfbot.ops.octahedral import octahedral_lookup
from nerfbot.ops.rendering import RenderOutput, composite
from nerfbot.ops.sampling import march_reference, ray_aabb

#: Scratch room per ray of the fused renderer, shared by the rays of a block (most rays hold far
#: fewer samples; many none). A block whose rays need more is rendered again with exact room.
SLOT_SAMPLES = 32
#: dtypes of the renderer's per-sample scratch arrays (:func:`nerfbot.kernels.fastnerf_cache.render`).
_SCRATCH_KINDS = (np.float32,) * 4 + (np.int32,) + (np.float32,) * 3


@dataclass
class FastNeRFCacheConfig:
    np: int = 192
    """Position-cache cells per axis (as baked; the stored tensors' shapes are what count). On
    the 128x128 tabletop 192 kept the source's PSNR better than 256 (-0.31 vs -0.40 dB) with
    half the memory (80 vs 151 MB) and 1.4x faster renders; 128 lost 1.7 dB."""
    nd: int = 128
    """Direction-cache vertices per axis of the octahedral map (as baked)."""
    render_steps: int = 256
    """Marching steps along the cube's diagonal (the source run's, by default)."""
    cone_angle: float = 0.0
    """Steps grow as t * cone_angle, clamped to [dt_min, 8 dt_min] (0: constant steps)."""
    early_stop_transmittance: float = 1e-2
    """A ray stops once its transmittance falls below this: 1e-2, as the PlenOctrees paper's
    renderer (volrend's ``stop_thresh``). On the tabletop the PSNR moved by -0.01 dB from 1e-3."""
    color_min_weight: float = 1e-2
    """Samples of at most this weight take their ray's mean colour instead of reading the
    cache's colour table (the fused renderer's; 0: every sample reads it). On the tabletop
    1e-2 renders 1.3x faster than 0, and 0.08 dB better: the faint samples in front of
    surfaces are the least trained ones."""


class CachedField(Field):
    """Density and colour read from the FastNeRF cache (trilinear in space, bilinear in
    direction over an octahedral map). Static: ``cond`` is ignored.

    Buffers (all sizes from shapes; layout in :mod:`nerfbot.kernels.fastnerf_cache`):
    ``bricks`` (NB, NB, NB) int32 brick ids or -1; ``density_codes`` (n_bricks, B+1, B+1, B+1)
    int16 raw-density codes and ``color_codes`` (n_bricks, B+1, B+1, B+1, 3D) uint8 component
    codes, with per-channel ``scale`` / ``offset`` (1 + 3D,) (channel 0: the density);
    ``occupancy`` (G, G, G) uint8 coarse cells for empty-space skipping; ``dir_weights``
    (ND, ND, D) float32. A point has zero density unless it lies in the scene bounds and in a
    stored brick.
    """

    def __init__(self, aabb):
        super().__init__()
        self.normalize = BoxNormalizer(aabb)
        self.register_buffer("bricks", torch.zeros(0, 0, 0, dtype=torch.int32))
        self.register_buffer("density_codes", torch.zeros(0, 0, 0, 0, dtype=torch.int16))
        self.register_buffer("color_codes", torch.zeros(0, 0, 0, 0, 0, dtype=torch.uint8))
        self.register_buffer("scale", torch.zeros(0))
        self.register_buffer("offset", torch.zeros(0))
        self.register_buffer("occupancy", torch.zeros(0, 0, 0, dtype=torch.uint8))
        self.register_buffer("dir_weights", torch.zeros(0, 0, 0))

    def set_cache(self, bricks, density, colors, scale, offset, occupancy, dir_weights) -> None:
        """Install baked tensors (shapes and dtypes as in the class docstring)."""
        nb, d, v1 = bricks.shape[0], dir_weights.shape[-1], _kc.BRICK + 1
        n = density.shape[0]
        if bricks.shape != (nb,) * 3 or density.shape != (n, v1, v1, v1) \
                or colors.shape != (n, v1, v1, v1, 3 * d) or scale.shape != (1 + 3 * d,) \
                or offset.shape != scale.shape:
            raise ValueError(f"inconsistent cache shapes: bricks {tuple(bricks.shape)}, density "
                             f"{tuple(density.shape)}, colors {tuple(colors.shape)}, scale "
                             f"{tuple(scale.shape)}, dir_weights {tuple(dir_weights.shape)}")
        if density.dtype != torch.int16 or colors.dtype != torch.uint8:
            raise ValueError(f"cache codes must be int16 (density) and uint8 (colors), got "
                             f"{density.dtype} and {colors.dtype}")
        self.bricks = bricks.to(torch.int32).contiguous()
        self.density_codes = density.contiguous()
        self.color_codes = colors.contiguous()
        self.scale = scale.float().contiguous()
        self.offset = offset.float().contiguous()
        self.occupancy = occupancy.to(torch.uint8).contiguous()
        self.dir_weights = dir_weights.float().contiguous()

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "values" in state_dict:
            raise ValueError(
                "this FastNeRF cache was baked by an older nerfbot (one int16 table, 'values'; "
                "now 16-bit densities and 8-bit colours): bake it again from its source run, "
                "`nerfbot bake SOURCE_RUN --cache NP,ND --out DIR`")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def empty(self) -> bool:
        return (self.bricks.shape[0] < 1 or self.density_codes.shape[0] == 0
                or self.density_codes.shape[1] < 2 or self.dir_weights.shape[0] < 2
                or self.occupancy.shape[0] < 1)

    @property
    def brick_size(self) -> int:
        """B, cells per brick edge."""
        return int(self.density_codes.shape[1]) - 1

    @property
    def cells_per_axis(self) -> int:
        """NC = NB * B."""
        return int(self.bricks.shape[0]) * self.brick_size

    @property
    def components(self) -> int:
        return int(self.dir_weights.shape[-1])

    def cache_bytes(self) -> int:
        """Memory of the cache tensors in bytes."""
        return sum(t.numel() * t.element_size() for t in
                   (self.bricks, self.density_codes, self.color_codes, self.scale, self.offset,
                    self.occupancy, self.dir_weights))

    # -- lookups (the torch twin of the kernel's) ----------------------------------------------
    def lookup(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x: (N, 3) world points -> raw density (N,) (<= 15), components u (N, 3D) and valid
        (N,) bool: inside the bounds and in a stored brick."""
        n = x.shape[0]
        d = self.components
        if self.empty:
            return (torch.full((n,), -math.inf, device=x.device),
                    torch.zeros(n, 3 * d, device=x.device),
                    torch.zeros(n, dtype=torch.bool, device=x.device))
        bs, nc = self.brick_size, self.cells_per_axis
        v1 = bs + 1
        f = (x.double() - self.normalize.cube_min.double()) * (nc / float(self.normalize.cube_size))
        i = torch.floor(f).long().clamp(0, nc - 1)
        w = (f - i).clamp(0.0, 1.0).float()
        b = torch.div(i, bs, rounding_mode="floor")
        a = i - b * bs
        bid = self.bricks[b[:, 0], b[:, 1], b[:, 2]].long()
        valid = (bid >= 0) & self.normalize.inside(x.float())
        codes = torch.cat([self.density_codes.reshape(-1, 1).float(),
                           self.color_codes.reshape(-1, 3 * d).float()], 1)
        base = ((bid.clamp_min(0) * v1 + a[:, 0]) * v1 + a[:, 1]) * v1 + a[:, 2]
        acc = torch.zeros(n, codes.shape[1], device=x.device)
        for c in range(8):
            bits = [(c >> 2) & 1, (c >> 1) & 1, c & 1]
            wc = torch.ones(n, device=x.device)
            for k in range(3):
                wc = wc * (w[:, k] if bits[k] else 1.0 - w[:, k])
            row = base + bits[0] * v1 * v1 + bits[1] * v1 + bits[2]
            acc = acc + wc[:, None] * codes[row]
        deq = acc * self.scale + self.offset
        return deq[:, 0].clamp_max(_kc.RAW_MAX), deq[:, 1:], valid

    def direction_weights(self, d: torch.Tensor) -> torch.Tensor:
        """d: (N, 3) unit directions -> beta (N, D), bilinear on the octahedral grid."""
        return octahedral_lookup(self.dir_weights, d)

    # -- Field interface -----------------------------------------------------------------------
    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        raw, u, valid = self.lookup(x)
        sigma = torch.where(valid, torch.exp(raw), torch.zeros_like(raw))
        return sigma, u

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        if self.empty:
            return torch.full((d.shape[0], 3), 0.5, device=d.device)
        return combine_components(self.direction_weights(d), feat)

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """A baked cache is not trained."""

    def param_groups(self) -> list[dict]:
        return []


class FastNeRFCacheModel(Model):
    """Renders a baked FastNeRF cache (eval only; see the module docstring)."""

    def __init__(self, aabb, background: nn.Module, config: FastNeRFCacheConfig | None = None):
        super().__init__()
        self._derived, self._derived_key = None, None
        self.config = cfg = config or FastNeRFCacheConfig()
        if cfg.render_steps < 1:
            raise ValueError(f"render_steps must be >= 1, got {cfg.render_steps}")
        if cfg.cone_angle < 0:
            raise ValueError(f"cone_angle must be >= 0, got {cfg.cone_angle}")
        if not 0.0 <= cfg.early_stop_transmittance < 1.0:
            raise ValueError("early_stop_transmittance must be in [0, 1), got "
                             f"{cfg.early_stop_transmittance}")
        if not 0.0 <= cfg.color_min_weight < 1.0:
            raise ValueError(f"color_min_weight must be in [0, 1), got {cfg.color_min_weight}")
        self.field = CachedField(aabb)
        self.background = background
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).clone())
        self.dt_min = float(self.field.normalize.cube_size) * math.sqrt(3.0) / cfg.render_steps
        self.dt_max = 8.0 * self.dt_min if cfg.cone_angle > 0 else self.dt_min
        self._scratch = ScratchArrays(_SCRATCH_KINDS)

    # -- not trainable -------------------------------------------------------------------------
    def _no_training(self):
        raise RuntimeError("fastnerf_cache is a baked renderer and cannot be trained: train "
                           "'fastnerf' and run `nerfbot bake RUN --cache NP,ND`")

    def rays_for_next_batch(self, last_samples, n_rays):
        self._no_training()

    def loss(self, rays, target_rgb, generator=None, cond=None, rays_per_pixel=1,
             pixel_weights=None):
        self._no_training()

    # -- rendering -----------------------------------------------------------------------------
    def render_rays(self, rays: Rays, generator=None, cond=None) -> RenderOutput:
        """Eval mode only: the fused numba renderer on CPU, the torch twin on other devices."""
        if self.training:
            self._no_training()
        if use_kernels(rays.origins, dtype=None):
            return self.render_fused(rays)
        return self.render_reference(rays)

    def _box(self, rays: Rays):
        t_near, t_far, _ = ray_aabb(rays.origins, rays.directions, self.aabb)
        return t_near, t_far

    @torch.no_grad()
    def render_reference(self, rays: Rays) -> RenderOutput:
        """Plain torch: march the coarse occupancy (:func:`~nerfbot.ops.sampling.march_reference`,
        same step rule as the kernel), look samples up through :class:`CachedField` and
        :func:`~nerfbot.ops.rendering.composite` them all (no early termination)."""
        n = len(rays)
        t_near, t_far = self._box(rays)
        bg = self.background(rays.directions)
        f = self.field
        if f.empty:
            zeros = torch.zeros(0, device=t_near.device)
            return composite(zeros, torch.zeros(0, 3, device=t_near.device), zeros, zeros,
                             torch.zeros(0, dtype=torch.long, device=t_near.device), n, bg, t_far,
                             rays.z_per_t)
        cell = float(f.normalize.cube_size) / f.occupancy.shape[0]
        s = march_reference(rays.origins, rays.directions, t_near, t_far, f.occupancy,
                            f.normalize.cube_min, cell, self.dt_min, self.dt_max,
                            self.config.cone_angle)
        t_mid = 0.5 * (s.t_starts.double() + s.t_ends.double())
        o, d = rays.origins[s.ray_indices].double(), rays.directions[s.ray_indices]
        sigma, u = f.density(o + d.double() * t_mid[:, None])
        rgb = f.color(u, d)
        return composite(sigma, rgb, s.t_starts, s.t_ends, s.ray_indices, n, bg, t_far,
                         rays.z_per_t)

    def _kernel_cache(self) -> tuple:
        """The cache as the kernel's arrays, after the box around the occupied cells and the
        distance to them (both derived once per cache)."""
        f = self.field
        cmin = f.normalize.cube_min.double().numpy()
        if f.empty:  # a degenerate cache: every ray sees the background
            return (np.stack([cmin, cmin]), np.full((1, 1, 1), -1, np.int32), 0,
                    np.zeros(0, np.int16), np.zeros((0, 0), np.uint8), np.zeros(1, np.float32),
                    np.zeros(1, np.float32), np.full((1, 1, 1), _kc.DISTANCE_CAP, np.uint8),
                    np.zeros((2, 2, 0), np.float32))
        key = (f.occupancy.data_ptr(), f.occupancy.shape, f.occupancy._version)
        if self._derived_key != key:
            occ = f.occupancy.numpy()
            self._derived = (_kc.occupied_box(occ, cmin, float(f.normalize.cube_size)),
                             _kc.empty_distance(occ))
            self._derived_key = key
        box, dist = self._derived
        colors = f.color_codes.numpy()
        return (box, f.bricks.numpy(), int(f.density_codes.shape[0]),
                f.density_codes.numpy().reshape(-1), colors.reshape(-1, colors.shape[-1]),
                f.scale.numpy(), f.offset.numpy(), dist, f.dir_weights.numpy())

    @torch.no_grad()
    def render_fused(self, rays: Rays) -> RenderOutput:
        """The numba renderer (:func:`nerfbot.kernels.fastnerf_cache.render`) on CPU rays; the
        background is read from its baked table
        (:meth:`~nerfbot.models.base.Model.baked_background`) once per batch and passed in."""
        n = len(rays)
        if n == 0:
            return self.render_reference(rays)
        f = self.field
        bg = self.baked_background(rays.directions)
        o = rays.origins.float().contiguous().numpy()
        d = rays.directions.float().contiguous().numpy()
        box, *cache = self._kernel_cache()
        params = (f.normalize.cube_min.double().numpy(), float(f.normalize.cube_size),
                  self.dt_min, self.dt_max, float(self.config.cone_angle),
                  float(self.config.early_stop_transmittance), float(self.config.color_min_weight))
        aabb = self.aabb.double().numpy()

        def run(sel, block_cap, scratch):
            m = n if sel is None else len(sel)
            out = (np.empty((m, 3), np.float32), np.empty(m, np.float32),
                   np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, np.int64),
                   np.empty(m, np.int64))
            pick = (lambda a: a) if sel is None else (lambda a: np.ascontiguousarray(a[sel]))
            _kc.render(pick(o), pick(d), aabb, box, pick(bg), *cache, *params, block_cap, *out,
                       *scratch)
            return out

        return render_blocks(run, n, _kc.RAY_BLOCK, SLOT_SAMPLES, self._scratch, rays.z_per_t)
