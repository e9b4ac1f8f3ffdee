"""Driving the fused CPU renderers (FastNeRF cache, KiloNeRF) whose kernels render blocks of
rays and write each ray's samples into its block's region of scratch arrays: room for a few
samples per ray, shared by the block; blocks that outrun it are rendered again with exact room.
The samples are then packed into a :class:`~nerfbot.ops.rendering.RenderOutput`."""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np
import torch

from nerfbot.kernels.packing import pack
from nerfbot.ops.rendering import RenderOutput


class ScratchArrays:
    """Per-sample scratch arrays (one per dtype of ``kinds``; the first four are float32
    t_start, t_end, sigma, weight), kept between calls: fresh memory costs a page fault per
    4 kB on first touch, as much as rendering a few hundred rays."""

    def __init__(self, kinds: tuple):
        self.kinds = kinds
        self.arrays: Optional[tuple] = None

    def get(self, size: int) -> tuple:
        if self.arrays is None or self.arrays[0].shape[0] < size:
            self.arrays = tuple(np.empty(size, k) for k in self.kinds)
        return self.arrays

    def fresh(self, size: int) -> tuple:
        return tuple(np.empty(size, k) for k in self.kinds)


def render_blocks(run: Callable, n_rays: int, block: int, slot_samples: int,
                  scratch: ScratchArrays, z_per_t: torch.Tensor) -> RenderOutput:
    """Render ``n_rays`` rays with a block kernel and pack its samples.

    Args:
        run: ``run(sel, block_cap, scratch) -> (rgb, opacity, depth, far, counts, src_start)``
            renders the rays ``sel`` (an index array; None: all) in blocks of ``block`` rays,
            ``block_cap`` scratch entries per block, and returns numpy arrays: rgb (m, 3),
            opacity, depth (expected ray distance), far (m,) float32, counts and src_start (m,)
            int64 (each ray's samples and where they start in the scratch).
        slot_samples: scratch room per ray of the first pass.
        z_per_t: (R,) for the z-depth.
    """
    n_blocks = -(-n_rays // block)
    block_cap = block * slot_samples
    arrays = scratch.get(n_blocks * block_cap)
    rgb, opacity, depth, far, counts, src_start = run(None, block_cap, arrays)
    # blocks whose rays outran their room: render just their rays again, with exact room
    totals = np.add.reduceat(counts, np.arange(0, n_rays, block))
    full = np.flatnonzero(totals > block_cap)
    if full.size:
        sel = np.concatenate([np.arange(b * block, min(n_rays, (b + 1) * block)) for b in full])
        room = int(np.add.reduceat(counts[sel], np.arange(0, sel.size, block)).max())
        extra = scratch.fresh(-(-sel.size // block) * room)
        again = run(sel, room, extra)
        rgb[sel] = again[0]  # a kernel may leave the colour of rays without room undone
        base = arrays[0].shape[0]
        arrays = tuple(np.concatenate([a, b]) for a, b in zip(arrays, extra))
        src_start = src_start.copy()
        src_start[sel] = base + again[-1]
    starts = np.cumsum(counts) - counts
    m = int(counts.sum())
    ray_indices = np.empty(m, np.int64)
    packed = tuple(np.empty(m, np.float32) for _ in range(4))
    median = np.empty(n_rays, np.float32)
    pack(counts, src_start, starts, opacity, far, *arrays[:4], ray_indices, *packed, median)
    ts, te, sigma, weights = (torch.from_numpy(a) for a in packed)
    depth_t = torch.from_numpy(depth)
    return RenderOutput(rgb=torch.from_numpy(rgb), opacity=torch.from_numpy(opacity),
                        depth=depth_t, z_depth=depth_t * z_per_t,
                        median_depth=torch.from_numpy(median), weights=weights, num_samples=m,
                        ray_indices=torch.from_numpy(ray_indices), t_starts=ts, t_ends=te,
                        sigmas=sigma)
