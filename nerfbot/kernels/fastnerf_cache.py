"""Numba CPU kernels of the FastNeRF cache: baking helpers and the fused renderer.

The cache (see :mod:`nerfbot.models.fastnerf_cache`) is a grid of NC = NB * B cells per axis over
the scene cube (vertex spacing h = cube_size / NC), stored sparsely in bricks of B^3 cells:

* ``bricks`` (NB, NB, NB) int32: the id of brick (I, J, K), or -1 where nothing is stored;
* ``density`` (n_bricks * (B+1)^3,) int16 and ``colors`` (n_bricks * (B+1)^3, 3D) uint8: the
  (B+1)^3 vertices of each brick, vertex (a, b, c) of brick ``id`` (grid vertex
  (B I + a, B J + b, B K + c)) at row ``((id * (B+1) + a) * (B+1) + b) * (B+1) + c``, each
  channel dequantised as ``q * scale + offset``: channel 0 (``density``) is the raw density
  (sigma = exp(min(raw, 15))), channel 1 + 3i + c (``colors[:, 3i + c]``) the component
  u_i[c];
* ``occ`` (G, G, G) uint8: coarse cells of the same cube holding occupied cache cells (for
  empty-space skipping);
* ``dir_weights`` (ND, ND, D) float32: beta at the vertices of the octahedral direction map.

The renderer uses B = :data:`BRICK`. A brick holds all 8 corners of each of its cells, so a
trilinear lookup reads one brick, and consecutive samples along a ray mostly the same one. Points in bricks that are not stored have
zero density. The plain-torch twin of the renderer is
:meth:`nerfbot.models.fastnerf_cache.FastNeRFCacheModel.render_reference`; tests assert they agree.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from nerfbot.kernels.octahedral import bilinear
from nerfbot.kernels.pixels import finish_pixel
from nerfbot.kernels.schedule import scattered

#: Rays per parallel work item of the renderer (scratch arrays are allocated once per item;
#: blocks are visited in the scattered order of :mod:`nerfbot.kernels.schedule`).
RAY_BLOCK = 64
#: B, cells per edge of a cache brick (a power of two: the renderer splits cell indices into
#: brick and offset with shifts).
BRICK = 4
BRICK_SHIFT = 2
BRICK_MASK = BRICK - 1
#: Largest Chebyshev distance (in coarse cells) :func:`empty_distance` records: a ray in an
#: empty cell jumps out of the empty cube of up to 2 * DISTANCE_CAP - 1 cells around it.
DISTANCE_CAP = 16
#: The renderer gathers a ray's samples in rounds of ROUND_MIN, doubling up to ROUND_MAX: their
#: cache lines are fetched together (the lookups are memory-bound), and colours are computed
#: only up to where the ray saturates.
ROUND_MIN = 4
ROUND_MAX = 32
#: Largest raw density: exp(15) = 3.3e6 /m, trunc_exp's ceiling.
RAW_MAX = 15.0
#: fastmath without "nnan" / "ninf": the marcher relies on comparisons with large distances.
_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}


# ----------------------------------------------------------------------------- baking helpers
def overlap_ranges(n_cells: int, g: int) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``n_cells`` fine cells per axis of the cube, the first and last of the ``g``
    coarse cells it overlaps: lo, hi (n_cells,) int64."""
    i = np.arange(n_cells, dtype=np.float64)
    ratio = g / n_cells
    lo = np.floor(i * ratio).astype(np.int64)
    hi = np.ceil((i + 1) * ratio).astype(np.int64) - 1
    return np.clip(lo, 0, g - 1), np.clip(np.maximum(hi, lo), 0, g - 1)


@njit(parallel=True, cache=True)
def candidate_cells(occ, lo, hi, out):
    """out[i, j, k] = 1 where fine cell (i, j, k) overlaps an occupied coarse cell of ``occ``
    (G, G, G) uint8; lo / hi from :func:`overlap_ranges`."""
    n = out.shape[0]
    for i in prange(n):
        for j in range(n):
            for k in range(n):
                hit = 0
                for a in range(lo[i], hi[i] + 1):
                    for b in range(lo[j], hi[j] + 1):
                        for c in range(lo[k], hi[k] + 1):
                            if occ[a, b, c] != 0:
                                hit = 1
                out[i, j, k] = hit


@njit(cache=True)
def mark_coarse(cells, lo, hi, out):
    """out (G, G, G) uint8 = 1 at every coarse cell overlapping a marked cell of ``cells``."""
    m = cells.shape[0]
    for i in range(m):
        for j in range(m):
            for k in range(m):
                if cells[i, j, k] != 0:
                    for a in range(lo[i], hi[i] + 1):
                        for b in range(lo[j], hi[j] + 1):
                            for c in range(lo[k], hi[k] + 1):
                                out[a, b, c] = 1


# ----------------------------------------------------------------------------- renderer
@njit(inline="always")
def _box_exit(rx, ry, rz, ivx, ivy, ivz, lx, ly, lz, n, size):
    """Ray distance at which a ray leaves the cube of n^3 cells of edge ``size`` whose first
    cell is (lx, ly, lz), in a grid whose corner is the origin; (rx, ry, rz): the ray origin
    relative to that corner, iv*: inverse direction components (0 for a zero component)."""
    t_exit = 1e30
    if ivx > 0:
        t_exit = min(t_exit, ((lx + n) * size - rx) * ivx)
    elif ivx < 0:
        t_exit = min(t_exit, (lx * size - rx) * ivx)
    if ivy > 0:
        t_exit = min(t_exit, ((ly + n) * size - ry) * ivy)
    elif ivy < 0:
        t_exit = min(t_exit, (ly * size - ry) * ivy)
    if ivz > 0:
        t_exit = min(t_exit, ((lz + n) * size - rz) * ivz)
    elif ivz < 0:
        t_exit = min(t_exit, (lz * size - rz) * ivz)
    return t_exit


@njit(inline="always")
def _box_clip(ox, oy, oz, dx, dy, dz, aabb):
    """(t_near, t_far) of a ray in the box ``aabb`` (2, 3), as :func:`nerfbot.ops.sampling.ray_aabb`
    (near 0; a ray that misses gets 0, 0)."""
    lo = -1e30
    hi = 1e30
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        d = dx if a == 0 else (dy if a == 1 else dz)
        if abs(d) < 1e-12:
            if o < aabb[0, a] or o > aabb[1, a]:
                return 0.0, 0.0
            continue
        t0 = (aabb[0, a] - o) / d
        t1 = (aabb[1, a] - o) / d
        lo = max(lo, min(t0, t1))
        hi = min(hi, max(t0, t1))
    lo = max(lo, 0.0)
    if hi > lo:
        return lo, hi
    return 0.0, 0.0


@njit(inline="always")
def _skip(t, tm, dt, t_exit, tf, dt_min, dt_max, cone):
    """Advance ``t`` by whole marching steps until the step's midpoint reaches ``t_exit``."""
    if cone == 0.0 or dt_min == dt_max:
        return t + max(1.0, np.ceil((t_exit - tm) / dt)) * dt
    t += dt
    while t < tf:
        dt = min(max(t * cone, dt_min), dt_max)
        if t + 0.5 * dt >= t_exit:
            break
        t += dt
    return t


@njit(inline="always")
def _trilinear(density, row, v1, wx, wy, wz):
    """``density`` (one int16 per vertex) interpolated in the brick cell whose first corner is
    ``row`` (corners at +1, +v1, +v1^2 along z, y, x), with local coordinates (wx, wy, wz)."""
    one = np.float32(1.0)
    r1 = row + v1 * v1
    q00 = (one - wz) * np.float32(density[row]) + wz * np.float32(density[row + 1])
    q01 = (one - wz) * np.float32(density[row + v1]) + wz * np.float32(density[row + v1 + 1])
    q10 = (one - wz) * np.float32(density[r1]) + wz * np.float32(density[r1 + 1])
    q11 = (one - wz) * np.float32(density[r1 + v1]) + wz * np.float32(density[r1 + v1 + 1])
    return (one - wx) * ((one - wy) * q00 + wy * q01) + wx * ((one - wy) * q10 + wy * q11)


@njit(inline="always")
def _interpolate(colors, row, v1, wx, wy, wz, acc):
    """Every channel of ``colors`` (rows of uint8 codes) interpolated like :func:`_trilinear`,
    written into ``acc``."""
    one = np.float32(1.0)
    ux, uy, uz = one - wx, one - wy, one - wz
    w0, w1, w2, w3 = ux * uy * uz, ux * uy * wz, ux * wy * uz, ux * wy * wz
    w4, w5, w6, w7 = wx * uy * uz, wx * uy * wz, wx * wy * uz, wx * wy * wz
    r0, r2, r4 = row, row + v1, row + v1 * v1
    r6 = r4 + v1
    for c in range(acc.shape[0]):
        acc[c] = (w0 * np.float32(colors[r0, c]) + w1 * np.float32(colors[r0 + 1, c])
                  + w2 * np.float32(colors[r2, c]) + w3 * np.float32(colors[r2 + 1, c])
                  + w4 * np.float32(colors[r4, c]) + w5 * np.float32(colors[r4 + 1, c])
                  + w6 * np.float32(colors[r6, c]) + w7 * np.float32(colors[r6 + 1, c]))


@njit(parallel=True, fastmath=_FAST, cache=True)
def render(origins, dirs, aabb, occ_box, background, bricks, n_bricks, density, colors, scale,
           offset, dist, dir_weights, cmin, cube_size, dt_min, dt_max, cone,
           stop_transmittance, min_weight, block_cap, rgb, opacity, depth, far, counts, src_start, s_ts, s_te,
           s_sigma, s_w, s_row, s_fx, s_fy, s_fz):
    """Render rays through the cache: clip to the box, march, look up, composite with early
    termination.

    Marching matches :func:`nerfbot.kernels.marching` (from the box entry, steps
    ``dt = clamp(t * cone, dt_min, dt_max)``, a sample [t, min(t + dt, t_far)] where the coarse
    cell at t + dt / 2 is occupied, evaluated at the interval's midpoint), except that empty
    space is jumped over: from an empty coarse cell at distance k from the nearest occupied
    one, to where the ray leaves the (2k - 1)^3 empty cells around it (the samples are the
    same as stepping cell by cell, in one jump instead of ~k). A ray stops once its
    transmittance falls below ``stop_transmittance``. Samples of weight at most ``min_weight``
    are composited but their colour is not read: they take the weight-averaged colour of the
    ray's other samples (their weight is kept, so opacity and depth are exact).

    Each block of :data:`RAY_BLOCK` rays is rendered in two passes. First every ray is marched
    and composited from densities alone, read from ``density`` (one int16 per vertex, 1/13 of
    the cache); samples are looked up in rounds (see :data:`ROUND_MIN`) whose memory accesses
    overlap. Then the colours of all the block's samples are read from ``colors``: loads that
    do not wait for each other, so the cache misses on the big table overlap too.

    Args:
        origins, dirs: (R, 3) float32, unit directions; aabb: (2, 3) float64 scene bounds;
            occ_box: (2, 3) float64 box around the occupied cells (marching skips to it).
        background: (R, 3) float32 colour behind each ray.
        bricks, density, colors, scale, offset, dir_weights: the cache (module docstring),
            with B = :data:`BRICK`; n_bricks: stored bricks.
        dist: (G, G, G) uint8, :func:`empty_distance` of the coarse occupancy ``occ``.
        cmin: (3,) float64 cube corner; cube_size: cube edge, metres.
        block_cap: scratch entries per block of :data:`RAY_BLOCK` rays: the rays of block b
            write their samples one after the other into ``s_*[b * block_cap:]``. Samples that
            find the block's room full are only counted, and their rays get no colour: render
            those rays again with more room.
    Outputs:
        rgb (R, 3), opacity (R,), depth (R,) expected ray distance (``far`` for empty rays),
        far (R,) box exit, counts (R,) int64 samples composited, src_start (R,) int64 where each
        ray's samples start in the scratch; s_ts, s_te, s_sigma, s_w: per-sample interval,
        density and weight (float32); s_row (int32), s_fx, s_fy, s_fz (float32): its cell's
        first vertex row and position in the cell.
    """
    n_rays = origins.shape[0]
    n_ch = colors.shape[1]
    n_comp = n_ch // 3
    v1 = BRICK + 1
    nc = bricks.shape[0] * BRICK
    g = dist.shape[0]
    inv_h = nc / cube_size
    cs = cube_size / g
    inv_cs = g / cube_size
    n_blocks = (n_rays + RAY_BLOCK - 1) // RAY_BLOCK
    for item in prange(n_blocks):
        blk = scattered(item, n_blocks)
        acc = np.empty(n_ch, np.float32)
        rows = np.empty(ROUND_MAX, np.int64)
        wts = np.empty((ROUND_MAX, 3), np.float32)
        tss = np.empty(ROUND_MAX, np.float64)
        tes = np.empty(ROUND_MAX, np.float64)
        sig = np.empty(ROUND_MAX, np.float32)
        beta = np.empty(max(n_comp, 1), np.float32)
        coef = np.empty(max(3 * n_comp, 1), np.float32)
        left = np.empty(RAY_BLOCK, np.float64)
        cursor = blk * block_cap
        room_end = cursor + block_cap
        r_first = blk * RAY_BLOCK
        r_last = min(n_rays, (blk + 1) * RAY_BLOCK)
        # 1. march and composite densities
        for r in range(r_first, r_last):
            ox, oy, oz = np.float64(origins[r, 0]), np.float64(origins[r, 1]), \
                np.float64(origins[r, 2])
            dx, dy, dz = np.float64(dirs[r, 0]), np.float64(dirs[r, 1]), np.float64(dirs[r, 2])
            t, tf = _box_clip(ox, oy, oz, dx, dy, dz, aabb)
            rx, ry, rz = ox - cmin[0], oy - cmin[1], oz - cmin[2]
            ivx = 1.0 / dx if dx != 0.0 else 0.0
            ivy = 1.0 / dy if dy != 0.0 else 0.0
            ivz = 1.0 / dz if dz != 0.0 else 0.0
            trans = 1.0
            dsum = 0.0
            n = 0
            # march only across the box of the occupied cells, on the same step lattice
            t_end = tf
            if t < tf and n_bricks > 0:
                b0_, b1_ = _box_clip(ox, oy, oz, dx, dy, dz, occ_box)
                if b1_ <= b0_:
                    t_end = t
                else:
                    t_end = min(tf, b1_)
                    dt = min(max(t * cone, dt_min), dt_max)
                    if t + 0.5 * dt < b0_:
                        t = _skip(t, t + 0.5 * dt, dt, b0_, tf, dt_min, dt_max, cone)
            want = ROUND_MIN
            alive = n_bricks > 0
            while alive and t < t_end:
                # march to the next ``want`` samples in stored bricks
                m = 0
                while m < want and t < t_end:
                    dt = min(max(t * cone, dt_min), dt_max)
                    tm = t + 0.5 * dt
                    px = rx + tm * dx
                    py = ry + tm * dy
                    pz = rz + tm * dz
                    gx = int(math.floor(px * inv_cs))
                    gy = int(math.floor(py * inv_cs))
                    gz = int(math.floor(pz * inv_cs))
                    if gx < 0 or gy < 0 or gz < 0 or gx >= g or gy >= g or gz >= g:
                        t_exit = _box_exit(rx, ry, rz, ivx, ivy, ivz, gx, gy, gz, 1, cs)
                        t = _skip(t, tm, dt, t_exit, tf, dt_min, dt_max, cone)
                        continue
                    k = np.int64(dist[gx, gy, gz])
                    if k > 0:
                        t_exit = _box_exit(rx, ry, rz, ivx, ivy, ivz, gx - k + 1, gy - k + 1,
                                           gz - k + 1, 2 * k - 1, cs)
                        t = _skip(t, tm, dt, t_exit, tf, dt_min, dt_max, cone)
                        continue
                    te = min(t + dt, tf)
                    ts = t
                    t += dt
                    tmid = 0.5 * (ts + te)
                    fx = (rx + tmid * dx) * inv_h
                    fy = (ry + tmid * dy) * inv_h
                    fz = (rz + tmid * dz) * inv_h
                    ix = min(max(int(math.floor(fx)), 0), nc - 1)
                    iy = min(max(int(math.floor(fy)), 0), nc - 1)
                    iz = min(max(int(math.floor(fz)), 0), nc - 1)
                    bid = bricks[ix >> BRICK_SHIFT, iy >> BRICK_SHIFT, iz >> BRICK_SHIFT]
                    if bid < 0:
                        continue
                    rows[m] = ((bid * v1 + (ix & BRICK_MASK)) * v1 + (iy & BRICK_MASK)) * v1 \
                        + (iz & BRICK_MASK)
                    wts[m, 0] = min(max(fx - ix, 0.0), 1.0)
                    wts[m, 1] = min(max(fy - iy, 0.0), 1.0)
                    wts[m, 2] = min(max(fz - iz, 0.0), 1.0)
                    tss[m] = ts
                    tes[m] = te
                    m += 1
                if m == 0:
                    break
                # densities of all of them (independent loads: their misses overlap)
                for s in range(m):
                    q = _trilinear(density, rows[s], v1, wts[s, 0], wts[s, 1], wts[s, 2])
                    sig[s] = math.exp(min(q * scale[0] + offset[0], np.float32(RAW_MAX)))
                # composite up to where the ray saturates
                for s in range(m):
                    sigma = sig[s]
                    ts = tss[s]
                    te = tes[s]
                    tau = min(np.float64(sigma) * max(te - ts, 0.0), 1e4)
                    e = math.exp(-tau)
                    w = trans * (1.0 - e)
                    dsum += w * 0.5 * (ts + te)
                    k = cursor + n
                    if k < room_end:
                        s_ts[k] = ts
                        s_te[k] = te
                        s_sigma[k] = sigma
                        s_w[k] = w
                        s_row[k] = rows[s]
                        s_fx[k] = wts[s, 0]
                        s_fy[k] = wts[s, 1]
                        s_fz[k] = wts[s, 2]
                    n += 1
                    trans *= e
                    if trans < stop_transmittance:
                        alive = False
                        break
                want = min(2 * want, ROUND_MAX)
            op = 1.0 - trans
            opacity[r] = op
            depth[r] = dsum / op if op > 1e-6 else tf
            far[r] = tf
            counts[r] = n
            src_start[r] = cursor
            cursor += n
            left[r - r_first] = trans
        # 2. colours of the block's samples; rays whose samples did not all fit are skipped
        for q in range(r_first, r_last):
            first = src_start[q]
            last = first + counts[q]
            if last > room_end:
                continue
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            w_all = 0.0
            w_read = 0.0
            if last > first:
                # colour logits are affine in the interpolated integers: fold beta and scales
                bilinear(dir_weights, np.float64(dirs[q, 0]), np.float64(dirs[q, 1]),
                         np.float64(dirs[q, 2]), beta)
                b0 = np.float32(0.0)
                b1 = np.float32(0.0)
                b2 = np.float32(0.0)
                for i in range(n_comp):
                    coef[3 * i] = beta[i] * scale[1 + 3 * i]
                    coef[3 * i + 1] = beta[i] * scale[2 + 3 * i]
                    coef[3 * i + 2] = beta[i] * scale[3 + 3 * i]
                    b0 += beta[i] * offset[1 + 3 * i]
                    b1 += beta[i] * offset[2 + 3 * i]
                    b2 += beta[i] * offset[3 + 3 * i]
                for j in range(first, last):
                    wj = np.float64(s_w[j])
                    w_all += wj
                    if wj <= min_weight:
                        continue
                    w_read += wj
                    _interpolate(colors, s_row[j], v1, s_fx[j], s_fy[j], s_fz[j], acc)
                    l0 = b0
                    l1 = b1
                    l2 = b2
                    for i in range(n_comp):
                        l0 += coef[3 * i] * acc[3 * i]
                        l1 += coef[3 * i + 1] * acc[3 * i + 1]
                        l2 += coef[3 * i + 2] * acc[3 * i + 2]
                    c0 += wj / (1.0 + math.exp(-l0))
                    c1 += wj / (1.0 + math.exp(-l1))
                    c2 += wj / (1.0 + math.exp(-l2))
            finish_pixel(rgb, q, c0, c1, c2, w_all, w_read, left[q - r_first], background)


def occupied_box(occ: np.ndarray, cmin: np.ndarray, cube_size: float) -> np.ndarray:
    """(2, 3) float64 world box around the set cells of ``occ`` (G, G, G) over the cube at
    ``cmin`` (an empty box at the corner when none is set)."""
    g = occ.shape[0]
    idx = np.argwhere(occ)
    if not idx.size:
        return np.stack([cmin, cmin]).astype(np.float64)
    cell = cube_size / g
    return np.stack([cmin + idx.min(0) * cell, cmin + (idx.max(0) + 1) * cell]).astype(np.float64)


def empty_distance(occ: np.ndarray, cap: int = DISTANCE_CAP) -> np.ndarray:
    """(G, G, G) uint8: for each cell of ``occ`` (G, G, G), the Chebyshev distance in cells to
    the nearest set cell (0 where set), capped at ``cap`` (also where none is set). Every cell
    within k - 1 of a cell at distance k is empty."""
    reached = occ != 0
    dist = np.where(reached, 0, cap).astype(np.uint8)
    for k in range(1, cap):
        if reached.all() or not reached.any():
            break
        grown = reached.copy()  # dilation by one cell in the max norm: one axis at a time
        for axis in range(3):
            src = grown.copy()
            lo = [slice(None)] * 3
            hi = [slice(None)] * 3
            lo[axis], hi[axis] = slice(None, -1), slice(1, None)
            grown[tuple(hi)] |= src[tuple(lo)]
            grown[tuple(lo)] |= src[tuple(hi)]
        dist[grown & ~reached] = k
        reached = grown
    return dist
