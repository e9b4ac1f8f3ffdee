"""Volume-rendering arithmetic (nerfbot.ops.rendering) and the density activation (trunc_exp).

Every result is compared with an independent float64 reference written here as plain Python
loops over rays (no packed tricks, no torch cumsum):

    tau_i = sigma_i * delta_i,  T_i = exp(-sum_{j<i} tau_j),  w_i = T_i * (1 - exp(-tau_i)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfbot.fields.base import trunc_exp
from nerfbot.ops.rendering import EMPTY_OPACITY, composite, depth_spread, render_weights

INF = float("inf")


# ----------------------------------------------------------------------------- reference

def ray_slices(ray_indices: torch.Tensor, n_rays: int) -> list[list[int]]:
    """Packed indices of every ray's samples, in order (independent of rendering.ray_starts)."""
    out: list[list[int]] = [[] for _ in range(n_rays)]
    for i, r in enumerate(ray_indices.tolist()):
        out[r].append(i)
    return out


def sample_tau(sigma: float, delta: float) -> float:
    """Optical thickness of one sample; a zero-length sample is transparent whatever sigma."""
    delta = max(delta, 0.0)
    return 0.0 if delta == 0.0 else sigma * delta


def reference_render(sigmas, rgbs, t_starts, t_ends, ray_indices, n_rays, background, far,
                     z_per_t):
    """float64 loop reference of composite(): dict of numpy arrays."""
    sig = [float(s) for s in sigmas.double()]
    col = rgbs.double().numpy()
    ts = t_starts.double().numpy()
    te = t_ends.double().numpy()
    bg = np.broadcast_to(background.double().numpy(), (n_rays, 3))
    far = far.double().numpy()
    zpt = z_per_t.double().numpy()
    m = len(sig)
    w = np.zeros(m)
    trans = np.zeros(m)
    rgb = np.zeros((n_rays, 3))
    opacity = np.zeros(n_rays)
    depth = np.zeros(n_rays)
    median = np.zeros(n_rays)
    for r, idx in enumerate(ray_slices(ray_indices, n_rays)):
        acc = 0.0  # sum of tau before the current sample
        for i in idx:
            tau = sample_tau(sig[i], te[i] - ts[i])
            trans[i] = math.exp(-acc)
            alpha = 1.0 if tau == INF else -math.expm1(-tau)
            w[i] = trans[i] * alpha if trans[i] > 0 else 0.0
            acc += tau
        op = sum(w[i] for i in idx)
        opacity[r] = op
        rgb[r] = sum((w[i] * col[i] for i in idx), np.zeros(3)) + (1.0 - op) * bg[r]
        t_mid = [0.5 * (ts[i] + te[i]) for i in idx]
        if op > EMPTY_OPACITY:
            depth[r] = sum(w[i] * t for i, t in zip(idx, t_mid)) / op
            cum = 0.0
            median[r] = far[r]
            for i, t in zip(idx, t_mid):
                cum += w[i]
                if cum >= 0.5 * op:
                    median[r] = t
                    break
        else:
            depth[r] = far[r]
            median[r] = far[r]
    return dict(weights=w, trans=trans, rgb=rgb, opacity=opacity, depth=depth,
                z_depth=depth * zpt, median_depth=median)


def random_batch(seed: int, n_rays: int = 40, max_samples: int = 30, dtype=torch.float64,
                 sigma_scale: float = 3.0):
    """A ragged packed batch: some empty rays, some single-sample rays, gaps between samples,
    some zero densities. Returns the composite() arguments as a dict."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_samples + 1, (n_rays,), generator=g)
    counts[0], counts[1], counts[2] = 0, 1, max_samples  # always: empty, single, full
    counts[n_rays // 2] = 0
    counts[-1] = 1
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
    m = int(counts.sum())
    deltas = torch.rand(m, generator=g, dtype=torch.float64) * 0.2 + 1e-3
    gaps = torch.rand(m, generator=g, dtype=torch.float64) * 0.05
    gaps[torch.rand(m, generator=g) < 0.5] = 0.0  # half the samples touch their predecessor
    t_starts = torch.empty(m, dtype=torch.float64)
    t_ends = torch.empty(m, dtype=torch.float64)
    near = torch.rand(n_rays, generator=g, dtype=torch.float64) * 0.5
    k = 0
    for r, c in enumerate(counts.tolist()):
        t = float(near[r])
        for _ in range(c):
            t += float(gaps[k])
            t_starts[k], t_ends[k] = t, t + float(deltas[k])
            t = float(t_ends[k])
            k += 1
    sigmas = torch.rand(m, generator=g, dtype=torch.float64) ** 2 * sigma_scale / 0.1
    sigmas[torch.rand(m, generator=g) < 0.15] = 0.0
    rgbs = torch.rand(m, 3, generator=g, dtype=torch.float64)
    background = torch.rand(n_rays, 3, generator=g, dtype=torch.float64)
    far = torch.full((n_rays,), 6.0, dtype=torch.float64)
    z_per_t = 0.5 + 0.5 * torch.rand(n_rays, generator=g, dtype=torch.float64)
    args = dict(sigmas=sigmas, rgbs=rgbs, t_starts=t_starts, t_ends=t_ends,
                ray_indices=ray_indices, n_rays=n_rays, background=background, far=far,
                z_per_t=z_per_t)
    return {k: (v.to(dtype) if torch.is_tensor(v) and v.is_floating_point() else v)
            for k, v in args.items()}


def run_composite(b: dict, **kw):
    return composite(b["sigmas"], b["rgbs"], b["t_starts"], b["t_ends"], b["ray_indices"],
                     b["n_rays"], b["background"], b["far"], b["z_per_t"], **kw)


def run_reference(b: dict):
    return reference_render(b["sigmas"], b["rgbs"], b["t_starts"], b["t_ends"],
                            b["ray_indices"], b["n_rays"], b["background"], b["far"],
                            b["z_per_t"])


def np_(t: torch.Tensor) -> np.ndarray:
    return t.detach().double().numpy()


def packed(rays: list[list[tuple[float, float, float]]], dtype=torch.float64):
    """(sigma, t_start, t_end) per sample per ray -> sigmas, t_starts, t_ends, ray_indices."""
    flat = [(r, s, a, b) for r, ray in enumerate(rays) for (s, a, b) in ray]
    if not flat:
        z = torch.zeros(0, dtype=dtype)
        return z, z.clone(), z.clone(), torch.zeros(0, dtype=torch.long)
    ri, s, a, b = zip(*flat)
    return (torch.tensor(s, dtype=dtype), torch.tensor(a, dtype=dtype),
            torch.tensor(b, dtype=dtype), torch.tensor(ri, dtype=torch.long))


# ----------------------------------------------------------------------------- against the reference

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_composite_matches_float64_reference(seed):
    b = random_batch(seed)
    out = run_composite(b)
    ref = run_reference(b)
    np.testing.assert_allclose(np_(out.weights), ref["weights"], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np_(out.opacity), ref["opacity"], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np_(out.rgb), ref["rgb"], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np_(out.depth), ref["depth"], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np_(out.z_depth), ref["z_depth"], rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(np_(out.median_depth), ref["median_depth"])
    assert out.num_samples == b["sigmas"].shape[0]


def test_render_weights_transmittance_matches_reference():
    b = random_batch(3)
    w, trans = render_weights(b["sigmas"], b["t_starts"], b["t_ends"], b["ray_indices"],
                              b["n_rays"])
    ref = run_reference(b)
    np.testing.assert_allclose(np_(trans), ref["trans"], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np_(w), ref["weights"], rtol=1e-12, atol=1e-15)
    assert w.dtype == trans.dtype == torch.float64


def test_weights_sum_to_opacity_closed_form():
    """sum_i w_i = 1 - exp(-sum_i tau_i) <= 1 for every ray; weights and opacity lie in [0, 1]."""
    b = random_batch(4, n_rays=60)
    out = run_composite(b)
    tau = (b["sigmas"] * (b["t_ends"] - b["t_starts"])).numpy()
    total = np.zeros(b["n_rays"])
    np.add.at(total, b["ray_indices"].numpy(), tau)
    np.testing.assert_allclose(np_(out.opacity), -np.expm1(-total), rtol=1e-12, atol=1e-15)
    assert float(out.weights.min()) >= 0.0
    per_ray = np.zeros(b["n_rays"])
    np.add.at(per_ray, b["ray_indices"].numpy(), np_(out.weights))
    np.testing.assert_allclose(np_(out.opacity), per_ray, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_opacity_exceeds_one_by_rounding_at_most(dtype):
    """opacity = sum_i w_i is documented to lie in [0, 1]. Each weight carries a relative error
    of a few ulps, so a ray of S samples may exceed 1 by about S ulps, no more; the float64
    loop reference stays within 1 ulp on this batch. (Beyond that, 1 - opacity goes negative
    and the background is subtracted.)"""
    eps = torch.finfo(dtype).eps
    worst = 0.0
    for seed in range(4):
        b = random_batch(20 + seed, n_rays=80, max_samples=60, dtype=dtype, sigma_scale=10.0)
        out = run_composite(b)
        worst = max(worst, float(out.opacity.max()) - 1.0)
        assert float(out.opacity.min()) >= 0.0
    assert worst <= 4 * 60 * eps, f"opacity exceeds 1 by {worst:.3g} ({worst / eps:.0f} ulp)"


def test_rgb_is_weighted_colour_plus_background():
    b = random_batch(5)
    out = run_composite(b)
    col = np.zeros((b["n_rays"], 3))
    np.add.at(col, b["ray_indices"].numpy(), np_(out.weights)[:, None] * b["rgbs"].numpy())
    expect = col + (1.0 - np_(out.opacity))[:, None] * b["background"].numpy()
    np.testing.assert_allclose(np_(out.rgb), expect, rtol=1e-13, atol=1e-15)
    # colours in [0, 1] and a background in [0, 1] give an rgb in [0, 1]
    assert float(out.rgb.min()) >= 0.0 and float(out.rgb.max()) <= 1.0 + 1e-12


def test_background_broadcasts_from_a_single_colour():
    b = random_batch(6)
    bg = torch.tensor([0.1, 0.7, 0.3], dtype=torch.float64)
    out = composite(b["sigmas"], b["rgbs"], b["t_starts"], b["t_ends"], b["ray_indices"],
                    b["n_rays"], bg, b["far"], b["z_per_t"])
    b2 = dict(b, background=bg.expand(b["n_rays"], 3).clone())
    np.testing.assert_allclose(np_(out.rgb), np_(run_composite(b2).rgb), rtol=0, atol=0)


def test_empty_rays_render_background_and_far():
    """Rays with no samples, and rays whose samples are all transparent, are empty."""
    b = random_batch(7)
    counts = torch.bincount(b["ray_indices"], minlength=b["n_rays"])
    # make ray 3 fully transparent (density zero everywhere)
    b["sigmas"] = b["sigmas"].clone()
    b["sigmas"][b["ray_indices"] == 3] = 0.0
    b["far"] = 2.0 + torch.arange(b["n_rays"], dtype=torch.float64) * 0.1  # distinct per ray
    out = run_composite(b)
    empty = (counts == 0).clone()
    empty[3] = True
    assert int((counts == 0).sum()) >= 2
    e = empty.numpy()
    np.testing.assert_array_equal(np_(out.rgb)[e], b["background"].numpy()[e])
    np.testing.assert_array_equal(np_(out.opacity)[e], 0.0)
    np.testing.assert_array_equal(np_(out.depth)[e], b["far"].numpy()[e])
    np.testing.assert_array_equal(np_(out.median_depth)[e], b["far"].numpy()[e])
    np.testing.assert_allclose(np_(out.z_depth)[e], (b["far"] * b["z_per_t"]).numpy()[e],
                               rtol=1e-15)
    for t in (out.rgb, out.opacity, out.depth, out.z_depth, out.median_depth, out.weights):
        assert torch.isfinite(t).all()


def test_zero_samples_at_all():
    """A batch with M = 0 (e.g. every ray missed the occupied cells) is all background."""
    n = 5
    z = torch.zeros(0)
    bg = torch.rand(n, 3, generator=torch.Generator().manual_seed(0))
    far = torch.linspace(1.0, 3.0, n)
    out = composite(z, torch.zeros(0, 3), z, z, torch.zeros(0, dtype=torch.long), n, bg, far,
                    torch.ones(n))
    assert torch.equal(out.rgb, bg)
    assert torch.equal(out.opacity, torch.zeros(n))
    assert torch.equal(out.depth, far)
    assert torch.equal(out.median_depth, far)
    assert out.num_samples == 0 and out.weights.shape == (0,)


def test_median_depth_hand_example():
    # two equal-thickness slabs: the first holds w0 = 1 - e^-1 = 0.632 > half of the opacity
    s, a, b_, ri = packed([[(1.0, 1.0, 2.0), (1.0, 2.0, 3.0)],
                           [(0.01, 1.0, 2.0), (5.0, 4.0, 5.0)]])
    out = composite(s, torch.zeros(4, 3), a, b_, ri, 2, torch.zeros(3),
                    torch.tensor([9.0, 9.0], dtype=torch.float64), torch.ones(2))
    assert out.median_depth.tolist() == [1.5, 4.5]
    # expected depth of ray 0: (w0 * 1.5 + w1 * 2.5) / (w0 + w1)
    w0 = 1 - math.exp(-1)
    w1 = math.exp(-1) * w0
    assert out.depth[0].item() == pytest.approx((w0 * 1.5 + w1 * 2.5) / (w0 + w1), rel=1e-14)


def test_with_median_false_reports_expected_depth():
    b = random_batch(8)
    out = run_composite(b, with_median=False)
    assert torch.equal(out.median_depth, out.depth.detach())


def test_depth_spread_matches_a_per_ray_reference_and_is_zero_for_empty_rays():
    b = random_batch(11)
    out = run_composite(b)
    t_mid = 0.5 * (b["t_starts"] + b["t_ends"])
    got = depth_spread(out.weights, t_mid, b["ray_indices"], b["n_rays"], out.opacity, out.depth)
    w, t = np_(out.weights), np_(t_mid)
    for r, idx in enumerate(ray_slices(b["ray_indices"], b["n_rays"])):
        op = w[idx].sum()
        if op <= EMPTY_OPACITY:
            assert got[r].item() == 0.0
            continue
        mean = (w[idx] * t[idx]).sum() / op
        assert got[r].item() == pytest.approx(math.sqrt((w[idx] * (t[idx] - mean) ** 2).sum() / op),
                                              rel=1e-9, abs=1e-12)
    assert (got[[0, b["n_rays"] // 2]] == 0).all()  # the batch's empty rays


def test_depth_spread_keeps_centimetres_at_kilometres_in_float32():
    # one ray: two equal weights 1 cm apart, 1 km away (spread 5 mm); in float32, where t^2
    # rounds to 0.06 m^2, E[t^2] - E[t]^2 would be all rounding
    t_mid = torch.tensor([1000.005, 1000.015], dtype=torch.float32)
    w = torch.tensor([0.5, 0.5])
    spread = depth_spread(w, t_mid, torch.zeros(2, dtype=torch.long), 1, torch.tensor([1.0]),
                          torch.tensor([1000.01]))
    assert spread.item() == pytest.approx(0.005, rel=2e-2)


# ----------------------------------------------------------------------------- gradients

def test_gradcheck_composite_float64():
    b = random_batch(9, n_rays=5, max_samples=4)
    ts, te, ri, n = b["t_starts"], b["t_ends"], b["ray_indices"], b["n_rays"]
    bg, far, zpt = b["background"], b["far"], b["z_per_t"]
    # densities bounded away from the EMPTY_OPACITY switch; include one exact zero
    sig = (b["sigmas"] + 0.5).clone()
    sig[0] = 0.0
    sig.requires_grad_(True)
    rgbs = b["rgbs"].clone().requires_grad_(True)

    def fn(s, c):
        out = composite(s, c, ts, te, ri, n, bg, far, zpt)
        return out.rgb, out.opacity, out.depth, out.z_depth

    assert torch.autograd.gradcheck(fn, (sig, rgbs), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradcheck_render_weights_float64():
    b = random_batch(10, n_rays=4, max_samples=5)
    sig = b["sigmas"].clone().requires_grad_(True)

    def fn(s):
        return render_weights(s, b["t_starts"], b["t_ends"], b["ray_indices"], b["n_rays"])

    assert torch.autograd.gradcheck(fn, (sig,), eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_finite_at_extreme_densities(dtype):
    s, a, b_, ri = packed([
        [(0.0, 0.0, 1.0), (1e-12, 1.0, 2.0), (1e10, 2.0, 2.001), (INF, 3.0, 4.0)],
        [(INF, 1.0, 1.0), (1e10, 1.0, 2.0), (3.0, 2.0, 3.0)],     # zero-length inf sample
        [(1e10, 0.0, 1e-12), (2.0, 1.0, 1e6 + 1.0)],              # tiny and huge deltas
        [(1e10, 0.5, 0.6)] * 1,
    ], dtype)
    sig = s.clone().requires_grad_(True)
    rgbs = torch.rand(len(s), 3, generator=torch.Generator().manual_seed(0),
                      dtype=dtype).requires_grad_(True)
    out = composite(sig, rgbs, a, b_, ri, 4, torch.full((3,), 0.5, dtype=dtype),
                    torch.full((4,), 10.0, dtype=dtype), torch.ones(4, dtype=dtype))
    for t in (out.rgb, out.opacity, out.depth, out.median_depth, out.weights):
        assert torch.isfinite(t).all()
    loss = (out.rgb - 0.3).square().sum() + out.depth.sum() + out.opacity.sum()
    loss.backward()
    assert torch.isfinite(sig.grad).all()
    assert torch.isfinite(rgbs.grad).all()
    # a sample hidden behind an opaque one gets no colour gradient; the visible one does
    assert rgbs.grad[3].abs().sum() == 0.0
    assert rgbs.grad[2].abs().sum() > 0.0


# ----------------------------------------------------------------------------- extremes

def test_extreme_densities_and_deltas_match_reference():
    rays = [
        [(0.0, 0.0, 1.0)] * 1,                                      # sigma 0: empty
        [(1e-12, 0.0, 1.0), (1e-12, 1.0, 2.0)],                     # tiny sigma
        [(1e10, 0.0, 0.5), (3.0, 0.5, 1.0)],                        # huge sigma: all weight
        [(INF, 2.0, 2.5), (5.0, 2.5, 3.0)],                         # inf first: all weight
        [(0.3, 0.0, 1.0), (INF, 1.0, 1.1), (7.0, 1.1, 2.0)],        # inf in the middle
        [(INF, 1.0, 1.0), (2.0, 1.0, 1.5)],                         # inf but zero length
        [(1.0, 3.0, 3.0), (1.0, 3.0, 3.0)],                         # delta 0: empty
        [(1e-7, 0.0, 1e6)],                                         # huge delta, tau 0.1
        [(2.0, 0.0, 1e6)],                                          # huge delta, opaque
        [(1e10, 0.0, 1e-12), (1e10, 1e-12, 2e-12)],                 # tau 1e-2 each
    ]
    s, a, b_, ri = packed(rays)
    n = len(rays)
    rgbs = torch.rand(len(s), 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    far = torch.full((n,), 50.0, dtype=torch.float64)
    zpt = torch.ones(n, dtype=torch.float64)
    out = composite(s, rgbs, a, b_, ri, n, bg, far, zpt)
    ref = reference_render(s, rgbs, a, b_, ri, n, bg, far, zpt)
    for t in (out.rgb, out.opacity, out.depth, out.median_depth, out.weights):
        assert torch.isfinite(t).all()
    np.testing.assert_allclose(np_(out.weights), ref["weights"], rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(np_(out.rgb), ref["rgb"], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np_(out.depth), ref["depth"], rtol=1e-12)
    np.testing.assert_array_equal(np_(out.median_depth), ref["median_depth"])
    w = np_(out.weights)
    # packed order: ray0 [0], ray1 [1, 2], ray2 [3, 4], ray3 [5, 6], ray4 [7, 8, 9],
    # ray5 [10, 11], ray6 [12, 13], ray7 [14], ray8 [15], ray9 [16, 17]
    # an infinitely (or 1e10-) dense first sample takes all the weight, exactly
    assert w[3] == 1.0 and w[4] == 0.0  # ray 2
    assert w[5] == 1.0 and w[6] == 0.0  # ray 3
    # ray 4: an inf sample after a 0.3-thick one takes all the remaining transmittance
    assert w[7] == pytest.approx(-math.expm1(-0.3), rel=1e-15)
    assert w[8] == pytest.approx(math.exp(-0.3), rel=1e-15)
    assert w[9] == 0.0
    # ray 5: an infinitely dense but zero-length sample is transparent
    assert w[10] == 0.0 and w[11] == pytest.approx(-math.expm1(-1.0), rel=1e-15)
    assert w[15] == 1.0  # ray 8: opaque over a 1e6 m interval
    assert out.opacity[0] == 0.0 and out.depth[0] == 50.0
    assert out.opacity[6] == 0.0 and out.depth[6] == 50.0
    assert out.opacity[1].item() == pytest.approx(2e-12, rel=1e-9)


def test_inf_density_float32():
    s, a, b_, ri = packed([[(INF, 0.0, 0.1), (1.0, 0.1, 0.2)], [(0.5, 0.0, 0.1), (INF, 0.1, 0.2)]],
                          torch.float32)
    w, trans = render_weights(s, a, b_, ri, 2)
    assert w.dtype == torch.float32
    assert w.tolist() == [1.0, 0.0, pytest.approx(-math.expm1(-0.05), rel=1e-6),
                          pytest.approx(math.exp(-0.05), rel=1e-6)]
    assert trans[1] == 0.0 and trans[0] == 1.0


def long_ray(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    deltas = torch.rand(n, generator=g, dtype=torch.float64) * 2e-3 + 1e-4
    t_ends = torch.cumsum(deltas, 0)
    t_starts = t_ends - deltas
    # optical thickness ~ 2e-3 per sample on average: the total reaches 2e-3 * n
    sigmas = torch.rand(n, generator=g, dtype=torch.float64) * 4e-3 / deltas.mean()
    return sigmas, t_starts, t_ends


def test_long_ray_float64_exact():
    n = 5000
    s, a, b_ = long_ray(n, 0)
    ri = torch.zeros(n, dtype=torch.long)
    w, trans = render_weights(s, a, b_, ri, 1)
    tau = (s * (b_ - a)).numpy()
    acc = 0.0
    ref_t = np.empty(n)
    for i in range(n):  # sequential float64 sum (error ~ n * 1e-16 relative)
        ref_t[i] = acc
        acc += tau[i]
    assert acc > 8.0  # the ray ends well into the opaque regime
    np.testing.assert_allclose(np_(trans), np.exp(-ref_t), rtol=1e-12)
    np.testing.assert_allclose(np_(w), np.exp(-ref_t) * -np.expm1(-tau), rtol=1e-12)


def test_long_ray_float32_matches_float64_reference():
    """float32 inputs: T_i and w_i within 1e-6 relative (~8 float32 ulps) of the float64
    reference computed from the same (float32-rounded) inputs over 20 000 samples reaching a
    total optical thickness of ~40. A float32 running sum drifts by ~1e-4 here and fails."""
    n = 20000
    s, a, b_ = long_ray(n, 1)
    s32, a32, b32 = s.float(), a.float(), b_.float()
    ri = torch.zeros(n, dtype=torch.long)
    w, trans = render_weights(s32, a32, b32, ri, 1)
    assert w.dtype == torch.float32
    tau = (s32.double() * (b32.double() - a32.double())).numpy()
    ref_before = np.concatenate([[0.0], np.cumsum(tau)[:-1]])
    ref_t = np.exp(-ref_before)
    ref_w = ref_t * -np.expm1(-tau)
    assert ref_before[-1] > 15.0
    np.testing.assert_allclose(np_(trans), ref_t, rtol=1e-6)
    np.testing.assert_allclose(np_(w), ref_w, rtol=1e-6)
    # a float32 running sum really is worse here (~1e-4), so the tolerance discriminates
    tau32 = (s32 * (b32 - a32)).numpy()
    naive_before = np.cumsum(tau32, dtype=np.float32) - tau32
    assert np.max(np.abs(np.exp(-naive_before.astype(np.float64)) / ref_t - 1)) > 1e-5


@pytest.mark.parametrize("seed", [11, 12])
def test_float32_batch_matches_float64_reference(seed):
    b64 = random_batch(seed, n_rays=80, max_samples=60)
    b32 = random_batch(seed, n_rays=80, max_samples=60, dtype=torch.float32)
    out = run_composite(b32)
    # reference from the float32-rounded inputs: what remains is the arithmetic error only
    ref = run_reference({k: (v.double() if torch.is_tensor(v) and v.is_floating_point() else v)
                         for k, v in b32.items()})
    assert out.rgb.dtype == torch.float32
    np.testing.assert_allclose(np_(out.weights), ref["weights"], rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(np_(out.opacity), ref["opacity"], rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(np_(out.rgb), ref["rgb"], rtol=2e-6, atol=1e-6)
    np.testing.assert_allclose(np_(out.depth), ref["depth"], rtol=2e-6, atol=1e-6)
    # the float32-rounded inputs are close to the float64 ones, so is the picture
    ref64 = run_reference(b64)
    np.testing.assert_allclose(np_(out.rgb), ref64["rgb"], atol=1e-4)


def test_ray_result_does_not_depend_on_preceding_rays_float64():
    """A ray's weights must not depend on which rays are packed before it in the batch.

    Here 16 opaque rays (64 samples each of density 1e10, i.e. clamped thickness 1e4) precede a
    moderate ray. Computed alone, and in the float64 reference, the moderate ray's weights agree
    to ~1e-16; packed after the opaque rays they must agree to 1e-12 as well.
    """
    n_opaque, per = 16, 64
    rays = [[(1e10, 0.01 * i, 0.01 * (i + 1)) for i in range(per)] for _ in range(n_opaque)]
    g = torch.Generator().manual_seed(3)
    probe = [(float(s), 0.05 * i, 0.05 * (i + 1))
             for i, s in enumerate(torch.rand(40, generator=g, dtype=torch.float64) * 2.0)]
    s, a, b_, ri = packed(rays + [probe])
    w_batch, t_batch = render_weights(s, a, b_, ri, n_opaque + 1)
    s1, a1, b1, ri1 = packed([probe])
    w_alone, t_alone = render_weights(s1, a1, b1, ri1, 1)
    ref = reference_render(s1, torch.zeros(len(s1), 3, dtype=torch.float64), a1, b1, ri1, 1,
                           torch.zeros(3), torch.ones(1), torch.ones(1))
    np.testing.assert_allclose(np_(w_alone), ref["weights"], rtol=1e-13)
    np.testing.assert_allclose(np_(t_batch[-len(probe):]), ref["trans"], rtol=1e-12)
    np.testing.assert_allclose(np_(w_batch[-len(probe):]), ref["weights"], rtol=1e-12)


def test_float32_ray_after_opaque_rays_within_float32_precision():
    """The same situation in float32 (1e5 samples, ~1e9 total clamped thickness before the
    probe ray): the error must stay within a few float32 ulps."""
    n_opaque, per = 100, 1000
    g = torch.Generator().manual_seed(4)
    probe_s = torch.rand(50, generator=g) * 2.0
    s = torch.cat([torch.full((n_opaque * per,), INF), probe_s])
    a = torch.cat([torch.arange(per).repeat(n_opaque) * 0.01, torch.arange(50) * 0.05]).float()
    b_ = a + torch.cat([torch.full((n_opaque * per,), 0.01), torch.full((50,), 0.05)])
    ri = torch.cat([torch.arange(n_opaque).repeat_interleave(per),
                    torch.full((50,), n_opaque)])
    w, trans = render_weights(s, a, b_, ri, n_opaque + 1)
    tau = (probe_s.double() * (b_[-50:].double() - a[-50:].double())).numpy()
    before = np.concatenate([[0.0], np.cumsum(tau)[:-1]])
    np.testing.assert_allclose(np_(trans[-50:]), np.exp(-before), rtol=5e-7)
    np.testing.assert_allclose(np_(w[-50:]), np.exp(-before) * -np.expm1(-tau), rtol=5e-7)
    assert (w[: n_opaque * per].reshape(n_opaque, per)[:, 0] == 1.0).all()
    assert (w[: n_opaque * per].reshape(n_opaque, per)[:, 1:] == 0.0).all()


def test_negative_length_sample_is_transparent():
    s, a, b_, ri = packed([[(5.0, 2.0, 1.0), (1.0, 2.0, 3.0)]])
    w, trans = render_weights(s, a, b_, ri, 1)
    assert w[0] == 0.0 and trans[1] == 1.0
    assert w[1].item() == pytest.approx(-math.expm1(-1.0), rel=1e-15)


# ----------------------------------------------------------------------------- trunc_exp

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_trunc_exp_forward_and_gradient(dtype):
    x = torch.tensor([-100.0, -15.0, 0.0, 3.5, 15.0, 100.0, 1e4], dtype=dtype, requires_grad=True)
    y = trunc_exp(x)
    assert torch.isfinite(y).all()
    expect = torch.exp(x.detach().clamp_max(15.0))
    torch.testing.assert_close(y.detach(), expect, rtol=1e-6 if dtype == torch.float32 else 1e-15,
                               atol=0)
    assert y[-1] == y[4]  # saturates at exp(15), ~3.3e6
    up = torch.linspace(0.5, 2.0, len(x), dtype=dtype)
    y.backward(up)
    assert torch.isfinite(x.grad).all()
    torch.testing.assert_close(x.grad, up * torch.exp(x.detach().clamp(-15.0, 15.0)), rtol=1e-6,
                               atol=0)
    assert (x.grad > 0).all()  # saturated densities still receive a gradient


def test_trunc_exp_gradcheck_in_range():
    x = torch.linspace(-14.0, 14.0, 9, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(trunc_exp, (x,), eps=1e-6, atol=1e-6, rtol=1e-6)


# ----------------------------------------------------------------------------- threshold depth

def test_threshold_depth_slab_no_crossing_and_first_sample():
    """Ray 0 enters a slab of density 10 at t = 2 (samples every 0.1 m, midpoints 1.95 / 2.05):
    m = 5 crosses half way, at 2.0. Ray 1 holds only faint density: never crosses, invalid
    (not the near plane). Ray 2 starts inside the slab: its first sample's start. Ray 3 is empty."""
    from nerfbot.ops.rendering import threshold_depth

    t0 = torch.arange(10, 30, dtype=torch.float64) * 0.1       # ray 0: 1.0 .. 2.9
    s0 = torch.where(t0 + 0.05 >= 2.0, 10.0, 0.0).double()
    t1 = torch.arange(10, 20, dtype=torch.float64) * 0.1       # ray 1: faint
    s1 = torch.full_like(t1, 4.0)
    t2 = torch.arange(20, 25, dtype=torch.float64) * 0.1       # ray 2: dense from the start
    s2 = torch.full_like(t2, 10.0)
    ts = torch.cat([t0, t1, t2])
    te = ts + 0.1
    sig = torch.cat([s0, s1, s2])
    idx = torch.cat([torch.full((len(t0),), 0), torch.full((len(t1),), 1), torch.full((len(t2),), 2)])
    depth, valid = threshold_depth(sig, ts, te, idx, 4, 5.0)
    assert valid.tolist() == [True, False, True, False]
    assert depth[0].item() == pytest.approx(2.0, abs=1e-12)
    assert torch.isnan(depth[1]) and torch.isnan(depth[3])
    assert depth[2].item() == pytest.approx(2.0, abs=1e-12)
    # a higher threshold than any density: nothing valid, all NaN, no error
    depth, valid = threshold_depth(sig, ts, te, idx, 4, 100.0)
    assert not valid.any() and torch.isnan(depth).all()
