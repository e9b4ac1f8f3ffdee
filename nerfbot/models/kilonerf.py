"""KiloNeRF's renderer (Reiser et al. 2021) around :class:`~nerfbot.fields.kilonerf.KiloNeRFField`:
occupancy-grid marching with one fused pass over the tiny networks, and training in two phases
inside the normal trainer: distillation from a trained teacher run (any method), then
photometric fine-tuning; see :class:`KiloNeRFModel`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.kilonerf import FUSED_SLOT_SAMPLES, PARAMETER_NAMES, KiloNeRFField, Layout
from nerfbot.kernels import kilonerf as _kk
from nerfbot.kernels import use_kernels
from nerfbot.models.occupancy import OccupancyModel, OccupancyModelConfig
from nerfbot.ops.block_render import ScratchArrays, render_blocks
from nerfbot.ops.rendering import RenderOutput, ray_starts
from nerfbot.ops.sampling import OccupancyGrid, ray_aabb


@dataclass
class KiloNeRFConfig:
    """Options of :class:`KiloNeRFModel`: distillation and rendering."""

    teacher_run: str = ""
    """Folder of a trained run of any method to distill from (loaded only while it is needed,
    frozen, never saved in checkpoints). Empty: train from scratch on the images."""
    distill_fraction: float = 0.5
    """Fraction of the training budget spent distilling; the rest fine-tunes on the images."""
    distill_batch: int = 32768
    """Points per distillation step."""
    distill_uniform_fraction: float = 0.25
    """Share of distillation points drawn uniformly in the cells of the kept networks (teaching
    them the teacher's empty space); the rest lie in occupancy cells the teacher occupies."""
    distill_rays: int = 4096
    """Training rays drawn per distillation step; their directions are the view directions of
    the distillation points (directions the cameras see, not the whole sphere)."""
    render_min_weight: float = 1e-2
    """When rendering (eval mode), samples whose weight is at most this get no colour
    evaluation: they take the weight-averaged colour of their ray's other samples (their weight
    is kept, so opacity and depth are exact); 0 evaluates all. On the tabletop 1e-2 renders
    14% faster than 1e-4 for -0.05 dB."""
    render_precision: str = "fp32"
    """Precision of the one-pass renderer: "fp32" (the fused numba kernel,
    :meth:`KiloNeRFModel.render_fused`) or "bf16" (batched matmuls with float32 accumulation,
    bfloat16 inputs and outputs; colours change by ~1e-3). On this project's AMX-BF16 Xeon the
    fused kernel renders the tabletop 1.4x faster than either precision of the batched
    matmuls. "auto" (older runs' default) means "fp32". Training always runs in float32."""
    fused_render: bool = True
    """Render (eval mode, CPU) in one marching pass with the numba kernels (see
    :meth:`KiloNeRFModel.render_fast`); False: the generic rounds of :class:`OccupancyModel`."""


def _overlaps(grid: OccupancyGrid, other: OccupancyGrid) -> torch.Tensor:
    """(G^3,) bool: cells of ``grid`` that overlap an occupied cell of ``other`` (any resolution
    and placement), probed at each cell's centre and 8 corners pulled in slightly (exact when
    ``other`` is as coarse as ``grid`` or coarser)."""
    device = grid._cell_index.device
    probes = torch.tensor([[0.5, 0.5, 0.5]] + [[i, j, k] for i in (0.01, 0.99)
                                                for j in (0.01, 0.99) for k in (0.01, 0.99)],
                          device=device)
    g = other.resolution
    out = torch.zeros(grid._cell_index.shape[0], dtype=torch.bool, device=device)
    for p in probes:
        x = grid.cube_min + (grid._cell_index + p) * grid.cell_size
        ijk = torch.floor((x - other.cube_min) / other.cell_size).long()
        valid = ((ijk >= 0) & (ijk < g)).all(-1)
        ijk = ijk.clamp(0, g - 1)
        out |= valid & other.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]].bool()
    return out


def _kernel_buffer(rows: int, cols: int, dtype: torch.dtype) -> torch.Tensor:
    """An uninitialised (rows, cols) float32 or bfloat16 tensor for a kernel to fill."""
    return torch.empty(rows, cols, dtype=dtype)


def _as_kernel_array(t: torch.Tensor) -> np.ndarray:
    """The numpy view a kernel writes into: float32 as is, bfloat16 as its uint16 bits."""
    return t.view(torch.uint16).numpy() if t.dtype == torch.bfloat16 else t.numpy()


class _Holder:
    """Keeps a module out of the owner's module tree (no state_dict, no .to(), no parameters)."""

    def __init__(self):
        self.model = None


class KiloNeRFModel(OccupancyModel):
    """Occupancy-grid marching over a :class:`KiloNeRFField`, trained by distillation, then
    fine-tuning.

    With ``teacher_run`` set, the first :meth:`before_step` loads the teacher and, once per run
    (a buffer records it, so resumed runs skip it):

    * takes the teacher's occupancy at this model's grid resolution (a copy of its grid when it
      has one of the same shape, else its densities at random points of every cell against the
      grid's threshold);
    * keeps only the networks whose cell holds an occupied grid cell (empty space gets no
      network: it costs neither parameters nor optimiser state);
    * copies the teacher's background when it is of the same kind.

    While ``progress < distill_fraction`` the loss is the distillation loss (:meth:`distill_loss`;
    the batch's rays only lend their directions, and grid updates wait); afterwards it is the
    photometric loss of :class:`OccupancyModel`, with occupancy updates from the student's own
    densities. Depth supervision, if asked for, acts in that second phase only. Without a
    teacher the whole budget trains on the images from scratch (all G^3 networks).
    """

    def __init__(self, field: KiloNeRFField, background: nn.Module, aabb,
                 config: OccupancyModelConfig | None = None,
                 kilo_config: KiloNeRFConfig | None = None):
        super().__init__(field, background, aabb, config)
        self.kilo_config = dc = kilo_config or KiloNeRFConfig()
        if not 0.0 <= dc.distill_fraction <= 1.0:
            raise ValueError(f"distill_fraction must be in [0, 1], got {dc.distill_fraction}")
        if not 0.0 <= dc.distill_uniform_fraction <= 1.0:
            raise ValueError(f"distill_uniform_fraction must be in [0, 1], got "
                             f"{dc.distill_uniform_fraction}")
        if not dc.render_min_weight >= 0.0:
            raise ValueError(f"render_min_weight must be >= 0, got {dc.render_min_weight}")
        if dc.render_precision not in ("auto", "fp32", "bf16"):
            raise ValueError(f"render_precision must be 'auto', 'fp32' or 'bf16', got "
                             f"{dc.render_precision!r}")
        if dc.distill_batch < 1 or dc.distill_rays < 1:
            raise ValueError(f"distill_batch and distill_rays must be >= 1, got "
                             f"{dc.distill_batch}, {dc.distill_rays}")
        self.register_buffer("teacher_initialized", torch.zeros((), dtype=torch.uint8))
        self._scratch = ScratchArrays((np.float32,) * 4)
        self._teacher = _Holder()
        self._distilling = False
        self._restart_batch_size = False

    # -- the teacher -------------------------------------------------------------------------
    def teacher(self):
        """The frozen teacher model (loaded on first use)."""
        if self._teacher.model is None:
            loader = self.__dict__.get("run_loader")
            if loader is None:
                raise ValueError("kilonerf with a teacher_run opens the teacher through a run "
                                 "loader: train it with nerfbot.train.trainer.Trainer, or call "
                                 "model.use_run_loader(nerfbot.train.runs.load_model)")
            model, info = loader(self.kilo_config.teacher_run, device=self.aabb.device)
            if not Conditioning.from_dict(info["spec"].get("conditioning")).is_static:
                raise ValueError(f"{self.kilo_config.teacher_run}: kilonerf distills static scenes "
                                 f"only; the teacher is conditioned")
            for p in model.parameters():
                p.requires_grad_(False)
            self._teacher.model = model
        return self._teacher.model

    @torch.no_grad()
    def _occupancy_from_teacher(self, teacher, generator=None, chunk: int = 1 << 16) -> None:
        """Set this model's occupancy grid from the teacher's densities: the max of two random
        points per cell against the grid's threshold (``min(mean, grid_threshold / dt_min)``
        as in :meth:`OccupancyGrid.update`), evaluated
        only in cells that overlap the teacher's own occupied cells; a teacher without an
        occupancy grid (NeRF) is first probed on a grid of at most 64^3 cells."""
        grid = self.grid
        coarse = getattr(teacher, "grid", None)
        density_fn = teacher.field.occupancy_density
        if not isinstance(coarse, OccupancyGrid):
            coarse = OccupancyGrid(self.aabb, min(grid.resolution, 64), grid.threshold)
            coarse.update(lambda x: density_fn(x, generator), self.dt_min, generator)
        inside = grid.inside.reshape(-1)
        candidates = torch.nonzero(inside & _overlaps(grid, coarse)).squeeze(-1)
        density = torch.zeros_like(grid.density)
        for _ in range(2):
            u = torch.rand(candidates.numel(), 3, generator=generator).to(candidates.device)
            pts = grid.cube_min + (grid._cell_index[candidates] + u) * grid.cell_size
            dens = torch.cat([density_fn(pts[i:i + chunk], generator).float()
                              for i in range(0, len(pts), chunk)] or [pts.new_zeros(0)])
            density[candidates] = torch.maximum(density[candidates], dens)
        # the grid's own rule (OccupancyGrid.update): a faint teacher still occupies its
        # denser-than-average cells
        mean = float(density[inside].mean()) if bool(inside.any()) else 0.0
        occupied = (density > min(mean, grid.threshold / self.dt_min)) & inside
        if not bool(occupied.any()):
            raise ValueError(f"{self.kilo_config.teacher_run}: the teacher occupies no cell of "
                             f"the occupancy grid")
        grid.density.copy_(density)
        grid.occupied.copy_(occupied.reshape(grid.occupied.shape).to(torch.uint8))

    @torch.no_grad()
    def _network_cells_in_use(self) -> torch.Tensor:
        """(G^3,) bool: network cells that overlap an occupied occupancy cell (tested at the 8
        corners of each occupied cell, pulled in slightly, so any resolutions work)."""
        grid = self.grid
        occ = torch.nonzero(grid.occupied.reshape(-1)).squeeze(-1)
        corners = torch.tensor([[i, j, k] for i in (0.01, 0.99) for j in (0.01, 0.99)
                                for k in (0.01, 0.99)], device=occ.device)
        ijk = grid._cell_index[occ]
        pts = grid.cube_min + (ijk[:, None, :] + corners) * grid.cell_size
        cells, _ = self.field.cells(pts.reshape(-1, 3))
        used = torch.zeros(self.field.net_index.shape, dtype=torch.bool, device=occ.device)
        used[cells] = True
        return used

    def _init_from_teacher(self, generator=None) -> dict:
        teacher = self.teacher()
        self._occupancy_from_teacher(teacher, generator)
        kept = self.field.keep_networks(self._network_cells_in_use())
        if type(teacher.background) is type(self.background):
            self.background.load_state_dict(teacher.background.state_dict())
        self.teacher_initialized.fill_(1)
        return {"networks": float(kept)}

    # -- distillation ------------------------------------------------------------------------
    def distill_points(self, n: int, generator=None) -> torch.Tensor:
        """(n, 3) world points: a ``distill_uniform_fraction`` share uniform in the kept
        networks' cells, the rest uniform in the occupied occupancy cells."""
        n_uni = int(round(n * self.kilo_config.distill_uniform_fraction))
        parts = []
        for count, cells, res in ((n - n_uni, self.grid.occupied.reshape(-1), self.grid.resolution),
                                  (n_uni, self.field.net_index >= 0, self.field.resolution)):
            ids = torch.nonzero(cells).squeeze(-1)
            if count == 0 or ids.numel() == 0:
                continue
            pick = ids[torch.randint(ids.numel(), (count,), generator=generator)]
            ijk = torch.stack([pick // (res * res), (pick // res) % res, pick % res], -1)
            u = (ijk.float() + torch.rand(count, 3, generator=generator).to(ijk.device)) / res
            parts.append(self.grid.cube_min + u * self.grid.cube_size)
        return torch.cat(parts) if parts else self.grid.cube_min.new_zeros(0, 3)

    def distill_loss(self, directions: torch.Tensor, generator=None) -> torch.Tensor:
        """Match the teacher at ``distill_batch`` points (see :meth:`distill_points`) viewed
        along directions drawn from ``directions`` (R, 3): MSE of the opacity of one marching
        step, alpha = 1 - exp(-sigma dt_min) (bounded, unlike sigma, and what rendering sees),
        plus MSE of the colour."""
        x = self.distill_points(self.kilo_config.distill_batch, generator)
        d = directions[torch.randint(directions.shape[0], (x.shape[0],), generator=generator)]
        teacher = self.teacher()
        with torch.no_grad():
            sigma_t, feat_t = teacher.field.density(x)
            rgb_t = teacher.field.color(feat_t, d)
            alpha_t = -torch.expm1(-(sigma_t * self.dt_min).clamp_max(1e4))
        sigma, feat = self.field.density(x)
        rgb = self.field.color(feat, d)
        alpha = -torch.expm1(-(sigma * self.dt_min).clamp_max(1e4))
        return F.mse_loss(alpha, alpha_t) + F.mse_loss(rgb, rgb_t)

    # -- training hooks ----------------------------------------------------------------------
    def before_step(self, step: int, generator=None, progress: float = 0.0) -> dict:
        out = {}
        if self.kilo_config.teacher_run and not bool(self.teacher_initialized):
            out.update(self._init_from_teacher(generator), params_changed=True)
        kc = self.kilo_config
        self._distilling = bool(kc.teacher_run) and progress < kc.distill_fraction
        if self._distilling:
            return {**out, "distill": 1.0}
        return {**out, **super().before_step(step, generator, progress)}

    def loss(self, rays, target_rgb, generator=None, cond=None, rays_per_pixel=1,
             pixel_weights=None):
        if not self._distilling:
            return super().loss(rays, target_rgb, generator, cond, rays_per_pixel, pixel_weights)
        loss = self.distill_loss(rays.directions, generator)
        n, z = len(rays), target_rgb.new_zeros(len(rays))
        empty = target_rgb.new_zeros(0)
        out = RenderOutput(rgb=target_rgb.new_zeros(n, 3), opacity=z, depth=z, z_depth=z,
                           median_depth=z, weights=empty, num_samples=0,
                           ray_indices=torch.zeros(0, dtype=torch.long, device=z.device),
                           t_starts=empty,
                           t_ends=empty, sigmas=empty)
        return loss, out

    def rays_for_next_batch(self, last_samples: Optional[int], n_rays: int) -> int:
        if self._distilling:
            self._restart_batch_size = True
            return self.kilo_config.distill_rays
        if self._restart_batch_size:  # the last batch was a distillation batch: no sample count
            self._restart_batch_size = False
            last_samples = None
        return super().rays_for_next_batch(last_samples, n_rays)

    # -- rendering ---------------------------------------------------------------------------
    def _render_inference(self, rays, cond=None) -> RenderOutput:
        if self.kilo_config.fused_render and use_kernels(
                rays.origins, backend=self.field.config.layout_backend, dtype=None):
            return self.render_fast(rays)
        return super()._render_inference(rays, cond)

    def render_dtype(self) -> torch.dtype:
        """The dtype of the one-pass renderer's matmuls (see ``render_precision``)."""
        return torch.bfloat16 if self.kilo_config.render_precision == "bf16" else torch.float32

    @torch.no_grad()
    def render_fast(self, rays) -> RenderOutput:
        """Eval-mode rendering in one marching pass on the CPU: in float32 the fused kernel
        (:meth:`render_fused`), in bfloat16 the batched matmuls (:meth:`render_batched`, which
        AMX runs in hardware)."""
        if self.render_dtype() == torch.float32 and len(rays) > 0:
            return self.render_fused(rays)
        return self.render_batched(rays)

    @torch.no_grad()
    def render_fused(self, rays) -> RenderOutput:
        """Every ray in one numba pass (:func:`nerfbot.kernels.kilonerf.render_fused`):
        marching, each sample's tiny network evaluated in place (its weights stay in cache for
        the neighbouring samples and rays that use the same network), compositing with early
        termination, the colour head only where a sample's weight exceeds
        ``render_min_weight``; the background from its baked table. The same
        :class:`RenderOutput` as the generic path, up to the termination rule (samples behind
        it are not marched) and float32 rounding."""
        n, f = len(rays), self.field
        t_near, t_far, _ = ray_aabb(rays.origins, rays.directions, self.aabb)
        o = rays.origins.float().contiguous().numpy()
        d = rays.directions.float().contiguous().numpy()
        tn, tf = t_near.numpy(), t_far.numpy()
        bg = self.baked_background(rays.directions)
        grid, nz = self.grid, f.normalize
        w = f.weights()
        consts = (grid.occupied.numpy(), grid.cube_min.double().numpy(), float(grid.cell_size),
                  self.dt_min, self.dt_max, float(self.config.cone_angle),
                  nz.aabb.float().contiguous().numpy(), nz.cube_min.float().numpy(),
                  np.float32(nz.cube_size), f.net_index.numpy(),
                  *(w[k].detach().contiguous().numpy() for k in PARAMETER_NAMES),
                  f.pos_enc.n_freqs, f.dir_enc.n_freqs, float(f.density_bias),
                  float(self.config.early_stop_transmittance),
                  float(self.kilo_config.render_min_weight))

        def run(sel, block_cap, scratch):
            m = n if sel is None else len(sel)
            pick = (lambda a: a) if sel is None else (lambda a: np.ascontiguousarray(a[sel]))
            out = (np.empty((m, 3), np.float32), np.empty(m, np.float32),
                   np.empty(m, np.float32), np.empty(m, np.int64), np.empty(m, np.int64))
            _kk.render_fused(pick(o), pick(d), pick(tn), pick(tf), *consts, pick(bg), block_cap,
                             *out, *scratch)
            rgb, opacity, depth, counts, src_start = out
            return rgb, opacity, depth, pick(tf), counts, src_start

        return render_blocks(run, n, _kk.RAY_BLOCK, FUSED_SLOT_SAMPLES, self._scratch,
                             rays.z_per_t)

    @torch.no_grad()
    def render_batched(self, rays) -> RenderOutput:
        """Eval-mode rendering in one marching pass (CPU, numba kernels + batched matmuls).

        1. March every ray through the occupancy grid (all occupied samples at once: the
           samples behind a ray's termination are few next to the rounds' overhead).
        2. Densities of all samples: one pass of the networks' trunks.
        3. Per ray: weights, early termination (samples after the transmittance falls below
           ``early_stop_transmittance`` get weight 0), opacity, depth, median depth.
        4. Colours of the trunk's chunks that hold a sample whose weight exceeds
           ``render_min_weight``; every such sample adds weight x colour to its ray, and the
           fainter samples take the weight-averaged colour of these.
        5. The background, read from its baked table
           (:meth:`~nerfbot.models.base.Model.baked_background`).

        Returns the same :class:`RenderOutput` as the generic path (packed samples included,
        for threshold-depth queries); results agree with it up to the termination rule.
        """
        n, f = len(rays), self.field
        t_near, t_far, _ = ray_aabb(rays.origins, rays.directions, self.aabb)
        s = self._march(rays, t_near, t_far)
        ri, ts, te = s.ray_indices, s.t_starts, s.t_ends
        m = ri.shape[0]
        o = rays.origins.float().contiguous()
        d = rays.directions.float().contiguous()
        slots = torch.empty(m, dtype=torch.long)
        local = torch.empty(m, 3)
        nz = f.normalize
        _kk.sample_cells(o.numpy(), d.numpy(), ri.numpy(), ts.numpy(), te.numpy(),
                         nz.aabb.float().contiguous().numpy(), nz.cube_min.float().numpy(),
                         np.float32(nz.cube_size), f.net_index.numpy(), slots.numpy(),
                         local.numpy())
        valid = torch.nonzero(slots >= 0).squeeze(-1)
        pos = torch.full((m,), -1, dtype=torch.long)
        raw = torch.zeros(0)
        dtype = self.render_dtype()
        w = f.weights(dtype)
        if valid.numel():
            lay = f.layout(slots[valid])
            pos[valid] = lay.pos
            row_sample = torch.full((lay.rows,), -1, dtype=torch.long)
            row_sample[lay.pos] = valid
            enc = _kernel_buffer(lay.rows, f.pos_enc.out_dim, dtype)
            angle = math.pi * local
            _kk.encode_padded(local.numpy(), torch.sin(angle).numpy(), torch.cos(angle).numpy(),
                              row_sample.numpy(), f.pos_enc.n_freqs, _as_kernel_array(enc))
            h, raw = f.trunk(enc, lay, w)
            raw = raw.float().reshape(-1)
        starts, counts = ray_starts(ri, n)
        sigmas, weights = torch.empty(m), torch.empty(m)
        opacity, depth, median = torch.empty(n), torch.empty(n), torch.empty(n)
        _kk.composite_density(starts.numpy(), counts.numpy(), ts.numpy(), te.numpy(), pos.numpy(),
                              raw.numpy(), f.density_bias, self.config.early_stop_transmittance,
                              t_far.float().contiguous().numpy(), sigmas.numpy(),
                              weights.numpy(), opacity.numpy(), depth.numpy(), median.numpy())
        rgb = torch.zeros(n, 3)
        min_w = self.kilo_config.render_min_weight
        need = pos[weights > min_w]
        if need.numel():
            c, nc = lay.chunk, lay.chunk_net.shape[0]
            chunk_need = torch.zeros(nc, dtype=torch.bool)
            chunk_need[need // c] = True
            sel = torch.nonzero(chunk_need).squeeze(-1)
            chunk_map = torch.full((nc,), -1, dtype=torch.long)
            chunk_map[sel] = torch.arange(sel.numel())
            if sel.numel() < nc:  # evaluate the selected chunks only
                h = h.reshape(nc, c, -1)[sel].reshape(sel.numel() * c, -1)
                row_sample = row_sample.reshape(nc, c)[sel].reshape(-1)
            sub = Layout(None, lay.chunk_net[sel], c)
            dp = _kernel_buffer(sub.rows, f.dir_enc.out_dim, dtype)
            _kk.padded_rows(f.dir_enc(d).contiguous().numpy(), ri.numpy(), row_sample.numpy(),
                            _as_kernel_array(dp))
            rgb_rows = f.head(h, dp, sub, w).float()
            _kk.accumulate_rgb(starts.numpy(), counts.numpy(), weights.numpy(), min_w,
                               pos.numpy(), chunk_map.numpy(), c, rgb_rows.numpy(), rgb.numpy())
        rgb = rgb + (1.0 - opacity)[:, None] * torch.from_numpy(self.baked_background(d))
        return RenderOutput(rgb=rgb, opacity=opacity, depth=depth, z_depth=depth * rays.z_per_t,
                            median_depth=median, weights=weights, num_samples=m, ray_indices=ri,
                            t_starts=ts, t_ends=te, sigmas=sigmas)
