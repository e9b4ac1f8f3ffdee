"""Numerical stability at the extremes: rendering arithmetic, samplers, encodings,
losses and training, fed the inputs the normal-case tests avoid.

* densities 0, 1e-12, 1e10, +inf (and activations fed 0, 1e-12, 1e10, +/-inf); deltas 0, 1e-9,
  1e6; near = far; far = 1e4; rays with every sample empty, a single sample, no sample;
* float16 / bfloat16 / float32 inputs against a float64 reference, gradcheck in float64;
* scenes from 1 mm to 1 km; points exactly on the bounds and one float32 ulp outside, for the
  hash grid and the occupancy (voxel) grid;
* training with a 10x learning rate, from inside an object, on all-black / all-white images.

Half-precision comparisons use the float64 reference *of the rounded inputs*, so what remains is
the library's own arithmetic; each tolerance is stated where it is used, in units of the unit
roundoff u of the dtype (the largest relative error of rounding one value to it).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from nerfbot.fields.base import trunc_exp
from nerfbot.methods import build_model
from nerfbot.ops.cameras import Rays, look_at, orbit_poses
from nerfbot.ops.encodings import (FrequencyEncoding, HashEncoding, hash_encode_reference,
                                   spherical_harmonics)
from nerfbot.ops.losses import distortion_loss
from nerfbot.ops.rendering import EMPTY_OPACITY, composite, render_weights
from nerfbot.ops.sampling import (OccupancyGrid, march_reference, pdf_samples, ray_aabb,
                                  stratified_samples)

pytestmark = pytest.mark.slow(30)  # rough single-core seconds (tests/conftest.py)

INF = float("inf")
F16, BF16, F32, F64 = torch.float16, torch.bfloat16, torch.float32, torch.float64
DTYPES = [F16, BF16, F32, F64]
#: unit roundoff: half the spacing of the type's numbers just above 1
U = {F16: 2.0 ** -11, BF16: 2.0 ** -8, F32: 2.0 ** -24, F64: 2.0 ** -53}
SCALES = [1e-3, 1e-2, 1e-1, 1.0, 1e1, 1e2, 1e3]
EXTREME = settings(derandomize=True, deadline=None, database=None, max_examples=60)


def np64(t: torch.Tensor) -> np.ndarray:
    return t.detach().double().numpy()


def ulp_out(x: float, direction: float) -> float:
    """The float32 neighbour of ``x`` towards ``direction`` (one ulp outside a bound)."""
    return float(np.nextafter(np.float32(x), np.float32(direction)))


# ============================================================================ activations

ACT_INPUTS = [0.0, 1e-12, 1e10, INF, -1e-12, -1e10, -INF, 15.0, 11.0, 30.0]


@pytest.mark.parametrize("dtype", DTYPES)
def test_trunc_exp_never_overflows_and_keeps_gradients_finite(dtype):
    """trunc_exp(x) = exp(min(x, L)), L = 15 (11 in float16, whose max 65504 < exp(15)).

    Tolerance: one rounding of the output (u relative) after exp of an exactly representable
    argument; 2u leaves room for the libm's last-bit error."""
    x = torch.tensor(ACT_INPUTS, dtype=dtype, requires_grad=True)
    y = trunc_exp(x)
    limit = 11.0 if dtype == F16 else 15.0
    x64 = x.detach().double()
    ref = torch.exp(x64.clamp_max(limit))
    assert torch.isfinite(y).all() and (y >= 0).all()
    assert float(y.detach().max()) <= torch.finfo(dtype).max
    np.testing.assert_allclose(np64(y), ref.numpy(), rtol=2 * U[dtype], atol=0)
    # a zero upstream gradient must give zero, not 0 * inf = NaN (float16 before the fix)
    (y * 0.0).sum().backward()
    assert torch.equal(x.grad, torch.zeros_like(x.grad))
    x.grad = None
    trunc_exp(x).sum().backward()
    assert torch.isfinite(x.grad).all() and (x.grad > 0).all()
    ref_grad = torch.exp(x64.clamp(-limit, limit))
    np.testing.assert_allclose(np64(x.grad), ref_grad.numpy(), rtol=2 * U[dtype], atol=0)


DENSITY_PRE = [0.0, 1e-12, 1e10, -1e10, INF, -INF]


@pytest.mark.parametrize("method", ["ngp", "nerf"])
def test_field_density_heads_at_extreme_pre_activations(method):
    """Each field's density head forced to output 0, 1e-12, 1e10, -1e10, +inf, -inf (weights 0,
    bias set): NGP's trunc_exp keeps sigma in [0, exp(15)]; NeRF's softplus gives sigma >= 0,
    finite for every finite input (inf only for +inf, which the renderer takes). Rendering a ray
    through each and back-propagating gives finite outputs and finite gradients in every
    parameter."""
    torch.manual_seed(0)
    options = SMALL_NGP if method == "ngp" else {"width": 32, "depth": 2, "color_width": 16}
    model = build_model(method, [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], "white", options)
    field = model.field
    x = torch.tensor([[0.1 * k - 0.2, 0.0, 0.05] for k in range(4)])
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(4, 3)
    for v in DENSITY_PRE:
        with torch.no_grad():
            if method == "ngp":
                head = field.density_mlp[-1]
                head.weight[0].zero_()
                head.bias[0] = v - field.density_bias
            else:
                field.sigma_head.weight.zero_()
                field.sigma_head.bias.fill_(v + 1.0)  # the field applies softplus(h - 1)
        field.zero_grad()
        sigma, feat = field.density(x)
        assert not torch.isnan(sigma).any() and (sigma >= 0).all(), (v, sigma)
        if method == "ngp":
            assert (sigma <= math.exp(15.0) * (1 + 1e-6)).all()
        if math.isfinite(v):
            assert torch.isfinite(sigma).all(), (v, sigma)
        rgb = field.color(feat, d)
        ts = torch.arange(4) * 0.1
        out = composite(sigma, rgb, ts, ts + 0.1, torch.zeros(4, dtype=torch.long), 1,
                        torch.ones(3), torch.full((1,), 5.0), torch.ones(1))
        for t in (out.rgb, out.opacity, out.depth, out.median_depth):
            assert torch.isfinite(t).all(), v
        (out.rgb.sum() + out.depth.sum()).backward()
        for name, prm in field.named_parameters():
            assert prm.grad is None or torch.isfinite(prm.grad).all(), (v, name)


# ============================================================================ rendering

def reference_render(rays, rgb, bg, far):
    """float64 loops (no packing, no scans): rays = per ray [(sigma, t_start, t_end)]."""
    out = dict(w=[], trans=[], rgb=[], opacity=[], depth=[], cum=[])
    k = 0
    for r, samples in enumerate(rays):
        acc, c, op, ds, cum = 0.0, np.zeros(3), 0.0, 0.0, []
        for s, a, b in samples:
            d = max(b - a, 0.0)
            tau = 0.0 if d == 0.0 else min(s * d, 1e4)  # zero length: transparent
            t = math.exp(-acc)
            w = t * -math.expm1(-tau)
            out["w"].append(w)
            out["trans"].append(t)
            c += w * rgb[k]
            op += w
            ds += w * 0.5 * (a + b)
            cum.append(op)
            acc += tau
            k += 1
        out["rgb"].append(c + (1.0 - op) * bg[r])
        out["opacity"].append(op)
        out["depth"].append(ds / op if op > EMPTY_OPACITY else far[r])
        out["cum"].append(cum)
    return {k: (np.array(v) if k != "cum" else v) for k, v in out.items()}


def pack(rays, dtype):
    """Per-ray sample lists -> (sigmas, t_starts, t_ends, ray_indices), rounded to dtype."""
    flat = [(r, s, a, b) for r, ray in enumerate(rays) for (s, a, b) in ray]
    if not flat:
        z = torch.zeros(0, dtype=dtype)
        return z, z.clone(), z.clone(), torch.zeros(0, dtype=torch.long)
    ri, s, a, b = zip(*flat)
    return (torch.tensor(s, dtype=F64).to(dtype), torch.tensor(a, dtype=F64).to(dtype),
            torch.tensor(b, dtype=F64).to(dtype), torch.tensor(ri))


def render_case(rays, dtype, far_value=1e4, seed=0):
    """Render ``rays`` in ``dtype`` (composite and render_weights) and the float64 reference of
    the same rounded inputs, with random colours, backgrounds and ray cosines. Returns a dict:
    out, w_only / trans (render_weights), sig / rgbs (leaf inputs), ref, rays (rounded, as
    float64 lists), far, zpt, n."""
    sig, ts, te, ri = pack(rays, dtype)
    n = len(rays)
    g = torch.Generator().manual_seed(seed)
    rgbs = torch.rand(len(sig), 3, generator=g, dtype=F64).to(dtype)
    bg = torch.rand(n, 3, generator=g, dtype=F64).to(dtype)
    far = torch.full((n,), far_value, dtype=F64).to(dtype)
    zpt = (0.5 + 0.5 * torch.rand(n, generator=g, dtype=F64)).to(dtype)
    sig_g = sig.clone().requires_grad_(True)
    rgb_g = rgbs.clone().requires_grad_(True)
    out = composite(sig_g, rgb_g, ts, te, ri, n, bg, far, zpt)
    w_only, trans = render_weights(sig, ts, te, ri, n)
    # rounded inputs as float64 lists for the reference
    rr, k = [], 0
    s64, a64, b64 = sig.double().tolist(), ts.double().tolist(), te.double().tolist()
    for ray in rays:
        rr.append([(s64[k + i], a64[k + i], b64[k + i]) for i in range(len(ray))])
        k += len(ray)
    ref = reference_render(rr, rgbs.double().numpy(), bg.double().numpy(), far.double().numpy())
    return dict(out=out, w_only=w_only, trans=trans, sig=sig_g, rgbs=rgb_g, ref=ref, rays=rr,
                far=far, zpt=zpt, n=n)


def render_tolerance(dtype, n_max=8):
    """(rtol, atol) of weights, transmittance, opacity and rgb against the float64 reference,
    for rays of at most ``n_max`` samples.

    float64 inputs run in float64: only summation order differs (1e-12 relative). float32 and
    half inputs run in float32 (half inputs are upcast), the scan in float64: each thickness
    carries two float32 roundings (delta, sigma * delta), so T_i = exp(-tau_before_i) is off by
    at most 2^-23 * T_i * tau_before_i <= 2^-23 / e = 4.4e-8 and w_i by as much again: 1e-6
    covers a ray's sum of those; the per-ray sums themselves run in float32 and add at most
    n * 2^-24 (the sequential summation bound; measured 7.7e-7 for n = 1000). Then every output
    is rounded once to its dtype: relative u, 2u for margin."""
    if dtype == F64:
        return 1e-12, 1e-14 + n_max * U[F64]
    return 2 * U[dtype], 1e-6 + n_max * U[F32]


def check_render(case, dtype):
    """Assert a rendered case against its reference; return the max errors seen."""
    out, ref, rays, n = case["out"], case["ref"], case["rays"], case["n"]
    rtol, atol = render_tolerance(dtype, max(len(ray) for ray in rays))
    far = np64(case["far"])
    errs = {}
    for name, got, want in [("weights", out.weights, ref["w"]),
                            ("weights", case["w_only"], ref["w"]),
                            ("trans", case["trans"], ref["trans"]),
                            ("opacity", out.opacity, ref["opacity"]), ("rgb", out.rgb, ref["rgb"])]:
        got = np64(got)
        assert np.isfinite(got).all(), name
        if got.size:
            np.testing.assert_allclose(got, want.reshape(got.shape), rtol=rtol, atol=atol,
                                       err_msg=name)
            err = float(np.abs(got - want.reshape(got.shape)).max())
            errs[name] = max(errs.get(name, 0.0), err)
    depth, med = np64(out.depth), np64(out.median_depth)
    assert np.isfinite(depth).all() and np.isfinite(med).all()
    np.testing.assert_allclose(np64(out.z_depth), depth * np64(case["zpt"]),
                               rtol=3 * U[dtype], atol=0)
    errs["depth_rel_span"] = 0.0
    for r in range(n):
        op = ref["opacity"][r]
        if 0.25 * EMPTY_OPACITY < op < 4 * EMPTY_OPACITY:
            continue  # at the empty-ray switch either answer is right: checked finite above
        if op <= EMPTY_OPACITY:
            # empty ray: depth and median are the far bound, exactly (a copy, no arithmetic)
            assert depth[r] == far[r] and med[r] == far[r], (r, depth[r], med[r], far[r])
            continue
        ts = [a for _, a, _ in rays[r]]
        te = [b for _, _, b in rays[r]]
        span = max(te) - min(ts)
        # depth = sum(w t) / sum(w): the weights' relative errors (<= ~1e-6 in float32 for the
        # samples that carry weight) and the two float32 sums (n 2^-24 each) move it by at most
        # that fraction of the ray's extent; then one output rounding (2u relative). float64:
        # 1e-12 of the extent.
        nr = len(rays[r])
        d_atol = (1e-12 + 2 * nr * U[F64] if dtype == F64 else 2e-6 + 2 * nr * U[F32]) * span
        assert abs(depth[r] - ref["depth"][r]) <= 2 * U[dtype] * abs(ref["depth"][r]) + d_atol, \
            (r, depth[r], ref["depth"][r])
        errs["depth_rel_span"] = max(errs["depth_rel_span"],
                                     abs(depth[r] - ref["depth"][r]) / max(span, 1e-300))
        # median: the midpoint (rounded to the dtype: 2u) of the first sample whose cumulative
        # weight reaches half the opacity; rounding may move the crossing by one sample only
        # where the cumulative weight is within the weight tolerance of the half
        mids = [0.5 * (a + b) for _, a, b in rays[r]]
        cum = ref["cum"][r]
        slack = 4 * (rtol + atol)

        def crossing(i):
            before = cum[i - 1] if i > 0 else 0.0
            return cum[i] >= 0.5 * op - slack and before <= 0.5 * op + slack

        assert any(abs(m - med[r]) <= 2 * U[dtype] * abs(med[r]) and crossing(i)
                   for i, m in enumerate(mids)), (r, med[r], mids, cum, op)
    return errs


SIGMAS = [0.0, 1e-12, 1e-3, 0.7, 5.0, 1e10, INF]
DELTAS = [0.0, 1e-9, 1e-3, 0.05, 1.0, 1e6]
NEARS = [0.0, 0.5, 2.0, 1e3]
GAPS = [0.0, 0.0, 0.1, 1.0]


@st.composite
def ragged_rays(draw, max_delta):
    """1-5 rays of 0-6 samples drawn from the extreme menus (empty, single-sample, zero-length,
    infinitely dense, huge-delta rays all occur)."""
    rays = []
    for _ in range(draw(st.integers(1, 5))):
        t = draw(st.sampled_from(NEARS))
        ray = []
        for _ in range(draw(st.integers(0, 6))):
            t += draw(st.sampled_from(GAPS))
            d = min(draw(st.sampled_from(DELTAS)), max_delta)
            ray.append((draw(st.sampled_from(SIGMAS)), t, t + d))
            t += d
        rays.append(ray)
    return rays


@pytest.mark.parametrize("dtype", DTYPES)
@EXTREME
@given(data=st.data())
def test_composite_extremes_match_float64_reference(dtype, data):
    """Ragged batches of extreme samples in every dtype. float16 cannot hold 1e6 (its max is
    65504), so its deltas stop at 1e4 (t stays below 6.2e4, inside its range)."""
    rays = data.draw(ragged_rays(1e4 if dtype == F16 else 1e6))
    case = render_case(rays, dtype)
    check_render(case, dtype)
    # gradients finite: the colour and opacity of every ray (all dtypes); the depth too in
    # float32 / float64 (a half gradient of depth w.r.t. a density, ~delta * t / opacity, can
    # exceed 65504 legitimately)
    out = case["out"]
    loss = out.rgb.float().sum() + out.opacity.float().sum()
    if dtype in (F32, F64):
        loss = loss + out.depth.sum()
    loss.backward()
    assert torch.isfinite(case["sig"].grad).all() and torch.isfinite(case["rgbs"].grad).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_half_precision_sums_do_not_stall(dtype):
    """1000 samples of thickness 1e-3 (a long faint ray): opacity 1 - e^-1 = 0.632. Before the
    sums ran in float32, bfloat16 gave 0.688 and float16 0.648 (half-precision sums drop
    small addends: 0.5 + 0.001 == 0.5 in bfloat16). Tolerance as :func:`render_tolerance`."""
    n = 1000
    rays = [[(1.0, 1e-3 * i, 1e-3 * (i + 1)) for i in range(n)]]
    case = render_case(rays, dtype)
    check_render(case, dtype)
    expect = -math.expm1(-sum(s * (b - a) for s, a, b in case["rays"][0]))
    rtol, atol = render_tolerance(dtype, n)
    assert abs(float(case["out"].opacity[0]) - expect) <= rtol * expect + atol


@pytest.mark.parametrize("dtype", DTYPES)
def test_near_equals_far_every_sample_empty_and_no_samples(dtype):
    """Ray 0: near = far (all samples zero-length, infinitely dense ones too); ray 1: 64 samples
    of zero density; ray 2: no samples. All render the background with depth = far exactly."""
    rays = [[(d, 5.0, 5.0) for d in (1.0, 1e10, INF)],
            [(0.0, 0.1 * i, 0.1 * (i + 1)) for i in range(64)],
            []]
    case = render_case(rays, dtype, far_value=7.0)
    check_render(case, dtype)
    out = case["out"]
    assert torch.equal(out.opacity, torch.zeros(3, dtype=dtype))
    assert torch.equal(out.depth, case["far"]) and torch.equal(out.median_depth, case["far"])
    bg_ref = case["ref"]["rgb"]
    np.testing.assert_array_equal(np64(out.rgb), bg_ref)  # 1 * bg, exactly
    (out.rgb.sum() + out.depth.sum()).backward()
    assert torch.isfinite(case["sig"].grad).all()
    # zero-length samples get no gradient; an empty sample of length 0.1 gets d(rgb)/d(sigma) =
    # 0.1 * T (c - bg) != 0: a transparent field can still learn density
    assert (case["sig"].grad[:3] == 0).all() and (case["sig"].grad[3] != 0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_far_1e4_and_single_samples(dtype):
    """Rays out to far = 1e4 m: 10 samples of 1000 m at density 1e-4 (thickness 0.1 each); one
    sample spanning [0, 1e4]; single samples of density 1e10 / +inf (all the weight) and 1e-12."""
    rays = [[(1e-4, 1000.0 * i, 1000.0 * (i + 1)) for i in range(10)],
            [(3e-4, 0.0, 1e4)],
            [(1e10, 9920.0, 1e4)],  # 9920: a float16 and bfloat16 number
            [(INF, 9000.0, 9500.0)],
            [(1e-12, 0.0, 1e4)]]
    case = render_case(rays, dtype)
    check_render(case, dtype)
    out = case["out"]
    assert float(out.opacity[2]) == 1.0 and float(out.opacity[3]) == 1.0
    assert float(out.opacity[4]) <= EMPTY_OPACITY and float(out.depth[4]) == float(case["far"][4])
    (out.rgb.sum() + out.opacity.sum()).backward()
    assert torch.isfinite(case["sig"].grad).all()


def test_fp16_positions_near_its_range_do_not_overflow():
    """float16 t = 6e4 .. 6.5e4 (finite, below 65504): t_start + t_end overflowed to inf in
    float16, giving depth = inf and a far-bound median before composite upcast."""
    rays = [[(1e-3, 6.0e4, 6.5e4)], [(2.0, 0.0, 1.0)]]
    case = render_case(rays, F16, far_value=6.0e4)
    check_render(case, F16)
    assert float(case["out"].depth[0]) == pytest.approx(6.25e4, rel=2 * U[F16])
    assert float(case["out"].median_depth[0]) == pytest.approx(6.25e4, rel=2 * U[F16])


def reference_threshold(rays, m):
    """float64 Dex-NeRF depth: the first sample with sigma >= m; its start if it is the ray's
    first sample, else linear interpolation of sigma between the two midpoints; NaN if none."""
    out = []
    for ray in rays:
        depth = float("nan")
        for i, (s, a, b) in enumerate(ray):
            if s >= m:
                if i == 0:
                    depth = a
                else:
                    s0, a0, b0 = ray[i - 1]
                    frac = min(max((m - s0) / max(s - s0, 1e-30), 0.0), 1.0)
                    depth = 0.5 * (a0 + b0) + frac * (0.5 * (a + b) - 0.5 * (a0 + b0))
                break
        out.append(depth)
    return np.array(out)


@pytest.mark.parametrize("dtype", DTYPES)
@EXTREME
@given(data=st.data())
def test_threshold_depth_extremes_and_the_invalid_is_nan_contract(dtype, data):
    """Ragged extreme batches (as above) at thresholds 1 and 4 (exact in every dtype): rays
    that never reach the threshold - empty, all-zero, no samples - are invalid with depth NaN
    by design; valid depths are finite, within the ray's samples, and equal the float64
    reference of the rounded inputs up to the output rounding (2u relative). Before the fix,
    float16 t_start + t_end overflowed beyond 32752 m (depth inf or NaN on a valid ray)."""
    from nerfbot.ops.rendering import threshold_depth

    rays = data.draw(ragged_rays(1e4 if dtype == F16 else 1e6))
    m = data.draw(st.sampled_from([1.0, 4.0]))
    sig, ts, te, ri = pack(rays, dtype)
    depth, valid = threshold_depth(sig, ts, te, ri, len(rays), m)
    rounded, k = [], 0
    for ray in rays:
        rounded.append([(float(sig[k + i]), float(ts[k + i]), float(te[k + i]))
                        for i in range(len(ray))])
        k += len(ray)
    ref = reference_threshold(rounded, m)
    assert valid.tolist() == np.isfinite(ref).tolist()
    got = np64(depth)
    assert np.isnan(got[~np.isfinite(ref)]).all()
    ok = np.isfinite(ref)
    assert np.isfinite(got[ok]).all()
    np.testing.assert_allclose(got[ok], ref[ok], rtol=2 * U[dtype], atol=0)
    for r in np.flatnonzero(ok):
        lo, hi = min(a for _, a, _ in rounded[r]), max(b for _, _, b in rounded[r])
        assert lo * (1 - 2 * U[dtype]) <= got[r] <= hi * (1 + 2 * U[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_threshold_depth_far_out(dtype):
    """Crossings at 4.75e4 m (interpolated) and 6e4 m (first sample), in range for every dtype:
    before the fix float16 midpoints overflowed (t_start + t_end > 65504) and the valid ray
    got a NaN depth. Tolerance: output rounding, 2u relative."""
    from nerfbot.ops.rendering import threshold_depth

    rays = [[(0.5, 4.0e4, 4.5e4), (8.0, 4.5e4, 5.0e4)], [(INF, 6.0e4, 6.5e4)], [(0.0, 0.0, 1e4)]]
    sig, ts, te, ri = pack(rays, dtype)
    depth, valid = threshold_depth(sig, ts, te, ri, 3, 4.0)
    assert valid.tolist() == [True, True, False] and torch.isnan(depth[2])
    # sigma 0.5 -> 8 between midpoints 42500 and 47500: 4 is reached at 7/15 of the way
    np.testing.assert_allclose(np64(depth[:2]), [42500.0 + 7.0 / 15.0 * 5000.0, 6.0e4],
                               rtol=2 * U[dtype])


# ---------------------------------------------------------------------------- gradcheck (float64)

def extreme_batch():
    """float64 rays with thickness from 1e-9 to 30 per sample, zero-length and zero-density
    samples, single-sample rays, an empty ray, deltas 1e-9 and 1e6."""
    rays = [[(0.0, 0.0, 1.0), (1e-9, 1.0, 2.0), (3.0, 2.0, 3.0), (30.0, 3.0, 4.0), (2.0, 4.0, 5.0)],
            [(5.0, 1.0, 1.0), (0.7, 1.0, 1.5)],           # zero-length first sample
            [(2e-6, 0.0, 1e6)],                           # one sample, delta 1e6, thickness 2
            [(1e9, 0.0, 1e-9)],                           # delta 1e-9, thickness 1
            [],                                           # no samples
            [(0.0, 0.0, 0.5), (0.0, 0.5, 1.0)]]           # every sample empty
    return rays


def relative_densities(sig: torch.Tensor):
    """sigma = sig * (1 + v) (sig + v where sig = 0), differentiated at v = 0: finite
    differences of a fixed step cannot resolve a derivative at sigma = 1e9 (1e9 + 1e-7 == 1e9)
    or at 2e-6 with delta 1e6 (a 5 % step), a step relative to sigma can."""
    scale = torch.where(sig > 0, sig, torch.ones_like(sig))
    return torch.zeros_like(sig, requires_grad=True), lambda v: sig + scale * v


def test_gradcheck_render_weights_at_extremes():
    sig, ts, te, ri = pack(extreme_batch(), F64)
    v, sigma = relative_densities(sig)
    fn = lambda v: render_weights(sigma(v), ts, te, ri, 6)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (v,), eps=1e-7, atol=1e-8, rtol=1e-5)


def test_gradcheck_composite_at_extremes():
    """rgb and opacity of every ray, depth of the non-empty rays (at opacity ~ EMPTY_OPACITY the
    depth switches to far by design: not differentiable there)."""
    rays = extreme_batch()
    sig, ts, te, ri = pack(rays, F64)
    g = torch.Generator().manual_seed(0)
    rgbs = torch.rand(len(sig), 3, generator=g, dtype=F64).requires_grad_(True)
    v, sigma = relative_densities(sig)
    bg, far, zpt = torch.rand(3, generator=g, dtype=F64), torch.full((6,), 9.0, dtype=F64), \
        torch.ones(6, dtype=F64)
    solid = torch.tensor([0, 1, 2, 3])

    def fn(v, c):
        out = composite(sigma(v), c, ts, te, ri, 6, bg, far, zpt)
        return out.rgb, out.opacity, out.depth[solid]

    assert torch.autograd.gradcheck(fn, (v, rgbs), eps=1e-7, atol=1e-7, rtol=1e-5)


# ============================================================================ distortion loss

def distortion_brute(rays_w, scale):
    """float64 double sum: rays_w = per ray [(w, t_start, t_end)]."""
    total = 0.0
    for ray in rays_w:
        for wi, a, b in ray:
            mi = 0.5 * (a + b) / scale
            total += wi * wi * (b - a) / scale / 3.0
            for wj, c, d in ray:
                total += wi * wj * abs(mi - 0.5 * (c + d) / scale)
    return total / max(len(rays_w), 1)


DIST_CASES = {
    "zero_weights": ([[(0.0, 0.1 * i, 0.1 * (i + 1)) for i in range(8)]], 1.0),
    "single_samples": ([[(0.7, 1.0, 1.25)], [(1.0, 3.0, 3.0)], [(0.3, 0.0, 8.0)]], 2.0),
    "near_eq_far": ([[(0.2, 4.0, 4.0)] * 5, []], 1.0),
    "far_1e4": ([[(0.01 * (i % 7), 1e4 - 1 + 0.004 * i, 1e4 - 1 + 0.004 * (i + 1))
                  for i in range(200)]], 0.01),
    "delta_1e6": ([[(0.5, 0.0, 1e6), (0.5, 1e6, 1e6 + 1e-9)]], 1e3),
}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", list(DIST_CASES))
def test_distortion_loss_extremes(dtype, name):
    """Against the float64 double sum of the same rounded inputs. The loss is computed in
    float64 from any input dtype; its O(M) form cancels (m_i W_i - M_i) and loses about
    log10(t / spread) of float64's 16 digits, at most 4 here: 1e-10 relative; then the output
    is rounded to its dtype (at least float32): 2u relative. Before the fix, float32 "far_1e4"
    was off by 6e-5 relative and float16 inputs overflowed (t / scale > 65504) to NaN."""
    rays, scale = DIST_CASES[name]
    if dtype == F16 and name == "delta_1e6":
        rays = [[(w, a * 6e-4, b * 6e-4) for w, a, b in ray] for ray in rays]  # fit 65504
    w, ts, te, ri = pack(rays, dtype)
    rounded = [[(float(w[k]), float(ts[k]), float(te[k])) for k in range(len(w)) if ri[k] == r]
               for r in range(len(rays))]
    loss = distortion_loss(w, ts, te, ri, len(rays), scale)
    ref = distortion_brute(rounded, scale)
    out_dtype = F64 if dtype == F64 else F32
    assert loss.dtype == out_dtype and math.isfinite(float(loss)) and float(loss) >= 0.0
    assert abs(float(loss) - ref) <= (2 * U[out_dtype] + 1e-10) * abs(ref), (float(loss), ref)


def test_gradcheck_distortion_at_extremes():
    """Zero weights, single-sample rays, zero-width samples, an empty ray, samples at 1e4 m with
    a 1 cm scale (normalised distances ~1e6). The loss is quadratic in the weights, so central
    differences are exact for any step: eps = 1e-3 keeps the float64 cancellation at 1e6
    (~1e-10 absolute) from dominating the finite differences."""
    rays = [[(0.0, 1.0, 1.5), (0.3, 1.5, 2.0), (0.0, 2.0, 2.0), (0.6, 2.5, 3.0)],
            [(0.4, 3.0, 3.0)], [],
            [(0.2, 1e4, 1e4 + 0.004), (0.5, 1e4 + 0.004, 1e4 + 0.008)]]
    w, ts, te, ri = pack(rays, F64)
    w.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: distortion_loss(x, ts, te, ri, 4, 0.01), (w,),
                                    eps=1e-3, atol=1e-6, rtol=1e-6)


# ============================================================================ samplers

FACE_OFFSETS = [(a, s) for a in range(3) for s in (0, 1)]


@pytest.mark.parametrize("scale", SCALES)
def test_ray_aabb_closed_box_at_every_scale(scale):
    """A box of edge ``scale`` centred at scale * (0.3, -0.2, 0.1): rays lying *in* each of the
    six faces hit it (the box is closed) with the full chord; the same rays one float32 ulp
    outside the face miss; a camera inside starts at near; a ray from 10 km and near = far
    behave. Before the fix, rays in the three max faces missed, those in the min faces hit."""
    c = torch.tensor([0.3, -0.2, 0.1], dtype=F64) * scale
    aabb = torch.stack([c - 0.5 * scale, c + 0.5 * scale]).float()
    lo, hi = aabb[0].double(), aabb[1].double()
    origins, dirs, outside = [], [], []
    for axis, side in FACE_OFFSETS:
        along = (axis + 1) % 3  # travel along another axis, inside the face
        o = (0.5 * (lo + hi)).clone()
        o[axis] = hi[axis] if side else lo[axis]
        o[along] = lo[along] - scale  # start before the box
        d = torch.zeros(3, dtype=F64)
        d[along] = 1.0
        origins.append(o)
        dirs.append(d)
        o2 = o.clone()
        o2[axis] = ulp_out(float(o[axis]), INF if side else -INF)
        outside.append(o2)
    o = torch.stack(origins + outside).float()
    d = torch.stack(dirs + dirs).float()
    t_near, t_far, hit = ray_aabb(o, d, aabb)
    assert hit.tolist() == [True] * 6 + [False] * 6
    np.testing.assert_allclose(np64(t_near[:6]), scale, rtol=1e-6)
    np.testing.assert_allclose(np64(t_far[:6]), 2 * scale, rtol=1e-6)
    # camera inside: starts at near; camera 10 km away: the chord, to float32 resolution at
    # t = 1e4 (two roundings of half an ulp, 9.8e-4 m); from 1 cm up it is a hit for sure
    o = torch.stack([0.5 * (lo + hi), 0.5 * (lo + hi) + torch.tensor([-1e4, 0, 0], dtype=F64)])
    d = torch.tensor([[0.6, 0.8, 0.0], [1.0, 0.0, 0.0]], dtype=F64)
    t_near, t_far, hit = ray_aabb(o.float(), d.float(), aabb)
    assert hit[0] and t_near[0] == 0.0 and torch.isfinite(t_far).all()
    if scale >= 1e-2:
        assert hit[1] and abs(float(t_far[1] - t_near[1]) - scale) <= 1e-3 + 1e-6 * scale
    # near = far of the hit interval: a miss by convention (t_near = t_far = near)
    t_near, t_far, hit = ray_aabb(o.float()[:1], d.float()[:1], aabb, near=float(t_far[0]))
    assert not hit.any() and t_near[0] == t_far[0]


def test_stratified_and_pdf_samples_at_extremes():
    """near = far, far = 1e4, one sample, one bin, one-hot weights: finite, sorted, within
    [near, far] with exact end points."""
    g = torch.Generator().manual_seed(0)
    t_near = torch.tensor([5.0, 0.0, 0.0, 1e4 - 1.0])
    t_far = torch.tensor([5.0, 1e4, 1e-3, 1e4])
    for n in (1, 2, 64):
        for jitter in (True, False):
            e = stratified_samples(t_near, t_far, n, generator=g, jitter=jitter)
            assert e.shape == (4, n + 1) and torch.isfinite(e).all()
            assert torch.equal(e[:, 0], t_near) and torch.equal(e[:, -1], t_far)
            assert (e.diff(dim=-1) >= 0).all()
    # near = far: every sample has zero length, so the ray renders the background at far
    e = stratified_samples(t_near[:1], t_far[:1], 8, generator=g)
    ts, te = e[:, :-1].reshape(-1), e[:, 1:].reshape(-1)
    out = composite(torch.full((8,), INF), torch.rand(8, 3, generator=g), ts, te,
                    torch.zeros(8, dtype=torch.long), 1, torch.ones(3), t_far[:1], torch.ones(1))
    assert out.opacity[0] == 0.0 and torch.equal(out.rgb[0], torch.ones(3))
    # pdf: a single bin; zero-width bins; one-hot weight in the last bin out at 1e4 m
    edges = torch.tensor([[0.0, 1e4], [5.0, 5.0]])
    for n, jitter in ((1, False), (1, True), (33, True)):
        s = pdf_samples(edges, torch.zeros(2, 1), n, generator=g, jitter=jitter)
        assert torch.isfinite(s).all()
        assert ((s[0] >= 0.0) & (s[0] <= 1e4)).all() and (s[1] == 5.0).all()
    edges = torch.linspace(0.0, 1e4, 65)[None]
    onehot = torch.zeros(1, 64)
    onehot[0, -1] = 1.0
    s = pdf_samples(edges, onehot, 16, jitter=False)
    # the 1e-5 padding leaves 6.4e-4 of the mass elsewhere; evenly spaced u >= 1/17 all land in
    # the last bin
    assert ((s >= edges[0, -2]) & (s <= 1e4)).all()


def full_grid(scale: float, res: int = 16):
    c = torch.tensor([0.3, -0.2, 0.1]) * scale
    return OccupancyGrid(torch.stack([c - 0.5 * scale, c + 0.5 * scale]), resolution=res)


@pytest.mark.parametrize("scale", SCALES)
def test_march_at_every_scale_and_on_the_bounds(scale):
    """A fully occupied 16^3 grid over a box of edge ``scale``: the numba marcher equals its
    torch twin; a ray through the box emits contiguous steps covering [t_near, t_far] (the
    float32 step ends are bit-identical to the next starts, so the lengths telescope); the
    sample count does not depend on the scale; rays in a face or one ulp outside it, or with
    near = far, emit nothing; and a step of 0 is an error rather than an endless loop."""
    grid = full_grid(scale)
    lo, hi = grid.aabb[0].double(), grid.aabb[1].double()
    ctr = 0.5 * (lo + hi)
    dt = scale * math.sqrt(3.0) / 64
    rays_o, rays_d = [], []
    rays_o.append(ctr - torch.tensor([2.0, 0.3, 0.1], dtype=F64) * scale)   # through the box
    rays_d.append(torch.tensor([1.0, 0.15, 0.05], dtype=F64))
    rays_o.append(ctr.clone())                                               # camera inside
    rays_d.append(torch.tensor([0.3, -0.9, 0.3], dtype=F64))
    o_face = ctr.clone()
    o_face[2], o_face[0] = float(hi[2]), float(lo[0]) - scale               # in the max face
    rays_o.append(o_face)
    rays_d.append(torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    o_out = o_face.clone()
    o_out[2] = ulp_out(float(hi[2]), INF)                                   # one ulp outside
    rays_o.append(o_out)
    rays_d.append(torch.tensor([1.0, 0.0, 0.0], dtype=F64))
    o = torch.stack(rays_o).float()
    d = F.normalize(torch.stack(rays_d), dim=-1).float()
    t_near, t_far, hit = ray_aabb(o, d, grid.aabb)
    assert hit.tolist() == [True, True, True, False]
    for begin, end in ((t_near, t_far), (t_far, t_far)):   # and near = far
        a = grid.march(o, d, begin, end, dt, dt)
        b = march_reference(o, d, begin, end, grid.occupied, grid.cube_min, grid.cell_size, dt, dt)
        assert torch.equal(a.ray_indices, b.ray_indices)
        torch.testing.assert_close(a.t_starts, b.t_starts, rtol=2e-7, atol=0)
        torch.testing.assert_close(a.t_ends, b.t_ends, rtol=2e-7, atol=0)
    a = grid.march(o, d, t_near, t_far, dt, dt)
    counts = torch.bincount(a.ray_indices, minlength=4)
    assert counts[3] == 0 and counts[0] > 30 and counts[1] > 10
    for r in (0, 1):
        sel = a.ray_indices == r
        ts, te = a.t_starts[sel], a.t_ends[sel]
        assert torch.equal(ts[1:], te[:-1])  # contiguous, bit for bit
        # from the entry to within one step of the exit (a last step whose midpoint falls
        # past the exit is outside the grid)
        assert ts[0] == t_near[r] and 0.0 <= float(t_far[r] - te[-1]) < dt
    # scale invariance of the sample count (the grid and the step scale together); the last
    # step may be one shorter or longer where t_far falls within rounding of a step end
    ref = full_grid(1.0)
    ref_t = ray_aabb(o / scale, d, ref.aabb)
    ref_counts = torch.bincount(ref.march(o / scale, d, ref_t[0], ref_t[1], dt / scale,
                                          dt / scale).ray_indices, minlength=4)
    assert (counts - ref_counts).abs().max() <= 1, (counts, ref_counts)
    with pytest.raises(ValueError, match="dt_min"):
        grid.march(o, d, t_near, t_far, 0.0, 0.0)
    with pytest.raises(ValueError, match="dt_min"):
        march_reference(o, d, t_near, t_far, grid.occupied, grid.cube_min, grid.cell_size,
                        dt, 0.5 * dt)


def test_occupancy_update_is_scale_invariant():
    """A ball of radius 0.3 scale with density 50 / scale (the same optical thickness at every
    scale), updated with the same random offsets: the same cells are occupied from 1 mm to
    1 km (cell points are float32 and scale exactly up to rounding, which decides no cell)."""
    grids = {}
    for scale in SCALES:
        grid = full_grid(scale, res=24)
        c = 0.5 * (grid.aabb[0] + grid.aabb[1])
        fn = lambda x, c=c, s=scale: torch.where((x - c).norm(dim=-1) < 0.3 * s,  # noqa: E731
                                                 torch.full(x.shape[:1], 50.0 / s),
                                                 torch.zeros(x.shape[:1]))
        frac = grid.update(fn, step_size=scale * math.sqrt(3.0) / 256,
                           generator=torch.Generator().manual_seed(0))
        assert 0.05 < frac < 0.2
        grids[scale] = grid.occupied.clone()
    for scale in SCALES:
        assert torch.equal(grids[scale], grids[1.0]), scale


# ============================================================================ encodings

HASH_CFG = dict(n_levels=5, n_features=2, log2_size=11, min_res=4, max_res=128)
#: per-axis coordinates: on the unit cube's faces, one float32 ulp inside and outside them,
#: the smallest subnormal, far outside, +/-inf
EDGE_COORDS = [0.0, 1.4e-45, float(np.nextafter(np.float32(0), np.float32(1)) * 2 ** 23),
               0.5, float(np.nextafter(np.float32(1), np.float32(0))), 1.0,
               float(np.nextafter(np.float32(1), np.float32(2))), -1e-7, 1e30, -INF, INF]


def edge_points() -> torch.Tensor:
    v = torch.tensor(EDGE_COORDS, dtype=F32)
    return torch.cartesian_prod(v, v, v)


def hash_tolerance(enc: HashEncoding) -> float:
    """Absolute tolerance of float32 features vs the float64 reference, per unit table scale.

    x * res rounds in float32 (<= res * 2^-24 of a cell, 7.6e-6 at res 128) on each of three
    axes, moving the trilinear weights by as much; 8 products then add ~8 * 2^-24. Bound:
    3 * 128 * 2^-24 + 8 * 2^-24 = 2.3e-5; 5e-5 leaves a factor 2."""
    return 5e-5


def test_hash_numba_matches_reference_on_the_bounds_and_outside():
    """11^3 points whose coordinates are on, one ulp inside / outside, or far outside the unit
    cube (clamped): the numba forward pass and table gradient equal the float64 twin."""
    enc = HashEncoding(**HASH_CFG, seed=3, init_scale=1.0)
    x = edge_points()
    y = enc(x)
    assert torch.isfinite(y).all()
    t64 = enc.table.detach().double().requires_grad_(True)
    y_ref = hash_encode_reference(x.double(), t64, enc.offsets, enc.res)
    tol = hash_tolerance(enc)
    np.testing.assert_allclose(np64(y), np64(y_ref), rtol=0, atol=tol)
    up = torch.randn(y.shape, generator=torch.Generator().manual_seed(1))
    y.backward(up)
    y_ref.backward(up.double())
    # a row's gradient sums the (<= 1) weights of up to N points times |up| (~3): tolerance
    # scales with the largest gradient
    g_ref = t64.grad.numpy()
    np.testing.assert_allclose(np64(enc.table.grad), g_ref, rtol=0,
                               atol=tol * np.abs(g_ref).max())


def test_hash_nan_positions_match_the_reference_safely():
    """NaN positions used to reach the numba kernels as row -2^63 (out-of-bounds reads, and
    writes in the backward pass). Now they take the twin: NaN features for those points only,
    the other points unchanged, and the table gradient equal to the twin's."""
    enc = HashEncoding(**HASH_CFG, seed=4, init_scale=1.0)
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(2))
    clean = enc(x).detach()
    x[5, 1] = float("nan")
    x[17] = float("nan")
    y = enc(x)
    nan_rows = torch.isnan(y).any(-1)
    assert nan_rows.tolist() == [i in (5, 17) for i in range(64)]
    torch.testing.assert_close(y[~nan_rows].detach(), clean[~nan_rows], rtol=0, atol=1e-6)
    t_ref = enc.table.detach().clone().requires_grad_(True)
    y_ref = hash_encode_reference(x, t_ref, enc.offsets, enc.res)
    up = torch.randn(y.shape, generator=torch.Generator().manual_seed(3))
    y.backward(up)
    y_ref.backward(up)
    torch.testing.assert_close(enc.table.grad, t_ref.grad, rtol=0, atol=1e-6, equal_nan=True)


@pytest.mark.parametrize("dtype", [F16, BF16])
def test_hash_half_precision_positions(dtype):
    """Half-precision positions against the float64 twin of the same rounded positions, with
    the float32 tolerance: before the fix x * res was rounded in half precision, up to half a
    cell off on the finest level (errors ~0.5 of the table scale)."""
    enc = HashEncoding(**HASH_CFG, seed=5, init_scale=1.0)
    x = torch.cat([torch.rand(500, 3, generator=torch.Generator().manual_seed(4)),
                   edge_points()[::7]]).to(dtype)
    y = enc(x)
    y_ref = hash_encode_reference(x.double(), enc.table.detach().double(), enc.offsets, enc.res)
    assert torch.isfinite(y).all()
    np.testing.assert_allclose(np64(y), np64(y_ref), rtol=0, atol=hash_tolerance(enc))


def test_gradcheck_hash_reference_table_and_positions():
    """float64 gradcheck of the twin w.r.t. the table and the positions, at points at least 1e-3
    of a cell from every cell face of every level (the encoding is piecewise trilinear) and
    at points outside the cube on every axis (clamped: zero position gradient). Table part in
    fast mode (random projections): the table has ~1200 entries."""
    enc = HashEncoding(n_levels=3, n_features=2, log2_size=8, min_res=3, max_res=12, seed=0,
                       init_scale=1.0)
    g = torch.Generator().manual_seed(5)
    x = torch.rand(400, 3, generator=g, dtype=F64)
    far_from_faces = torch.ones(len(x), dtype=torch.bool)
    for r in enc.res.tolist():
        frac = (x * r) % 1.0
        far_from_faces &= ((frac > 1e-3) & (frac < 1 - 1e-3)).all(-1)
    x = torch.cat([x[far_from_faces][:12], torch.tensor([[-0.5, 1.3, -0.2], [1.5, 1.2, 1.6]],
                                                         dtype=F64)])
    assert len(x) == 14
    x.requires_grad_(True)
    table = enc.table.detach().double().requires_grad_(True)
    fn = lambda p, t: hash_encode_reference(p, t, enc.offsets, enc.res)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (x, table.detach()), eps=1e-6, atol=1e-6, rtol=1e-5)
    assert torch.autograd.gradcheck(fn, (x.detach(), table), eps=1e-6, atol=1e-6, rtol=1e-5,
                                    fast_mode=True)
    y = fn(x, table)
    (gx,) = torch.autograd.grad(y.sum(), x)
    assert (gx[-2:] == 0).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_frequency_and_sh_encodings_in_every_dtype(dtype):
    """Against float64 evaluations of the same rounded inputs.

    Frequency encoding (10 frequencies, x in [-1.1, 1.1] incl. exactly +/-1 and 0): the
    frequencies are float32 pi * 2^k (the reference uses the same), the argument x * f is
    rounded in float32 unless x is float64: |arg| <= 1.1 * 512 pi = 1769, half an ulp 6.1e-5,
    so |error| <= 1.22e-4 (1.5e-4 stated); float64: 1e-12.
    Spherical harmonics (degree 4, unit directions incl. the axes) are evaluated in the input
    dtype: terms up to ~7 in magnitude (0.106 * (35 z^4 + 30 z^2 + 3)), about six roundings
    each, bound 8u absolute for half types (measured 5.4u float16, 3.5u bfloat16), 1e-6 float32
    (measured 3.5e-7), 1e-14 float64."""
    g = torch.Generator().manual_seed(6)
    x = torch.cat([torch.rand(2000, 3, generator=g, dtype=F64) * 2.2 - 1.1,
                   torch.tensor([[1.0, -1.0, 0.0], [-1.1, 1.1, 1e-12]], dtype=F64)]).to(dtype)
    enc = FrequencyEncoding(3, 10)
    y = enc(x)
    arg = (x.double()[:, None, :] * enc.freqs.double()[:, None]).flatten(-2)
    ref = torch.cat([x.double(), arg.sin(), arg.cos()], -1)
    assert torch.isfinite(y).all()
    np.testing.assert_allclose(np64(y), ref.numpy(), rtol=0, atol=1e-12 if dtype == F64 else 1.5e-4)
    d = F.normalize(torch.randn(2000, 3, generator=g, dtype=F64), dim=-1)
    d = torch.cat([d, torch.eye(3, dtype=F64), -torch.eye(3, dtype=F64)]).to(dtype)
    sh = spherical_harmonics(d, 4)
    sh_ref = spherical_harmonics(d.double(), 4)
    atol = {F16: 8 * U[F16], BF16: 8 * U[BF16], F32: 1e-6, F64: 1e-14}[dtype]
    assert torch.isfinite(sh).all()
    np.testing.assert_allclose(np64(sh), sh_ref.numpy(), rtol=0, atol=atol)


# ============================================================================ fields at scale

SMALL_NGP = {"n_levels": 4, "log2_hashmap_size": 12, "max_res": 64, "hidden": 16,
             "grid_resolution": 16}


def scaled_ngp(scale: float):
    c = np.array([0.3, -0.2, 0.1]) * scale
    aabb = np.stack([c - 0.5 * scale, c + 0.5 * scale])
    torch.manual_seed(0)  # the MLPs' initialisation draws from the global generator
    model = build_model("ngp", aabb, background="white", options=SMALL_NGP, seed=0)
    return model.eval(), torch.as_tensor(aabb, dtype=F32)


def probe_rays(aabb: torch.Tensor, scale: float) -> Rays:
    """Through the centre along an axis and a diagonal, from inside, grazing the max z face,
    and missing the box."""
    lo, hi = aabb[0].double(), aabb[1].double()
    ctr = 0.5 * (lo + hi)
    o = torch.stack([ctr - torch.tensor([2.0, 0, 0], dtype=F64) * scale,
                     ctr - torch.tensor([1.5, 1.5, 1.5], dtype=F64) * scale,
                     ctr,
                     torch.stack([lo[0] - scale, ctr[1], hi[2]]),
                     ctr + torch.tensor([0, 3.0, 0], dtype=F64) * scale])
    d = F.normalize(torch.tensor([[1.0, 0, 0], [1, 1, 1], [0.2, 0.9, -0.3], [1, 0, 0],
                                  [1, 0, 0]], dtype=F64), dim=-1)
    return Rays(o.float(), d.float(), torch.ones(5))


@pytest.fixture(scope="module")
def unit_render():
    model, aabb = scaled_ngp(1.0)
    with torch.no_grad():
        return model.render_rays(probe_rays(aabb, 1.0))


@pytest.mark.parametrize("scale", SCALES)
def test_ngp_field_and_render_from_1mm_to_1km(scale, unit_render):
    """Instant-NGP models for boxes of edge 1 mm .. 1 km (float32 world coordinates):

    * density is finite and >= 0 everywhere, > 0 exactly on the bounds (a closed box), exactly
      0 one float32 ulp outside them and far outside;
    * density x scale is the same function of the normalised position at every scale (the
      density bias follows the box), within 1e-5 relative: normalised positions differ by
      float32 rounding (<= 2e-7), which the 64-cell finest level and the MLP amplify a few
      times (measured 5e-7);
    * renders agree with the 1 m render: rgb / opacity within 1e-5 and depth / scale within
      1e-5 relative (marching steps scale with the box, so the sums run over the same samples;
      measured 5e-7).
      Ray 3 lies exactly in the max z face: it hits the (closed) box, but whether its samples
      fall in the last grid cell or just past it depends on the float32 rounding of the cube
      corner, so it is only required to be finite.
    """
    model, aabb = scaled_ngp(scale)
    lo, hi = aabb[0], aabb[1]
    g = torch.Generator().manual_seed(7)
    u = torch.rand(256, 3, generator=g)
    faces = torch.rand(6, 3, generator=g)
    for k, (axis, side) in enumerate(FACE_OFFSETS):
        faces[k, axis] = float(side)
    x_in = lo + u * (hi - lo)
    x_face = lo + faces * (hi - lo)
    for k, (axis, side) in enumerate(FACE_OFFSETS):  # exactly the float32 bound
        x_face[k, axis] = hi[axis] if side else lo[axis]
    x_out = x_face.clone()
    for k, (axis, side) in enumerate(FACE_OFFSETS):
        x_out[k, axis] = ulp_out(float(x_face[k, axis]), INF if side else -INF)
    x_far = torch.tensor([[1e30, 0.0, 0.0], [-INF, 0.0, 0.0], [0.0, 0.0, INF]])
    with torch.no_grad():
        s_in, feat = model.field.density(x_in)
        s_face, _ = model.field.density(x_face)
        s_out, _ = model.field.density(x_out)
        s_far, _ = model.field.density(x_far)
        rgb = model.field.color(feat, F.normalize(torch.randn(256, 3, generator=g), dim=-1))
    assert torch.isfinite(s_in).all() and (s_in > 0).all() and torch.isfinite(rgb).all()
    assert torch.isfinite(s_face).all() and (s_face > 0).all()
    assert torch.equal(s_out, torch.zeros(6)) and torch.equal(s_far, torch.zeros(3))
    unit, unit_aabb = scaled_ngp(1.0)
    with torch.no_grad():
        s_unit, _ = unit.field.density(unit_aabb[0] + u * (unit_aabb[1] - unit_aabb[0]))
    np.testing.assert_allclose(np64(s_in) * scale, np64(s_unit), rtol=1e-5)
    with torch.no_grad():
        out = model.render_rays(probe_rays(aabb, scale))
    for t in (out.rgb, out.opacity, out.depth, out.median_depth):
        assert torch.isfinite(t).all()
    assert 0.2 < float(out.opacity[0]) < 0.9  # the untrained field is a light fog at any scale
    assert float(out.opacity[4]) == 0.0 and torch.equal(out.rgb[4], torch.ones(3))
    same = [0, 1, 2, 4]
    np.testing.assert_allclose(np64(out.rgb[same]), np64(unit_render.rgb[same]), atol=1e-5)
    np.testing.assert_allclose(np64(out.opacity[same]), np64(unit_render.opacity[same]),
                               atol=1e-5)
    np.testing.assert_allclose(np64(out.depth[:3]) / scale, np64(unit_render.depth[:3]),
                               rtol=1e-5)


# ============================================================================ training

TRAIN_NGP = {"samples_per_batch": 2048, "grid_update_every": 4, "grid_warmup_steps": 8,
             **SMALL_NGP}
TRAIN_NERF = {"width": 32, "depth": 2, "color_width": 16, "coarse_samples": 16,
              "fine_samples": 16, "rays_per_batch": 128}


def synthetic_dataset(root: Path, kind: str, scale: float = 1.0, size: int = 16, n: int = 8):
    """A tiny nerfstudio dataset with a manifest ``bounds`` cube of edge ``scale`` (metres):
    ``black`` / ``white`` images from an orbit, ``inside`` (cameras at the centre of the
    bounds looking out at a uniform grey wall), ``noise`` (random images from an orbit)."""
    from nerfbot.ops.cameras import focal_from_fov
    from nerfbot.data import load_dataset
    from nerfbot.data.writers import open_writer

    f = focal_from_fov(50.0, size)
    writer = open_writer("nerfstudio", root, f, f, size / 2, size / 2, size, size)
    if kind == "inside":
        poses = [look_at([0.0, 0.0, 0.0], [math.cos(a), math.sin(a), 0.1])
                 for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]
    else:
        poses = list(orbit_poses([0.0, 0.0, 0.0], 2.5 * scale, 20.0, n))
    rng = np.random.default_rng(0)
    for i, pose in enumerate(poses):
        img = {"black": np.zeros((size, size, 3), np.uint8),
               "white": np.full((size, size, 3), 255, np.uint8),
               "inside": np.full((size, size, 3), 128, np.uint8)}.get(kind)
        if img is None:
            img = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
        writer.add_frame(img, pose, split="train" if i < n - 2 else "test")
    h = 0.5 * scale
    writer.finish({"bounds": [[-h, -h, -h], [h, h, h]]})
    return load_dataset(root)


def train_and_check(ds, out_dir, method="ngp", steps=12, lr=None, options=None):
    """Train, then assert: every parameter and float buffer finite, a test view renders finite
    rgb / depth / opacity. Returns (trainer, render)."""
    from nerfbot.train.trainer import TrainConfig, Trainer

    opts = options if options is not None else (TRAIN_NGP if method == "ngp" else TRAIN_NERF)
    trainer = Trainer(ds, out_dir, TrainConfig(method=method, max_steps=steps, lr=lr,
                                                progress=False, options=opts))
    trainer.train()
    assert trainer.step == steps
    for name, p in trainer.model.named_parameters():
        assert torch.isfinite(p).all(), name
    for name, b in trainer.model.named_buffers():
        if b.is_floating_point():
            assert torch.isfinite(b).all(), name
    trainer.model.eval()
    with torch.no_grad():
        out = trainer.model.render_rays(ds.cameras().rays(ds.indices("test")[0]))
    for t in (out.rgb, out.depth, out.opacity):
        assert torch.isfinite(t).all()
    return trainer, out


@pytest.mark.parametrize("method", ["ngp", "nerf"])
def test_training_with_a_10x_learning_rate_stays_finite(tiny_capture, tmp_path, method):
    """10x the method's learning rate on the real tiny capture: Adam's steps are ~lr whatever
    the gradient, trunc_exp / softplus keep densities finite, so parameters stay finite."""
    from nerfbot.data import load_dataset
    from nerfbot.methods import get_method

    ds = load_dataset(tiny_capture[0])
    train_and_check(ds, tmp_path / "run", method, steps=12, lr=10 * get_method(method).lr)


@pytest.mark.parametrize("kind", ["black", "white", "inside"])
def test_training_on_degenerate_images_stays_finite(tmp_path, kind):
    """All-black and all-white images (the colour heads start at logit(0.02) / logit(0.98),
    the sigmoid's flat ends), and cameras inside the bounds (every ray starts in the box,
    t_near = 0): finite, and the render stays at the images' uniform colour (within 0.1)."""
    ds = synthetic_dataset(tmp_path / "ds", kind)
    _, out = train_and_check(ds, tmp_path / "run")
    target = {"black": 0.0, "white": 1.0, "inside": 128 / 255}[kind]
    assert abs(float(out.rgb.mean()) - target) < 0.1, float(out.rgb.mean())


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_training_at_1mm_and_1km(tmp_path, scale):
    """Manifest bounds of edge 1 mm and 1 km, normalised by the loader (padded 5 %, at least
    1 cm): the box contains the content, training steps stay finite."""
    ds = synthetic_dataset(tmp_path / "ds", "noise", scale)
    h = 0.5 * scale
    assert (ds.aabb[0] <= -h).all() and (ds.aabb[1] >= h).all()
    assert ds.aabb[1, 0] - ds.aabb[0, 0] <= 1.1 * scale + 0.02
    train_and_check(ds, tmp_path / "run", steps=8)


def test_diverging_training_gives_a_clear_error(tmp_path):
    """lr = 1e37 (float32 parameters reach ~1e38 in one Adam step, the next forward pass
    overflows): the loss check stops the run with FloatingPointError. A step that leaves
    non-finite parameters as the *last* step (simulated by corrupting one after it) must not be
    saved either: before the fix the run ended normally with a NaN checkpoint. Non-positive or
    non-finite learning rates are rejected up front."""
    from nerfbot.train.checkpoints import CHECKPOINT
    from nerfbot.train.trainer import TrainConfig, Trainer

    ds = synthetic_dataset(tmp_path / "ds", "noise")
    cfg = dict(method="ngp", progress=False, options=TRAIN_NGP)
    trainer = Trainer(ds, tmp_path / "a", TrainConfig(max_steps=3, lr=1e37, **cfg))
    with pytest.raises(FloatingPointError, match="learning rate"):
        trainer.train()
    assert trainer.step == 1 and not (tmp_path / "a" / CHECKPOINT).exists()

    def corrupt(t):
        if t.step == 2:
            with torch.no_grad():
                t.model.field.encoding.table[0, 0] = float("nan")

    trainer = Trainer(ds, tmp_path / "b", TrainConfig(max_steps=2, **cfg))
    with pytest.raises(FloatingPointError, match="non-finite parameters.*encoding.table"):
        trainer.train(on_step=corrupt)
    assert not (tmp_path / "b" / CHECKPOINT).exists()
    for lr in (0.0, -1e-3, INF, float("nan")):
        with pytest.raises(ValueError, match="lr"):
            Trainer(ds, tmp_path / "bad", TrainConfig(method="ngp", max_steps=1, lr=lr))
