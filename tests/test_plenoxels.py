"""Plenoxels: dense-grid kernels against their torch twins, SH colour against float64, coarse-to-
fine upsampling, pruning, checkpoints and training on the tiny capture."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.fields.plenoxels import PlenoxelField, PlenoxelFieldConfig
from nerfbot.kernels import densegrid as dg
from nerfbot.methods import build_model
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer

AABB = [[-0.6, -0.4, 0.0], [0.6, 0.4, 0.9]]
# small batches keep a step cheap on 32x32 images
TINY = {"samples_per_batch": 8192, "grid_update_every": 8, "resolutions": [32, 64],
        "upsample_at": [0.7]}


def _unit_directions(n: int, gen: torch.Generator, dtype=torch.float32) -> torch.Tensor:
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=dtype), dim=-1)


def _sparse_links(shape, gen: torch.Generator, keep: float = 0.7) -> torch.Tensor:
    """Links of a grid with about ``1 - keep`` of its vertices pruned, rows in C order."""
    mask = torch.rand(shape, generator=gen) < keep
    links = torch.full(shape, -1, dtype=torch.int32)
    links[mask] = torch.arange(int(mask.sum()), dtype=torch.int32)
    return links


def _box_points(n: int, gen: torch.Generator) -> torch.Tensor:
    """Random box coordinates, with the faces, edges and corners of the box among them."""
    u = torch.rand(n, 3, generator=gen)
    u[:8] = torch.tensor([[c & 1, (c >> 1) & 1, c >> 2] for c in range(8)], dtype=torch.float32)
    u[8:16, 0] = 1.0
    u[16:24, 2] = 0.0
    return u


# ----------------------------------------------------------------------------------- kernels

def test_stencil_gather_and_scatter_match_the_torch_twins():
    """Corner rows and weights, interpolated values and the table gradient of the numba kernels
    equal the plain-torch twins' (autograd) on a grid with pruned vertices."""
    gen = torch.Generator().manual_seed(0)
    links = _sparse_links((7, 5, 6), gen, keep=0.4)
    n_rows = int((links >= 0).sum())
    u = _box_points(3000, gen)
    rows, weights, coverage = dg.stencil(u, links)
    rows_ref, weights_ref, coverage_ref = dg.stencil_reference(u, links)
    assert torch.equal(rows.long(), rows_ref)
    torch.testing.assert_close(weights, weights_ref, atol=1e-6, rtol=0)
    torch.testing.assert_close(coverage, coverage_ref, atol=1e-6, rtol=0)
    # pruned corners weigh nothing, the stored ones are renormalised; coverage is their share
    assert bool((weights >= 0).all())
    some = coverage > 0
    torch.testing.assert_close(weights[some].sum(1), torch.ones(int(some.sum())), atol=1e-6, rtol=0)
    assert bool((weights[~some] == 0).all()) and not bool(some.all())
    assert bool(((coverage > 0.01) & (coverage < 0.99)).any())

    for channels in (1, 28):
        table = torch.randn(n_rows, channels, generator=gen)
        grad_out = torch.randn(u.shape[0], channels, generator=gen)
        t_fast = table.clone().requires_grad_()
        out = dg.gather(t_fast, rows, weights)
        out.backward(grad_out)
        t_ref = table.clone().requires_grad_()
        ref = dg.gather_reference(t_ref, rows_ref, weights_ref)
        ref.backward(grad_out)
        torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(t_fast.grad, t_ref.grad, atol=1e-4, rtol=1e-5)


def test_total_variation_kernels_match_the_torch_twin():
    gen = torch.Generator().manual_seed(4)
    for channels in (1, 27):
        table = torch.randn(300, channels, generator=gen)
        pairs = torch.randint(300, (2, 1000), generator=gen)
        t_fast = table.clone().requires_grad_()
        t_ref = table.clone().requires_grad_()
        fast, ref = dg.TVFunction.apply(t_fast, pairs), dg.tv_reference(t_ref, pairs)
        (3.0 * fast).backward()
        (3.0 * ref).backward()
        torch.testing.assert_close(fast, ref, atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(t_fast.grad, t_ref.grad, atol=1e-7, rtol=1e-5)


def test_stencil_weights_sum_to_one_without_pruning_and_clamp_outside():
    gen = torch.Generator().manual_seed(1)
    links = torch.arange(4 * 3 * 5, dtype=torch.int32).reshape(4, 3, 5)
    u = _box_points(500, gen)
    _, weights, coverage = dg.stencil(u, links)
    torch.testing.assert_close(weights.sum(1), torch.ones(500), atol=1e-6, rtol=0)
    torch.testing.assert_close(coverage, torch.ones(500), atol=1e-6, rtol=0)
    # points outside the box (and NaN) read the border, never out of bounds
    far = torch.tensor([[-3.0, 0.5, 0.5], [4.0, 9.0, -1.0], [float("nan"), 0.5, 0.5]])
    rows, weights, _ = dg.stencil(far, links)
    assert bool((rows >= 0).all() and (rows < links.numel()).all())
    torch.testing.assert_close(weights.sum(1), torch.ones(3), atol=1e-6, rtol=0)


def _sh_float64(d: np.ndarray) -> np.ndarray:
    """Real orthonormal SH, degrees 0..2, from their closed forms (float64): (N, 9).

    Signs as in PlenOctrees / svox2 (the -1 factors on odd-m terms)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    pi = math.pi
    return np.stack([
        np.full_like(x, 0.5 / math.sqrt(pi)),
        -math.sqrt(3 / (4 * pi)) * y, math.sqrt(3 / (4 * pi)) * z, -math.sqrt(3 / (4 * pi)) * x,
        0.5 * math.sqrt(15 / pi) * x * y, -0.5 * math.sqrt(15 / pi) * y * z,
        0.25 * math.sqrt(5 / pi) * (3 * z * z - 1), -0.5 * math.sqrt(15 / pi) * x * z,
        0.25 * math.sqrt(15 / pi) * (x * x - y * y)], -1)


def test_sh_basis_is_orthonormal_in_float64():
    """The closed forms the colour is checked against are the orthonormal basis: their Gram
    matrix over the sphere (Fibonacci quadrature) is the identity."""
    n = 200_000
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    y = _sh_float64(d)
    gram = y.T @ y * (4 * math.pi / n)
    np.testing.assert_allclose(gram, np.eye(9), atol=1e-4)


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_sh_colour_matches_float64_reference(degree):
    """The field's colour (numba kernel, float32) equals sigmoid(sum_k c_k Y_k(d)) evaluated in
    float64 from the closed forms, values and coefficient gradients; so does the torch twin."""
    gen = torch.Generator().manual_seed(degree)
    k = (degree + 1) ** 2
    n = 4000
    d = _unit_directions(n, gen, torch.float64)
    coeffs = torch.randn(n, 3 * k, generator=gen, dtype=torch.float64)
    grad_out = torch.randn(n, 3, generator=gen, dtype=torch.float64)

    basis = torch.from_numpy(_sh_float64(d.numpy())[:, :k])
    c64 = coeffs.clone().requires_grad_()
    ref = torch.sigmoid((c64.reshape(n, 3, k) * basis[:, None, :]).sum(-1))
    ref.backward(grad_out)

    field = PlenoxelField(AABB, PlenoxelFieldConfig(sh_degree=degree))
    for backend in ("numba", "torch"):
        field.config.backend = backend
        c32 = coeffs.float().requires_grad_()
        rgb = field.color(c32, d.float())
        rgb.backward(grad_out.float())
        np.testing.assert_allclose(rgb.detach().numpy(), ref.detach().numpy(), atol=2e-6)
        np.testing.assert_allclose(c32.grad.numpy(), c64.grad.numpy(), atol=2e-6)


# ------------------------------------------------------------------------- upsampling, pruning

def _field(resolutions=(8, 16), **kw) -> PlenoxelField:
    cfg = PlenoxelFieldConfig(resolutions=resolutions, upsample_at=(0.5,) * (len(resolutions) - 1),
                              **kw)
    return PlenoxelField(AABB, cfg, seed=0)


def _world_points(n: int, gen: torch.Generator) -> torch.Tensor:
    lo, hi = torch.tensor(AABB[0]), torch.tensor(AABB[1])
    return lo + torch.rand(n, 3, generator=gen) * (hi - lo)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_upsampling_keeps_the_function(backend):
    """Doubling the resolution keeps density and colour at random points (a trilinear function
    is trilinear on every sub-cell); the grid has 2x the cells per axis."""
    gen = torch.Generator().manual_seed(2)
    field = _field(prune_opacity=0.0, backend=backend)
    with torch.no_grad():
        field.density_data.copy_(torch.randn(field.density_data.shape, generator=gen))
        field.sh_data.copy_(torch.randn(field.sh_data.shape, generator=gen))
    x = _world_points(5000, gen)
    d = _unit_directions(5000, gen)
    with torch.no_grad():
        sigma0, rgb0 = field(x, d)
        cells = field.cells
        out = field.before_step(step=10, progress=0.6)
        sigma1, rgb1 = field(x, d)
    assert out == {"params_changed": True, "kept": 1.0}
    assert field.cells == tuple(2 * c for c in cells) and max(field.cells) == 16
    torch.testing.assert_close(sigma1, sigma0, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(rgb1, rgb0, rtol=1e-4, atol=1e-5)
    assert field.before_step(step=11, progress=0.9) == {}   # the last stage stays


def _ball_field(**kw) -> PlenoxelField:
    """A 32-cell field whose density is high (e^5 /m) inside a ball of radius 0.12 m around
    (0, 0, 0.3) and ~0 elsewhere (exp activation: log-density -10)."""
    field = _field(resolutions=(32, 64), **kw)
    shape = field.links.shape
    axes = [torch.linspace(float(field.lo[a]), float(field.lo[a] + field.extent[a]), shape[a])
            for a in range(3)]
    pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = (pts - torch.tensor([0.0, 0.0, 0.3])).norm(dim=-1) < 0.12
    with torch.no_grad():
        field.density_data.copy_(torch.where(inside, 5.0, -10.0)[:, None])
    return field


def test_pruning_masks_empty_voxels_and_keeps_them_empty():
    """Upsampling prunes the vertices far from the dense ball: they have no storage (the mask
    buffer is False), read zero density, and stay at zero through optimisation steps that push
    density up everywhere; the vertices in the ball are kept."""
    field = _ball_field(prune_opacity=0.01, prune_dilation=1, prune_min_step=0)
    n_before = field.density_data.shape[0]
    out = field.before_step(step=5, progress=0.5)
    kept = out["kept"]
    mask = field.mask
    assert 0.0 < kept < 0.1 and kept == pytest.approx(float(mask.float().mean()))
    assert field.density_data.shape[0] == int(mask.sum()) < n_before
    assert "links" in dict(field.named_buffers())

    gen = torch.Generator().manual_seed(3)
    x = _world_points(20000, gen)
    # every corner of a coarse cell within 5 cm of the centre is in the ball; the dense region
    # reaches at most a coarse cell diagonal (6.5 cm) beyond it, plus one fine cell of dilation
    r = (x - torch.tensor([0.0, 0.0, 0.3])).norm(dim=-1)
    near_ball, far = r < 0.05, r > 0.3
    with torch.no_grad():
        assert bool((field.density(x[far])[0] == 0).all())
        assert bool((field.density(x[near_ball])[0] > 10).all())

    opt = torch.optim.Adam([{"params": g["params"]} for g in field.param_groups()], lr=0.5)
    for _ in range(3):
        opt.zero_grad()
        sigma, feat = field.density(x)
        (-(sigma.clamp_max(1e3).mean()) + feat.square().mean()).backward()
        opt.step()
    with torch.no_grad():
        assert bool((field.density(x[far])[0] == 0).all())
        assert bool((field.density(x[near_ball])[0] > 10).all())

    # upsampling a pruned grid without pruning: vertices in pruned space store ~zero density
    # (not the activation of a zero raw value, exp(0) = 1 /m)
    field.upsample(128, prune=False)
    assert field.kept_fraction == 1.0
    with torch.no_grad():
        assert bool((field.density(x[far])[0] < 1e-3).all())
        assert bool((field.density(x[near_ball])[0] > 10).all())


def test_pruning_never_empties_the_grid():
    field = _field(prune_opacity=0.5)
    with torch.no_grad():
        field.density_data.fill_(-20.0)
    assert field.upsample(16) == 1.0


def test_total_variation_is_zero_on_a_constant_grid_and_skips_pruned_neighbours():
    field = _ball_field(prune_opacity=0.01, prune_dilation=1, tv_samples=4096)
    field.upsample(64)
    with torch.no_grad():
        field.density_data.fill_(2.0)
        field.sh_data.fill_(-1.0)
    assert float(field.regularizer()) == 0.0       # pruned neighbours (zero) are not compared
    with torch.no_grad():
        field.sh_data.normal_()
    reg = field.regularizer()
    assert float(reg) > 0.0
    reg.backward()
    assert field.sh_data.grad.abs().sum() > 0 and torch.isfinite(field.sh_data.grad).all()
    assert _field(tv_density_weight=0.0, tv_sh_weight=0.0).regularizer() is None


def test_bad_options_are_value_errors():
    for kw in ({"resolutions": (64, 32), "upsample_at": (0.5,)},
               {"resolutions": (32, 64), "upsample_at": ()},
               {"resolutions": (32, 64), "upsample_at": (1.5,)},
               {"sh_degree": 3}, {"density_activation": "tanh"}, {"backend": "cuda"},
               {"initial_transmittance": 1.0}, {"tv_sh_weight": -1.0},
               {"resolutions": "a,b"}):
        with pytest.raises(ValueError):
            PlenoxelField(AABB, PlenoxelFieldConfig(**kw))
    # command-line spellings of the schedule
    model = build_model("plenoxels", AABB, options={"resolutions": "16,32", "upsample_at": 0.4})
    assert model.field.resolutions == (16, 32) and model.field.upsample_at == (0.4,)


@pytest.mark.parametrize("activation", ["exp", "relu", "softplus"])
def test_initial_density_matches_initial_transmittance(activation):
    field = _field(density_activation=activation, initial_transmittance=0.2)
    diagonal = math.sqrt(3.0) * 1.2
    sigma = field.density(_world_points(100, torch.Generator().manual_seed(0)))[0]
    torch.testing.assert_close(sigma, torch.full((100,), -math.log(0.2) / diagonal),
                               rtol=1e-5, atol=0)


# ---------------------------------------------------------------------------------- training

def test_plenoxels_trains_tiny_capture_and_reloads_after_upsampling(tiny_capture, tmp_path):
    """plenoxels on 16 views of 32x32 reaches >= 20 dB test PSNR in 150 steps, through one
    upsampling (32 -> 64 cells, at step 105) with pruning; the run folder reloads to the same
    renders.

    Measured here: 24.8 dB, 57 % of the vertices kept (ngp: ~23.5 dB in 120 steps); the
    trivial mean-colour predictor scores ~11 dB, so 20 dB needs the scene learned; the margin
    absorbs platform variation."""
    ds = load_dataset(tiny_capture[0])
    cfg = TrainConfig(method="plenoxels", max_steps=150, seed=0, progress=False, options=TINY)
    trainer = Trainer(ds, tmp_path / "run", cfg)
    trainer.train()
    field = trainer.model.field
    assert max(field.cells) == 64 and field.kept_fraction < 0.8
    metrics = evaluate(trainer.model, ds, "test")
    assert metrics["psnr"] >= 20.0, metrics
    assert metrics["depth_mae_m"] is not None and metrics["depth_mae_m"] < 0.15, metrics
    model, info = load_model(tmp_path / "run")
    assert info["step"] == 150 and model.field.cells == field.cells
    assert torch.equal(model.field.links, field.links)
    again = evaluate(model, ds, "test", with_ssim=False)
    assert again["psnr"] == pytest.approx(metrics["psnr"], abs=1e-4)


def test_resume_after_upsampling_is_exact(tiny_capture, tmp_path):
    """A run stopped after its upsampling and resumed from the checkpoint (grid and optimiser
    state of the upsampled size) ends bit-identical to an uninterrupted run."""
    ds = load_dataset(tiny_capture[0])
    opts = dict(TINY, samples_per_batch=4096, upsample_at=[0.5], prune_min_step=0,
                prune_opacity=0.003)  # keeps where density grew (initial alpha: 0.002)
    cfg = TrainConfig(method="plenoxels", max_steps=12, seed=1, progress=False, options=opts)
    straight = Trainer(ds, tmp_path / "straight", cfg)
    straight.train()

    def interrupt(trainer):
        if trainer.step == 8:
            raise KeyboardInterrupt

    first = Trainer(ds, tmp_path / "resumed", cfg)
    with pytest.raises(KeyboardInterrupt):
        first.train(on_step=interrupt)
    assert max(first.model.field.cells) == 64 and first.model.field.kept_fraction < 1.0
    second = Trainer(ds, tmp_path / "resumed", cfg)
    assert max(second.model.field.cells) == 32
    assert second.load() and second.step == 8 and max(second.model.field.cells) == 64
    second.train()
    a, b = straight.model.state_dict(), second.model.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), f"{k} differs after resume"
