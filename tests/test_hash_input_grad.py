"""Gradient of the hash encoding w.r.t. its input positions on the fast numba path
(nerfbot.kernels.hashgrid.hash_backward_input), against the autograd of the plain-torch twin
:func:`nerfbot.ops.encodings.hash_encode_reference` and against finite differences.

The trilinear interpolation is continuous but its derivative jumps across cell faces, so the
exact comparisons use points at least ``MARGIN`` cells away from every face of every level; on a
face both paths take the one-sided derivative of the same cell (the one ``floor(x * res)``
picks), which a separate test checks with the same tolerance.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.kernels import hashgrid as hk
from nerfbot.ops.encodings import HashEncoding, hash_encode_reference

CONFIGS = {
    # every level dense: (res + 1)^3 <= 2^14
    "dense": dict(n_levels=3, n_features=2, log2_size=14, min_res=4, max_res=16),
    # coarse dense levels, fine hashed ones, one feature
    "mixed_f1": dict(n_levels=5, n_features=1, log2_size=11, min_res=6, max_res=96),
    # every level hashed (tiny table: many collisions), four features
    "hashed_f4": dict(n_levels=4, n_features=4, log2_size=9, min_res=16, max_res=128),
    # more levels, finer grid, the usual two features
    "fine_f2": dict(n_levels=8, n_features=2, log2_size=12, min_res=4, max_res=512),
}
MARGIN = 1e-3  # cells


def level_kinds(enc: HashEncoding) -> list[bool]:
    res, off = enc.res.tolist(), enc.offsets.tolist()
    return [(r + 1) ** 3 <= off[i + 1] - off[i] for i, r in enumerate(res)]


def away_from_faces(x: torch.Tensor, res: torch.Tensor, margin: float) -> torch.Tensor:
    """(N,) True where every coordinate is more than ``margin`` cells from a face on every level
    (positions as the kernels compute them: float32 x * res)."""
    pos = (x[:, None, :] * res.float()[None, :, None]).double()
    frac = pos - pos.floor()
    return ((frac > margin) & (frac < 1 - margin)).all(-1).all(-1)


def smooth_points(n: int, res: torch.Tensor, seed: int, margin: float = MARGIN) -> torch.Tensor:
    """About ``n`` random points in (0, 1)^3 away from every cell face."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2 * n, 3, generator=g)
    x = x[away_from_faces(x, res, margin)][:n]
    assert len(x) > n // 2
    return x


def upstream(enc: HashEncoding, n: int, seed: int) -> torch.Tensor:
    return torch.randn(n, enc.out_dim, generator=torch.Generator().manual_seed(seed))


def numba_grads(enc: HashEncoding, x: torch.Tensor, up: torch.Tensor):
    """(d loss / d x, d loss / d table) through the numba path, loss = sum(enc(x) * up)."""
    xg = x.clone().requires_grad_(True)
    enc.table.grad = None
    y = enc(xg)
    assert "HashEncodeNumba" in type(y.grad_fn).__name__  # x.requires_grad: still the fast path
    (y * up).sum().backward()
    return xg.grad, enc.table.grad.clone()


def reference_grads(enc: HashEncoding, x: torch.Tensor, up: torch.Tensor, dtype=torch.float32):
    xr = x.to(dtype).clone().requires_grad_(True)
    table = enc.table.detach().to(dtype).requires_grad_(True)
    y = hash_encode_reference(xr, table, enc.offsets, enc.res)
    (y * up.to(dtype)).sum().backward()
    return xr.grad, table.grad


def assert_grads_close(g, g_ref, rtol=1e-4, atol=2e-5):
    """Elementwise within ``rtol``, or within ``atol`` times the largest reference component
    (sums of differences cancel; and against a float64 reference, the float32 rounding of x
    moves the gradient by about res^2 * 6e-8 relative on fine levels)."""
    g, g_ref = g.double().numpy(), g_ref.double().numpy()
    scale = np.abs(g_ref).max()
    assert scale > 1.0
    np.testing.assert_allclose(g, g_ref, rtol=rtol, atol=atol * scale)


def test_configs_cover_dense_and_hashed_levels():
    kinds = {name: level_kinds(HashEncoding(**cfg, seed=0)) for name, cfg in CONFIGS.items()}
    assert all(kinds["dense"]) and not any(kinds["hashed_f4"])
    assert any(kinds["mixed_f1"]) and not all(kinds["mixed_f1"])
    assert any(kinds["fine_f2"]) and not all(kinds["fine_f2"])


@pytest.mark.parametrize("name", list(CONFIGS))
def test_input_grad_matches_reference_autograd(name):
    enc = HashEncoding(**CONFIGS[name], seed=1, init_scale=1.0)
    x = smooth_points(2000, enc.res, seed=2)
    up = upstream(enc, len(x), seed=3)
    g, _ = numba_grads(enc, x, up)
    assert g.dtype == torch.float32 and g.shape == x.shape
    g32, _ = reference_grads(enc, x, up)
    g64, _ = reference_grads(enc, x, up, torch.float64)
    assert_grads_close(g, g32)
    assert_grads_close(g, g64)
    assert (g.abs().sum(-1) > 0).all()


def test_input_grad_outside_the_cube_is_zero_and_matches_on_the_boundary():
    """Coordinates outside [0, 1] are clamped: zero gradient, like the autograd of torch.clamp.
    Exactly on 0 or 1 the clamp is not active (torch.clamp passes the gradient at its bounds):
    the gradient is the one-sided derivative from inside the cube, in both paths."""
    enc = HashEncoding(**CONFIGS["mixed_f1"], seed=4, init_scale=1.0)
    x = smooth_points(1200, enc.res, seed=5)
    n = len(x)
    g = torch.Generator().manual_seed(6)
    which = torch.rand(n, 3, generator=g)
    far = torch.where(torch.rand(n, 3, generator=g) < 0.5, -torch.rand(n, 3, generator=g) * 2 - 1e-3,
                      1 + 1e-3 + torch.rand(n, 3, generator=g) * 2)
    x = torch.where(which < 0.25, far, x)                                # outside
    x = torch.where((which >= 0.25) & (which < 0.35), torch.zeros_like(x), x)  # exactly 0
    x = torch.where((which >= 0.35) & (which < 0.45), torch.ones_like(x), x)   # exactly 1
    x[:4] = torch.tensor([[float("inf"), 0.3, 0.7], [-float("inf"), 1.0, 0.0],
                          [1e30, -1e30, 0.5], [1.0 + 1e-7, -1e-8, 0.2]])
    outside = (x < 0) | (x > 1)
    assert outside.sum() > 500 and (x == 0).sum() > 200 and (x == 1).sum() > 200
    up = upstream(enc, n, seed=7)
    gx, _ = numba_grads(enc, x, up)
    assert torch.isfinite(gx).all()
    assert (gx[outside] == 0).all()
    assert (gx[~outside] != 0).all()
    g_ref, _ = reference_grads(enc, x, up)
    assert (g_ref[outside] == 0).all()
    assert_grads_close(gx, g_ref)
    assert_grads_close(gx, reference_grads(enc, x, up, torch.float64)[0])


def test_input_grad_on_cell_faces_takes_the_same_cell_as_the_reference():
    """On a face (or vertex) both paths differentiate inside the cell floor(x * res) picks."""
    enc = HashEncoding(**CONFIGS["dense"], seed=8, init_scale=1.0)
    r = enc.res.tolist()
    g = torch.Generator().manual_seed(9)
    x = smooth_points(600, enc.res, seed=10)
    k = torch.randint(0, 3, (len(x), 3), generator=g)
    lvl_res = torch.tensor(r, dtype=torch.float32)[torch.randint(0, len(r), (len(x), 3),
                                                                 generator=g)]
    on_face = torch.floor(x * lvl_res) / lvl_res  # a face of one level on this axis
    x = torch.where(k == 0, on_face, x)
    x[:50] = torch.floor(x[:50] * r[0]) / r[0]  # vertices of the coarsest level
    assert (~away_from_faces(x, enc.res, 0.0)).sum() > 300
    up = upstream(enc, len(x), seed=11)
    gx, _ = numba_grads(enc, x, up)
    g_ref, _ = reference_grads(enc, x, up)
    assert_grads_close(gx, g_ref)


@pytest.mark.parametrize("name", ["mixed_f1", "hashed_f4"])
def test_table_grad_unchanged_when_x_requires_grad(name):
    enc = HashEncoding(**CONFIGS[name], seed=12, init_scale=1.0)
    g = torch.Generator().manual_seed(13)
    x = torch.rand(1500, 3, generator=g) * 1.2 - 0.1
    up = upstream(enc, len(x), seed=14)
    enc.table.grad = None
    y = enc(x)
    (y * up).sum().backward()
    g_plain = enc.table.grad.clone()
    _, g_with_x = numba_grads(enc, x, up)
    torch.testing.assert_close(g_with_x, g_plain, rtol=0, atol=0)
    torch.testing.assert_close(enc(x.clone().requires_grad_(True)).detach(), y.detach(),
                               rtol=0, atol=0)
    _, g_ref = reference_grads(enc, x, up, torch.float64)
    np.testing.assert_allclose(g_plain.double().numpy(), g_ref.numpy(), rtol=1e-5,
                               atol=1e-5 * float(g_ref.abs().max()))


def test_first_order_backward_runs_the_kernel_not_the_twin(monkeypatch):
    import nerfbot.ops.encodings as encodings

    calls = []
    kernel = hk.hash_backward_input
    monkeypatch.setattr(encodings._hk, "hash_backward_input",
                        lambda *a: calls.append(1) or kernel(*a))
    monkeypatch.setattr(encodings, "hash_encode_reference",
                        lambda *a: pytest.fail("the twin ran in a first-order backward pass"))
    enc = HashEncoding(**CONFIGS["dense"], seed=30, init_scale=1.0)
    x = smooth_points(100, enc.res, seed=31)
    numba_grads(enc, x, upstream(enc, len(x), seed=32))
    assert calls == [1]


def test_only_the_requested_gradients_are_computed():
    enc = HashEncoding(**CONFIGS["mixed_f1"], seed=15, init_scale=1.0)
    x = smooth_points(300, enc.res, seed=16)
    up = upstream(enc, len(x), seed=17)
    enc.table.requires_grad_(False)  # frozen field, e.g. inverse rendering of poses or joints
    try:
        xg = x.clone().requires_grad_(True)
        y = enc(xg)
        assert "HashEncodeNumba" in type(y.grad_fn).__name__
        (gx,) = torch.autograd.grad((y * up).sum(), xg)
    finally:
        enc.table.requires_grad_(True)
    assert_grads_close(gx, reference_grads(enc, x, up)[0])
    assert enc.table.grad is None


def test_input_grad_matches_finite_differences():
    """Central differences of the float32 numba forward pass. Inside a cell the interpolation is
    linear along each axis, so the difference quotient is exact up to rounding."""
    enc = HashEncoding(**CONFIGS["mixed_f1"], seed=18, init_scale=1.0)
    eps = 1e-4  # at most 0.0096 cells on the finest level (96): stays inside the cell
    x = smooth_points(400, enc.res, seed=19, margin=0.02)
    up = upstream(enc, len(x), seed=20)
    gx, _ = numba_grads(enc, x, up)
    fd = torch.empty(x.shape, dtype=torch.float64)
    with torch.no_grad():
        for a in range(3):
            xp, xm = x.clone(), x.clone()
            xp[:, a] += eps
            xm[:, a] -= eps
            lp = (enc(xp) * up).double().sum(-1)
            lm = (enc(xm) * up).double().sum(-1)
            fd[:, a] = (lp - lm) / (xp[:, a].double() - xm[:, a].double())
    scale = float(fd.abs().max())
    np.testing.assert_allclose(gx.double().numpy(), fd.numpy(), rtol=1e-2, atol=1e-3 * scale)


def test_kernel_is_deterministic_across_thread_counts():
    enc = HashEncoding(**CONFIGS["fine_f2"], seed=21, init_scale=1.0)
    x = torch.rand(999, 3, generator=torch.Generator().manual_seed(22))
    grad_out = np.random.default_rng(23).standard_normal(
        (enc.n_levels, len(x), enc.n_features)).astype(np.float32)
    table = enc.table.detach().numpy()
    outs = []
    for n_threads in (1, 3, 4096):
        gx = np.full((len(x), 3), np.nan, np.float32)  # overwritten, not accumulated
        hk.hash_backward_input(x.numpy(), table, grad_out, enc._offsets_np, enc._res_np, gx,
                               n_threads)
        outs.append(gx)
    assert np.isfinite(outs[0]).all()
    np.testing.assert_array_equal(outs[0], outs[1])
    np.testing.assert_array_equal(outs[0], outs[2])


def test_second_order_gradient_goes_through_the_twin():
    """The kernels are not themselves differentiable: when the position gradient is to be
    differentiated again (create_graph=True, e.g. an Eikonal or normal loss), the backward pass
    rebuilds it with the twin, so second-order gradients equal the torch backend's."""
    kw = dict(seed=24, init_scale=1.0)
    enc, enc_t = HashEncoding(**CONFIGS["mixed_f1"], **kw), \
        HashEncoding(**CONFIGS["mixed_f1"], **kw, backend="torch")
    x0 = smooth_points(200, enc.res, seed=25)
    up = upstream(enc, len(x0), seed=26)
    results = []
    for e in (enc, enc_t):
        x = x0.clone().requires_grad_(True)
        (gx,) = torch.autograd.grad((e(x) * up).sum(), x, create_graph=True)
        assert gx.requires_grad
        (gx.square().sum() + (gx * x).sum()).backward()
        results.append((gx.detach(), x.grad, e.table.grad))
    (gx, gxx, gt), (gx_t, gxx_t, gt_t) = results
    assert float(gt.abs().max()) > 0
    torch.testing.assert_close(gx, gx_t, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(gxx, gxx_t, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(gt, gt_t, rtol=1e-6, atol=1e-6)


def test_fallbacks_kept_for_nan_and_other_dtypes():
    enc = HashEncoding(**CONFIGS["dense"], seed=26, init_scale=1.0)
    x = smooth_points(50, enc.res, seed=27)
    x_nan = x.clone()
    x_nan[3, 1] = float("nan")
    y = enc(x_nan.requires_grad_(True))
    assert "HashEncodeNumba" not in type(y.grad_fn).__name__
    y64 = enc(x.double().requires_grad_(True))
    assert "HashEncodeNumba" not in type(y64.grad_fn).__name__
