"""Factorised plane encoding (nerfbot.ops.encodings.PlaneEncoding): the numba kernels against the
plain-torch twin, the table layout, clamping and NaN handling, the K-Planes regularisers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.kernels.planes import plane_layout
from nerfbot.ops.encodings import PlaneEncoding, plane_encode_reference, plane_pairs

CONFIGS = {
    "space": dict(in_dim=3, n_levels=2, n_features=3, spatial_res=(4, 7)),
    "spacetime": dict(in_dim=4, n_levels=2, n_features=4, spatial_res=(5, 9), time_res=(3, 6)),
    "spacetime_f1": dict(in_dim=4, n_levels=1, n_features=1, spatial_res=(6,), time_res=(2,)),
}


def spread_table(enc: PlaneEncoding, seed: int) -> PlaneEncoding:
    """Features uniform in [0.5, 1.5], and exact zeros on every 7th row (the product's gradient
    must stay exact where another plane is zero)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        enc.table.copy_(torch.rand(enc.table.shape, generator=g) + 0.5)
        enc.table[::7] = 0.0
    return enc


def sample_points(dim: int, n: int = 2000, seed: int = 0) -> torch.Tensor:
    """Random points in [-0.1, 1.1]^dim plus the corners of the unit box, points outside it on
    every axis, on its faces, and on grid lines of the levels."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, dim, generator=g) * 1.2 - 0.1
    corners = torch.tensor([[(k >> i) & 1 for i in range(dim)] for k in range(2**dim)],
                           dtype=torch.float32)
    c = len(corners)
    x[:c] = corners                                 # exactly on 0 and 1
    x[c:2 * c] = corners * 1.5 - 0.25               # just outside on every axis
    x[2 * c:2 * c + 30, 0] = 0.0
    x[2 * c + 30:2 * c + 60, 1] = 1.0
    x[2 * c + 60:2 * c + 96, dim - 1] = torch.arange(36) / 36.0   # on grid lines (res | 36)
    return x


@pytest.mark.parametrize("name", list(CONFIGS))
def test_numba_forward_and_table_grad_match_the_reference(name):
    enc = spread_table(PlaneEncoding(**CONFIGS[name], seed=1), seed=2)
    x = sample_points(enc.in_dim, seed=3)
    y = enc(x)  # float32 CPU without position gradient: the numba path
    assert "PlaneEncodeNumba" in type(y.grad_fn).__name__
    assert y.shape == (len(x), enc.out_dim) and y.dtype == torch.float32
    table = enc.table.detach().clone().requires_grad_(True)
    y_ref = plane_encode_reference(x, table, enc.offsets, enc.res, enc.pairs)
    scale = float(y_ref.detach().abs().max())
    assert scale > 0.5 and (y_ref == 0).any()
    torch.testing.assert_close(y, y_ref, rtol=1e-5, atol=1e-5 * scale)
    up = torch.randn(y.shape, generator=torch.Generator().manual_seed(4))
    y.backward(up)
    y_ref.backward(up)
    g, g_ref = enc.table.grad, table.grad
    assert g_ref.abs().max() > 1.0
    torch.testing.assert_close(g, g_ref, rtol=1e-5, atol=1e-5 * float(g_ref.abs().max()))
    # rows no point reaches (with a non-zero weight) get exactly zero gradient in both
    assert torch.equal(g == 0, g_ref == 0)
    # and the float32 reference itself is right (float64 twin)
    y64 = plane_encode_reference(x.double(), enc.table.detach().double(), enc.offsets, enc.res,
                                 enc.pairs)
    torch.testing.assert_close(y.double(), y64, rtol=1e-5, atol=1e-5 * scale)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_outside_points_get_the_border_value_and_nan_reads_as_zero(backend):
    enc = spread_table(PlaneEncoding(**CONFIGS["spacetime"], backend=backend, seed=5), seed=6)
    g = torch.Generator().manual_seed(7)
    x = torch.rand(400, 4, generator=g) * 3 - 1
    assert ((x < 0) | (x > 1)).any(-1).sum() > 300
    torch.testing.assert_close(enc(x), enc(x.clamp(0, 1)), rtol=0, atol=0)
    x[::3, 1] = float("nan")
    x[1::5] = float("nan")
    x[2, 0], x[4, 3] = float("inf"), -float("inf")
    y = enc(x)
    assert torch.isfinite(y).all()
    torch.testing.assert_close(y, enc(torch.nan_to_num(x, nan=0.0).clamp(0, 1)), rtol=0, atol=0)
    y.square().sum().backward()
    assert torch.isfinite(enc.table.grad).all() and enc.table.grad.abs().sum() > 0


def test_encoding_at_a_grid_vertex_is_the_product_of_the_stored_plane_values():
    enc = spread_table(PlaneEncoding(**CONFIGS["spacetime"], seed=8), seed=9)
    pairs, res, offsets = plane_pairs(4), enc.res.tolist(), enc.offsets.tolist()
    for lvl in range(enc.n_levels):
        s, t = res[lvl][0], res[lvl][3]
        idx = torch.tensor([[0, 0, 0, 0], [s, s, s, t], [1, s - 2, 3, t - 1], [s, 0, 2, 1]])
        y = enc(idx.float() / torch.tensor(res[lvl]).float())
        expect = torch.ones(len(idx), enc.n_features)
        for p, (a, b) in enumerate(pairs):
            rows = offsets[lvl * len(pairs) + p] + idx[:, a] + idx[:, b] * (res[lvl][a] + 1)
            stored = enc.table.detach()[rows]
            torch.testing.assert_close(stored, enc.plane(lvl, p).detach()[idx[:, b], idx[:, a]],
                                       rtol=0, atol=0)
            expect = expect * stored
        cols = slice(lvl * enc.n_features, (lvl + 1) * enc.n_features)
        torch.testing.assert_close(y[:, cols], expect, rtol=1e-5, atol=1e-6)


def test_reference_gradcheck_float64():
    enc = PlaneEncoding(in_dim=4, n_levels=2, n_features=1, spatial_res=(1, 2), time_res=(2, 3),
                        seed=10, backend="torch")
    g = torch.Generator().manual_seed(11)
    table = (torch.rand(enc.table.shape, generator=g, dtype=torch.float64) + 0.5)
    # points away from the cell boundaries (all multiples of 1/6), where x is not differentiable
    x = (torch.randint(0, 6, (3, 4), generator=g) + 0.1
         + 0.8 * torch.rand(3, 4, generator=g, dtype=torch.float64)) / 6

    def f(tab, pts):
        return plane_encode_reference(pts, tab, enc.offsets, enc.res, enc.pairs)

    assert torch.autograd.gradcheck(f, (table.requires_grad_(True), x.requires_grad_(True)),
                                    eps=1e-6, atol=1e-6, rtol=1e-5)


def test_fast_path_only_for_float32_cpu_without_position_gradient():
    enc = spread_table(PlaneEncoding(**CONFIGS["space"], seed=12), seed=13)
    x = sample_points(3, 300, seed=14)
    y_ref = plane_encode_reference(x, enc.table, enc.offsets, enc.res, enc.pairs)
    xg = x.clone().requires_grad_(True)
    y = enc(xg)
    assert "PlaneEncodeNumba" not in type(y.grad_fn).__name__
    torch.testing.assert_close(y, y_ref, rtol=0, atol=0)
    y.sum().backward()
    assert torch.isfinite(xg.grad).all() and xg.grad.abs().sum() > 0
    enc_t = spread_table(PlaneEncoding(**CONFIGS["space"], seed=12, backend="torch"), seed=13)
    assert "PlaneEncodeNumba" not in type(enc_t(x).grad_fn).__name__
    # leading batch dimensions pass through
    assert enc(x[:300].reshape(10, 30, 3)).shape == (10, 30, enc.out_dim)
    with torch.no_grad():
        torch.testing.assert_close(enc(x), y_ref, rtol=1e-5, atol=1e-6)


def test_regularisers_on_hand_made_planes():
    enc = PlaneEncoding(**CONFIGS["spacetime"], seed=15)
    with torch.no_grad():
        enc.table.fill_(0.7)
    assert enc.tv_loss().item() == 0.0 and enc.smoothness_loss().item() == 0.0
    with torch.no_grad():
        for lvl in range(enc.n_levels):
            for p in enc.spatial_planes:   # slope 1 along the plane's first axis only
                plane = enc.plane(lvl, p)
                plane.copy_(torch.arange(plane.shape[1], dtype=torch.float32)[None, :, None])
            for p in enc.time_planes:      # t^2 along time: second difference 2 everywhere
                plane = enc.plane(lvl, p)
                plane.copy_(torch.arange(plane.shape[0], dtype=torch.float32)[:, None, None] ** 2)
    assert enc.tv_loss().item() == pytest.approx(1.0 * 3 * enc.n_levels)
    assert enc.smoothness_loss().item() == pytest.approx(4.0 * 3 * enc.n_levels)
    (enc.tv_loss() + enc.smoothness_loss()).backward()
    assert enc.table.grad.abs().sum() > 0
    enc3 = PlaneEncoding(**CONFIGS["space"], seed=15)
    assert enc3.smoothness_loss().item() == 0.0 and enc3.tv_loss().item() > 0.0


def test_init_layout_and_arguments():
    a = PlaneEncoding(seed=3)
    assert torch.equal(a.table, PlaneEncoding(seed=3).table)
    assert a.out_dim == 16 and plane_pairs(4) == [(0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3)]
    assert 0.9 <= float(a.table.detach().min()) and float(a.table.detach().max()) <= 1.1
    res = a.res.tolist()
    rows = [(res[l][i] + 1) * (res[l][j] + 1) for l in range(2) for i, j in plane_pairs(4)]
    assert a.offsets.tolist() == np.concatenate([[0], np.cumsum(rows)]).tolist()
    # K-Planes init: time planes exactly 1, so the space-time encoding is the spatial one
    k4 = PlaneEncoding(init="kplanes", seed=4)
    k3 = PlaneEncoding(in_dim=3, spatial_res=(32, 64), seed=5)
    with torch.no_grad():
        for lvl in range(2):
            assert (k4.plane(lvl, 3) == 1).all() and (k4.plane(lvl, 5) == 1).all()
            s = k4.plane(lvl, 0)
            assert 0.1 <= float(s.min()) and float(s.max()) <= 0.5
            for p in range(3):
                k3.plane(lvl, p).copy_(k4.plane(lvl, p))
        x = torch.rand(200, 4, generator=torch.Generator().manual_seed(6))
        torch.testing.assert_close(k4(x), k3(x[:, :3]), rtol=1e-5, atol=0)
    for bad in (dict(backend="cuda"), dict(init="zeros"), dict(in_dim=5),
                dict(spatial_res=(32,)), dict(time_res=(16, 24, 32))):
        with pytest.raises(ValueError):
            PlaneEncoding(**bad)
    with pytest.raises(ValueError):
        plane_layout(np.ones((2, 3), np.int64), np.array([[0, 3]]))
    with pytest.raises(ValueError):
        a(torch.rand(4, 3))
