"""Where to put samples along rays: box clipping, stratified and hierarchical (pdf) sampling,
and occupancy-grid marching with packed outputs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from nerfbot.kernels import boxes as _bk
from nerfbot.kernels import marching as _mk
from nerfbot.kernels import use_kernels
from nerfbot.ops.contraction import CONTRACTED_HALF, contract, step_scale, uncontract


def ray_aabb(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor,
             near: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Slab intersection of rays with an axis-aligned box.

    Args:
        origins, directions: (R, 3); aabb: (2, 3) min / max corners, metres.
        near: rays start no closer than this.
    Returns:
        t_near, t_far (R,) and hit (R,) bool. Rays that miss get t_near = t_far = near.
        The box is closed: a ray lying in one of its faces hits it.
        Float32 CPU tensors without gradients go through the numba twin
        (:func:`nerfbot.kernels.boxes.ray_aabb`), which gives the same bits.
    """
    if (use_kernels(origins, directions, aabb)
            and not (origins.requires_grad or directions.requires_grad or aabb.requires_grad)
            and origins.dim() == 2 and origins.shape == directions.shape
            and origins.shape[-1] == 3):
        n = origins.shape[0]
        t_near, t_far = torch.empty(n), torch.empty(n)
        hit = torch.empty(n, dtype=torch.bool)
        _bk.ray_aabb(origins.contiguous().numpy(), directions.contiguous().numpy(),
                     aabb.contiguous().numpy(), np.float32(near), t_near.numpy(), t_far.numpy(),
                     hit.numpy())
        return t_near, t_far, hit
    return ray_aabb_reference(origins, directions, aabb, near)


def ray_aabb_reference(origins: torch.Tensor, directions: torch.Tensor, aabb: torch.Tensor,
                       near: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Plain-torch :func:`ray_aabb` (any device, dtype and batch shape, differentiable)."""
    # A direction component below 1e-12 (parallel to a slab) bounds nothing when the origin is
    # within that slab, faces included, and excludes the ray otherwise. (Dividing by a stand-in
    # of +1e-12 instead made rays lying in a max face miss while those in a min face hit.)
    parallel = directions.abs() < 1e-12
    inv = 1.0 / torch.where(parallel, torch.ones_like(directions), directions)
    t0 = (aabb[0] - origins) * inv
    t1 = (aabb[1] - origins) * inv
    in_slab = (origins >= aabb[0]) & (origins <= aabb[1])
    inf = torch.full_like(t0, float("inf"))
    lo = torch.where(parallel, torch.where(in_slab, -inf, inf), torch.minimum(t0, t1))
    hi = torch.where(parallel, torch.where(in_slab, inf, -inf), torch.maximum(t0, t1))
    t_near = lo.amax(-1).clamp_min(near)
    t_far = hi.amin(-1)
    hit = t_far > t_near
    t_near = torch.where(hit, t_near, torch.full_like(t_near, near))
    t_far = torch.where(hit, t_far, t_near)
    return t_near, t_far, hit


def crosses_top_to_bottom(origins: torch.Tensor, directions: torch.Tensor, t_near: torch.Tensor,
                          t_far: torch.Tensor, hit: torch.Tensor, aabb: torch.Tensor
                          ) -> torch.Tensor:
    """(R,) bool: which rays from outside the box (``aabb`` (2, 3), metres) enter it through its
    top face and leave it through its bottom face, given their :func:`ray_aabb` entry and exit
    ``t_near``, ``t_far`` and ``hit`` (R,). A ray enters (leaves) through the face of the axis
    whose slab it enters last (leaves first): for these, z's on both ends, pointing down. Rays
    that miss the box, or start inside it, cross nothing; a ray through an edge or corner
    counts as crossing the top or bottom face there."""
    with torch.no_grad():
        box = aabb.reshape(2, 3).to(origins)
        dz = directions[:, 2]
        down = dz < 0
        step = torch.where(down, dz, -torch.ones_like(dz))
        t_top = (box[1, 2] - origins[:, 2]) / step
        t_bottom = (box[0, 2] - origins[:, 2]) / step
        # within float32 rounding of the slab test's own distances
        enters = (t_top - t_near).abs() <= 1e-5 * (t_near.abs() + 1.0)
        leaves = (t_bottom - t_far).abs() <= 1e-5 * (t_far.abs() + 1.0)
        return hit & down & (origins[:, 2] > box[1, 2]) & enters & leaves


def stratified_samples(t_near: torch.Tensor, t_far: torch.Tensor, n: int,
                       generator: torch.Generator | None = None, jitter: bool = True) -> torch.Tensor:
    """``n + 1`` interval edges per ray (R, n + 1) between near and far, one uniform sample per bin.

    With ``jitter`` every inner edge moves randomly within its bin (NeRF's stratified sampling);
    the outer edges stay at near and far.
    """
    u = torch.linspace(0.0, 1.0, n + 1, device=t_near.device)
    edges = t_near[:, None] + (t_far - t_near)[:, None] * u
    if jitter and n > 1:
        mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
        lo = torch.cat([edges[:, :1], mids], -1)
        hi = torch.cat([mids, edges[:, -1:]], -1)
        r = torch.rand(edges.shape, generator=generator, device=t_near.device)
        edges = (lo + (hi - lo) * r).sort(-1).values
    edges[:, 0], edges[:, -1] = t_near, t_far
    return edges


def pdf_samples(edges: torch.Tensor, weights: torch.Tensor, n: int,
                generator: torch.Generator | None = None, jitter: bool = True) -> torch.Tensor:
    """Hierarchical sampling: ``n`` distances (R, n) drawn from the piecewise-constant pdf given
    by ``weights`` (R, S) on the bins between ``edges`` (R, S + 1).

    Rays whose weights are all zero get a uniform pdf (a small constant pads every bin), and the
    inverse CDF never divides by zero.
    """
    w = weights.detach() + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1).clamp_max(1.0)
    if jitter:
        u = torch.rand(pdf.shape[0], n, generator=generator, device=pdf.device)
    else:
        u = torch.linspace(0.0, 1.0, n + 2, device=pdf.device)[1:-1].expand(pdf.shape[0], n)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    e0, e1 = edges.gather(-1, idx - 1), edges.gather(-1, idx)
    frac = torch.nan_to_num((u - c0) / (c1 - c0).clamp_min(1e-12), 0.0).clamp(0.0, 1.0)
    return (e0 + frac * (e1 - e0)).detach()


@dataclass
class PackedSamples:
    """Samples of R rays, packed (sorted by ray).

    Attributes:
        ray_indices: (M,) int64; t_starts, t_ends: (M,) float32 metres;
        t_stop: (R,) where each ray's marching stopped (to resume from there).
    """

    ray_indices: torch.Tensor
    t_starts: torch.Tensor
    t_ends: torch.Tensor
    t_stop: torch.Tensor

    def __len__(self) -> int:
        return int(self.ray_indices.shape[0])


class OccupancyGrid(nn.Module):
    """A G^3 grid over the cube enclosing the scene bounds, marking where density lives.

    Kept as an exponential moving maximum of densities sampled at random points of each cell
    (Instant-NGP): ``density = max(density * decay, sampled)``; see :meth:`update` for when a
    cell counts as occupied. Cells outside the scene bounds stay empty.

    With ``contract`` the grid covers all of space through the scene contraction
    (:mod:`nerfbot.ops.contraction`) around the bounds' enclosing cube (the inner cube, whose
    centre and half-size are ``centre`` and ``half``): its cells tile the contracted cube of
    twice the inner cube's size, the inner cube takes the middle G/2 cells per axis, and every
    cell is inside the scene.

    Args:
        aabb: (2, 3) scene bounds, metres.
        resolution: G.
        threshold: opacity of one marching step above which a cell is occupied.
        contract: cover all of space through the scene contraction.
    """

    def __init__(self, aabb: torch.Tensor, resolution: int = 64, threshold: float = 0.01,
                 decay: float = 0.95, contract: bool = False):
        super().__init__()
        aabb = torch.as_tensor(aabb, dtype=torch.float32)
        center = 0.5 * (aabb[0] + aabb[1])
        half = 0.5 * float((aabb[1] - aabb[0]).max())
        self.resolution, self.threshold, self.decay = resolution, threshold, decay
        self.contract = bool(contract)
        self.half = half
        #: edge of the bounds' enclosing cube, metres (where marching step sizes come from)
        self.inner_size = 2.0 * half
        extent = CONTRACTED_HALF * half if self.contract else half
        self.register_buffer("aabb", aabb.clone())
        self.register_buffer("centre", center.clone(), persistent=False)
        self.register_buffer("cube_min", center - extent)
        self.cube_size = 2.0 * extent
        self.register_buffer("density", torch.zeros(resolution ** 3))
        self.register_buffer("occupied", torch.ones(resolution, resolution, resolution,
                                                    dtype=torch.uint8))
        idx = torch.arange(resolution, dtype=torch.float32)
        centers = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), -1).reshape(-1, 3)
        self.register_buffer("_cell_index", centers, persistent=False)
        mid = self.cell_points(torch.full_like(centers, 0.5))
        if self.contract:
            inside = torch.ones(len(centers), dtype=torch.bool)
            scale = step_scale((mid - self.centre) / half)
        else:
            inside = self._inside_bounds(mid)
            scale = torch.ones(len(centers))
        self.register_buffer("inside", inside.reshape(resolution, resolution, resolution),
                             persistent=False)
        self.register_buffer("_inside_cells", torch.nonzero(inside).squeeze(1), persistent=False)
        #: (G^3,) how much longer than the base step a marching step through each cell is
        self.register_buffer("step_scale", scale, persistent=False)
        self.occupied &= self.inside.to(torch.uint8)

    @property
    def cell_size(self) -> float:
        """Cell edge in metres (of contracted space when ``contract``)."""
        return self.cube_size / self.resolution

    def _inside_bounds(self, centers: torch.Tensor) -> torch.Tensor:
        """Cells (given by their centres) whose interior overlaps the scene bounds."""
        pad = 0.5 * self.cell_size
        return ((centers > self.aabb[0] - pad) & (centers < self.aabb[1] + pad)).all(-1)

    def cell_points(self, offsets: torch.Tensor) -> torch.Tensor:
        """World points at ``offsets`` (G^3, 3) in [0, 1) within every cell: (G^3, 3)."""
        p = self.cube_min + (self._cell_index + offsets) * self.cell_size
        if self.contract:
            p = self.centre + self.half * uncontract((p - self.centre) / self.half)
        return p

    def random_occupied_points(self, n: int, generator: torch.Generator | None = None
                               ) -> torch.Tensor:
        """(n, 3) world points drawn uniformly from the occupied cells ((0, 3) if none is):
        a cell is picked uniformly, then a point within it."""
        cells = torch.nonzero(self.occupied.reshape(-1)).squeeze(1)
        if len(cells) == 0:
            return torch.zeros(0, 3, device=self.cube_min.device)
        pick = cells[torch.randint(len(cells), (n,), generator=generator).to(cells.device)]
        offsets = torch.rand(n, 3, generator=generator).to(self.cube_min.device)
        p = self.cube_min + (self._cell_index[pick] + offsets) * self.cell_size
        if self.contract:
            p = self.centre + self.half * uncontract((p - self.centre) / self.half)
        return p

    def lookup_points(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N, 3) the points the grid is indexed by: ``x`` itself, or
        under ``contract`` its contracted image in metres around ``centre``."""
        if not self.contract:
            return x
        return self.centre + self.half * contract((x - self.centre) / self.half)

    @torch.no_grad()
    def update(self, density_fn, step_size: float, generator: torch.Generator | None = None,
               chunk: int = 1 << 18, prune: bool = True) -> float:
        """Re-sample the density of every cell that overlaps the bounds (the others stay at 0)
        with ``density_fn(points (N, 3)) -> (N,)``, at one random point of each cell.

        A cell is occupied when its density times ``step_scale`` (the growth of the marching
        step through it under the contraction; 1 otherwise) exceeds ``min(mean of the same,
        threshold / step_size)`` (Instant-NGP; ``step_size`` in metres): one step through it
        would be at least ``threshold`` opaque, or it is denser than average while the field is
        still faint.
        The relative part matters early: with only the absolute threshold, nothing passes until
        the first cell crosses it, and then that update prunes almost the whole volume at once.
        Pruning an *untrained* field this way removes cells at random, so callers pass
        ``prune=False`` during a warm-up: densities are tracked, every cell inside the bounds
        stays occupied. An update that would leave no cell occupied keeps the previous occupancy.
        Returns the fraction of the cells inside the bounds that are occupied.
        """
        pts = self.cell_points(torch.rand(self._cell_index.shape, generator=generator))
        inside = self.inside.reshape(-1)
        # flat scenes fill a small part of their enclosing cube: only cells overlapping the
        # bounds are evaluated (the others hold no density)
        cells = self._inside_cells
        pts = pts[cells]
        new = torch.zeros_like(self.density)
        if len(cells):
            new[cells] = torch.cat([density_fn(pts[i:i + chunk]).float()
                                    for i in range(0, len(pts), chunk)])
        self.density.copy_(torch.maximum(self.density * self.decay, new))
        if prune:
            # density times the cell's step over the base step: what one step through the
            # cell sees, comparable between cells of a contracted grid
            per_step = self.density * self.step_scale
            mean = float(per_step[inside].mean()) if bool(inside.any()) else 0.0
            occ = (per_step > min(mean, self.threshold / step_size)) & inside
            if bool(occ.any()):
                self.occupied.copy_(occ.reshape(self.occupied.shape).to(torch.uint8))
        else:
            self.occupied.copy_(self.inside.to(torch.uint8))
        return float(self.occupied.float().sum() / inside.float().sum().clamp_min(1.0))

    def march(self, origins: torch.Tensor, directions: torch.Tensor, t_begin: torch.Tensor,
              t_far: torch.Tensor, dt_min: float, dt_max: float, cone: float = 0.0,
              max_per_ray: int = 1 << 30) -> PackedSamples:
        """March rays from ``t_begin`` to ``t_far`` (R,) and emit samples in occupied cells.

        Step rule ``dt = clamp(t * cone, dt_min, dt_max)`` (metres), ``0 < dt_min <= dt_max``,
        grown by ``max(1, n^2)`` under the contraction.
        CPU: :func:`march_kernels`. Other devices: :func:`march_reference`.
        """
        march_fn = march_kernels if use_kernels(origins, dtype=None) else march_reference
        contraction = (self.centre, self.half) if self.contract else None
        return march_fn(origins, directions, t_begin, t_far, self.occupied, self.cube_min,
                        self.cell_size, dt_min, dt_max, cone, max_per_ray,
                        contraction=contraction)


def march_kernels(origins, directions, t_begin, t_far, occupied, cube_min, cell_size, dt_min,
                  dt_max, cone=0.0, max_per_ray=1 << 30, contraction=None) -> PackedSamples:
    """The numba marcher (:mod:`nerfbot.kernels.marching`: a counting pass, then a filling
    one) on CPU tensors; arguments and result as :func:`march_reference`."""
    _check_steps(dt_min, dt_max)
    o = origins.detach().float().contiguous().numpy()
    d = directions.detach().float().contiguous().numpy()
    tb = t_begin.detach().float().contiguous().numpy()
    tf = t_far.detach().float().contiguous().numpy()
    occ = occupied.numpy()
    gmin = cube_min.double().numpy()
    if contraction is None:
        ccentre, chalf = np.zeros(3), 0.0
    else:
        ccentre, chalf = contraction[0].double().numpy(), float(contraction[1])
    n_rays = o.shape[0]
    counts = np.empty(n_rays, np.int64)
    t_stop = np.empty(n_rays, np.float32)
    args = (o, d, tb, tf, occ, gmin, float(cell_size), ccentre, chalf, float(dt_min),
            float(dt_max), float(cone), int(max_per_ray))
    _mk.march_count(*args, counts, t_stop)
    starts = np.cumsum(counts) - counts
    total = int(counts.sum())
    ray_idx = np.empty(total, np.int64)
    ts = np.empty(total, np.float32)
    te = np.empty(total, np.float32)
    _mk.march_fill(*args, starts, ray_idx, ts, te)
    return PackedSamples(torch.from_numpy(ray_idx), torch.from_numpy(ts), torch.from_numpy(te),
                         torch.from_numpy(t_stop))


def march_reference(origins, directions, t_begin, t_far, occupied, cube_min, cell_size, dt_min,
                    dt_max, cone=0.0, max_per_ray=1 << 30, contraction=None) -> PackedSamples:
    """Plain-torch twin of the numba marcher (same step rule and cell test, any device).

    Marches all rays in lock-step, one step per iteration, so it is slow for long rays: use it
    for checks and for devices without the CPU kernels.

    Args:
        contraction: None, or (centre (3,), half) of the inner cube of the scene contraction:
            ``occupied`` then covers contracted points and steps grow by ``max(1, n^2)``.
    """
    _check_steps(dt_min, dt_max)
    if contraction is not None:
        ccentre, chalf = contraction[0].double(), float(contraction[1])
    g = occupied.shape[0]
    t = t_begin.double().clone()
    tf = t_far.double()
    count = torch.zeros_like(t, dtype=torch.long)
    rays, starts_l, ends_l = [], [], []
    alive = (t < tf) & (count < max_per_ray)
    while bool(alive.any()):
        dt = (t * cone).clamp(dt_min, dt_max)
        if contraction is not None:
            y0 = (origins.double() + t[:, None] * directions.double() - ccentre) / chalf
            dt = dt * step_scale(y0)
        tm = t + 0.5 * dt
        p = origins.double() + tm[:, None] * directions.double()
        if contraction is not None:
            p = ccentre + chalf * contract((p - ccentre) / chalf)
        ijk = torch.floor((p - cube_min.double()) / cell_size).long()
        valid = ((ijk >= 0) & (ijk < g)).all(-1)
        ijk = ijk.clamp(0, g - 1)
        occ = occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]].bool() & valid
        emit = alive & occ
        idx = torch.nonzero(emit).squeeze(-1)
        rays.append(idx)
        starts_l.append(t[idx])
        ends_l.append(torch.minimum(t + dt, tf)[idx])
        count += emit.long()
        t = torch.where(alive, t + dt, t)
        alive = (t < tf) & (count < max_per_ray)
    ray_idx = torch.cat(rays) if rays else torch.zeros(0, dtype=torch.long)
    ts = torch.cat(starts_l) if rays else torch.zeros(0, dtype=torch.float64)
    te = torch.cat(ends_l) if rays else torch.zeros(0, dtype=torch.float64)
    order = torch.sort(ray_idx, stable=True).indices  # group by ray, keep t order
    return PackedSamples(ray_idx[order], ts[order].float(), te[order].float(), t.float())


def _check_steps(dt_min: float, dt_max: float) -> None:
    """A step of 0 (or NaN) would march forever: require 0 < dt_min <= dt_max."""
    if not 0.0 < dt_min <= dt_max:
        raise ValueError(f"marching steps need 0 < dt_min <= dt_max, got dt_min={dt_min}, "
                         f"dt_max={dt_max}")
