"""Input encodings (nerfbot.ops.encodings): the numba hash-grid kernels against the plain-torch
twin evaluated in float64, the level layout, spherical harmonics against scipy, and the
frequency encoding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from nerfbot.kernels import hashgrid as hk
from nerfbot.kernels.hashgrid import level_layout
from nerfbot.ops.encodings import (FrequencyEncoding, HashEncoding, SHEncoding,
                                   hash_encode_reference, spherical_harmonics)

# ----------------------------------------------------------------------------- hash grid

CONFIGS = {
    # every level dense: (res + 1)^3 <= 2^14
    "dense": dict(n_levels=3, n_features=2, log2_size=14, min_res=4, max_res=16),
    # coarse dense levels, fine hashed ones, one feature
    "mixed_f1": dict(n_levels=5, n_features=1, log2_size=11, min_res=6, max_res=96),
    # every level hashed (tiny table: many collisions), four features
    "hashed_f4": dict(n_levels=4, n_features=4, log2_size=9, min_res=16, max_res=128),
    # the usual two features, a single level
    "single": dict(n_levels=1, n_features=2, log2_size=12, min_res=20, max_res=20),
}


def level_kinds(enc: HashEncoding) -> list[bool]:
    """True for dense levels (computed from the layout, independently of the kernels)."""
    res, off = enc.res.tolist(), enc.offsets.tolist()
    return [(r + 1) ** 3 <= off[i + 1] - off[i] for i, r in enumerate(res)]


def test_configs_cover_dense_and_hashed_levels():
    kinds = {name: level_kinds(HashEncoding(**cfg, seed=0)) for name, cfg in CONFIGS.items()}
    assert all(kinds["dense"]) and not any(kinds["hashed_f4"])
    assert any(kinds["mixed_f1"]) and not all(kinds["mixed_f1"])


def sample_points(n: int = 3000, seed: int = 0) -> torch.Tensor:
    """Random points in [-0.1, 1.1]^3 plus the corners and faces of the unit cube."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 1.2 - 0.1
    corners = torch.tensor([[(k >> i) & 1 for i in range(3)] for k in range(8)],
                           dtype=torch.float32)
    x[:8] = corners                                  # exactly on 0 and 1
    x[8:16] = corners * 1.5 - 0.25                   # outside on every axis (clamped)
    x[16:40, 0] = 0.0
    x[40:64, 1] = 1.0
    x[64:88, 2] = torch.linspace(0, 1, 24)           # on grid planes of many levels
    return x


@pytest.mark.parametrize("name", list(CONFIGS))
def test_hash_numba_forward_and_table_grad_match_float64_reference(name):
    enc = HashEncoding(**CONFIGS[name], seed=1, init_scale=1.0)
    x = sample_points(seed=2)
    y = enc(x)  # x needs no gradient: the numba path
    assert y.shape == (len(x), enc.out_dim) and y.dtype == torch.float32
    table64 = enc.table.detach().double().requires_grad_(True)
    y_ref = hash_encode_reference(x.double(), table64, enc.offsets, enc.res)
    scale = float(y_ref.abs().max())
    assert scale > 0.1
    np.testing.assert_allclose(y.detach().double().numpy(), y_ref.detach().numpy(), rtol=1e-5,
                               atol=1e-5 * scale)
    up = torch.randn(y.shape, generator=torch.Generator().manual_seed(3))
    enc.table.grad = None
    y.backward(up)
    y_ref.backward(up.double())
    g, g_ref = enc.table.grad.double().numpy(), table64.grad.numpy()
    assert np.abs(g_ref).max() > 1.0
    np.testing.assert_allclose(g, g_ref, rtol=1e-5, atol=1e-5 * np.abs(g_ref).max())
    # rows no point touches get exactly zero gradient in both
    np.testing.assert_array_equal(g == 0.0, g_ref == 0.0)
    # the kernel overwrites its output: a table gradient buffer full of NaN gives the same
    grad_lnf = up.reshape(len(x), len(enc.res), -1).permute(1, 0, 2).contiguous()
    dirty = np.full(tuple(enc.table.shape), np.nan, np.float32)
    hk.hash_backward(x.clamp(0, 1).contiguous().numpy(), grad_lnf.numpy(), enc._offsets_np,
                     enc._res_np, dirty, 2)
    np.testing.assert_array_equal(dirty, enc.table.grad.numpy())


def test_hash_points_outside_the_unit_cube_are_clamped():
    enc = HashEncoding(**CONFIGS["mixed_f1"], seed=4, init_scale=1.0)
    g = torch.Generator().manual_seed(5)
    x = torch.rand(500, 3, generator=g)
    push = torch.where(torch.rand(500, 3, generator=g) < 0.3, torch.randn(500, 3, generator=g) * 3,
                       torch.zeros(500, 3))
    outside = x + push
    assert ((outside < 0) | (outside > 1)).any(-1).sum() > 200
    torch.testing.assert_close(enc(outside), enc(outside.clamp(0, 1)), rtol=0, atol=0)


def test_hash_interpolation_hits_table_rows_at_vertices():
    """At a grid vertex of a dense level the encoding is exactly that vertex's table row."""
    enc = HashEncoding(n_levels=1, n_features=2, log2_size=12, min_res=8, max_res=8, seed=0,
                       init_scale=1.0)
    ijk = torch.tensor([[0, 0, 0], [8, 8, 8], [3, 5, 7], [8, 0, 2]])
    y = enc(ijk.float() / 8)
    rows = ijk[:, 0] + 9 * ijk[:, 1] + 81 * ijk[:, 2]
    torch.testing.assert_close(y, enc.table.detach()[rows], rtol=0, atol=1e-7)
    # halfway between two vertices along x: the mean of their rows
    y_mid = enc(torch.tensor([[3.5, 5.0, 7.0]]) / 8)
    torch.testing.assert_close(y_mid[0], 0.5 * (enc.table.detach()[rows[2]]
                                                + enc.table.detach()[rows[2] + 1]),
                               rtol=0, atol=1e-6)


def test_hash_hashed_level_uses_the_documented_hash():
    enc = HashEncoding(n_levels=1, n_features=1, log2_size=8, min_res=32, max_res=32, seed=0,
                       init_scale=1.0)
    assert not level_kinds(enc)[0]
    ijk = torch.tensor([[0, 0, 0], [31, 2, 17], [5, 32, 9]])
    rows = ((ijk[:, 0] ^ (ijk[:, 1] * 2654435761) ^ (ijk[:, 2] * 805459861)) & 255)
    y = enc(ijk.float() / 32)
    torch.testing.assert_close(y[:, 0], enc.table.detach()[rows, 0], rtol=0, atol=1e-7)


def test_hash_fast_path_also_with_position_gradient():
    enc = HashEncoding(**CONFIGS["mixed_f1"], seed=6, init_scale=1.0)
    x = sample_points(500, seed=7)
    # with x.requires_grad: still the numba path, differentiable w.r.t. x
    xg = x.clone().requires_grad_(True)
    y = enc(xg)
    assert "HashEncodeNumba" in type(y.grad_fn).__name__
    y_ref = hash_encode_reference(x, enc.table, enc.offsets, enc.res)
    torch.testing.assert_close(y, y_ref, rtol=1e-5, atol=1e-6)
    y_fast = enc(x)
    assert "HashEncodeNumba" in type(y_fast.grad_fn).__name__
    torch.testing.assert_close(y_fast, y_ref, rtol=1e-5, atol=1e-6)
    up = torch.randn(y.shape, generator=torch.Generator().manual_seed(8))
    (y * up).sum().backward()
    assert xg.grad is not None and torch.isfinite(xg.grad).all()
    inside = ((x > 0) & (x < 1)).all(-1)
    assert (xg.grad[inside].abs().sum(-1) > 0).all()
    outside = ((x < 0) | (x > 1))
    assert (xg.grad[outside] == 0).all()  # clamped coordinates carry no gradient
    # the position gradient of the trilinear interpolation is right (float64 finite differences)
    table64 = enc.table.detach().double()
    x64 = x[100:106].double().clamp(0.01, 0.99).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: hash_encode_reference(p, table64, enc.offsets, enc.res), (x64,), eps=1e-7,
        atol=1e-5, rtol=1e-4)
    # the torch backend never takes the fast path
    enc_t = HashEncoding(**CONFIGS["mixed_f1"], seed=6, init_scale=1.0, backend="torch")
    y_t = enc_t(x)
    assert "HashEncodeNumba" not in type(y_t.grad_fn).__name__
    torch.testing.assert_close(y_t, y_ref, rtol=0, atol=0)


def test_hash_seed_is_deterministic_and_init_scale_bounds_the_table():
    a = HashEncoding(**CONFIGS["dense"], seed=3, init_scale=1e-4)
    b = HashEncoding(**CONFIGS["dense"], seed=3, init_scale=1e-4)
    assert torch.equal(a.table, b.table)
    assert float(a.table.abs().max()) <= 1e-4
    assert a.table.shape == (int(a.offsets[-1]), 2)
    with pytest.raises(ValueError, match="backend"):
        HashEncoding(backend="cuda")


@pytest.mark.parametrize("n_levels,log2_size,min_res,max_res", [
    (16, 19, 16, 2048), (8, 14, 16, 512), (1, 10, 7, 7), (4, 12, 3, 60), (12, 15, 16, 4096),
])
def test_level_layout(n_levels, log2_size, min_res, max_res):
    res, offsets = level_layout(n_levels, log2_size, min_res, max_res)
    assert res.dtype == np.int64 and offsets.dtype == np.int64
    assert res.shape == (n_levels,) and offsets.shape == (n_levels + 1,)
    assert res[0] == min_res and res[-1] == max_res
    assert (np.diff(res) >= 0).all()
    if n_levels > 1:
        b = math.exp((math.log(max_res) - math.log(min_res)) / (n_levels - 1))
        expect = np.floor(min_res * b ** np.arange(n_levels) + 1e-6)
        np.testing.assert_array_equal(res, expect)  # geometric growth N_l = floor(N_min b^l)
        ratios = res[1:] / res[:-1]
        assert np.all(np.abs(ratios / b - 1) < 2.0 / res[:-1] + 1e-9)
    size = 2 ** log2_size
    rows = np.diff(offsets)
    assert offsets[0] == 0 and (rows > 0).all()
    assert (rows % 8 == 0).all()
    for r, n in zip(res, rows):
        full = (r + 1) ** 3
        if full <= size:   # dense: every vertex has its own row, padded to a multiple of 8
            assert full <= n < full + 8
        else:              # hashed: the whole table, a power of two (the kernels mask with it)
            assert n == size and n & (n - 1) == 0
    with pytest.raises(ValueError):
        level_layout(4, 10, 32, 16)
    with pytest.raises(ValueError):
        level_layout(0, 10, 16, 32)


def test_hash_kernel_constants_match_the_paper():
    assert hk.PRIME_Y == 2654435761 and hk.PRIME_Z == 805459861


# ----------------------------------------------------------------------------- spherical harmonics

def real_sh_scipy(l: int, m: int, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Real orthonormal SH from scipy's complex ones (theta polar from +z, phi azimuth from +x)."""
    if m == 0:
        return sph_harm_y(l, 0, theta, phi).real
    y = sph_harm_y(l, abs(m), theta, phi)
    return math.sqrt(2.0) * (-1) ** m * (y.imag if m < 0 else y.real)


def quadrature(n_theta: int = 12, n_phi: int = 24):
    """Directions and weights integrating polynomials of degree < 2 * n_theta exactly on S^2."""
    u, wu = np.polynomial.legendre.leggauss(n_theta)       # u = cos(theta)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    uu, pp = np.meshgrid(u, phi, indexing="ij")
    w = (wu[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]).reshape(-1)
    theta = np.arccos(uu).reshape(-1)
    pp = pp.reshape(-1)
    s = np.sin(theta)
    dirs = np.stack([s * np.cos(pp), s * np.sin(pp), np.cos(theta)], -1)
    return dirs, theta, pp, w


def test_quadrature_integrates_the_sphere():
    dirs, _, _, w = quadrature()
    assert w.sum() == pytest.approx(4 * math.pi, rel=1e-14)
    assert (w * dirs[:, 2] ** 2).sum() == pytest.approx(4 * math.pi / 3, rel=1e-14)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sh_orthonormal(degree):
    dirs, _, _, w = quadrature()
    basis = spherical_harmonics(torch.from_numpy(dirs), degree).numpy()
    assert basis.shape == (len(dirs), (degree + 1) ** 2)
    gram = basis.T @ (w[:, None] * basis)
    np.testing.assert_allclose(gram, np.eye((degree + 1) ** 2), atol=1e-12)


def test_sh_matches_scipy_real_basis_up_to_sign():
    """Each nerfbot function equals, up to a sign, the scipy real SH of the same (l, m), with
    nerfbot's index l^2 + l + m. The cross-Gram matrix is a signed identity."""
    dirs, theta, phi, w = quadrature()
    ours = spherical_harmonics(torch.from_numpy(dirs), 4).numpy()
    ref = np.stack([real_sh_scipy(l, m, theta, phi) for l in range(5) for m in range(-l, l + 1)],
                   -1)
    cross = ours.T @ (w[:, None] * ref)
    np.testing.assert_allclose(np.abs(cross), np.eye(25), atol=1e-12)
    signs = np.sign(np.diag(cross))
    np.testing.assert_allclose(ours, ref * signs, atol=1e-12)  # pointwise, not just in L2
    # the sign convention is the PlenOctrees/svox2 one: (-1)^m relative to this scipy basis
    ms = np.array([m for l in range(5) for m in range(-l, l + 1)])
    np.testing.assert_array_equal(signs, np.where(ms % 2 == 0, 1.0, -1.0))


def test_sh_hand_values():
    c0 = 0.5 / math.sqrt(math.pi)
    c1 = math.sqrt(3.0 / (4.0 * math.pi))
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0],
                      [0.6, -0.8, 0.0]], dtype=torch.float64)
    sh = spherical_harmonics(d, 1)
    expect = torch.tensor([[c0, 0, 0, -c1], [c0, -c1, 0, 0], [c0, 0, c1, 0],
                           [c0, 0.8 * c1, 0, -0.6 * c1]], dtype=torch.float64)
    torch.testing.assert_close(sh, expect, rtol=1e-15, atol=1e-15)
    # Y_2^0 at the pole: sqrt(5 / 4pi); Y_4^0 at the pole: 3 / (2 sqrt(pi))
    pole = spherical_harmonics(d[2:3], 4)[0]
    assert pole[6].item() == pytest.approx(math.sqrt(5 / (4 * math.pi)), rel=1e-14)
    assert pole[20].item() == pytest.approx(3 / (2 * math.sqrt(math.pi)), rel=1e-14)
    # addition theorem: sum_m Y_lm(d)^2 = (2l + 1) / 4pi for every unit d
    g = torch.Generator().manual_seed(0)
    u = torch.nn.functional.normalize(torch.randn(100, 3, generator=g, dtype=torch.float64), dim=-1)
    full = spherical_harmonics(u, 4)
    for l in range(5):
        band = full[:, l * l:(l + 1) ** 2].square().sum(-1)
        torch.testing.assert_close(band, torch.full_like(band, (2 * l + 1) / (4 * math.pi)),
                                   rtol=1e-13, atol=0)


def test_sh_encoding_module_and_degree_check():
    enc = SHEncoding(3)
    d = torch.nn.functional.normalize(torch.randn(7, 3, generator=torch.Generator().manual_seed(1)),
                                      dim=-1)
    assert enc.out_dim == 16 and enc(d).shape == (7, 16)
    torch.testing.assert_close(enc(d), spherical_harmonics(d, 3))
    for bad in (-1, 5):
        with pytest.raises(ValueError, match="degree"):
            spherical_harmonics(d, bad)


# ----------------------------------------------------------------------------- frequency encoding

def test_frequency_encoding_shape_and_values():
    enc = FrequencyEncoding(3, 4)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(10, 3, generator=g, dtype=torch.float64) * 2 - 1
    y = enc(x)
    assert enc.out_dim == 3 * 9 and y.shape == (10, 27)
    torch.testing.assert_close(y[:, :3], x)
    xs = x.numpy()
    for k in range(4):
        for dim in range(3):
            f = math.pi * 2 ** k
            # layout: [x (D), sin (F x D, frequency-major), cos (F x D)]
            np.testing.assert_allclose(y[:, 3 + 3 * k + dim].numpy(), np.sin(f * xs[:, dim]),
                                       atol=1e-6)
            np.testing.assert_allclose(y[:, 15 + 3 * k + dim].numpy(), np.cos(f * xs[:, dim]),
                                       atol=1e-6)
    enc_no = FrequencyEncoding(2, 3, include_input=False)
    y2 = enc_no(x[:, :2])
    assert enc_no.out_dim == 12 and y2.shape == (10, 12)
    torch.testing.assert_close(y2, y[:, [3, 4, 6, 7, 9, 10, 15, 16, 18, 19, 21, 22]])
    # leading batch dimensions pass through
    assert enc(x.reshape(2, 5, 3)).shape == (2, 5, 27)


@pytest.mark.parametrize("degree", [0, 1, 2, 3, 4])
def test_sh_kernel_path_matches_float64_reference_and_the_gradient_path(degree):
    """Directions that need no gradient take the numba kernel; it agrees with the float64 torch
    basis and with the differentiable float32 path."""
    gen = torch.Generator().manual_seed(degree)
    d64 = torch.nn.functional.normalize(torch.randn(5000, 3, generator=gen, dtype=torch.float64),
                                        dim=-1)
    d = d64.float()
    fast = spherical_harmonics(d, degree)
    assert fast.shape == (5000, (degree + 1) ** 2) and fast.dtype == torch.float32
    torch.testing.assert_close(fast.double(), spherical_harmonics(d64, degree), atol=2e-6,
                               rtol=0)
    graded = spherical_harmonics(d.clone().requires_grad_(True), degree)
    assert graded.requires_grad or degree == 0  # degree 0 is a constant
    torch.testing.assert_close(fast, graded.detach(), atol=1e-6, rtol=0)


def test_sh_warmup_fades_bands_in_one_after_another():
    """``sh_warmup``: band l >= 1 of the direction encoding opens over the l-th part of the
    warm-up, band 0 is always on, and afterwards nothing is scaled."""
    from nerfbot.fields.ngp import sh_band_weights

    assert sh_band_weights(4, 0.0, 0.0) is None and sh_band_weights(0, 0.5, 0.0) is None
    assert sh_band_weights(4, 0.5, 0.5) is None and sh_band_weights(4, 0.5, 0.9) is None
    band = torch.tensor([b for b in range(5) for _ in range(2 * b + 1)])
    start = sh_band_weights(4, 0.5, 0.0)
    assert start.shape == (25,) and torch.equal(start, (band == 0).float())
    mid = sh_band_weights(4, 0.5, 0.25)  # bands 1 and 2 open, 3 and 4 closed
    torch.testing.assert_close(mid, (band <= 2).float())
    quarter = sh_band_weights(4, 0.5, 0.0625)  # half-way through band 1's ramp
    torch.testing.assert_close(quarter[1:4], torch.full((3,), 0.5))
    ws = torch.stack([sh_band_weights(4, 0.5, p) for p in np.linspace(0, 0.49, 50)])
    assert bool((ws[1:] >= ws[:-1]).all())  # bands only open


def test_ngp_sh_warmup_starts_view_independent_and_trains_each_band_once_open():
    from nerfbot.fields.ngp import NGPField, NGPFieldConfig

    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    field = NGPField(aabb, NGPFieldConfig(sh_warmup=0.4, backend="torch", n_levels=4,
                                          log2_hashmap_size=10), seed=0)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(64, 3, generator=g) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    feat = field.density(x)[1]
    # zero weights on bands >= 1: the same colour from every direction at the start
    torch.testing.assert_close(field.color(feat, d), field.color(feat, -d))
    cols = slice(field.config.geo_feat_dim + 1, None)
    for progress, open_ in ((0.0, False), (0.5, True)):
        field.zero_grad()
        field.before_step(0, progress)
        field.color(field.density(x)[1], d).sum().backward()
        grad = field.color_mlp[0].weight.grad[:, cols]
        assert bool((grad.abs().sum() > 0) == open_)
    with pytest.raises(ValueError, match="sh_warmup"):
        NGPField(aabb, NGPFieldConfig(sh_warmup=1.0))


def test_level_warmup_fades_hash_levels_in_from_coarse_to_fine():
    """``level_warmup``: the ``first`` coarsest levels at full weight from the start, the
    finer ones opening one after another, only ever opening, and nothing scaled afterwards."""
    from nerfbot.fields.ngp import hash_level_weights

    assert hash_level_weights(16, 4, 0.0, 0.0) is None
    assert hash_level_weights(16, 16, 0.3, 0.0) is None
    assert hash_level_weights(16, 4, 0.3, 0.3) is None and hash_level_weights(16, 4, 0.3, 0.9) is None
    start = hash_level_weights(16, 4, 0.3, 0.0)
    torch.testing.assert_close(start, (torch.arange(16) < 4).float())
    half = hash_level_weights(16, 4, 0.3, 0.15)  # a = 4 + 12 / 2 = 10: levels 0-9 open
    torch.testing.assert_close(half, (torch.arange(16) < 10).float())
    ramp = hash_level_weights(16, 4, 0.3, 0.0125)  # a = 4.5: level 4 half-way open
    assert float(ramp[4]) == pytest.approx(0.5) and float(ramp[5]) == 0.0
    ws = torch.stack([hash_level_weights(16, 4, 0.3, p) for p in np.linspace(0, 0.299, 60)])
    assert bool((ws[1:] >= ws[:-1]).all())


def test_ngp_level_warmup_leaves_fine_levels_out_of_the_field_until_they_open():
    from nerfbot.fields.ngp import NGPField, NGPFieldConfig

    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    cfg = NGPFieldConfig(level_warmup=0.5, level_warmup_first=2, backend="torch", n_levels=6,
                         n_features=2, log2_hashmap_size=10)
    field = NGPField(aabb, cfg, seed=0)
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    table_rows = field.encoding.offsets.long()
    for progress, open_levels in ((0.0, 2), (0.25, 4), (0.6, 6)):
        field.zero_grad()
        field.before_step(0, progress)
        field.density(x)[0].sum().backward()
        grad = field.encoding.table.grad
        touched = [bool(grad[table_rows[k]:table_rows[k + 1]].abs().sum() > 0) for k in range(6)]
        assert touched == [k < open_levels for k in range(6)], progress
    for bad, match in (({"level_warmup": 1.0}, "level_warmup"),
                       ({"level_warmup": 0.3, "level_warmup_first": 0}, "level_warmup_first"),
                       ({"level_warmup": 0.3, "level_warmup_first": 17}, "level_warmup_first")):
        with pytest.raises(ValueError, match=match):
            NGPField(aabb, NGPFieldConfig(**bad))


def test_bf16_mlp_pads_rows_and_matches_float32():
    """run_mlp in bf16: any row count, float32 output of that many rows, values and weight
    gradients within bfloat16's precision of the float32 network's; padding rows add nothing
    to the gradients."""
    from nerfbot.fields.base import MLP_ROW_BUCKET, mlp, run_mlp
    torch.manual_seed(0)
    net = mlp(32, 64, 2, 4)
    n = MLP_ROW_BUCKET + 37
    x = torch.randn(n, 32)
    grads = {}
    outs = {}
    for precision in ("fp32", "bf16"):
        net.zero_grad()
        out = run_mlp(net, x, precision)
        assert out.shape == (n, 4) and out.dtype == torch.float32
        out.square().mean().backward()
        outs[precision] = out.detach()
        grads[precision] = [p.grad.clone() for p in net.parameters()]
    scale = outs["fp32"].abs().max()
    assert (outs["bf16"] - outs["fp32"]).abs().max() < 0.03 * scale
    for g32, g16 in zip(grads["fp32"], grads["bf16"]):
        assert torch.isfinite(g16).all()
        assert (g16 - g32).norm() < 0.05 * g32.norm()
