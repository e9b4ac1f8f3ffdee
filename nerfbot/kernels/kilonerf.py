"""Numba CPU kernels of KiloNeRF: grouping samples by network, encoding them into the padded
rows of the batched matmuls, the batched renderer's per-sample and per-ray steps, and the fused
renderer (:func:`render_fused`: every sample's network evaluated in place, in one pass).

:func:`chunk_layout`: samples are assigned to networks (``slots``, -1 for none). Network ``k``
with ``n_k`` samples gets ``ceil(n_k / C)`` consecutive chunks of ``C`` rows; chunks are ordered
by network, and within a network samples keep their input order (a stable counting sort).
Sample ``i`` lands on padded row ``pos[i] = first_chunk[k] * C + rank_k(i)``; padding rows
belong to no sample. Each layer of all networks is then one batched matmul over the chunks.

Plain-torch twins: :func:`nerfbot.fields.kilonerf.chunk_layout_reference` (layout),
:class:`nerfbot.ops.encodings.FrequencyEncoding` (:func:`encode_rows`),
:meth:`nerfbot.fields.kilonerf.KiloNeRFField.slots` (:func:`sample_cells`) and
:func:`nerfbot.ops.rendering.composite` (:func:`composite_density`); tests assert they agree.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.extending import overload

from nerfbot.kernels.pixels import finish_pixel, sigmoid32
from nerfbot.kernels.schedule import scattered


@njit(inline="always")
def _bf16_bits(x):
    """The bfloat16 nearest to ``x`` (ties to even), as its 16 bits (the upper half of the
    float32's bits, rounded): how torch converts float32 to bfloat16 (NaN aside)."""
    u = np.float32(x).view(np.uint32)
    return np.uint16((u + np.uint32(0x7FFF) + ((u >> np.uint32(16)) & np.uint32(1)))
                     >> np.uint32(16))


def _store(out, r, c, x):
    """out[r, c] = x; into a uint16 array as bfloat16 bits (see the overload)."""


@overload(_store, inline="always")
def _store_impl(out, r, c, x):
    if out.dtype == types.uint16:
        def impl(out, r, c, x):
            out[r, c] = _bf16_bits(x)
    else:
        def impl(out, r, c, x):
            out[r, c] = x
    return impl


@njit(cache=True, nogil=True)
def chunk_layout(slots, n_nets, chunk):
    """The padded layout of ``slots`` (a stable counting sort, O(N + K), serial).

    Args:
        slots: (N,) int64 network of each sample in [0, n_nets), or -1 (no network).
        n_nets: K. chunk: C rows per chunk.
    Returns:
        pos: (N,) int64 padded row of each sample (-1 where ``slots`` is -1);
        chunk_net: (n_chunks,) int64 network of each chunk, n_chunks = sum_k ceil(n_k / C).
    """
    counts = np.zeros(n_nets, np.int64)
    for i in range(slots.shape[0]):
        if slots[i] >= 0:
            counts[slots[i]] += 1
    first = np.empty(n_nets, np.int64)
    n_chunks = 0
    for k in range(n_nets):
        first[k] = n_chunks
        n_chunks += (counts[k] + chunk - 1) // chunk
    chunk_net = np.empty(n_chunks, np.int64)
    for k in range(n_nets):
        for j in range((counts[k] + chunk - 1) // chunk):
            chunk_net[first[k] + j] = k
    pos = np.empty(slots.shape[0], np.int64)
    fill = np.zeros(n_nets, np.int64)
    for i in range(slots.shape[0]):
        k = slots[i]
        if k < 0:
            pos[i] = -1
        else:
            pos[i] = first[k] * chunk + fill[k]
            fill[k] += 1
    return pos, chunk_net


@njit(parallel=True, cache=True, nogil=True)
def encode_rows(values, sin_pi, cos_pi, pos, n_freqs, out, col):
    """Write the frequency encoding of ``values[i]`` into row ``pos[i]`` of ``out``.

    The encoding is :class:`nerfbot.ops.encodings.FrequencyEncoding`'s: ``[v, sin(2^k pi v) for k,
    cos(2^k pi v) for k]``, frequency-major and coordinate-minor. sin and cos of 2^k pi v come
    from those of pi v (computed by the caller, vectorised, in float64) by the double-angle
    formulas in float64: each doubling at most doubles the error, and 2^10 x 1e-16 stays far
    below float32 resolution.

    Args:
        values: (M, D) float32 points (local coordinates in [-1, 1], or unit directions).
        sin_pi, cos_pi: (M, D) float64 sin(pi v) and cos(pi v).
        pos: (M,) int64 row of each point in ``out`` (-1: skip).
        n_freqs: F. col: first column written (the encoding fills D * (1 + 2F) columns).
        out: (rows, >= col + D * (1 + 2F)) float32, rows without a point left untouched.
    """
    d = values.shape[1]
    for i in prange(values.shape[0]):
        r = pos[i]
        if r < 0:
            continue
        for a in range(d):
            out[r, col + a] = values[i, a]
            s = sin_pi[i, a]
            c = cos_pi[i, a]
            for k in range(n_freqs):
                out[r, col + d + d * k + a] = s
                out[r, col + d + d * (n_freqs + k) + a] = c
                s, c = 2.0 * s * c, c * c - s * s


@njit(inline="always")
def _sample_cell(origins, dirs, r, tm, aabb, cube_min, cube_size, g, net_index, local):
    """Network slot of the point ``o_r + d_r tm`` (-1 outside the bounds or without a network),
    its local coordinates in [-1, 1] written into ``local`` (3,); the float32 arithmetic of
    :meth:`nerfbot.fields.kilonerf.KiloNeRFField.slots` (G networks per axis)."""
    gf = np.float32(g)
    one, two = np.float32(1.0), np.float32(2.0)
    inside = True
    flat = 0
    for a in range(3):
        p = origins[r, a] + dirs[r, a] * tm
        if not (p >= aabb[0, a] and p <= aabb[1, a]):
            inside = False
        u = (p - cube_min[a]) / cube_size * gf
        fl = np.floor(u)
        j = min(max(int(fl), 0), g - 1) if fl == fl else 0
        local[a] = (u - np.float32(j)) * two - one
        flat = flat * g + j
    return net_index[flat] if inside else -1


@njit(parallel=True, cache=True, nogil=True)
def sample_cells(origins, dirs, ray_indices, t_starts, t_ends, aabb, cube_min, cube_size,
                 net_index, slots, local):
    """Network slot and local coordinates of the midpoint of every packed sample.

    Same float32 arithmetic as :meth:`nerfbot.fields.kilonerf.KiloNeRFField.slots` on the
    points ``o + d * (t_start + t_end) / 2``.

    Args:
        origins, dirs: (R, 3) float32; ray_indices: (M,) int64; t_starts, t_ends: (M,) float32.
        aabb: (2, 3) float32 scene bounds; cube_min: (3,) float32; cube_size: float32 scalar.
        net_index: (G^3,) int64 slot of every network cell (-1: none).
        slots: (M,) int64 output (-1 outside the bounds or without a network).
        local: (M, 3) float32 output, local coordinates in [-1, 1].
    """
    g = int(round(net_index.shape[0] ** (1.0 / 3.0)))
    half = np.float32(0.5)
    for i in prange(ray_indices.shape[0]):
        r = ray_indices[i]
        slots[i] = _sample_cell(origins, dirs, r, half * (t_starts[i] + t_ends[i]), aabb,
                                cube_min, cube_size, g, net_index, local[i])


@njit(parallel=True, cache=True, nogil=True)
def composite_density(starts, counts, t_starts, t_ends, pos, raw, density_bias, early_stop,
                      far, sigmas, weights, opacity, depth, median):
    """Per-ray compositing of the densities of packed samples, with early termination.

    sigma = exp(min(raw + bias, 15)) (the field's ``trunc_exp``; 0 where ``pos`` is -1). Along
    each ray, weights are T_i (1 - exp(-sigma_i delta_i)) with T accumulated in float64; once T
    drops below ``early_stop`` the remaining samples get weight 0 (their colour is never
    needed). Depth is the weighted mean midpoint, median the first midpoint where the
    accumulated weight reaches half the opacity; both are ``far`` for rays with opacity
    <= 1e-6 (:data:`nerfbot.ops.rendering.EMPTY_OPACITY`).

    Args:
        starts, counts: (R,) int64 packed range of each ray; t_starts, t_ends: (M,) float32.
        pos: (M,) int64 padded row of each sample (-1: no network); raw: (rows,) float32.
        density_bias, early_stop: floats. far: (R,) float32.
        sigmas, weights: (M,) float32 outputs. opacity, depth, median: (R,) float32 outputs.
    """
    log_stop = np.log(early_stop)
    for r in prange(starts.shape[0]):
        log_t = 0.0
        acc = 0.0
        dsum = 0.0
        done = False
        a, b = starts[r], starts[r] + counts[r]
        for i in range(a, b):
            sigma = np.float32(0.0)
            if pos[i] >= 0:
                sigma = np.exp(min(raw[pos[i]] + np.float32(density_bias), np.float32(15.0)))
            sigmas[i] = sigma
            if done:
                weights[i] = 0.0
                continue
            tau = min(np.float64(sigma) * max(np.float64(t_ends[i]) - t_starts[i], 0.0), 1e4)
            w = np.exp(log_t) * -np.expm1(-tau)
            weights[i] = w
            acc += w
            dsum += w * 0.5 * (np.float64(t_starts[i]) + t_ends[i])
            log_t -= tau
            done = log_t < log_stop
        opacity[r] = acc
        if acc <= 1e-6:
            depth[r] = far[r]
            median[r] = far[r]
            continue
        depth[r] = dsum / acc
        cum = 0.0
        med = far[r]
        for i in range(a, b):
            cum += weights[i]
            if cum >= 0.5 * acc:
                med = 0.5 * (np.float64(t_starts[i]) + t_ends[i])
                break
        median[r] = med


@njit(parallel=True, cache=True, nogil=True)
def encode_padded(values, sin_pi, cos_pi, row_sample, n_freqs, out):
    """Every row of ``out`` (rows, D (1 + 2F)): the encoding of ``values[row_sample[r]]`` (as
    :func:`encode_rows`), or zeros where ``row_sample[r]`` is -1 (padding). Writing all rows
    once costs less than zeroing the buffer first and scattering into it. ``out`` is float32,
    or uint16 to receive bfloat16 bits (what the bfloat16 matmuls read, without a conversion
    pass)."""
    d = values.shape[1]
    for r in prange(row_sample.shape[0]):
        i = row_sample[r]
        if i < 0:
            for c in range(out.shape[1]):
                _store(out, r, c, 0.0)
            continue
        for a in range(d):
            _store(out, r, a, values[i, a])
            s = np.float64(sin_pi[i, a])
            c = np.float64(cos_pi[i, a])
            for k in range(n_freqs):
                _store(out, r, d + d * k + a, s)
                _store(out, r, d + d * (n_freqs + k) + a, c)
                s, c = 2.0 * s * c, c * c - s * s


@njit(parallel=True, cache=True, nogil=True)
def padded_rows(src, src_index, row_sample, out):
    """out[r] = src[src_index[row_sample[r]]], or zeros where ``row_sample[r]`` is -1.

    Args:
        src: (S, D) float32 (e.g. one encoded direction per ray); src_index: (M,) int64 row of
        src for every sample (e.g. its ray); row_sample: (rows,) int64; out: (rows, D) float32,
        or uint16 for bfloat16 bits.
    """
    for r in prange(row_sample.shape[0]):
        i = row_sample[r]
        if i < 0:
            for c in range(out.shape[1]):
                _store(out, r, c, 0.0)
        else:
            j = src_index[i]
            for c in range(out.shape[1]):
                _store(out, r, c, src[j, c])


@njit(parallel=True, cache=True, nogil=True)
def accumulate_rgb(starts, counts, weights, min_weight, pos, chunk_map, chunk, rgb_rows, out):
    """out[r] = sum of w_i rgb_i over the samples of ray r whose weight exceeds ``min_weight``
    (per ray, in sample order: deterministic), scaled by (all the ray's weight) / (theirs): the
    fainter samples take the weight-averaged colour of these.

    The colour of sample i is row ``chunk_map[pos[i] // C] * C + pos[i] % C`` of ``rgb_rows``:
    colours are evaluated on a selection of the trunk's chunks, ``chunk_map`` (n_chunks,)
    giving each chunk's place in that selection (-1: not evaluated; such chunks hold no sample
    above ``min_weight``).

    Args:
        starts, counts: (R,) int64; weights: (M,) float32; pos: (M,) int64 trunk row (-1: none);
        rgb_rows: (selected rows, 3) float32; out: (R, 3) float32.
    """
    for r in prange(starts.shape[0]):
        acc0 = 0.0
        acc1 = 0.0
        acc2 = 0.0
        w_all = 0.0
        w_read = 0.0
        for i in range(starts[r], starts[r] + counts[r]):
            w = weights[i]
            w_all += w
            if w > min_weight and pos[i] >= 0:
                row = chunk_map[pos[i] // chunk] * chunk + pos[i] % chunk
                acc0 += w * rgb_rows[row, 0]
                acc1 += w * rgb_rows[row, 1]
                acc2 += w * rgb_rows[row, 2]
                w_read += w
        scale = w_all / w_read if w_read > 0.0 else 1.0
        out[r, 0] = acc0 * scale
        out[r, 1] = acc1 * scale
        out[r, 2] = acc2 * scale


# ----------------------------------------------------------------------------- fused renderer
#: Rays per work item of :func:`render_fused` (visited in the scattered order of
#: :mod:`nerfbot.kernels.schedule`; a block's rays share a scratch region).
RAY_BLOCK = 64


@njit(inline="always")
def _dense(x, n_in, w, b, k, row0, out):
    """out = b[k] + x[:n_in] @ w[k, row0:row0 + n_in] (the first ``n_in`` inputs; ``out``'s
    length is the layer's width). Loops over the outputs innermost: they are contiguous in
    ``w``, so the compiler turns them into vector FMAs."""
    for j in range(out.shape[0]):
        out[j] = b[k, j]
    for i in range(n_in):
        xi = x[i]
        for j in range(out.shape[0]):
            out[j] += xi * w[k, row0 + i, j]


@njit(inline="always")
def _frequency_encode(x0, x1, x2, n_freqs, out):
    """NeRF's encoding of a float32 3-vector into ``out`` (3 (1 + 2 F),), in the layout of
    :class:`nerfbot.ops.encodings.FrequencyEncoding`: [x, sin(2^k pi x) (k-major), cos(2^k pi x)];
    as the batched renderer computes it: sin and cos of the float32 angle pi x, the octaves by
    the double-angle recurrence in float64 (:func:`encode_padded`)."""
    pi32 = np.float32(np.pi)
    for a in range(3):
        v = x0 if a == 0 else (x1 if a == 1 else x2)
        out[a] = v
        s = np.float64(np.sin(pi32 * v))
        c = np.float64(np.cos(pi32 * v))
        for k in range(n_freqs):
            out[3 + 3 * k + a] = s
            out[3 + 3 * (n_freqs + k) + a] = c
            s, c = 2.0 * s * c, c * c - s * s


@njit(parallel=True, fastmath={"nsz", "arcp", "contract", "reassoc", "afn"}, cache=True,
      nogil=True)
def render_fused(origins, dirs, t_near, t_far, occ, gmin, cell, dt_min, dt_max, cone, aabb,
                 cube_min, cube_size, net_index, w_in, b_in, w_hid, b_hid, w_sigma, b_sigma,
                 w_color, b_color, w_rgb, b_rgb, pos_freqs, dir_freqs, density_bias, early_stop,
                 min_weight, background, block_cap, rgb, opacity, depth, counts, src_start,
                 s_ts, s_te, s_sigma, s_w):
    """KiloNeRF's renderer in one pass per ray: march the occupancy grid, evaluate each
    sample's tiny network in place, composite with early termination, and evaluate the colour
    head only for samples whose weight exceeds ``min_weight``.

    Marching is :func:`nerfbot.kernels.marching` 's rule (from ``t_near``, steps
    ``clamp(t * cone, dt_min, dt_max)``, a sample where the cell of the step's midpoint is
    occupied); slots and local coordinates are :func:`sample_cells`'s float32 arithmetic;
    compositing is :func:`composite_density`'s (float64 transmittance, ``expm1``), except that
    the ray stops once its transmittance is below ``early_stop`` instead of giving the rest
    weight 0, and that samples of weight at most ``min_weight`` take the weight-averaged colour
    of the ray's other samples instead of none (their weight is kept: opacity and depth are
    exact). Networks: h = relu(W_in gamma(x) + b_in), the hidden layers, sigma =
    exp(min(w_sigma . h + b_sigma + bias, 15)), rgb = sigmoid(W_rgb relu(W_color [h, gamma(d)]
    + b_color) + b_rgb), with the weights of :class:`nerfbot.fields.kilonerf.KiloNeRFField`.

    Args:
        origins, dirs: (R, 3) float32; t_near, t_far: (R,) float32 (``ray_aabb``).
        occ: (G, G, G) uint8 occupancy over [gmin, gmin + G cell]^3 (float64 corner, edge).
        aabb: (2, 3) float32 bounds; cube_min: (3,) float32; cube_size: float32;
            net_index: (N^3,) int64 slot of every network cell (-1: none).
        w_*, b_*: the stacked float32 parameters. pos_freqs, dir_freqs: encoding octaves.
        background: (R, 3) float32 colour behind each ray.
        block_cap: scratch entries per block of :data:`RAY_BLOCK` rays (block b writes from
            ``b * block_cap``); samples that find the room full are only counted, and their
            rays get no colour (render them again with more room).
    Outputs:
        rgb (R, 3), opacity (R,) (sum of weights), depth (R,) expected ray distance (``t_far``
        for rays with opacity <= 1e-6), counts (R,) int64 samples, src_start (R,) int64 where
        each ray's samples start in the scratch; s_ts, s_te, s_sigma, s_w: float32 per-sample
        interval, density and weight.
    """
    n_rays = origins.shape[0]
    g = occ.shape[0]
    n = int(round(net_index.shape[0] ** (1.0 / 3.0)))
    inv_cell = 1.0 / cell
    hdim = w_in.shape[2]
    d_in = w_in.shape[1]
    n_hid = w_hid.shape[1]
    d_dir = 3 * (1 + 2 * dir_freqs)
    half = np.float32(0.5)
    n_blocks = (n_rays + RAY_BLOCK - 1) // RAY_BLOCK
    for item in prange(n_blocks):
        blk = scattered(item, n_blocks)
        enc = np.empty(d_in, np.float32)
        denc = np.empty(d_dir, np.float32)
        h = np.empty(hdim, np.float32)
        h2 = np.empty(hdim, np.float32)
        c = np.empty(w_color.shape[2], np.float32)
        cursor = blk * block_cap
        room_end = cursor + block_cap
        for r in range(blk * RAY_BLOCK, min(n_rays, (blk + 1) * RAY_BLOCK)):
            t = np.float64(t_near[r])
            tf = np.float64(t_far[r])
            trans = 1.0
            acc = 0.0
            dsum = 0.0
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            w_read = 0.0
            m = 0
            have_dir = False
            while t < tf and trans >= early_stop:
                dt = min(max(t * cone, dt_min), dt_max)
                tm64 = t + 0.5 * dt
                ix = int(np.floor((origins[r, 0] + tm64 * dirs[r, 0] - gmin[0]) * inv_cell))
                iy = int(np.floor((origins[r, 1] + tm64 * dirs[r, 1] - gmin[1]) * inv_cell))
                iz = int(np.floor((origins[r, 2] + tm64 * dirs[r, 2] - gmin[2]) * inv_cell))
                occupied = (0 <= ix < g and 0 <= iy < g and 0 <= iz < g
                            and occ[ix, iy, iz] != 0)
                ts = t
                t += dt
                if not occupied:
                    continue
                ts32 = np.float32(ts)
                te32 = np.float32(min(ts + dt, tf))
                # the sample's network and local coordinates (sample_cells' arithmetic)
                k = _sample_cell(origins, dirs, r, half * (ts32 + te32), aabb, cube_min,
                                 cube_size, n, net_index, enc)
                sigma = 0.0
                if k >= 0:
                    _frequency_encode(enc[0], enc[1], enc[2], pos_freqs, enc)
                    _dense(enc, d_in, w_in, b_in, k, 0, h)
                    for j in range(hdim):
                        h[j] = max(h[j], 0.0)
                    for layer in range(n_hid):
                        for j in range(hdim):
                            h2[j] = b_hid[k, layer, j]
                        for i in range(hdim):
                            hi = h[i]
                            for j in range(hdim):
                                h2[j] += hi * w_hid[k, layer, i, j]
                        for j in range(hdim):
                            h[j] = max(h2[j], 0.0)
                    raw = b_sigma[k, 0]
                    for j in range(hdim):
                        raw += h[j] * w_sigma[k, j, 0]
                    sigma = np.exp(min(raw + np.float32(density_bias), np.float32(15.0)))
                tau = min(np.float64(sigma) * max(np.float64(te32) - ts32, 0.0), 1e4)
                em1 = np.expm1(-tau)
                w = trans * -em1
                trans *= 1.0 + em1
                acc += w
                dsum += w * 0.5 * (np.float64(ts32) + te32)
                if w > min_weight and k >= 0:
                    w_read += w
                    if not have_dir:
                        _frequency_encode(dirs[r, 0], dirs[r, 1], dirs[r, 2], dir_freqs, denc)
                        have_dir = True
                    _dense(h, hdim, w_color, b_color, k, 0, c)
                    for i in range(d_dir):
                        di = denc[i]
                        for j in range(c.shape[0]):
                            c[j] += di * w_color[k, hdim + i, j]
                    l0 = b_rgb[k, 0]
                    l1 = b_rgb[k, 1]
                    l2 = b_rgb[k, 2]
                    for j in range(c.shape[0]):
                        cj = max(c[j], np.float32(0.0))
                        l0 += cj * w_rgb[k, j, 0]
                        l1 += cj * w_rgb[k, j, 1]
                        l2 += cj * w_rgb[k, j, 2]
                    c0 += w * sigmoid32(l0)
                    c1 += w * sigmoid32(l1)
                    c2 += w * sigmoid32(l2)
                q = cursor + m
                if q < room_end:
                    s_ts[q] = ts32
                    s_te[q] = te32
                    s_sigma[q] = sigma
                    s_w[q] = w
                m += 1
            counts[r] = m
            src_start[r] = cursor
            cursor += m
            opacity[r] = acc
            depth[r] = dsum / acc if acc > 1e-6 else tf
            finish_pixel(rgb, r, c0, c1, c2, acc, w_read, 1.0 - np.float64(np.float32(acc)),
                         background)
