"""Losses against brute-force references."""

from __future__ import annotations

import math

import pytest
import torch

from nerfbot.ops.losses import OPACITY_EPS, distortion_loss, opacity_entropy_loss


def _brute_force(weights, t0, t1, ray_indices, n_rays, scale):
    total = 0.0
    for r in range(n_rays):
        sel = ray_indices == r
        w, s0, s1 = weights[sel].double(), t0[sel].double() / scale, t1[sel].double() / scale
        m = 0.5 * (s0 + s1)
        total += (w[:, None] * w[None, :] * (m[:, None] - m[None, :]).abs()).sum()
        total += (w ** 2 * (s1 - s0)).sum() / 3.0
    return total / n_rays


def _packed(seed, n_rays=7, max_len=9):
    """Random packed samples: weights and disjoint sorted intervals, ray 0 empty."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, max_len, (n_rays,), generator=g)
    counts[0] = 0  # an empty ray
    ray_idx = torch.arange(n_rays).repeat_interleave(counts)
    # disjoint intervals sorted along each ray, as the samplers produce them
    t0s, t1s = [], []
    for c in counts:
        gaps = torch.rand(int(c), generator=g) * 0.1 + 0.01
        start = 1.0 + torch.cumsum(gaps, 0) - gaps
        t0s.append(start)
        t1s.append(start + gaps * (0.2 + 0.8 * torch.rand(int(c), generator=g)))
    t0, t1 = torch.cat(t0s), torch.cat(t1s)
    w = torch.rand(t0.shape, generator=g, dtype=torch.float64) * 0.3
    return w, t0.double(), t1.double(), ray_idx, n_rays


def test_distortion_matches_quadratic_form():
    for seed in range(4):
        w, t0, t1, idx, n = _packed(seed)
        fast = distortion_loss(w, t0, t1, idx, n, scale=2.0)
        assert torch.allclose(fast, _brute_force(w, t0, t1, idx, n, 2.0), rtol=1e-10, atol=1e-14)


def test_distortion_prefers_a_surface_to_fog():
    """The same total weight on one short interval costs less than spread along the ray."""
    n = 32
    t0 = torch.linspace(1.0, 2.0, n + 1)[:-1].double()
    t1 = t0 + 1.0 / n
    idx = torch.zeros(n, dtype=torch.long)
    fog = torch.full((n,), 0.8 / n, dtype=torch.float64)
    surface = torch.zeros(n, dtype=torch.float64)
    surface[10] = 0.8
    assert distortion_loss(surface, t0, t1, idx, 1, 1.0) < 0.2 * distortion_loss(fog, t0, t1, idx, 1, 1.0)
    empty = torch.zeros(0, dtype=torch.float64)
    assert distortion_loss(empty, empty, empty, torch.zeros(0, dtype=torch.long), 3, 1.0) == 0


def test_distortion_gradcheck():
    w, t0, t1, idx, n = _packed(7, n_rays=4, max_len=5)
    w.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: distortion_loss(x, t0, t1, idx, n, 1.5), (w,))


def test_opacity_entropy_is_zero_at_empty_and_opaque_rays_and_largest_halfway():
    a = torch.tensor([0.0, 1.0, 0.5, 0.9], dtype=torch.float64)
    each = [float(opacity_entropy_loss(a[i:i + 1])) for i in range(4)]
    assert each[0] < 2e-3 and each[1] < 2e-3
    assert each[2] == pytest.approx(math.log(2.0), rel=1e-12)
    p = 0.9
    assert each[3] == pytest.approx(-(p * math.log(p) + (1 - p) * math.log(1 - p)), rel=1e-12)
    assert float(opacity_entropy_loss(a)) == pytest.approx(sum(each) / 4, rel=1e-12)
    assert opacity_entropy_loss(torch.zeros(0)) == 0


def test_opacity_entropy_pushes_rays_away_from_halfway_with_finite_gradients():
    a = torch.tensor([0.0, 0.3, 0.7, 1.0], dtype=torch.float32, requires_grad=True)
    opacity_entropy_loss(a).backward()
    g = a.grad
    assert torch.isfinite(g).all()
    # descent lowers a ray below 1/2 and raises one above it
    assert g[1] > 0 and g[2] < 0
    assert g.abs().max() <= math.log((1 - OPACITY_EPS) / OPACITY_EPS) / 4 + 1e-4
    b = torch.tensor([0.2, 0.45, 0.8], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(opacity_entropy_loss, (b,))


def test_occupancy_models_add_the_weighted_opacity_entropy_to_their_loss():
    from nerfbot.methods import build_model
    from nerfbot.ops.cameras import Rays

    g = torch.Generator().manual_seed(3)
    n = 256
    origins = torch.tensor([0.0, 0.0, 3.0]).expand(n, 3).clone()
    d = torch.nn.functional.normalize(
        torch.cat([torch.rand(n, 2, generator=g) * 0.6 - 0.3, -torch.ones(n, 1)], 1), dim=1)
    rays, target = Rays(origins, d, torch.ones(n)), torch.rand(n, 3, generator=g)
    losses = {}
    for w in (0.0, 0.5):
        torch.manual_seed(0)
        model = build_model("ngp", [[-1, -1, -1], [1, 1, 1]], options={
            "log2_hashmap_size": 12, "opacity_entropy_weight": w, "density_noise": 0.0,
            "carving_weight": 0.0, "supersample": 1})
        model.train()
        losses[w], out = model.loss(rays, target, torch.Generator().manual_seed(1))
        assert 0.05 < float(out.opacity.detach().mean()) < 0.95   # translucent at the start
    expected = losses[0.0] + 0.5 * opacity_entropy_loss(out.opacity)
    torch.testing.assert_close(losses[0.5], expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="opacity_entropy_weight"):
        build_model("ngp", [[-1, -1, -1], [1, 1, 1]], options={"opacity_entropy_weight": -1.0})
