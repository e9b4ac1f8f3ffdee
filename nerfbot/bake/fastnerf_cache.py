"""Bake a trained ``fastnerf`` run into a :class:`~nerfbot.models.fastnerf_cache.FastNeRFCacheModel`
(FastNeRF's caching step, :func:`bake_cache`): F_pos sampled on a sparse grid of bricks, F_dir on
an octahedral map, both quantised.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from tqdm.auto import tqdm

from nerfbot.fields.background import make_background
from nerfbot.fields.fastnerf import RAW_DENSITY_RANGE, FastNeRFField
from nerfbot.kernels import fastnerf_cache as kc
from nerfbot.kernels.fastnerf_cache import BRICK
from nerfbot.models.fastnerf_cache import FastNeRFCacheConfig, FastNeRFCacheModel
from nerfbot.ops.octahedral import direction_grid


# ----------------------------------------------------------------------------- baking
def bake_cache(model, spec: dict, np_: int, nd: int, progress: bool = True,
               alpha_threshold: float = 1e-3, batch_bricks: int = 2048):
    """Cache a trained ``fastnerf`` model's two networks on grids (FastNeRF's caching step).

    F_pos is cached on a grid of NP cells per axis over the scene cube (NP rounded up to a
    multiple of the brick size B = 4; vertex spacing cube / NP), sparsely, in bricks of B^3
    cells that store their (B + 1)^3 vertices together (a trilinear lookup reads one brick, a
    few adjacent cache lines, and consecutive samples along a ray mostly the same brick). A
    brick is stored when it holds an *occupied* cell: one the source's occupancy grid marks
    occupied where the density at some corner exceeds ``alpha_threshold / dt`` (dt: the
    source's marching step), i.e. where one marching step could be more than
    ``alpha_threshold`` opaque. Trilinear interpolation of the raw density (the argument of
    exp) never exceeds its corners, so an empty cell hides at most that much opacity per step.
    F_dir is cached on the ND x ND vertices of an octahedral map.

    Args:
        model: the loaded ``fastnerf`` model (an OccupancyModel around a :class:`FastNeRFField`).
        spec: its run spec (method, aabb, background, options, seed, conditioning).
        np_: cells per axis of the position cache (>= 1); nd: vertices per axis of the direction
            cache (>= 2).
        progress: show progress bars while evaluating F_pos.
        alpha_threshold: opacity per marching step below which a cell counts as empty.
        batch_bricks: bricks per F_pos evaluation.
    Returns:
        (baked FastNeRFCacheModel, its spec, extra) with extra = cache_mb, occupied_cells, bricks,
        np (as rounded), nd, alpha_threshold.
    """
    field = getattr(model, "field", None)
    if not isinstance(field, FastNeRFField) or not hasattr(model, "grid"):
        raise ValueError(f"bake --cache needs a 'fastnerf' run, got method {spec.get('method')!r}")
    np_, nd = int(np_), int(nd)
    if np_ < 1 or nd < 2:
        raise ValueError(f"--cache NP,ND needs NP >= 1 and ND >= 2, got {np_},{nd}")
    if not alpha_threshold >= 0.0:
        raise ValueError(f"alpha_threshold must be >= 0, got {alpha_threshold}")
    model.eval()
    nb = -(-np_ // BRICK)
    nc = nb * BRICK
    cube_min = field.normalize.cube_min.double().cpu().numpy()
    spacing = float(field.normalize.cube_size) / nc
    src_occ = model.grid.occupied.cpu().numpy().astype(np.uint8)
    sigma_min = alpha_threshold / float(model.dt_min)
    raw_min = math.log(sigma_min) if sigma_min > 0 else -math.inf

    # cells overlapping occupied source cells, gathered per brick: (NB^3, B, B, B)
    lo, hi = kc.overlap_ranges(nc, src_occ.shape[0])
    cells = np.zeros((nc,) * 3, np.uint8)
    kc.candidate_cells(src_occ, lo, hi, cells)
    cells = cells.reshape(nb, BRICK, nb, BRICK, nb, BRICK).transpose(0, 2, 4, 1, 3, 5) \
        .reshape(nb ** 3, BRICK, BRICK, BRICK)
    candidates = np.flatnonzero(cells.any(axis=(1, 2, 3)))
    order = morton_code(np.stack(np.unravel_index(candidates, (nb,) * 3), -1))
    candidates = candidates[np.argsort(order, kind="stable")]

    # pass 1: which candidate bricks hold an occupied cell, and the channel ranges
    keep = np.zeros(candidates.size, bool)
    lo_ch = np.full(1 + 3 * field.components, np.inf)
    hi_ch = np.full(1 + 3 * field.components, -np.inf)
    n_cells = 0
    for s, v in _brick_outputs(field, candidates, nb, cube_min, spacing, batch_bricks, progress,
                               "bake: occupancy"):
        occupied = (_cell_max(v[..., 0]) > raw_min) & (cells[candidates[s:s + len(v)]] != 0)
        cells[candidates[s:s + len(v)]] = occupied
        kept = occupied.any(axis=(1, 2, 3))
        keep[s:s + len(v)] = kept
        n_cells += int(occupied.sum())
        if kept.any():
            flat = v[kept].reshape(-1, v.shape[-1])
            lo_ch = np.minimum(lo_ch, flat.min(0))
            hi_ch = np.maximum(hi_ch, flat.max(0))
    stored = candidates[keep]
    bricks = np.full(nb ** 3, -1, np.int32)
    bricks[stored] = np.arange(stored.size, dtype=np.int32)

    # the coarse occupancy the renderer marches: cells of the source's grid holding occupied
    # cache cells (and occupied in the source: it never sampled its empty cells)
    coarse = np.zeros_like(src_occ)
    occupied_cells = cells.reshape(nb, nb, nb, BRICK, BRICK, BRICK).transpose(0, 3, 1, 4, 2, 5) \
        .reshape(nc, nc, nc)
    kc.mark_coarse(np.ascontiguousarray(occupied_cells), lo, hi, coarse)
    coarse &= src_occ
    del cells, occupied_cells

    # pass 2: F_pos at the stored bricks' vertices, quantised per channel: the raw density to
    # int16 (exp() magnifies its errors), the colour components to uint8
    scale, offset = np.empty_like(lo_ch, np.float32), np.empty_like(lo_ch, np.float32)
    scale[:1], offset[:1] = quantization(lo_ch[:1], hi_ch[:1], np.int16)
    scale[1:], offset[1:] = quantization(lo_ch[1:], hi_ch[1:], np.uint8)
    v1 = BRICK + 1
    density = np.empty((stored.size, v1, v1, v1), np.int16)
    colors = np.empty((stored.size, v1, v1, v1, lo_ch.size - 1), np.uint8)
    for s, v in _brick_outputs(field, stored, nb, cube_min, spacing, batch_bricks, progress,
                               "bake: cache"):
        density[s:s + len(v)] = quantize(v[..., 0], scale[0], offset[0], np.int16)
        colors[s:s + len(v)] = quantize(v[..., 1:], scale[1:], offset[1:], np.uint8)

    with torch.no_grad():
        dir_weights = field.direction_weights(direction_grid(nd).reshape(-1, 3)).float()
    dir_weights = dir_weights.reshape(nd, nd, -1)

    options = {"np": nc, "nd": nd}
    src_opts = spec.get("options", {})
    for key in ("render_steps", "cone_angle", "early_stop_transmittance"):
        if key in src_opts:
            options[key] = src_opts[key]
    baked_spec = {**spec, "method": "fastnerf_cache", "options": options}
    baked = FastNeRFCacheModel(np.asarray(spec["aabb"], np.float32),
                               make_background(spec["background"]), FastNeRFCacheConfig(**options))
    baked.field.set_cache(torch.from_numpy(bricks.reshape((nb,) * 3)), torch.from_numpy(density),
                          torch.from_numpy(colors), torch.from_numpy(scale),
                          torch.from_numpy(offset),
                          torch.from_numpy(coarse), dir_weights)
    baked.background.load_state_dict(model.background.state_dict())
    baked.eval()
    extra = {"cache_mb": round(baked.field.cache_bytes() / 1e6, 3), "occupied_cells": n_cells,
             "bricks": int(stored.size), "np": nc, "nd": nd, "alpha_threshold": alpha_threshold}
    return baked, baked_spec, extra


def _cell_max(v: np.ndarray) -> np.ndarray:
    """(n, B+1, B+1, B+1) vertex values -> (n, B, B, B) the largest of each cell's 8 corners."""
    bs = v.shape[1] - 1
    out = v[:, :-1, :-1, :-1]
    for c in range(1, 8):
        a, b, d = (c >> 2) & 1, (c >> 1) & 1, c & 1
        out = np.maximum(out, v[:, a:a + bs, b:b + bs, d:d + bs])
    return out


@torch.no_grad()
def _brick_outputs(field: FastNeRFField, bricks: np.ndarray, nb: int, cube_min, spacing: float,
                   batch: int, progress: bool, desc: str):
    """Yield (first, values) for batches of bricks (flat indices into (NB, NB, NB)): F_pos at
    their vertices, values (n, B+1, B+1, B+1, 1 + 3D) float32 numpy, the raw density (channel 0)
    clamped to :data:`RAW_DENSITY_RANGE`."""
    v1 = BRICK + 1
    local = np.stack(np.meshgrid(*[np.arange(v1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    for s in tqdm(range(0, bricks.size, batch), desc=desc, unit="batch", disable=not progress,
                  leave=False):
        ijk = np.stack(np.unravel_index(bricks[s:s + batch], (nb,) * 3), -1) * BRICK
        vertices = (ijk[:, None, :] + local[None]).reshape(-1, 3)
        x = torch.from_numpy((cube_min + vertices * spacing).astype(np.float32))
        raw, u = field.position_outputs(x)
        v = torch.cat([raw.float().clamp(*RAW_DENSITY_RANGE)[:, None], u.float()], 1)
        yield s, v.numpy().reshape(len(ijk), v1, v1, v1, -1)


def morton_code(ijk: np.ndarray) -> np.ndarray:
    """Z-order codes (N,) int64 of grid coordinates ijk (N, 3) < 2^21: sorting rows by them
    keeps the corners of a cell, and the cells along a ray, close together in memory."""
    def spread(v):
        v = v.astype(np.int64) & 0x1FFFFF
        v = (v | (v << 32)) & 0x1F00000000FFFF
        v = (v | (v << 16)) & 0x1F0000FF0000FF
        v = (v | (v << 8)) & 0x100F00F00F00F00F
        v = (v | (v << 4)) & 0x10C30C30C30C30C3
        return (v | (v << 2)) & 0x1249249249249249

    return (spread(ijk[:, 0]) << 2) | (spread(ijk[:, 1]) << 1) | spread(ijk[:, 2])


def _code_range(dtype) -> tuple[int, int]:
    """The codes used of an integer dtype: symmetric for signed ones ([-32767, 32767] for
    int16), all of them for unsigned ones ([0, 255] for uint8)."""
    info = np.iinfo(dtype)
    return (-info.max, info.max) if info.min < 0 else (0, info.max)


def quantization(lo: np.ndarray, hi: np.ndarray, dtype=np.int16) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel fixed point in integer ``dtype`` for values in [lo, hi] (C,): scale, offset
    (C,) float32 with v ~= q * scale + offset for the codes q of :func:`_code_range` (error
    <= scale / 2). Dequantisation is affine, so it commutes with trilinear interpolation:
    renderers interpolate the integers and dequantise once per sample."""
    q_lo, q_hi = _code_range(dtype)
    lo = np.where(np.isfinite(lo), lo, 0.0)
    hi = np.where(np.isfinite(hi), hi, 0.0)
    scale = np.maximum((hi - lo) / (q_hi - q_lo), 1e-12)
    return scale.astype(np.float32), (lo - q_lo * scale).astype(np.float32)


def quantize(v: np.ndarray, scale: np.ndarray, offset: np.ndarray, dtype=np.int16) -> np.ndarray:
    """v (..., C) float -> ``dtype`` codes for :func:`quantization`'s scale and offset."""
    q_lo, q_hi = _code_range(dtype)
    return np.rint((v - offset) / scale).clip(q_lo, q_hi).astype(dtype)
