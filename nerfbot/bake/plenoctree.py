"""Bake a trained ``plenoctree`` (NeRF-SH) run into a
:class:`~nerfbot.models.plenoctree.PlenOctreeModel` (:func:`bake_octree`): leaves where the source
is dense, visibility pruning on the training cameras, and optional fine-tuning of the leaves on
the training images (:func:`finetune_octree`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from nerfbot.data.pixels import PixelBank
from nerfbot.fields.background import make_background
from nerfbot.fields.base import Field
from nerfbot.fields.nerfsh import NeRFSHField
from nerfbot.models.base import Model
from nerfbot.models.plenoctree import (MAX_DEPTH, PlenOctreeConfig, PlenOctreeModel, build_octree,
                                      leaf_cells, walk_segments)
from nerfbot.ops.cameras import Rays
from nerfbot.ops.rendering import render_weights
from nerfbot.ops.sampling import ray_aabb
from nerfbot.ops.schedules import learning_rate


log = logging.getLogger(__name__)


@dataclass
class OctreeBakeConfig:
    """Options of baking a PlenOctree that the baked renderer does not keep (the bake recipe
    of ``plenoctree_octree``; the octree's ``depth`` is a :class:`PlenOctreeConfig` option)."""

    finetune_steps: int = 0
    """Steps of fine-tuning the baked leaves on the training images (:func:`finetune_octree`);
    0: none."""

    def __post_init__(self):
        if self.finetune_steps < 0:
            raise ValueError(f"option finetune_steps: must be >= 0, got {self.finetune_steps}")


# -- baking ----------------------------------------------------------------------------------
def _coarse_cells(model: Model, level: int) -> np.ndarray:
    """(N, 3) int64 cells at ``level`` that overlap an occupied cell of the source's occupancy
    grid (every cell when the model has none). Grid and octree span the same cube."""
    grid = getattr(model, "grid", None)
    n = 2 ** level
    if grid is None:
        idx = np.arange(n)
        return np.stack(np.meshgrid(idx, idx, idx, indexing="ij"), -1).reshape(-1, 3)
    g = grid.occupied.shape[0]
    occ = np.argwhere(grid.occupied.cpu().numpy() != 0).astype(np.int64)
    lo = (occ * n) // g
    hi = -((-(occ + 1) * n) // g) - 1  # ceil((i + 1) n / g) - 1
    span = int((hi - lo).max()) + 1 if occ.size else 1
    cells = []
    for a in range(span):
        for b in range(span):
            for c in range(span):
                cand = lo + np.array([a, b, c])
                cells.append(cand[(cand <= hi).all(-1)])
    cells = np.concatenate(cells) if cells else np.zeros((0, 3), np.int64)
    return np.unique(cells, axis=0)


@torch.no_grad()
def _candidate_leaves(field: Field, cube_min: torch.Tensor, cube_size: float, coarse: np.ndarray,
                      level: int, depth: int, min_density: float, chunk: int, bar) -> np.ndarray:
    """(L, 3) leaf cells at ``depth`` inside the ``coarse`` cells (at ``level``) where the
    density at one of the leaf's 8 corners reaches ``min_density``: a conservative test, a
    surface passing through a leaf between sample points still marks it."""
    m = 2 ** (depth - level)
    lattice = torch.stack(torch.meshgrid(*(torch.arange(m + 1),) * 3, indexing="ij"), -1)
    lattice = lattice.reshape(-1, 3)
    per = max(1, chunk // lattice.shape[0])
    leaf_edge = cube_size / 2 ** depth
    kept = []
    for i in range(0, len(coarse), per):
        cells = torch.from_numpy(coarse[i:i + per])
        corners = cells[:, None, :] * m + lattice[None]                       # (C, (m+1)^3, 3)
        x = cube_min + corners.reshape(-1, 3).float() * leaf_edge
        sigma = field.density(x)[0].reshape(-1, m + 1, m + 1, m + 1)
        dense = sigma >= min_density
        any_corner = torch.zeros(dense.shape[0], m, m, m, dtype=torch.bool)
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    any_corner |= dense[:, a:a + m, b:b + m, c:c + m]
        ci, a, b, c = torch.nonzero(any_corner, as_tuple=True)
        kept.append((cells[ci] * m + torch.stack([a, b, c], -1)).numpy())
        bar.update(len(cells))
    return np.concatenate(kept) if kept else np.zeros((0, 3), np.int64)


@torch.no_grad()
def _leaf_values(field: Field, cube_min: torch.Tensor, cube_size: float, leaves: np.ndarray,
                 depth: int, samples_per_leaf: int, generator: torch.Generator, chunk: int,
                 bar) -> np.ndarray:
    """(L, 1 + 3 n_sh) float32: density and SH coefficients averaged over ``samples_per_leaf``
    = s^3 stratified points per leaf (one jittered point in each of s^3 sub-cells; s = 1:
    the leaf centre exactly)."""
    s = round(samples_per_leaf ** (1.0 / 3.0))
    sub = torch.stack(torch.meshgrid(*(torch.arange(s),) * 3, indexing="ij"), -1).reshape(-1, 3)
    leaf_edge = cube_size / 2 ** depth
    per = max(1, chunk // sub.shape[0])
    out = []
    for i in range(0, len(leaves), per):
        cells = torch.from_numpy(leaves[i:i + per]).float()
        if s == 1:
            frac = torch.full((len(cells), 1, 3), 0.5)
        else:
            frac = (sub[None] + torch.rand(len(cells), sub.shape[0], 3, generator=generator)) / s
        x = cube_min + (cells[:, None, :] + frac).reshape(-1, 3) * leaf_edge
        sigma, coeffs = field.density(x)
        values = torch.cat([sigma[:, None], coeffs], -1).reshape(len(cells), sub.shape[0], -1)
        out.append(values.mean(1).float().numpy())
        bar.update(len(cells))
    return np.concatenate(out) if out else np.zeros((0, 1 + 3 * field.n_sh), np.float32)


def _default_min_density(model: Model) -> float:
    """The density below which the source's own renderer skips space: one marching step
    ``dt_min`` through it is less than the grid threshold opaque (1/m); 1.0 without a grid."""
    grid, dt = getattr(model, "grid", None), getattr(model, "dt_min", None)
    if grid is None or not dt:
        return 1.0
    return float(grid.threshold) / float(dt)


def bake_octree(model: Model, spec: dict, depth: int, dataset=None, finetune_steps: int = 0,
                seed: int = 0, progress: bool = True, samples_per_leaf: int = 8,
                min_density: Optional[float] = None, prune_weight: float = 0.01,
                chunk: int = 1 << 17) -> tuple[PlenOctreeModel, dict, dict]:
    """Bake a trained ``plenoctree`` (NeRF-SH) model into a :class:`PlenOctreeModel`.

    Leaves (cells of cube / 2^depth) are kept inside the occupied cells of the source's
    occupancy grid where a leaf corner's density reaches ``min_density`` (1/m; default: where
    the source's own marching would stop skipping, see :func:`_default_min_density`). Each
    leaf stores the density and SH coefficients averaged over ``samples_per_leaf`` (1, 8, 27,
    ...) stratified jittered points. With a ``dataset``, leaves whose largest rendering weight
    over the training pixels stays below ``prune_weight`` are then removed (PlenOctrees'
    visibility pruning: hidden interiors and faint fog, which cost rendering time and memory
    but barely change a pixel; 0 keeps all). With ``finetune_steps`` > 0 the leaves are
    finally optimised on the training images of ``dataset`` (:func:`finetune_octree`).

    Returns:
        (baked model in eval mode, its spec: the source's with method ``plenoctree_octree``
        and options {"depth", "sh_degree"}, extra: octree_mb, leaves, nodes, depth,
        samples_per_leaf, min_density, leaves_baked (before pruning), prune_weight (when
        pruned), bake_seconds and, when fine-tuned,
        finetune_psnr_before / finetune_psnr_after / finetune_steps).
    """
    field = model.field
    if not isinstance(field, NeRFSHField):
        raise ValueError(f"an octree is baked from a 'plenoctree' (NeRF-SH) run; method "
                         f"{spec.get('method')!r} has a {type(field).__name__}")
    if not 1 <= int(depth) <= MAX_DEPTH:
        raise ValueError(f"octree depth must be 1..{MAX_DEPTH}, got {depth}")
    s = round(samples_per_leaf ** (1.0 / 3.0)) if samples_per_leaf > 0 else 0
    if samples_per_leaf < 1 or s ** 3 != samples_per_leaf:
        raise ValueError(f"samples_per_leaf must be a cube (1, 8, 27, ...), got {samples_per_leaf}")
    if finetune_steps < 0:
        raise ValueError(f"finetune_steps must be >= 0, got {finetune_steps}")
    if not 0.0 <= prune_weight < 1.0:
        raise ValueError(f"prune_weight must be in [0, 1), got {prune_weight}")
    if finetune_steps and dataset is None:
        raise ValueError("fine-tuning the octree needs the training dataset")
    depth = int(depth)
    t0 = time.perf_counter()
    min_density = _default_min_density(model) if min_density is None else float(min_density)
    model.eval()
    cube_min = field.normalize.cube_min.float().cpu()
    cube_size = float(field.normalize.cube_size)
    grid = getattr(model, "grid", None)
    grid_level = math.ceil(math.log2(grid.occupied.shape[0])) if grid is not None else 6
    level = min(depth, grid_level)
    coarse = _coarse_cells(model, level)
    with tqdm(total=len(coarse), disable=not progress, desc="octree: find leaves",
              unit="cell") as bar:
        leaves = _candidate_leaves(field, cube_min, cube_size, coarse, level, depth, min_density,
                                   chunk, bar)
    generator = torch.Generator().manual_seed(seed)
    with tqdm(total=len(leaves), disable=not progress, desc="octree: bake leaves",
              unit="leaf") as bar:
        values = _leaf_values(field, cube_min, cube_size, leaves, depth, samples_per_leaf,
                              generator, chunk, bar)
    child, order = build_octree(leaves, depth)

    baked_spec = {**spec, "method": "plenoctree_octree",
                  "options": {"depth": depth, "sh_degree": field.sh_degree}}
    baked = PlenOctreeModel(np.asarray(spec["aabb"], np.float32),
                            make_background(spec["background"]),
                            PlenOctreeConfig(**baked_spec["options"]))
    baked.field.set_tree(child, values[order])
    baked.background.load_state_dict(model.background.state_dict())
    baked.eval()
    extra = {"depth": depth, "samples_per_leaf": samples_per_leaf, "min_density": min_density,
             "leaves_baked": baked.field.n_leaves}
    if prune_weight > 0 and dataset is not None:
        seen = leaf_visibility(baked, dataset, progress=progress)
        extra["prune_weight"] = prune_with_fidelity(baked, seen, prune_weight, dataset)
    extra.update(octree_mb=round(baked.field.size_mb(), 3), leaves=baked.field.n_leaves,
                 nodes=baked.field.n_nodes)
    if finetune_steps:
        extra.update(finetune_octree(baked, dataset, finetune_steps, seed=seed, progress=progress))
    extra["bake_seconds"] = round(time.perf_counter() - t0, 2)
    return baked, baked_spec, extra


@torch.no_grad()
def leaf_visibility(model: PlenOctreeModel, dataset, supersample: int = 2,
                    chunk: int = 1 << 16, progress: bool = True) -> torch.Tensor:
    """(leaves,) the largest rendering weight each leaf receives from the training cameras
    (0: never seen, hidden behind others, or too faint to matter), over ``supersample``^2 rays
    per pixel: with one ray per pixel, small or low-resolution captures leave leaves between
    pixel centres unseen that test views need (16 views of 32 x 32 lost 1 dB that way)."""
    field = model.field
    best = torch.zeros(field.n_leaves)
    idx = dataset.indices("train")
    cams = dataset.cameras(idx).scaled(supersample)
    sigma = F.relu(field.leaf_data.detach()[:, 0])
    for slot in tqdm(range(len(idx)), disable=not progress, desc="octree: visibility",
                     unit="image"):
        rays = cams.rays(slot)
        for i in range(0, len(rays), chunk):
            sub = rays[i:i + chunk]
            t_near, t_far, _ = ray_aabb(sub.origins, sub.directions, model.aabb)
            ray, leaf, ts, te = walk_segments(sub.origins, sub.directions, t_near, t_far,
                                              field.child, sigma, field.normalize.cube_min,
                                              field.cube_size,
                                              model.config.early_stop_transmittance)
            if ray.numel():
                w, _ = render_weights(sigma[leaf], ts, te, ray, len(sub))
                best.scatter_reduce_(0, leaf, w.float(), reduce="amax")
    return best


#: Pruning may change the training views' renders by at most this (PSNR of the pruned tree's
#: pixels against the unpruned tree's, dB): a mean squared change of 1e-4.
PRUNE_FIDELITY_DB = 40.0


@torch.no_grad()
def prune_with_fidelity(model: PlenOctreeModel, seen: torch.Tensor, prune_weight: float,
                        dataset, views: int = 4, max_halvings: int = 6) -> float:
    """Prune the leaves whose largest weight ``seen`` (leaves,) is below ``prune_weight``, but
    only as far as the first ``views`` training views still render within
    :data:`PRUNE_FIDELITY_DB` of the unpruned tree; otherwise halve the threshold and try again
    (at most ``max_halvings`` times, then keep every leaf).

    The per-leaf weight test alone is not safe: faint density spread over many leaves (a field
    trained briefly, or deeper trees with smaller leaves) adds up along a ray although no single
    leaf reaches the threshold; on a 60-step 32x32 capture a fixed 0.01 cost 4 dB.
    Returns the threshold used (0.0: nothing pruned)."""
    field = model.field
    child, data = field.child.clone(), field.leaf_data.detach().clone()
    idx = dataset.indices("train")[:views]
    cams = dataset.cameras(idx)
    rays = [cams.rays(i) for i in range(len(idx))]
    reference = [model.render_rays(r).rgb for r in rays]
    threshold = prune_weight
    for _ in range(max_halvings + 1):
        prune_leaves(model, (seen >= threshold).numpy())
        mse = torch.stack([F.mse_loss(model.render_rays(r).rgb, ref)
                           for r, ref in zip(rays, reference)]).mean()
        if -10.0 * math.log10(max(float(mse), 1e-12)) >= PRUNE_FIDELITY_DB:
            return threshold
        field.set_tree(child.numpy(), data.numpy())
        threshold *= 0.5
    log.warning("octree: pruning changed the training views at every threshold down to %g; "
                "keeping every leaf", threshold * 2)
    return 0.0


def prune_leaves(model: PlenOctreeModel, keep: torch.Tensor | np.ndarray) -> None:
    """Keep only the leaves where ``keep`` (leaves,) bool is set, rebuilding the tree."""
    field = model.field
    keep = np.asarray(keep, dtype=bool)
    ijk, level = leaf_cells(field.child.numpy())
    if level.size and (level != level[0]).any():
        raise ValueError("pruning needs every leaf at the same depth")
    depth = int(level[0]) if level.size else model.config.depth
    child, order = build_octree(ijk[keep], depth)
    field.set_tree(child, field.leaf_data.detach().numpy()[keep][order])


def _batch_psnr(model: PlenOctreeModel, rays: Rays, target: torch.Tensor) -> float:
    model.eval()
    with torch.no_grad():
        mse = float(F.mse_loss(model.render_rays(rays).rgb, target))
    return -10.0 * math.log10(max(mse, 1e-10))


def finetune_octree(model: PlenOctreeModel, dataset, steps: int, seed: int = 0,
                    lr: float = 1e-2, lr_final_factor: float = 0.1, progress: bool = True,
                    eval_rays: int = 8192) -> dict:
    """Optimise the leaves (density and SH coefficients) on the training images with Adam.

    Adam moves every parameter by about ``lr`` per step, so density is optimised as the optical
    thickness of one leaf edge (sigma * leaf edge), whose useful steps are as small as those of
    the SH coefficients. The background stays fixed. Returns finetune_psnr_before /
    finetune_psnr_after (dB, on one fixed batch of ``eval_rays`` training pixels) and
    finetune_steps.
    """
    bank = PixelBank(dataset, dataset.indices("train"))
    generator = torch.Generator().manual_seed(seed)
    eval_batch, eval_target, _ = bank.sample(eval_rays, generator)
    before = _batch_psnr(model, eval_batch, eval_target)
    field = model.field
    if field.n_leaves == 0:
        return {"finetune_psnr_before": before, "finetune_psnr_after": before,
                "finetune_steps": 0}
    leaf_edge = field.cube_size / 2 ** model.config.depth
    scale = torch.ones(field.leaf_data.shape[1])
    scale[0] = 1.0 / leaf_edge
    z = (field.leaf_data.detach() / scale).clone().requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr, betas=(0.9, 0.99), eps=1e-15)
    model.train()
    bar = tqdm(range(steps), disable=not progress, desc="octree: fine-tune", unit="step")
    for step in bar:
        for group in opt.param_groups:
            group["lr"] = learning_rate(lr, lr_final_factor, step / max(steps, 1))
        rays, target, _ = bank.sample(model.config.rays_per_batch, generator)
        out = model.render_segments(rays, leaf_data=z * scale, with_median=False)
        loss = F.mse_loss(out.rgb, target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 10 == 0:
            bar.set_postfix(psnr=f"{-10 * math.log10(max(loss.item(), 1e-10)):.2f}", refresh=False)
    bar.close()
    with torch.no_grad():
        field.leaf_data.copy_(z * scale)
    after = _batch_psnr(model, eval_batch, eval_target)
    return {"finetune_psnr_before": before, "finetune_psnr_after": after,
            "finetune_steps": steps}
