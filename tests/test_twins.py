"""Every numba kernel against its plain-torch twin, from one table: forward outputs and, where
the op is differentiable, the gradients of its inputs. Then the single dispatch point
(:func:`nerfbot.kernels.use_kernels`): every public op takes the kernel by default and the twin
under ``NERFBOT_KERNELS=torch``; and short trainings with the twins forced, which run on the
CPU the paths a GPU takes, reach the quality of the kernels' runs."""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from numba.core.dispatcher import Dispatcher

import nerfbot.kernels
from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.fields.background import FixedBackground
from nerfbot.fields.kilonerf import (KiloNeRFField, KiloNeRFFieldConfig, Layout,
                                     chunk_layout_reference)
from nerfbot.fields.tensorf import VMGrid, _VMNumba, vm_reference
from nerfbot.kernels import ENV_VAR, boxes, densegrid, kernel_mode, use_kernels
from nerfbot.kernels import kilonerf as kilonerf_kernels
from nerfbot.kernels import octahedral as octahedral_kernels
from nerfbot.kernels import octree as octree_kernels
from nerfbot.kernels.fastnerf_cache import BRICK
from nerfbot.kernels.sh import sh_encode
from nerfbot.models.fastnerf_cache import FastNeRFCacheConfig, FastNeRFCacheModel
from nerfbot.models.kilonerf import KiloNeRFConfig, KiloNeRFModel
from nerfbot.models.occupancy import OccupancyModel, OccupancyModelConfig
from nerfbot.models.plenoctree import (PlenOctreeConfig, PlenOctreeModel, build_octree,
                                       octree_lookup_reference, walk_segments,
                                       walk_segments_reference)
from nerfbot.ops.cameras import Rays
from nerfbot.ops.encodings import (FrequencyEncoding, HashEncoding, PlaneEncoding, _HashEncodeNumba,
                                   _PlaneEncodeNumba, hash_encode_reference, plane_encode_reference,
                                   spherical_harmonics, spherical_harmonics_reference)
from nerfbot.ops.octahedral import octahedral_lookup
from nerfbot.ops.rendering import (_SegmentScan, ray_starts, segment_exclusive_cumsum,
                                   segment_exclusive_cumsum_reference)
from nerfbot.ops.sampling import (OccupancyGrid, march_kernels, march_reference, ray_aabb,
                                  ray_aabb_reference)
from nerfbot.train.trainer import TrainConfig, Trainer

AABB = [[-0.6, -0.4, 0.0], [0.6, 0.4, 0.9]]


# ----------------------------------------------------------------------------- the table

@dataclass(frozen=True)
class Twin:
    """One kernel / twin pair.

    ``make(generator)`` builds the inputs (a dict: tensors and settings); ``kernel(**inputs)``
    and ``twin(**inputs)`` return tuples of output tensors, compared pairwise (integer outputs
    exactly, floating ones within ``atol + rtol * |twin|``). The inputs named in ``grads`` are
    made leaves that require a gradient; their gradients of one random weighting of the
    floating outputs are compared within ``grad_atol + grad_rtol * |twin's|``. The twin runs
    with ``NERFBOT_KERNELS=torch``, so the ops it calls take their twins too (a GPU's path).
    ``entry(**inputs)``, when given, is the public op that dispatches between the two.
    """

    name: str
    make: Callable[[torch.Generator], dict]
    kernel: Callable[..., tuple]
    twin: Callable[..., tuple]
    atol: float = 0.0
    rtol: float = 0.0
    grads: tuple = ()
    grad_atol: float = 0.0
    grad_rtol: float = 0.0
    entry: Callable[..., tuple] | None = None


def _unit(n: int, g: torch.Generator) -> torch.Tensor:
    return F.normalize(torch.randn(n, 3, generator=g), dim=-1)


def _far(x: torch.Tensor, g: torch.Generator, share: float = 0.3, value: float = 1e6
         ) -> torch.Tensor:
    """``x`` with a ``share`` of its coordinates moved to +-``value``."""
    pick = torch.rand(x.shape, generator=g) < share
    sign = torch.where(torch.rand(x.shape, generator=g) < 0.5, -1.0, 1.0)
    return torch.where(pick, sign * value, x)


# -- spherical harmonics (nerfbot.kernels.sh) -----------------------------------------------------
def _sh(n: int, degree: int):
    return lambda g: {"d": _unit(n, g), "degree": degree}


def _sh_kernel(d, degree):
    out = torch.empty(d.shape[0], (degree + 1) ** 2)
    sh_encode(d.contiguous().numpy(), degree, out.numpy())
    return (out,)


def _sh_twin(d, degree):
    return (spherical_harmonics_reference(d, degree),)


# -- hash grid (nerfbot.kernels.hashgrid) ---------------------------------------------------------
#: Coarse dense levels and fine hashed ones.
HASH = {"n_levels": 5, "n_features": 2, "log2_size": 11, "min_res": 6, "max_res": 96}


def _hash(n: int, far: bool = False):
    def make(g):
        enc = HashEncoding(**HASH, seed=int(torch.randint(1 << 20, (1,), generator=g)),
                           init_scale=1.0)
        x = torch.rand(n, 3, generator=g) * 1.2 - 0.1
        x[:8] = torch.tensor([[c & 1, (c >> 1) & 1, c >> 2] for c in range(8)],
                             dtype=torch.float32)[:n]  # the cube's corners
        return {"x": _far(x, g) if far else x, "table": enc.table.detach().clone(), "enc": enc}
    return make


def _hash_kernel(x, table, enc):
    return (_HashEncodeNumba.apply(x, table, enc._offsets_np, enc._res_np),)


def _hash_twin(x, table, enc):
    return (hash_encode_reference(x, table, enc.offsets, enc.res),)


# -- planes (nerfbot.kernels.planes) --------------------------------------------------------------
PLANES = {"in_dim": 4, "n_levels": 2, "n_features": 4, "spatial_res": (8, 16),
          "time_res": (4, 6)}


def _planes(n: int, far: bool = False):
    def make(g):
        enc = PlaneEncoding(**PLANES, seed=int(torch.randint(1 << 20, (1,), generator=g)))
        x = torch.rand(n, 4, generator=g) * 1.2 - 0.1
        return {"x": _far(x, g) if far else x, "table": enc.table.detach().clone(), "enc": enc}
    return make


def _planes_kernel(x, table, enc):
    return (_PlaneEncodeNumba.apply(x, table, enc._offsets_np, enc._res_np, enc._pairs_np),)


def _planes_twin(x, table, enc):
    return (plane_encode_reference(x, table, enc.offsets, enc.res, enc.pairs),)


# -- ray / box (nerfbot.kernels.boxes) ------------------------------------------------------------
def _rays_at_box(n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from about 2 m away aimed near the box (some miss)."""
    lo, hi = torch.tensor(AABB[0]), torch.tensor(AABB[1])
    o = 0.5 * (lo + hi) + 2.0 * _unit(n, g)
    target = lo - 0.2 + (hi - lo + 0.4) * torch.rand(n, 3, generator=g)
    return o, F.normalize(target - o, dim=-1)


def _boxes(n: int, edge: bool = False):
    def make(g):
        o, d = _rays_at_box(n, g)
        if edge:  # axis-parallel rays in the faces, origins 1e6 m away
            axes = torch.eye(3)
            o[:6] = torch.tensor([[0.6, 0.0, -1e6], [-0.6, 0.4, 1e6], [0.0, 0.4, -1e6],
                                  [1e6, -0.4, 0.9], [0.6, -1e6, 0.0], [-1e6, 0.0, 0.0]])
            d[:6] = torch.stack([axes[2], -axes[2], axes[2], -axes[0], axes[1], axes[0]])
        return {"o": o, "d": d, "aabb": torch.tensor(AABB), "near": 0.1}
    return make


def _boxes_kernel(o, d, aabb, near):
    n = o.shape[0]
    t_near, t_far, hit = torch.empty(n), torch.empty(n), torch.empty(n, dtype=torch.bool)
    boxes.ray_aabb(o.numpy(), d.numpy(), aabb.numpy(), np.float32(near), t_near.numpy(),
                   t_far.numpy(), hit.numpy())
    return t_near, t_far, hit


def _boxes_twin(o, d, aabb, near):
    return ray_aabb_reference(o, d, aabb, near)


# -- occupancy marching (nerfbot.kernels.marching) ------------------------------------------------
def _marching(n: int, fill: float = 0.4, cone: float = 0.0):
    def make(g):
        grid = OccupancyGrid(torch.tensor(AABB), 16)
        occ = torch.rand(16, 16, 16, generator=g) < fill
        grid.occupied.copy_((occ & grid.inside).to(torch.uint8))
        o, d = _rays_at_box(n, g)
        t_near, t_far, _ = ray_aabb_reference(o, d, grid.aabb)
        return {"grid": grid, "o": o, "d": d, "t_near": t_near, "t_far": t_far,
                "steps": (0.01, 0.04 if cone else 0.01, cone, 1 << 30)}
    return make


def _marching_contracted(n: int, fill: float = 0.4):
    """Rays from inside and outside the inner cube, in every direction, to 1000 half-sizes,
    through a grid over contracted space whose outer shell is partly occupied."""
    def make(g):
        grid = OccupancyGrid(torch.tensor(AABB), 16, contract=True)
        occ = torch.rand(16, 16, 16, generator=g) < fill
        grid.occupied.copy_(occ.to(torch.uint8))
        centre = torch.tensor(AABB).mean(0)
        o = centre + 0.4 * torch.randn(n, 3, generator=g) * torch.rand(n, 1, generator=g) * 4
        d = _unit(n, g)
        t_near = torch.zeros(n)
        t_far = torch.full((n,), 1000.0 * grid.half)
        return {"grid": grid, "o": o, "d": d, "t_near": t_near, "t_far": t_far,
                "steps": (0.02, 0.02, 0.0, 1 << 30)}
    return make


def _packed(s) -> tuple:
    return s.ray_indices, s.t_starts, s.t_ends, s.t_stop


def _march_kernel(grid, o, d, t_near, t_far, steps):
    return _packed(march_kernels(o, d, t_near, t_far, grid.occupied, grid.cube_min,
                                 grid.cell_size, *steps))


def _march_twin(grid, o, d, t_near, t_far, steps):
    return _packed(march_reference(o, d, t_near, t_far, grid.occupied, grid.cube_min,
                                   grid.cell_size, *steps))


def _march_contracted_kernel(grid, o, d, t_near, t_far, steps):
    return _packed(march_kernels(o, d, t_near, t_far, grid.occupied, grid.cube_min,
                                 grid.cell_size, *steps, contraction=(grid.centre, grid.half)))


def _march_contracted_twin(grid, o, d, t_near, t_far, steps):
    return _packed(march_reference(o, d, t_near, t_far, grid.occupied, grid.cube_min,
                                   grid.cell_size, *steps, contraction=(grid.centre, grid.half)))


def _march_contracted_entry(grid, o, d, t_near, t_far, steps):
    return _packed(grid.march(o, d, t_near, t_far, *steps))


# -- per-ray scan (nerfbot.kernels.scan) ----------------------------------------------------------
def _scan(n_rays: int, scale: float = 3.0):
    def make(g):
        counts = torch.randint(0, 7, (n_rays,), generator=g)  # rays without samples among them
        ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
        values = torch.rand(ray_indices.shape[0], generator=g, dtype=torch.float64) * scale
        return {"values": values, "ray_indices": ray_indices,
                "starts": ray_starts(ray_indices, n_rays)[0]}
    return make


def _scan_kernel(values, ray_indices, starts):
    return (_SegmentScan.apply(values, ray_indices),)


def _scan_twin(values, ray_indices, starts):
    return (segment_exclusive_cumsum_reference(values, ray_indices, starts),)


# -- TensoRF VM (nerfbot.kernels.vm) --------------------------------------------------------------
VM_NAMES = ("p0", "p1", "p2", "l0", "l1", "l2")


def _vm(n: int, far: bool = False):
    def make(g):
        grid = VMGrid((5, 7, 4), 3, generator=g)
        x = torch.rand(n, 3, generator=g) * 1.2 - 0.1
        if far:
            x = _far(x, g)
            x[:4, 1] = float("nan")
        grids = [t.detach().clone() for t in (*grid.planes, *grid.lines)]
        return {"x": x, **dict(zip(VM_NAMES, grids)), "grid": grid}
    return make


def _vm_kernel(x, p0, p1, p2, l0, l1, l2, grid):
    return (_VMNumba.apply(x, False, p0, p1, p2, l0, l1, l2),)


def _vm_twin(x, p0, p1, p2, l0, l1, l2, grid):
    return (vm_reference(x, (p0, p1, p2), (l0, l1, l2)),)


# -- Plenoxels' dense grid (nerfbot.kernels.densegrid) --------------------------------------------
def _links(shape, g: torch.Generator, keep: float) -> torch.Tensor:
    """Links of a grid with about ``1 - keep`` of its vertices pruned, rows in C order."""
    mask = torch.rand(shape, generator=g) < keep
    links = torch.full(shape, -1, dtype=torch.int32)
    links[mask] = torch.arange(int(mask.sum()), dtype=torch.int32)
    return links


def _stencil(n: int, keep: float = 0.4, far: bool = False):
    def make(g):
        u = torch.rand(n, 3, generator=g)
        u[:8] = torch.tensor([[c & 1, (c >> 1) & 1, c >> 2] for c in range(8)],
                             dtype=torch.float32)[:n]
        if far:
            u = _far(u, g)
            u[:4, 0] = float("nan")
        return {"u": u, "links": _links((7, 5, 6), g, keep)}
    return make


def _stencil_kernel(u, links):
    rows, weights, coverage = densegrid.stencil(u, links)
    return rows.long(), weights, coverage


def _stencil_twin(u, links):
    # the field's own preparation of the twin's input (PlenoxelField._stencil)
    return densegrid.stencil_reference(torch.nan_to_num(u, nan=0.0).clamp(0.0, 1.0), links)


def gather_rows(n: int, channels: int):
    def make(g):
        links = _links((7, 5, 6), g, 0.4)
        rows, weights, _ = densegrid.stencil(torch.rand(n, 3, generator=g), links)
        table = torch.randn(int((links >= 0).sum()), channels, generator=g)
        return {"table": table, "rows": rows, "weights": weights}
    return make


def _gather_kernel(table, rows, weights):
    return (densegrid.gather(table, rows, weights),)


def _gather_twin(table, rows, weights):
    return (densegrid.gather_reference(table, rows.long(), weights),)


def _sh_color(n: int, degree: int):
    def make(g):
        k = (degree + 1) ** 2
        return {"coeffs": torch.randn(n, 3 * k, generator=g), "d": _unit(n, g)}
    return make


def _sh_color_kernel(coeffs, d):
    return (densegrid.SHColorFunction.apply(coeffs, d),)


def _sh_color_twin(coeffs, d):
    return (densegrid.sh_color_reference(coeffs, d),)


def _tv(rows: int, pairs: int, channels: int):
    def make(g):
        return {"table": torch.randn(rows, channels, generator=g),
                "pairs": torch.randint(rows, (2, pairs), generator=g)}
    return make


def _tv_kernel(table, pairs):
    return (densegrid.TVFunction.apply(table, pairs),)


def _tv_twin(table, pairs):
    return (densegrid.tv_reference(table, pairs),)


# -- KiloNeRF (nerfbot.kernels.kilonerf) ----------------------------------------------------------
def _slots(n: int, n_nets: int = 9, chunk: int = 4, none: bool = True):
    def make(g):
        slots = torch.randint(-1 if none else 0, n_nets, (n,), generator=g)
        slots[slots == 4] = -1 if none else 3  # a network without samples gets no chunk
        return {"slots": slots, "n_nets": n_nets, "chunk": chunk}
    return make


def _layout_kernel(slots, n_nets, chunk):
    pos, chunk_net = kilonerf_kernels.chunk_layout(slots.numpy(), n_nets, chunk)
    return torch.from_numpy(pos), torch.from_numpy(chunk_net)


def _layout_twin(slots, n_nets, chunk):
    return chunk_layout_reference(slots, n_nets, chunk)


def _encode_rows(n: int, n_freqs: int = 4):
    def make(g):
        slots = _slots(n, none=False)(g)
        pos, chunk_net = chunk_layout_reference(**slots)
        return {"values": torch.rand(n, 3, generator=g) * 2 - 1,
                "layout": Layout(pos, chunk_net, slots["chunk"]),
                "enc": FrequencyEncoding(3, n_freqs)}
    return make


def _encode_rows_kernel(values, layout, enc):
    # the kernel call of KiloNeRFField.encoded_rows
    out = torch.zeros(layout.rows, enc.out_dim)
    angle = math.pi * values.double()
    kilonerf_kernels.encode_rows(values.numpy(), torch.sin(angle).numpy(),
                                 torch.cos(angle).numpy(), layout.pos.numpy(), enc.n_freqs,
                                 out.numpy(), 0)
    return (out,)


def _encode_rows_twin(values, layout, enc):
    return (layout.padded(enc(values)),)


def _kilonerf_model() -> KiloNeRFModel:
    """A KiloNeRF model whose random networks make opaque rays, over a grid with empty cells
    (no early termination, every colour evaluated: what the generic rounds do)."""
    cfg = KiloNeRFFieldConfig(network_resolution=4, hidden=16, pos_freqs=3, dir_freqs=2)
    field = KiloNeRFField(AABB, cfg, seed=1)
    keep = torch.ones(field.net_index.shape, dtype=torch.bool)
    keep[::5] = False
    field.keep_networks(keep)
    with torch.no_grad():
        field.b_sigma.add_(4.0)
    model = KiloNeRFModel(field, FixedBackground((0.2, 0.4, 0.9)), AABB,
                          OccupancyModelConfig(grid_resolution=16, render_steps=128,
                                               early_stop_transmittance=1e-9,
                                               shade_min_weight=0.0),
                          KiloNeRFConfig(render_min_weight=0.0))
    occ = torch.rand(16, 16, 16, generator=torch.Generator().manual_seed(3)) < 0.6
    model.grid.occupied.copy_((occ & model.grid.inside).to(torch.uint8))
    return model.eval()


def _rendering(build: Callable, n: int):
    def make(g):
        o, d = _rays_at_box(n, g)
        d[:5] = F.normalize(o[:5], dim=-1)  # looking away from the box: empty rays
        return {"model": build(g), "rays": Rays(o, d, torch.ones(n))}
    return make


def _pixels(out) -> tuple:
    return out.rgb, out.opacity, out.depth, out.median_depth


def _generic_render(model, rays):
    """OccupancyModel's rounds of marching: the KiloNeRF renderers' twin."""
    return _pixels(OccupancyModel._render_inference(model, rays))


def _entry_render(model, rays):
    return _pixels(model.render_rays(rays))


# -- PlenOctrees (nerfbot.kernels.octree) ---------------------------------------------------------
def _octree_model(g: torch.Generator, depth: int = 5, n: int = 3000) -> PlenOctreeModel:
    """A model holding a random octree: ``n`` random leaves, densities in [0, 50) 1/m, shading
    every segment (as the torch path does)."""
    rng = np.random.default_rng(int(torch.randint(1 << 20, (1,), generator=g)))
    ijk = np.unique(rng.integers(0, 2 ** depth, (n, 3)), axis=0)
    child, order = build_octree(ijk, depth)
    model = PlenOctreeModel(AABB, FixedBackground((0.2, 0.4, 0.9)),
                            PlenOctreeConfig(depth=depth, sh_degree=2, color_min_weight=0.0))
    data = np.concatenate([rng.random((len(ijk), 1)) * 50, rng.normal(size=(len(ijk), 27))], 1)
    model.field.set_tree(child, data[order].astype(np.float32))
    return model.eval()


def _octree_points(n: int):
    def make(g):
        field = _octree_model(g).field
        lo = field.normalize.cube_min
        x = lo - 0.05 + (field.cube_size + 0.1) * torch.rand(n, 3, generator=g)
        return {"x": x, "field": field}
    return make


def _lookup_kernel(x, field):
    out = np.empty(x.shape[0], np.int64)
    octree_kernels.octree_lookup(x.numpy(), field.child.numpy(),
                                 field.normalize.cube_min.double().numpy(), field.cube_size, out)
    return (torch.from_numpy(out),)


def _lookup_twin(x, field):
    return (octree_lookup_reference(x, field.child, field.normalize.cube_min, field.cube_size),)


def _walk(n: int, stop: float):
    def make(g):
        model = _octree_model(g)
        o, d = _rays_at_box(n, g)
        t_near, t_far, _ = ray_aabb_reference(o, d, model.aabb)
        f = model.field
        return {"args": (o, d, t_near, t_far, f.child, f.leaf_data[:, 0].detach(),
                         f.normalize.cube_min, f.cube_size, stop)}
    return make


def _walk_kernel(args):
    return walk_segments(*args)


def _walk_twin(args):
    return walk_segments_reference(*args)


def _render_segments(model, rays):
    return _pixels(model.render_segments(rays, reference=True))


# -- octahedral maps (nerfbot.kernels.octahedral) -------------------------------------------------
def _octahedral(n: int, nd: int = 9, channels: int = 3):
    def make(g):
        return {"table": torch.rand(nd, nd, channels, generator=g), "d": _unit(n, g)}
    return make


def _octahedral_kernel(table, d):
    out = np.empty((d.shape[0], table.shape[2]), np.float32)
    octahedral_kernels.lookup(d.numpy(), table.numpy(), out)
    return (torch.from_numpy(out),)


def _octahedral_twin(table, d):
    return (octahedral_lookup(table, d),)


# -- the FastNeRF cache (nerfbot.kernels.fastnerf_cache) ------------------------------------------
def _cache_model(g: torch.Generator, nb: int = 3, components: int = 2) -> FastNeRFCacheModel:
    """A random cache: 3^3 bricks (a few not stored), raw densities in [-3, 5], components in
    [-2, 2], random direction weights; coarse occupancy 60 % of 4^3 cells. Early termination
    and the colour cut off, as in the torch twin."""
    model = FastNeRFCacheModel(AABB, FixedBackground((0.2, 0.4, 0.9)),
                               FastNeRFCacheConfig(render_steps=96, early_stop_transmittance=0.0,
                                                   color_min_weight=0.0))
    stored = torch.rand(nb ** 3, generator=g) < 0.8
    bricks = torch.full((nb ** 3,), -1, dtype=torch.int32)
    bricks[stored] = torch.arange(int(stored.sum()), dtype=torch.int32)
    v1, n = BRICK + 1, int(stored.sum())
    density = torch.randint(-32768, 32768, (n, v1, v1, v1), generator=g, dtype=torch.int16)
    colors = torch.randint(0, 256, (n, v1, v1, v1, 3 * components), generator=g,
                           dtype=torch.uint8)
    scale = torch.cat([torch.tensor([4.0 / 32768]), torch.full((3 * components,), 4.0 / 255)])
    offset = torch.cat([torch.tensor([1.0]), torch.full((3 * components,), -2.0)])
    occupancy = torch.rand(4, 4, 4, generator=g) < 0.6
    model.field.set_cache(bricks.reshape(nb, nb, nb), density, colors, scale, offset, occupancy,
                          torch.randn(9, 9, components, generator=g))
    return model.eval()


TABLE = [
    Twin("sh_encode", _sh(2000, 4), _sh_kernel, _sh_twin, atol=1e-6,
         entry=lambda d, degree: (spherical_harmonics(d, degree),)),
    Twin("sh_encode/degree_0", _sh(100, 0), _sh_kernel, _sh_twin, atol=1e-7),
    Twin("sh_encode/empty", _sh(0, 2), _sh_kernel, _sh_twin),
    Twin("hash_encode", _hash(2000), _hash_kernel, _hash_twin, atol=1e-6, rtol=1e-5,
         grads=("x", "table"), grad_atol=5e-4, grad_rtol=1e-5,
         entry=lambda x, table, enc: (enc(x),)),
    Twin("hash_encode/far_outside", _hash(500, far=True), _hash_kernel, _hash_twin, atol=1e-6,
         rtol=1e-5, grads=("x", "table"), grad_atol=5e-4, grad_rtol=1e-5),
    Twin("hash_encode/empty", _hash(0), _hash_kernel, _hash_twin, grads=("x", "table")),
    Twin("plane_encode", _planes(2000), _planes_kernel, _planes_twin, atol=5e-6, rtol=1e-5,
         grads=("table",), grad_atol=5e-5, grad_rtol=1e-5,
         entry=lambda x, table, enc: (enc(x),)),
    Twin("plane_encode/far_outside", _planes(500, far=True), _planes_kernel, _planes_twin,
         atol=5e-6, rtol=1e-5, grads=("table",), grad_atol=5e-5, grad_rtol=1e-5),
    Twin("plane_encode/empty", _planes(0), _planes_kernel, _planes_twin, grads=("table",)),
    Twin("ray_aabb", _boxes(1000), _boxes_kernel, _boxes_twin,
         entry=lambda o, d, aabb, near: ray_aabb(o, d, aabb, near)),
    Twin("ray_aabb/faces_and_far_origins", _boxes(50, edge=True), _boxes_kernel, _boxes_twin),
    Twin("ray_aabb/empty", _boxes(0), _boxes_kernel, _boxes_twin),
    Twin("march", _marching(300), _march_kernel, _march_twin, atol=1e-5,
         entry=lambda grid, o, d, t_near, t_far, steps: _packed(
             grid.march(o, d, t_near, t_far, *steps))),
    Twin("march/cone", _marching(300, cone=0.02), _march_kernel, _march_twin, atol=1e-5),
    Twin("march/no_samples", _marching(100, fill=0.0), _march_kernel, _march_twin, atol=1e-5),
    Twin("march/empty", _marching(0), _march_kernel, _march_twin),
    Twin("march/contracted", _marching_contracted(200), _march_contracted_kernel,
         _march_contracted_twin, atol=1e-5, rtol=1e-5, entry=_march_contracted_entry),
    Twin("march/contracted_empty", _marching_contracted(0), _march_contracted_kernel,
         _march_contracted_twin),
    Twin("segment_cumsum", _scan(200), _scan_kernel, _scan_twin, atol=1e-12,
         grads=("values",), grad_atol=1e-12,
         entry=lambda values, ray_indices, starts: (segment_exclusive_cumsum(
             values, ray_indices, starts),)),
    # the twin's global cumsum loses what precedes a ray: ~1e-16 of the running total
    Twin("segment_cumsum/large", _scan(200, scale=1e4), _scan_kernel, _scan_twin, atol=1e-8,
         grads=("values",), grad_atol=1e-8),
    Twin("segment_cumsum/empty", _scan(0), _scan_kernel, _scan_twin, grads=("values",)),
    Twin("vm", _vm(2000), _vm_kernel, _vm_twin, atol=1e-6, rtol=1e-5, grads=VM_NAMES,
         grad_atol=1e-4, grad_rtol=1e-5, entry=lambda x, grid, **_: (grid(x),)),
    Twin("vm/far_outside_and_nan", _vm(500, far=True), _vm_kernel, _vm_twin, atol=1e-6,
         rtol=1e-5, grads=VM_NAMES, grad_atol=1e-4, grad_rtol=1e-5),
    Twin("vm/empty", _vm(0), _vm_kernel, _vm_twin, grads=VM_NAMES),
    Twin("grid_stencil", _stencil(3000), _stencil_kernel, _stencil_twin, atol=1e-6),
    Twin("grid_stencil/far_outside_and_nan", _stencil(300, far=True), _stencil_kernel,
         _stencil_twin, atol=1e-6),
    Twin("grid_stencil/all_pruned", _stencil(100, keep=0.0), _stencil_kernel, _stencil_twin),
    Twin("grid_gather", gather_rows(3000, 28), _gather_kernel, _gather_twin, atol=5e-6, rtol=1e-5,
         grads=("table",), grad_atol=5e-5, grad_rtol=1e-5),
    Twin("grid_gather/empty", gather_rows(0, 3), _gather_kernel, _gather_twin, grads=("table",)),
    Twin("sh_color", _sh_color(2000, 2), _sh_color_kernel, _sh_color_twin, atol=1e-6,
         grads=("coeffs",), grad_atol=1e-6),
    Twin("sh_color/degree_0", _sh_color(200, 0), _sh_color_kernel, _sh_color_twin, atol=1e-6,
         grads=("coeffs",), grad_atol=1e-6),
    Twin("total_variation", _tv(300, 1000, 27), _tv_kernel, _tv_twin, atol=1e-6, rtol=1e-5,
         grads=("table",), grad_atol=1e-7, grad_rtol=1e-5),
    Twin("chunk_layout", _slots(777), _layout_kernel, _layout_twin),
    Twin("chunk_layout/no_network", _slots(50, n_nets=1), _layout_kernel, _layout_twin),
    Twin("chunk_layout/empty", _slots(0), _layout_kernel, _layout_twin),
    # the twin rounds 2^k pi v to float32 (2^k pi |v| 2^-24 = 1.5e-6 at k = 3)
    Twin("encode_rows", _encode_rows(500), _encode_rows_kernel, _encode_rows_twin, atol=3e-6),
    Twin("kilonerf_fused_render", _rendering(lambda g: _kilonerf_model(), 300),
         lambda model, rays: _pixels(model.render_fused(rays)), _generic_render, atol=1e-5,
         entry=_entry_render),
    Twin("kilonerf_batched_render", _rendering(lambda g: _kilonerf_model(), 300),
         lambda model, rays: _pixels(model.render_batched(rays)), _generic_render, atol=1e-5),
    Twin("octree_lookup", _octree_points(3000), _lookup_kernel, _lookup_twin,
         entry=lambda x, field: (field.leaf_index(x),)),
    Twin("octree_walk", _walk(400, 0.3), _walk_kernel, _walk_twin, atol=1e-6),
    Twin("octree_walk/no_early_stop", _walk(400, 0.0), _walk_kernel, _walk_twin, atol=1e-6),
    Twin("octree_fused_render", _rendering(_octree_model, 400),
         lambda model, rays: _pixels(model._render_fused(rays)), _render_segments, atol=2e-5,
         rtol=1e-5, entry=_entry_render),
    Twin("octahedral_lookup", _octahedral(2000), _octahedral_kernel, _octahedral_twin,
         atol=1e-5),
    Twin("fastnerf_cache_render", _rendering(_cache_model, 400),
         lambda model, rays: _pixels(model.render_fused(rays)),
         lambda model, rays: _pixels(model.render_reference(rays)), atol=2e-5,
         entry=_entry_render),
]


def _inputs(row: Twin, seed: int = 0) -> dict:
    return row.make(torch.Generator().manual_seed(seed))


def _run(fn: Callable, inputs: dict, grads: tuple) -> tuple[tuple, dict]:
    """Outputs of ``fn`` on fresh leaves of ``inputs``, and the gradients of the ``grads`` inputs
    for one fixed random weighting of the floating outputs."""
    leaves = {k: (v.detach().clone().requires_grad_(True) if k in grads else v)
              for k, v in inputs.items()}
    outs = tuple(fn(**leaves))
    if not grads:
        return outs, {}
    g = torch.Generator().manual_seed(99)
    total = sum((o.double() * torch.randn(o.shape, generator=g, dtype=torch.float64)).sum()
                for o in outs if o.is_floating_point() and o.requires_grad)
    wanted = [leaves[k] for k in grads]
    got = torch.autograd.grad(total, wanted, allow_unused=True) if torch.is_tensor(total) \
        else [None] * len(wanted)
    return outs, {k: (torch.zeros_like(w) if d is None else d)
                  for k, w, d in zip(grads, wanted, got)}


def _assert_same(a: torch.Tensor, b: torch.Tensor, atol: float, rtol: float, what: str):
    assert a.shape == b.shape, (what, a.shape, b.shape)
    if not (a.is_floating_point() or b.is_floating_point()):
        assert torch.equal(a.long(), b.long()), what
        return
    torch.testing.assert_close(a.double(), b.double(), atol=atol, rtol=rtol, equal_nan=True,
                               msg=lambda m: f"{what}: {m}")


@pytest.mark.parametrize("row", TABLE, ids=[row.name for row in TABLE])
def test_kernel_matches_its_twin(row, monkeypatch):
    """Forward outputs, and gradients of the differentiable inputs, of the numba kernel and its
    plain-torch twin on the same inputs (the twin with every op inside it on its twin too)."""
    inputs = _inputs(row)
    monkeypatch.delenv(ENV_VAR, raising=False)
    fast, fast_grads = _run(row.kernel, inputs, row.grads)
    monkeypatch.setenv(ENV_VAR, "torch")
    slow, slow_grads = _run(row.twin, inputs, row.grads)
    assert len(fast) == len(slow)
    for i, (a, b) in enumerate(zip(fast, slow)):
        _assert_same(a.detach(), b.detach(), row.atol, row.rtol, f"{row.name} output {i}")
    for k in row.grads:
        _assert_same(fast_grads[k], slow_grads[k], row.grad_atol, row.grad_rtol,
                     f"{row.name} gradient of {k}")


def test_the_table_covers_every_kernel_with_a_twin():
    """Each module of nerfbot.kernels with a kernel reachable from torch code has a row."""
    covered = {row.name.split("/")[0] for row in TABLE}
    by_module = {"sh": "sh_encode", "hashgrid": "hash_encode", "planes": "plane_encode",
                 "boxes": "ray_aabb", "marching": "march", "scan": "segment_cumsum",
                 "vm": "vm", "densegrid": {"grid_stencil", "grid_gather", "sh_color",
                                           "total_variation"},
                 "kilonerf": {"chunk_layout", "encode_rows", "kilonerf_fused_render",
                              "kilonerf_batched_render"},
                 "octree": {"octree_lookup", "octree_walk", "octree_fused_render"},
                 "octahedral": "octahedral_lookup", "fastnerf_cache": "fastnerf_cache_render",
                 # helpers inlined into the kernels above, and the packing of fused renderers
                 "pixels": set(), "schedule": set(), "packing": set()}
    modules = {p.stem for p in Path(nerfbot.kernels.__file__).parent.glob("*.py")
               if p.stem != "__init__"}
    assert modules == set(by_module), modules ^ set(by_module)
    for names in by_module.values():
        assert set([names] if isinstance(names, str) else names) <= covered


# ----------------------------------------------------------------------------- dispatch

def _forbid_kernels(monkeypatch) -> set[str]:
    """Make every numba kernel that Python code reaches raise: the module attributes through
    which nerfbot calls them (its kernels' modules and the names they are imported under).
    Returns the names replaced."""

    def forbidden(name):
        def call(*args, **kwargs):
            raise AssertionError(f"numba kernel {name} called with {ENV_VAR}=torch")
        return call

    replaced = set()
    for mod_name, module in list(sys.modules.items()):
        if module is None or not (mod_name == "nerfbot" or mod_name.startswith("nerfbot.")):
            continue
        for attr, value in list(vars(module).items()):
            if isinstance(value, Dispatcher):
                name = f"{mod_name}.{attr}"
                monkeypatch.setattr(module, attr, forbidden(name))
                replaced.add(name)
    return replaced


def test_use_kernels_reads_the_switch_at_every_call(monkeypatch):
    x = torch.zeros(4, 3)
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert kernel_mode() == "auto" and use_kernels(x, torch.zeros(4, dtype=torch.long))
    assert not use_kernels(x, backend="torch")
    assert not use_kernels(x.double()) and use_kernels(x.double(), dtype=None)
    assert not use_kernels(x.to("meta"), dtype=None)
    assert use_kernels()  # no tensors: only the switch and the backend count
    for value, expected in (("torch", False), ("TORCH ", False), ("numba", True), ("auto", True),
                            ("", True)):
        monkeypatch.setenv(ENV_VAR, value)
        assert use_kernels(x) is expected, value
    monkeypatch.setenv(ENV_VAR, "cuda")
    with pytest.raises(ValueError, match=ENV_VAR):
        use_kernels(x)


ENTRIES = [row for row in TABLE if row.entry is not None]


@pytest.mark.parametrize("row", ENTRIES, ids=[row.name for row in ENTRIES])
def test_public_ops_take_the_kernel_by_default_and_the_twin_when_forced(row, monkeypatch):
    """The op that dispatches returns exactly the kernel's outputs by default, and exactly the
    twin's with ``NERFBOT_KERNELS=torch`` (while every numba kernel raises)."""
    inputs = _inputs(row, seed=1)
    with torch.no_grad():
        monkeypatch.delenv(ENV_VAR, raising=False)
        for a, b in zip(row.entry(**inputs), row.kernel(**inputs)):
            _assert_same(a, b, 0.0, 0.0, f"{row.name} by default")
        monkeypatch.setenv(ENV_VAR, "torch")
        _forbid_kernels(monkeypatch)
        for a, b in zip(row.entry(**inputs), row.twin(**inputs)):
            _assert_same(a, b, 0.0, 0.0, f"{row.name} with {ENV_VAR}=torch")


# ----------------------------------------------------------------------------- training

#: Per method, options that keep 40 steps cheap on the 32x32 capture; ngp's hash grid is small
#: because its twin costs about as much per level as the rest of a step.
TRAININGS = {
    "ngp": {"n_levels": 6, "log2_hashmap_size": 14, "max_res": 128, "render_steps": 96},
    "plenoxels": {"resolutions": [32, 64], "upsample_at": [0.5]},
    "tensorf": {"init_res": 32, "final_res": 64},
    "kilonerf": {"network_resolution": 8, "grid_resolution": 64},
}
TRAIN_STEPS = 40
#: Largest test-PSNR gap (dB) between the two runs. Measured (1 thread): ngp and tensorf equal
#: to 1e-5 dB, plenoxels 1e-4 dB; kilonerf 0.053 dB, all of it from rendering: the fused
#: renderer skips the colour of samples of weight <= render_min_weight, the generic rounds the
#: twins take do not (either run's model scores the same under the other's renderer).
PSNR_GAP_DB = 0.25


def _train_and_test(ds, out, method: str) -> float:
    """Test PSNR (at half resolution, to keep the twins' renders short) after TRAIN_STEPS."""
    cfg = TrainConfig(method=method, max_steps=TRAIN_STEPS, seed=0, progress=False,
                      options={"samples_per_batch": 8192, "grid_update_every": 8,
                               **TRAININGS[method]})
    trainer = Trainer(ds, out, cfg)
    trainer.train()
    return evaluate(trainer.model.eval(), ds, "test", with_ssim=False, downscale=2)["psnr"]


@pytest.mark.slow(170)  # rough single-core seconds of this module, mostly these (tests/conftest.py)
@pytest.mark.parametrize("method", list(TRAININGS))
def test_training_with_the_twins_forced_matches_the_kernels(method, tiny_capture, tmp_path,
                                                            monkeypatch):
    """With ``NERFBOT_KERNELS=torch`` a run (training and test renders) calls no numba kernel
    (each raises) and reaches the test PSNR of the kernels' run of the same steps within
    :data:`PSNR_GAP_DB`; both learn the scene (the mean-colour predictor scores ~11 dB)."""
    ds = load_dataset(tiny_capture[0])
    monkeypatch.delenv(ENV_VAR, raising=False)
    fast = _train_and_test(ds, tmp_path / "numba", method)

    asked = []

    def counted_mode():
        asked.append(1)
        return "torch"

    monkeypatch.setenv(ENV_VAR, "torch")
    monkeypatch.setattr(nerfbot.kernels, "kernel_mode", counted_mode)
    forbidden = _forbid_kernels(monkeypatch)
    assert {"nerfbot.kernels.hashgrid.hash_forward", "nerfbot.ops.encodings.sh_encode",
            "nerfbot.kernels.marching._march", "nerfbot.kernels.scan.segment_exclusive_cumsum",
            "nerfbot.kernels.densegrid.grid_gather", "nerfbot.kernels.vm.vm_forward",
            "nerfbot.kernels.kilonerf.chunk_layout"} <= forbidden
    slow = _train_and_test(ds, tmp_path / "torch", method)
    assert asked, "the dispatch point was never consulted"
    assert min(fast, slow) > 13.0, (fast, slow)
    assert abs(fast - slow) < PSNR_GAP_DB, (fast, slow)
