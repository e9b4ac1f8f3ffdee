"""Numba CPU kernels of the PlenOctree renderer: point lookup, ray walking, fused rendering.

Octree layout (flat arrays, built by :func:`nerfbot.models.plenoctree.build_octree`):

* ``child``: (nodes, 8) int32. Node 0 is the root and covers the cube
  ``[cube_min, cube_min + cube_size]^3``; each node splits its cell in 2 x 2 x 2. The child in
  slot ``c = 4 bx + 2 by + bz`` (``b = 1`` for the upper half along an axis; a point on the
  split plane goes to the upper half) is ``v >= 0``: internal node ``v``; ``v == -1``: empty
  space; ``v <= -2``: leaf number ``-2 - v``.
* ``leaf_data``: (leaves, 1 + 3 n_sh) float32: density (1/m; negative values read as 0), then
  the SH coefficients of red, green and blue (channel-major); rgb = sigmoid(SH(d) . k).

A ray is walked cell by cell: from the current distance ``t`` the cell holding the point just
beyond it (``t + eps``) is found by descending from the root, and the ray jumps to where it
leaves that cell. Empty cells are skipped whole, however large; a leaf contributes one segment
with its constant density and colour (PlenOctrees' piecewise-constant model).

The plain-torch twins are :func:`nerfbot.models.plenoctree.octree_lookup_reference` and
:func:`nerfbot.models.plenoctree.walk_segments_reference`; the fused renderer's twin is the
differentiable path (segments + :func:`nerfbot.ops.rendering.composite`). Tests assert they agree.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from nerfbot.kernels.boxes import ray_box
from nerfbot.kernels.pixels import finish_pixel, sigmoid32
from nerfbot.kernels.schedule import block_range
from nerfbot.kernels.sh import sh_basis

EMPTY = -1
#: Floating-point liberties of the fused renderer: reassociation and contraction (so the SH
#: dot products vectorise) but no "finite math only": the walker relies on inf.
_SHADE_MATH = {"nsz", "arcp", "contract", "reassoc", "afn"}
#: Rays per work item of the parallel loops (a block shares its scratch arrays; blocks are
#: visited in the scattered order of :mod:`nerfbot.kernels.schedule`).
_BLOCK = 32
#: Entries of the ancestor stack of a walk: deeper than any tree (MAX_DEPTH in plenoctree.py).
_STACK = 32
#: Step past a cell boundary, relative to the cube edge, when locating the next cell.
_EPS_REL = 1e-7


@njit(inline="always")
def _descend(child, px, py, pz, x0, y0, z0, size):
    """(value, cell corner x, y, z, cell edge) of the deepest child cell holding the point."""
    node = 0
    while True:
        size *= 0.5
        c = 0
        if px >= x0 + size:
            x0 += size
            c += 4
        if py >= y0 + size:
            y0 += size
            c += 2
        if pz >= z0 + size:
            z0 += size
            c += 1
        v = child[node, c]
        if v < 0:
            return v, x0, y0, z0, size
        node = v


@njit(inline="always")
def _locate(child, px, py, pz, nodes, corners, level, gsize):
    """:func:`_descend` that resumes from a stack of ancestors: ``nodes[l]``, ``corners[l]``
    (level l, edge ``gsize / 2^l``) hold the path to the last cell found, ``level`` its
    parent's level. Climbs to the deepest ancestor containing the point (consecutive cells
    along a ray are mostly siblings), descends from there and updates the stack.
    Returns (value, parent level, cell corner x, y, z, cell edge)."""
    size = gsize / (1 << level)
    while level > 0:
        x0, y0, z0 = corners[level, 0], corners[level, 1], corners[level, 2]
        if (x0 <= px < x0 + size and y0 <= py < y0 + size and z0 <= pz < z0 + size):
            break
        level -= 1
        size *= 2.0
    node = nodes[level]
    x0, y0, z0 = corners[level, 0], corners[level, 1], corners[level, 2]
    while True:
        size *= 0.5
        c = 0
        if px >= x0 + size:
            x0 += size
            c += 4
        if py >= y0 + size:
            y0 += size
            c += 2
        if pz >= z0 + size:
            z0 += size
            c += 1
        v = child[node, c]
        if v < 0:
            return v, level, x0, y0, z0, size
        node = v
        level += 1
        nodes[level] = node
        corners[level, 0] = x0
        corners[level, 1] = y0
        corners[level, 2] = z0


@njit(inline="always")
def _exit(o0, o1, o2, i0, i1, i2, x0, y0, z0, size):
    """Ray distance at which a ray (origin o, inverse direction i; inf for a zero component)
    leaves the box [corner, corner + size]^3."""
    t = np.inf
    if i0 > 0:
        t = min(t, (x0 + size - o0) * i0)
    elif i0 < 0:
        t = min(t, (x0 - o0) * i0)
    if i1 > 0:
        t = min(t, (y0 + size - o1) * i1)
    elif i1 < 0:
        t = min(t, (y0 - o1) * i1)
    if i2 > 0:
        t = min(t, (z0 + size - o2) * i2)
    elif i2 < 0:
        t = min(t, (z0 - o2) * i2)
    return t


@njit(inline="always")
def _inverse(d):
    return 1.0 / d if abs(d) > 1e-12 else 0.0


@njit(inline="always")
def _next_cell(child, o0, o1, o2, d0, d1, d2, i0, i1, i2, t, t_far, gsize, eps, nodes, corners,
               level):
    """(value, segment end, stack level) of the cell the ray enters at ``t`` (see
    :func:`_locate` for the stack). A zero inverse-direction component means the ray never
    crosses that axis's faces."""
    tm = t + eps
    v, level, x0, y0, z0, s = _locate(child, o0 + tm * d0, o1 + tm * d1, o2 + tm * d2, nodes,
                                      corners, level, gsize)
    te = min(_exit(o0, o1, o2, i0, i1, i2, x0, y0, z0, s), t_far)
    if te <= tm:  # rounding at a boundary: always make progress
        te = min(tm + eps, t_far)
    return v, te, level


@njit(inline="always")
def _reset_stack(nodes, corners, gmin):
    nodes[0] = 0
    corners[0, 0], corners[0, 1], corners[0, 2] = gmin[0], gmin[1], gmin[2]
    return 0


@njit(parallel=True, fastmath=False, cache=True, nogil=True)
def octree_lookup(points, child, gmin, gsize, out):
    """Leaf holding each point, or -1 (empty space or outside the cube).

    Args:
        points: (N, 3) float32 world points, metres.
        child: (nodes, 8) int32 child table; gmin: (3,) float64 cube corner; gsize: cube edge.
        out: (N,) int64 output.
    """
    for n in prange(points.shape[0]):
        px, py, pz = np.float64(points[n, 0]), np.float64(points[n, 1]), np.float64(points[n, 2])
        inside = (gmin[0] <= px <= gmin[0] + gsize and gmin[1] <= py <= gmin[1] + gsize
                  and gmin[2] <= pz <= gmin[2] + gsize)
        out[n] = -1
        if inside:
            v, _, _, _, _ = _descend(child, px, py, pz, gmin[0], gmin[1], gmin[2], gsize)
            if v <= -2:
                out[n] = -2 - v


@njit(parallel=True, fastmath=False, cache=True, nogil=True)
def _walk(origins, dirs, t_near, t_far, child, sigma, gmin, gsize, stop, fill, starts,
          ray_indices, leaf_indices, t_starts, t_ends, counts):
    """Both passes of the segment walker: counts (``fill`` False) or writes (``fill`` True)."""
    eps = _EPS_REL * gsize
    n_rays = origins.shape[0]
    for b in prange((n_rays + _BLOCK - 1) // _BLOCK):
        nodes = np.empty(_STACK, np.int64)
        corners = np.empty((_STACK, 3), np.float64)
        r0, r1 = block_range(b, n_rays, _BLOCK)
        for r in range(r0, r1):
            o0, o1, o2 = np.float64(origins[r, 0]), np.float64(origins[r, 1]), np.float64(origins[r, 2])
            d0, d1, d2 = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
            i0, i1, i2 = _inverse(d0), _inverse(d1), _inverse(d2)
            t, tf = np.float64(t_near[r]), np.float64(t_far[r])
            level = _reset_stack(nodes, corners, gmin)
            trans = 1.0
            n = 0
            k = starts[r] if fill else 0
            while t < tf and trans >= stop:
                v, te, level = _next_cell(child, o0, o1, o2, d0, d1, d2, i0, i1, i2, t, tf, gsize,
                                          eps, nodes, corners, level)
                if v <= -2:
                    leaf = -2 - v
                    if fill:
                        ray_indices[k] = r
                        leaf_indices[k] = leaf
                        t_starts[k] = t
                        t_ends[k] = te
                        k += 1
                    n += 1
                    trans *= math.exp(-max(np.float64(sigma[leaf]), 0.0) * (te - t))
                t = te
            if not fill:
                counts[r] = n


_NO_I64 = np.empty(0, np.int64)
_NO_F32 = np.empty(0, np.float32)


def walk_count(origins, dirs, t_near, t_far, child, sigma, gmin, gsize, stop, counts):
    """Count the leaf segments of every ray (first pass of :func:`walk_fill`).

    Args:
        origins, dirs: (R, 3) float32 rays (unit directions), metres.
        t_near, t_far: (R,) float32 where walking starts / stops (inside the cube).
        child: (nodes, 8) int32; sigma: (leaves,) float32 leaf densities (1/m, < 0 reads as 0);
        gmin: (3,) float64 cube corner; gsize: cube edge, metres.
        stop: a ray stops after the segment that brings its transmittance below this
            (0: never).
        counts: (R,) int64 output.
    """
    _walk(origins, dirs, t_near, t_far, child, sigma, gmin, gsize, stop, False, _NO_I64,
          _NO_I64, _NO_I64, _NO_F32, _NO_F32, counts)


def walk_fill(origins, dirs, t_near, t_far, child, sigma, gmin, gsize, stop, starts, ray_indices,
              leaf_indices, t_starts, t_ends):
    """Write the leaf segments counted by :func:`walk_count` (same arguments), packed by ray
    from ``starts`` (R,): ray_indices, leaf_indices (M,) int64, t_starts, t_ends (M,) float32."""
    _walk(origins, dirs, t_near, t_far, child, sigma, gmin, gsize, stop, True, starts,
          ray_indices, leaf_indices, t_starts, t_ends, _NO_I64)


@njit(parallel=True, fastmath=_SHADE_MATH, cache=True, nogil=True)
def octree_render(origins, dirs, box, child, leaf_data, leaf_sigma, gmin, gsize, stop,
                  min_weight, background, slot_start, slot_cap, rgb, opacity, depth, far, counts,
                  s_ts, s_te, s_sigma, s_w, s_leaf):
    """Fused renderer: walk, composite with early termination, shade (SH colour per leaf).

    Each block of :data:`_BLOCK` rays is rendered in two passes: first every ray is walked and
    composited from the leaves' densities alone (``leaf_sigma``, small enough to stay in cache),
    its segments written to the scratch arrays; then the colours of all the block's segments
    are read from the big table of coefficients, in a loop whose loads do not wait on the walk.

    Args:
        origins, dirs, child, gmin, gsize, stop: as in :func:`walk_count`.
        min_weight: segments of at most this weight are composited but their colour is not
            read: they take the weight-averaged colour of the ray's other segments (0: every
            segment of positive weight is shaded).
        box: (2, 3) float32 scene bounds: rays are walked where they are inside (t_near and
            t_far as :func:`nerfbot.ops.sampling.ray_aabb` computes them).
        leaf_data: (leaves, 1 + 3 n_sh) float32 (see the module docstring); leaf_sigma: (leaves,)
            float32, its first column.
        background: (R, 3) float32 colour behind each ray.
        slot_start, slot_cap: (R,) int64 where ray r may write its segments in the scratch
            arrays and how many fit. A ray with more (``counts[r] > slot_cap[r]``) writes the
            first ``slot_cap[r]`` only and gets no colour: the caller renders it again with
            more room.
        rgb: (R, 3), opacity, depth (expected ray distance; 0 where opacity is 0), far
            (t_far): (R,) float32 outputs;
        counts: (R,) int64 output, leaf segments composited per ray.
        s_ts, s_te, s_sigma, s_w: float32 scratch: each segment's start, end, density, weight;
            s_leaf: int32 scratch, its leaf.

    Weights follow :mod:`nerfbot.ops.rendering`: w_i = T_i (1 - exp(-tau_i)), tau_i = sigma_i dt_i,
    in float64.
    """
    n_sh = (leaf_data.shape[1] - 1) // 3
    degree = int(round(math.sqrt(n_sh))) - 1
    eps = _EPS_REL * gsize
    n_rays = origins.shape[0]
    for b in prange((n_rays + _BLOCK - 1) // _BLOCK):
        basis = np.empty(25, np.float32)
        nodes = np.empty(_STACK, np.int64)
        corners = np.empty((_STACK, 3), np.float64)
        left = np.empty(_BLOCK, np.float64)
        r0, r1 = block_range(b, n_rays, _BLOCK)
        # 1. walk and composite densities
        for r in range(r0, r1):
            o0, o1, o2 = np.float64(origins[r, 0]), np.float64(origins[r, 1]), np.float64(origins[r, 2])
            d0, d1, d2 = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
            i0, i1, i2 = _inverse(d0), _inverse(d1), _inverse(d2)
            t, tf = ray_box(origins, dirs, r, box)
            level = _reset_stack(nodes, corners, gmin)
            trans = 1.0
            dsum = 0.0
            n = 0
            k, cap = slot_start[r], slot_cap[r]
            while t < tf and trans >= stop:
                v, te, level = _next_cell(child, o0, o1, o2, d0, d1, d2, i0, i1, i2, t, tf, gsize,
                                          eps, nodes, corners, level)
                if v <= -2:
                    leaf = -2 - v
                    sig = max(np.float64(leaf_sigma[leaf]), 0.0)
                    after = trans * math.exp(-sig * (te - t))
                    w = trans - after
                    dsum += w * 0.5 * (t + te)
                    if n < cap:
                        s_ts[k + n] = t
                        s_te[k + n] = te
                        s_sigma[k + n] = sig
                        s_w[k + n] = w
                        s_leaf[k + n] = leaf
                    trans = after
                    n += 1
                t = te
            op = 1.0 - trans
            counts[r] = n
            far[r] = tf
            opacity[r] = op
            depth[r] = dsum / op if op > 0.0 else 0.0
            left[r - r0] = trans
        # 2. colours: the block's segments, in float32 as the torch path computes them
        for q in range(r0, r1):
            first, last = slot_start[q], slot_start[q] + counts[q]
            if counts[q] > slot_cap[q]:
                continue
            sh_basis(np.float64(dirs[q, 0]), np.float64(dirs[q, 1]), np.float64(dirs[q, 2]),
                     degree, basis)
            cr, cg, cb = 0.0, 0.0, 0.0
            w_all = 0.0
            w_read = 0.0
            for j in range(first, last):
                wj = np.float64(s_w[j])
                w_all += wj
                if wj > min_weight:
                    w_read += wj
                    lj = s_leaf[j]
                    kr, kg, kb = np.float32(0.0), np.float32(0.0), np.float32(0.0)
                    for i in range(n_sh):
                        kr += leaf_data[lj, 1 + i] * basis[i]
                        kg += leaf_data[lj, 1 + n_sh + i] * basis[i]
                        kb += leaf_data[lj, 1 + 2 * n_sh + i] * basis[i]
                    cr += wj * sigmoid32(kr)
                    cg += wj * sigmoid32(kg)
                    cb += wj * sigmoid32(kb)
            finish_pixel(rgb, q, cr, cg, cb, w_all, w_read, left[q - r0], background)


@njit(parallel=True, fastmath=False, cache=True, nogil=True)
def pack_segments(counts, src_start, starts, opacity, depth, far, empty_opacity, s_ts, s_te,
                  s_sigma, s_w, ray_indices, t_starts, t_ends, sigmas, weights, median):
    """Pack the scratch segments of :func:`octree_render` by ray and finish the depths.

    Args:
        counts, src_start: (R,) segments of each ray and where they are in the scratch arrays.
        starts: (R,) where each ray's segments go in the packed outputs (exclusive cumsum).
        opacity, far: (R,) float32 from :func:`octree_render`; depth (R,) is updated in place:
            ``far`` where the opacity is at most ``empty_opacity``.
        s_ts, s_te, s_sigma, s_w: the scratch arrays.
        ray_indices (M,) int64, t_starts, t_ends, sigmas, weights (M,) float32: packed outputs.
        median: (R,) float32 output: the midpoint of the first segment where the accumulated
            weight (float64) reaches half the opacity (:func:`nerfbot.ops.rendering.median_depth`),
            ``far`` for empty rays.
    """
    for r in prange(counts.shape[0]):
        src, dst = src_start[r], starts[r]
        half = 0.5 * np.float64(opacity[r])
        med = np.inf
        cum = 0.0
        for j in range(counts[r]):
            ray_indices[dst + j] = r
            t_starts[dst + j] = s_ts[src + j]
            t_ends[dst + j] = s_te[src + j]
            sigmas[dst + j] = s_sigma[src + j]
            weights[dst + j] = s_w[src + j]
            cum += np.float64(s_w[src + j])
            if med == np.inf and cum >= half:
                med = np.float32(0.5) * (s_ts[src + j] + s_te[src + j])
        empty = opacity[r] <= empty_opacity
        if empty:
            depth[r] = far[r]
        median[r] = far[r] if empty or med == np.inf else med
