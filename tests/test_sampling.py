"""Sample placement (nerfbot.ops.sampling): box clipping, stratified and pdf sampling, and the
occupancy grid (numba marcher vs its plain-torch twin, grid updates)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfbot.ops.rendering import composite
from nerfbot.ops.sampling import (OccupancyGrid, march_reference, pdf_samples, ray_aabb,
                                  ray_aabb_reference, stratified_samples)

SQ3 = math.sqrt(3.0)


# ----------------------------------------------------------------------------- ray_aabb

def test_ray_aabb_hand_computed():
    aabb = torch.tensor([[-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    d = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64) / SQ3
    origins = torch.tensor([
        [-5.0, 0.0, 0.0],    # +x into the box: x in [-1, 1] at t 4..6
        [0.0, 10.0, 0.0],    # -y: y in [-2, 2] at t 8..12
        [0.0, 0.0, -10.0],   # +z: t 7..13
        [-2.0, -3.0, -4.0],  # diagonal: slabs x [1, 3], y [1, 5], z [1, 7] * sqrt(3)
        [-5.0, 5.0, 0.0],    # +x, but y = 5 is outside the box: miss
        [0.0, 0.0, 0.0],     # starts inside: t 0 .. 1
        [5.0, 0.0, 0.0],     # box behind the ray: miss
        [0.5, -10.0, 1.0],   # +y, inside in x and z
    ], dtype=torch.float64)
    dirs = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0], d.tolist(), [1.0, 0, 0],
                         [1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]], dtype=torch.float64)
    t_near, t_far, hit = ray_aabb(origins, dirs, aabb)
    assert hit.tolist() == [True, True, True, True, False, True, False, True]
    np.testing.assert_allclose(t_near.numpy(), [4, 8, 7, SQ3, 0, 0, 0, 8], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(t_far.numpy(), [6, 12, 13, 3 * SQ3, 0, 1, 0, 12], rtol=1e-12,
                               atol=1e-12)


def test_ray_aabb_near_clip_and_miss_convention():
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    o = torch.tensor([[-1.0, 0.5, 0.5], [0.5, 0.5, 0.5], [-1.0, 3.0, 0.5], [-1.0, 0.5, 0.5]])
    d = torch.tensor([[1.0, 0, 0], [0, 0, -1.0], [1.0, 0, 0], [1.0, 0, 0]])
    # near = 1.5: ray 0 starts inside its hit interval [1, 2]; ray 1 exits at 0.5 < near
    t_near, t_far, hit = ray_aabb(o, d, aabb, near=1.5)
    assert hit.tolist() == [True, False, False, True]
    assert t_near.tolist() == [1.5, 1.5, 1.5, 1.5]  # misses get t_near = t_far = near
    assert t_far.tolist() == [2.0, 1.5, 1.5, 2.0]


def test_ray_aabb_numba_twin_gives_the_same_bits():
    """Float32 CPU rays go through the numba kernel: bitwise the torch reference's results, on
    random rays and on the edge cases (parallel, lying in a face, starting inside, near > 0)."""
    g = torch.Generator().manual_seed(3)
    aabb = torch.tensor([[-0.5, -1.0, 0.0], [1.5, 0.5, 0.7]])
    o = torch.randn(5000, 3, generator=g) * 2
    d = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=-1)
    d[:500, 0] = 0.0                         # parallel to the x slabs
    d[500:700, 1:] = 0.0                     # along x only
    d[500:700, 0] = 1.0
    o[600:700, 1] = aabb[0, 1]               # lying in a face
    o[700:800] = aabb.mean(0)                # starting inside
    for near in (0.0, 0.3):
        fast = ray_aabb(o, d, aabb, near)
        ref = ray_aabb_reference(o, d, aabb, near)
        for a, b in zip(fast, ref):
            assert torch.equal(a, b)
    assert 200 < int(fast[2].sum()) < 4800  # hits and misses both
    # float64 and gradient-carrying rays take the torch path
    o64 = o.double().requires_grad_()
    t_near, _, _ = ray_aabb(o64, d.double(), aabb.double())
    assert t_near.requires_grad


def test_ray_aabb_random_rays_agree_with_point_tests():
    """Midpoints of hit intervals lie inside the box; points just outside lie outside it."""
    g = torch.Generator().manual_seed(0)
    aabb = torch.tensor([[-0.5, -1.0, 0.0], [1.5, 0.5, 0.7]], dtype=torch.float64)
    o = torch.randn(2000, 3, generator=g, dtype=torch.float64) * 2
    aim = torch.randn(2000, 3, generator=g, dtype=torch.float64) * 0.8 + aabb.mean(0)
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    t_near, t_far, hit = ray_aabb(o, d, aabb)
    assert 400 < int(hit.sum()) < 1600
    inside = lambda p: ((p >= aabb[0] - 1e-9) & (p <= aabb[1] + 1e-9)).all(-1)
    mid = o + 0.5 * (t_near + t_far)[:, None] * d
    assert inside(mid[hit]).all()
    assert inside((o + t_near[:, None] * d)[hit]).all()
    assert inside((o + t_far[:, None] * d)[hit]).all()
    after = o + (t_far + 1e-6)[:, None] * d
    assert not inside(after[hit]).any()
    # a missing ray has no point inside the box along it (probe densely)
    ts = torch.linspace(0, 8, 801, dtype=torch.float64)
    pts = o[~hit][:, None, :] + ts[None, :, None] * d[~hit][:, None, :]
    assert not inside(pts).any()


# ----------------------------------------------------------------------------- stratified

def near_far(seed: int, n_rays: int = 500):
    g = torch.Generator().manual_seed(seed)
    t_near = torch.rand(n_rays, generator=g) * 2.0
    return t_near, t_near + torch.rand(n_rays, generator=g) * 5.0 + 1e-3


@pytest.mark.parametrize("jitter", [True, False])
@pytest.mark.parametrize("n", [1, 2, 16])
def test_stratified_edges_sorted_and_spaced(n, jitter):
    t_near, t_far = near_far(n)
    edges = stratified_samples(t_near, t_far, n, generator=torch.Generator().manual_seed(0),
                               jitter=jitter)
    assert edges.shape == (500, n + 1)
    assert (edges.diff(dim=-1) >= 0).all()
    if not jitter:
        expect = t_near[:, None] + (t_far - t_near)[:, None] * torch.linspace(0, 1, n + 1)
        torch.testing.assert_close(edges, expect, rtol=0, atol=1e-6)


def test_stratified_endpoints_exact_and_edges_within_near_far():
    """The outer edges are exactly near and far (docstring: "the outer edges stay at near and
    far"), in every mode, so every edge lies within [near, far]."""
    bad = []
    for n in (1, 2, 16):
        for jitter in (True, False):
            t_near, t_far = near_far(n)
            edges = stratified_samples(t_near, t_far, n,
                                       generator=torch.Generator().manual_seed(0), jitter=jitter)
            n_bad = int(((edges[:, 0] != t_near) | (edges[:, -1] != t_far)
                         | (edges < t_near[:, None]).any(-1)
                         | (edges > t_far[:, None]).any(-1)).sum())
            if n_bad:
                bad.append(f"n={n} jitter={jitter}: {n_bad}/500 rays")
    assert not bad, "edges not exactly [near .. far]: " + "; ".join(bad)


def test_stratified_jitter_keeps_one_edge_per_bin_and_is_deterministic():
    n = 8
    t_near, t_far = torch.zeros(4000), torch.full((4000,), 8.0)  # bins of width 1
    e1 = stratified_samples(t_near, t_far, n, generator=torch.Generator().manual_seed(5))
    e2 = stratified_samples(t_near, t_far, n, generator=torch.Generator().manual_seed(5))
    assert torch.equal(e1, e2)
    inner = e1[:, 1:-1]
    k = torch.arange(1, n, dtype=torch.float32)
    # inner edge k moves within [k - 0.5, k + 0.5] and covers it uniformly
    assert ((inner >= k - 0.5) & (inner <= k + 0.5)).all()
    frac = inner - (k - 0.5)
    assert abs(float(frac.mean()) - 0.5) < 0.01
    assert abs(float((frac < 0.25).float().mean()) - 0.25) < 0.01
    e3 = stratified_samples(t_near, t_far, n, generator=torch.Generator().manual_seed(6))
    assert not torch.equal(e1, e3)


# ----------------------------------------------------------------------------- pdf sampling

def piecewise_cdf(edges: np.ndarray, weights: np.ndarray, t: np.ndarray) -> np.ndarray:
    """CDF of the piecewise-constant pdf (bins with mass ``weights``) at ``t``, float64."""
    mass = weights / weights.sum()
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    return np.interp(t, edges, cdf)


def test_pdf_samples_concentrate_where_the_weight_is():
    g = torch.Generator().manual_seed(0)
    n_rays, s = 16, 32
    edges = torch.sort(torch.rand(n_rays, s + 1, generator=g) * 4.0, -1).values
    weights = torch.full((n_rays, s), 0.05 / (s - 1))
    hot = torch.randint(0, s, (n_rays,), generator=g)
    weights[torch.arange(n_rays), hot] = 0.95
    samples = pdf_samples(edges, weights, 1000, generator=g)
    lo = edges.gather(-1, hot[:, None])
    hi = edges.gather(-1, hot[:, None] + 1)
    frac_in_hot = ((samples >= lo) & (samples <= hi)).float().mean(-1)
    assert (frac_in_hot > 0.9).all(), frac_in_hot
    assert ((samples >= edges[:, :1]) & (samples <= edges[:, -1:])).all()


def test_pdf_samples_follow_the_piecewise_constant_cdf():
    """Kolmogorov-Smirnov distance between the samples and the pdf's CDF is small."""
    g = torch.Generator().manual_seed(1)
    n_rays, s, n = 8, 20, 4000
    edges = torch.sort(torch.rand(n_rays, s + 1, generator=g, dtype=torch.float64), -1).values
    weights = torch.rand(n_rays, s, generator=g, dtype=torch.float64) ** 3
    samples = pdf_samples(edges, weights, n, generator=g)
    for r in range(n_rays):
        x = np.sort(samples[r].numpy())
        cdf = piecewise_cdf(edges[r].numpy(), weights[r].numpy() + 1e-5, x)
        ks = np.max(np.maximum(np.arange(1, n + 1) / n - cdf, cdf - np.arange(n) / n))
        assert ks < 1.63 / math.sqrt(n) + 0.005, (r, ks)  # 1% level of the KS test
    # without jitter the samples are the exact quantiles at (k + 1) / (n + 1): sorted, inside
    q = pdf_samples(edges, weights, 50, jitter=False)
    assert (q.diff(dim=-1) >= 0).all()
    for r in range(n_rays):
        cdf = piecewise_cdf(edges[r].numpy(), weights[r].numpy() + 1e-5, q[r].numpy())
        np.testing.assert_allclose(cdf, np.arange(1, 51) / 51, atol=1e-6)


def test_pdf_samples_all_zero_weights_are_uniform():
    n_rays, s = 6, 10
    edges = torch.linspace(1.0, 3.0, s + 1).expand(n_rays, s + 1).contiguous()
    weights = torch.zeros(n_rays, s)
    samples = pdf_samples(edges, weights, 2000, generator=torch.Generator().manual_seed(2))
    assert torch.isfinite(samples).all()
    assert ((samples >= 1.0) & (samples <= 3.0)).all()
    counts = torch.stack([((samples >= edges[0, i]) & (samples < edges[0, i + 1])).sum(-1)
                          for i in range(s)], -1).float()
    assert (counts / 2000 - 0.1).abs().max() < 0.03
    q = pdf_samples(edges, weights, 9, jitter=False)
    torch.testing.assert_close(q, torch.linspace(1.0, 3.0, 11)[1:-1].expand(n_rays, 9),
                               rtol=0, atol=1e-5)


def test_pdf_samples_degenerate_inputs_no_nan():
    # zero-width bins and a zero-length ray
    edges = torch.tensor([[0.0, 1.0, 1.0, 1.0, 2.0], [3.0, 3.0, 3.0, 3.0, 3.0]])
    weights = torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]])
    out = pdf_samples(edges, weights, 64, generator=torch.Generator().manual_seed(3))
    assert torch.isfinite(out).all()
    assert ((out[0] >= 0.0) & (out[0] <= 2.0)).all()
    assert (out[1] == 3.0).all()


def test_pdf_samples_deterministic_given_generator_and_detached():
    g0 = torch.Generator().manual_seed(0)
    edges = torch.sort(torch.rand(4, 9, generator=g0), -1).values
    weights = torch.rand(4, 8, generator=g0).requires_grad_(True)
    a = pdf_samples(edges, weights, 32, generator=torch.Generator().manual_seed(7))
    b = pdf_samples(edges, weights, 32, generator=torch.Generator().manual_seed(7))
    c = pdf_samples(edges, weights, 32, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert not a.requires_grad


# ----------------------------------------------------------------------------- occupancy grid

def make_grid(res: int, seed: int, p: float = 0.3, aabb=None) -> OccupancyGrid:
    aabb = torch.tensor([[-1.0, -0.6, -0.3], [1.0, 0.6, 0.9]]) if aabb is None else aabb
    grid = OccupancyGrid(aabb, resolution=res)
    g = torch.Generator().manual_seed(seed)
    occ = (torch.rand(res, res, res, generator=g) < p) & grid.inside
    grid.occupied.copy_(occ.to(torch.uint8))
    return grid


def random_rays(n: int, seed: int):
    """Rays from around the scene (~1.5 m from its centre) aimed at random points in it; most
    cross the grid, some start inside it, some end before reaching it."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g) * 0.9
    aim = (torch.rand(n, 3, generator=g) * 2 - 1) * torch.tensor([1.0, 0.6, 0.6])
    aim[:, 2] += 0.3
    d = torch.nn.functional.normalize(aim - o, dim=-1)
    t_begin = torch.rand(n, generator=g) * 0.3
    t_far = t_begin + 0.5 + torch.rand(n, generator=g) * 3.0
    return o, d, t_begin, t_far


def assert_same_samples(a, b):
    assert torch.equal(a.ray_indices, b.ray_indices)
    torch.testing.assert_close(a.t_starts, b.t_starts, rtol=0, atol=1e-5)
    torch.testing.assert_close(a.t_ends, b.t_ends, rtol=0, atol=1e-5)
    torch.testing.assert_close(a.t_stop, b.t_stop, rtol=0, atol=1e-5)


def check_packed(s, grid, o, d, t_begin, t_far, dt_min, dt_max, cone, max_per_ray):
    """Independent checks of the marcher's output contract (float64, own cell arithmetic)."""
    ri, ts, te = s.ray_indices, s.t_starts.double(), s.t_ends.double()
    assert ri.dtype == torch.int64 and s.t_starts.dtype == torch.float32
    assert (ri.diff() >= 0).all()  # sorted by ray
    same = ri[1:] == ri[:-1]
    assert (ts[1:][same] >= te[:-1][same] - 1e-6).all()  # increasing, non-overlapping per ray
    assert (te > ts).all()
    assert (ts >= t_begin.double()[ri] - 1e-6).all() and (te <= t_far.double()[ri] + 1e-6).all()
    dt = (ts * cone).clamp(dt_min, dt_max)
    assert ((te - ts) <= dt + 1e-5).all()
    counts = torch.bincount(ri, minlength=len(o))
    assert (counts <= max_per_ray).all()
    # every sample's midpoint (of its unclipped step) lies in an occupied cell
    mid = ts + 0.5 * dt
    p = o.double()[ri] + mid[:, None] * d.double()[ri]
    ijk = torch.floor((p - grid.cube_min.double()) / grid.cell_size).long()
    assert ((ijk >= 0) & (ijk < grid.resolution)).all()
    assert grid.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]].bool().all()
    return counts


@pytest.mark.parametrize("res,cone,dt_min,dt_max", [
    (16, 0.0, 0.02, 0.02),     # constant steps; cells of 1/8 m (power of two)
    (24, 0.0, 0.013, 0.013),   # cells of 1/12 m
    (16, 0.04, 0.005, 0.08),   # cone rule: steps grow with t, clamped both sides
])
def test_march_numba_matches_reference(res, cone, dt_min, dt_max):
    grid = make_grid(res, seed=res)
    o, d, tb, tf = random_rays(300, seed=1)
    # some rays point away from the scene / start past their far bound
    o[:20] = torch.tensor([5.0, 5.0, 5.0])
    d[:20] = torch.nn.functional.normalize(torch.ones(3), dim=0)
    tf[20:25] = tb[20:25]
    a = grid.march(o, d, tb, tf, dt_min, dt_max, cone)
    b = march_reference(o, d, tb, tf, grid.occupied, grid.cube_min, grid.cell_size, dt_min,
                        dt_max, cone)
    assert len(a) > 500
    assert_same_samples(a, b)
    counts = check_packed(a, grid, o, d, tb, tf, dt_min, dt_max, cone, 1 << 30)
    assert (counts[:25] == 0).all()
    assert (counts > 0).sum() > 100
    # a ray that marched to the end stops at or past its far bound
    assert (a.t_stop.double() >= tf.double() - 1e-6).all()


@pytest.mark.parametrize("max_per_ray", [1, 5])
def test_march_max_per_ray_matches_reference_and_resumes(max_per_ray):
    grid = make_grid(16, seed=3)
    o, d, tb, tf = random_rays(200, seed=2)
    dt = 0.02
    full = grid.march(o, d, tb, tf, dt, dt)
    a = grid.march(o, d, tb, tf, dt, dt, max_per_ray=max_per_ray)
    b = march_reference(o, d, tb, tf, grid.occupied, grid.cube_min, grid.cell_size, dt, dt,
                        0.0, max_per_ray)
    assert_same_samples(a, b)
    counts = check_packed(a, grid, o, d, tb, tf, dt, dt, 0.0, max_per_ray)
    full_counts = torch.bincount(full.ray_indices, minlength=200)
    assert torch.equal(counts, full_counts.clamp_max(max_per_ray))
    limited = counts == max_per_ray
    assert limited.sum() > 20
    # a ray that hit the limit stopped right after its last sample (to resume from there)
    last = torch.cumsum(counts, 0) - 1
    # (t_stop = t_start + dt; the sample's t_end may be clipped to t_far)
    torch.testing.assert_close(a.t_stop[limited], a.t_starts[last[limited]] + dt, rtol=0,
                               atol=1e-6)
    # rounds of max_per_ray samples, resumed from t_stop, reproduce the single full march
    t_cur, pieces = tb.clone(), []
    for _ in range(200):
        alive = torch.nonzero(t_cur < tf).squeeze(-1)
        if alive.numel() == 0:
            break
        s = grid.march(o[alive], d[alive], t_cur[alive], tf[alive], dt, dt,
                       max_per_ray=max_per_ray)
        t_cur[alive] = s.t_stop
        pieces.append((alive[s.ray_indices], s.t_starts, s.t_ends))
    ri, ts, te = (torch.cat(p) for p in zip(*pieces))
    order = torch.sort(ri, stable=True).indices
    assert torch.equal(ri[order], full.ray_indices)
    torch.testing.assert_close(ts[order], full.t_starts, rtol=0, atol=1e-5)
    torch.testing.assert_close(te[order], full.t_ends, rtol=0, atol=1e-5)


def test_march_max_per_ray_zero_emits_nothing_in_both_twins():
    grid = make_grid(16, seed=4)
    o, d, tb, tf = random_rays(100, seed=3)
    a = grid.march(o, d, tb, tf, 0.02, 0.02, max_per_ray=0)
    b = march_reference(o, d, tb, tf, grid.occupied, grid.cube_min, grid.cell_size, 0.02, 0.02,
                        0.0, 0)
    assert len(a) == 0
    assert torch.equal(a.t_stop, tb)  # nothing marched: resume from where we began
    assert len(b) == 0, f"march_reference emitted {len(b)} samples with max_per_ray=0"
    assert torch.equal(b.t_stop, tb)


def test_march_empty_grid_gives_zero_samples_and_background():
    grid = make_grid(16, seed=5, p=0.0)
    assert int(grid.occupied.sum()) == 0
    o, d, tb, tf = random_rays(64, seed=4)
    s = grid.march(o, d, tb, tf, 0.02, 0.02)
    r = march_reference(o, d, tb, tf, grid.occupied, grid.cube_min, grid.cell_size, 0.02, 0.02)
    assert len(s) == 0 and len(r) == 0
    n = len(o)
    bg = torch.rand(n, 3, generator=torch.Generator().manual_seed(0))
    out = composite(torch.zeros(0), torch.zeros(0, 3), s.t_starts, s.t_ends, s.ray_indices, n,
                    bg, tf, torch.ones(n))
    assert torch.equal(out.rgb, bg)
    assert torch.equal(out.depth, tf)
    assert torch.equal(out.opacity, torch.zeros(n))
    assert torch.isfinite(out.median_depth).all()


def test_march_full_grid_covers_the_box_with_contiguous_steps():
    """All cells occupied: a ray through the box emits contiguous steps exactly where its step
    midpoints are inside the cube."""
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = OccupancyGrid(aabb, resolution=8)
    assert int(grid.occupied.sum()) == 8 ** 3  # a fresh grid is fully occupied inside the box
    o = torch.tensor([[-3.0, 0.1, 0.2]])
    d = torch.tensor([[1.0, 0.0, 0.0]])
    s = grid.march(o, d, torch.zeros(1), torch.full((1,), 6.0), 0.25, 0.25)
    # steps [0, .25), ..., midpoints at 0.125 + 0.25 k; inside x in [-1, 1] <=> t in [2, 4]
    np.testing.assert_allclose(s.t_starts.numpy(), 2.0 + 0.25 * np.arange(8))
    np.testing.assert_allclose(s.t_ends.numpy(), 2.25 + 0.25 * np.arange(8))


def sphere_density(center, radius, value=1000.0):
    c = torch.tensor(center)

    def fn(x):
        return torch.where((x - c).norm(dim=-1) < radius, torch.full(x.shape[:1], value),
                           torch.zeros(x.shape[:1]))
    return fn


def cell_boxes(res: int):
    """lo, hi corners (G, G, G, 3) float64 of the cells of a grid over the cube [-1, 1]^3."""
    idx = torch.arange(res, dtype=torch.float64)
    lo = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), -1) * (2.0 / res) - 1.0
    return lo, lo + 2.0 / res


def test_update_marks_the_sphere_and_nothing_else():
    # non-cubic bounds: the cube is [-1, 1]^3, the bounds cover z in [-0.45, 0.45] only
    z_lo, z_hi = -0.45, 0.45
    aabb = torch.tensor([[-1.0, -1.0, z_lo], [1.0, 1.0, z_hi]])
    res = 16
    grid = OccupancyGrid(aabb, resolution=res)
    center, radius = (0.2, -0.1, 0.0), 0.42
    sphere = sphere_density(center, radius)
    # dense everywhere outside the bounds too: those cells must stay empty regardless
    outside = lambda x: torch.where(x[:, 2].abs() > 0.5, torch.full(x.shape[:1], 1e4),
                                    torch.zeros(x.shape[:1]))
    frac = grid.update(lambda x: sphere(x) + outside(x), step_size=0.01,
                       generator=torch.Generator().manual_seed(0))
    occ = grid.occupied.bool()
    # cell geometry, computed here independently
    lo, hi = cell_boxes(res)
    c = torch.tensor(center, dtype=torch.float64)
    nearest = torch.maximum(torch.minimum(c, hi), lo)          # point of the cell nearest c
    corners = torch.stack([torch.where(torch.tensor([(k >> i) & 1 for i in range(3)]).bool(),
                                       hi, lo) for k in range(8)], 0)
    farthest = (corners - c).norm(dim=-1).amax(0)
    fully_in = farthest < radius
    fully_out = (nearest - c).norm(dim=-1) > radius
    in_bounds = (hi[..., 2] > z_lo) & (lo[..., 2] < z_hi)  # the cell overlaps the bounds
    assert int(fully_in.sum()) > 20 and int((~in_bounds).sum()) > 1000
    assert occ[fully_in].all()
    assert not occ[fully_out].any()
    assert not occ[~in_bounds].any()
    assert torch.equal(grid.inside.bool(), in_bounds)
    assert frac == pytest.approx(float(occ.sum()) / float(in_bounds.sum()), rel=1e-6)
    # the decaying maximum keeps the cells occupied after one update with no density at all
    grid.update(lambda x: torch.zeros(x.shape[:1]), step_size=0.01,
                generator=torch.Generator().manual_seed(1))
    assert torch.equal(grid.occupied.bool(), occ)


def test_update_cells_just_outside_face_aligned_bounds_stay_empty():
    """Bounds z in [-0.5, 0.5] fall on cell faces (cells of 1/8 m): the layer of cells
    z in [0.5, 0.625] touches the bounds only along a face and lies outside them, so it must
    stay empty even where the density function is high."""
    aabb = torch.tensor([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]])
    res = 16
    grid = OccupancyGrid(aabb, resolution=res)
    lo, hi = cell_boxes(res)
    in_bounds = (hi[..., 2] > -0.5) & (lo[..., 2] < 0.5)
    assert int(in_bounds[0, 0].sum()) == 8  # 8 of the 16 z-layers overlap the bounds
    grid.update(lambda x: torch.full(x.shape[:1], 1e4) * (x[:, 2].abs() > 0.5).float()
                + torch.full(x.shape[:1], 1.0), step_size=0.01,
                generator=torch.Generator().manual_seed(0))
    occ = grid.occupied.bool()
    bad = occ & ~in_bounds
    assert not bad.any(), (f"{int(bad.sum())} cells outside the bounds are occupied, at z layers "
                           f"{sorted(set(torch.nonzero(bad)[:, 2].tolist()))}")


def test_update_evaluates_only_the_cells_overlapping_the_bounds():
    """A flat scene fills a small part of its enclosing cube: the update asks the field for one
    point per cell that overlaps the bounds (a quarter of the cells here), each within its
    cell, and none elsewhere."""
    aabb = torch.tensor([[-1.0, -1.0, -0.25], [1.0, 1.0, 0.25]])
    res = 16
    grid = OccupancyGrid(aabb, resolution=res)
    seen = []

    def fn(x):
        seen.append(x.clone())
        return torch.ones(x.shape[:1])

    grid.update(fn, step_size=0.01, generator=torch.Generator().manual_seed(0))
    x = torch.cat(seen)
    assert len(x) == int(grid.inside.sum()) == res ** 3 // 4
    cells = torch.floor((x + 1.0) * res / 2.0).long()
    assert torch.equal(grid.inside[cells[:, 0], cells[:, 1], cells[:, 2]],
                       torch.ones(len(x), dtype=torch.bool))
    assert len(torch.unique(cells, dim=0)) == len(x)  # one point in every such cell


def test_update_never_prunes_to_an_empty_grid():
    """A field with no density anywhere keeps the previous occupancy (an empty grid would give
    no samples, hence no gradient, and training could never recover); a later update with
    structure prunes as usual."""
    grid = OccupancyGrid(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), resolution=8)
    gen = torch.Generator().manual_seed(0)
    frac = grid.update(lambda x: torch.zeros(x.shape[:1]), step_size=0.01, generator=gen)
    assert frac == 1.0 and int(grid.occupied.sum()) == 8 ** 3
    frac = grid.update(lambda x: 100.0 * (x[:, 0] < 0.5).float(), step_size=0.01, generator=gen)
    assert frac == 0.5 and int(grid.occupied[:4].sum()) == 4 * 8 * 8


def test_update_threshold_uses_step_opacity():
    """A uniform density sigma is occupied iff one step through it is at least ``threshold``
    opaque: sigma > threshold / step_size (unless the mean is lower, which it is not here)."""
    aabb = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    for sigma, expect in [(0.5, 0), (2.0, 8 ** 3)]:
        grid = OccupancyGrid(aabb, resolution=8, threshold=0.01)

        def fn(x, s=sigma):
            return torch.full(x.shape[:1], s)
        # a non-uniform field so the mean exceeds threshold / step_size = 1.0
        grid.update(lambda x: fn(x) + 100.0 * (x[:, 0] > 0.875).float(), step_size=0.01,
                    generator=torch.Generator().manual_seed(0))
        hot = 8 ** 2  # the last slab of cells in x
        assert int(grid.occupied.sum()) == (expect if expect else hot)


def test_scattered_block_schedule_visits_every_ray_once():
    """The parallel loops visit ray blocks in a scattered order (both cores get sky and scene
    alike); every ray must still be visited exactly once, for any count."""
    from nerfbot.kernels.schedule import SPREAD, block_range, scattered

    for n_items, block in ((1, 64), (63, 64), (16384, 64), (16384, 32), (SPREAD * 64, 64),
                           (5000, 7)):
        n_blocks = -(-n_items // block)
        seen = np.zeros(n_items, np.int64)
        for i in range(n_blocks):
            r0, r1 = block_range(i, n_items, block)
            seen[r0:r1] += 1
        assert (seen == 1).all(), (n_items, block)
        order = [scattered(i, n_blocks) for i in range(n_blocks)]
        assert sorted(order) == list(range(n_blocks))
    # neighbouring iterations land far apart (what spreads an image's rows over the threads)
    assert abs(scattered(1, 256) - scattered(0, 256)) > 16


@pytest.mark.parametrize("contract", [False, True])
def test_random_occupied_points_fill_the_occupied_cells_evenly(contract):
    """Points land only in occupied cells (looked up through the contraction when the grid
    covers all of space), every occupied cell gets its share, and an empty grid gives none."""
    grid = OccupancyGrid(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), resolution=8,
                         contract=contract)
    grid.occupied.zero_()
    cells = torch.tensor([[1, 2, 3], [6, 6, 6], [0, 7, 4]])
    grid.occupied[cells[:, 0], cells[:, 1], cells[:, 2]] = 1
    x = grid.random_occupied_points(30000, torch.Generator().manual_seed(0))
    assert x.shape == (30000, 3) and torch.isfinite(x).all()
    ijk = ((grid.lookup_points(x) - grid.cube_min) / grid.cell_size).floor().long()
    hit = grid.occupied[ijk[:, 0], ijk[:, 1], ijk[:, 2]].bool()
    assert hit.all()
    counts = torch.stack([(ijk == c).all(1).sum() for c in cells]).double()
    assert counts.sum() == 30000 and (counts / 10000 - 1).abs().max() < 0.05
    grid.occupied.zero_()
    assert grid.random_occupied_points(10).shape == (0, 3)
