"""TensoRF: VM kernels against their torch twin, coarse-to-fine upsampling, the L1 regulariser,
training on the tiny capture and reloading an upsampled run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.fields.tensorf import TensoRFField, TensoRFFieldConfig, VMGrid, vm_reference
from nerfbot.kernels import vm as vk
from nerfbot.methods import build_model
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer

AABB = [[-0.6, -0.4, 0.0], [0.6, 0.4, 0.9]]


def _points(n: int, seed: int) -> torch.Tensor:
    """Random points in [0, 1]^3 plus the awkward ones: faces, vertices, outside the box."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g)
    special = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.25, 0.75],
                            [-0.3, 1.4, 0.5], [1.0, 0.0, 0.5], [0.125, 0.2, 1.0 / 6.0]])
    return torch.cat([x, special])


def _smooth_(grid: VMGrid) -> None:
    """Fill a VM grid with smooth functions of the vertex positions (a well-resolved field)."""
    with torch.no_grad():
        for m, (p, line) in enumerate(zip(grid.planes, grid.lines)):
            nb, na, ch = p.shape
            v = torch.linspace(0, 1, nb)[:, None, None]
            u = torch.linspace(0, 1, na)[None, :, None]
            k = torch.arange(ch, dtype=torch.float32)
            p.copy_(torch.cos(2.0 * u + (m + 1) * v + 0.3 * k) + 0.5)
            w = torch.linspace(0, 1, line.shape[0])[:, None]
            line.copy_(torch.sin(1.5 * w + 0.7 * k + m) + 1.2)


def test_vm_kernels_match_reference_values_and_gradients():
    grid = VMGrid((9, 6, 7), 5, generator=torch.Generator().manual_seed(0))
    x = _points(500, 1)
    fast = grid(x)
    ref = vm_reference(x, grid.planes, grid.lines)
    assert fast.shape == (x.shape[0], 3, 5)
    torch.testing.assert_close(fast, ref, atol=1e-6, rtol=1e-5)
    w = torch.randn(fast.shape, generator=torch.Generator().manual_seed(2))
    params = list(grid.parameters())
    g_fast = torch.autograd.grad((fast * w).sum(), params)
    g_ref = torch.autograd.grad((ref * w).sum(), params)
    for a, b in zip(g_fast, g_ref):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    # the channel blocks of the backward kernel partition the work: same sums for any count
    arrays = [p.detach().numpy() for p in params]
    xs = x.clamp(0, 1).numpy()
    grads = []
    for n_blocks in (1, 2, 5):
        out = [np.zeros_like(a) for a in arrays]
        vk.vm_backward(xs, *arrays, w.numpy(), *out, n_blocks)
        grads.append(out)
    for other in grads[1:]:
        for a, b in zip(grads[0], other):
            np.testing.assert_array_equal(a, b)


def test_vm_grid_position_gradient_uses_the_twin():
    grid = VMGrid((5, 4, 6), 3, generator=torch.Generator().manual_seed(0))
    x = torch.rand(64, 3, generator=torch.Generator().manual_seed(1)).requires_grad_(True)
    (gx,) = torch.autograd.grad(grid(x).sum(), x)
    x2 = x.detach().clone().requires_grad_(True)
    (gx2,) = torch.autograd.grad(vm_reference(x2, grid.planes, grid.lines).sum(), x2)
    torch.testing.assert_close(gx, gx2)
    assert torch.isfinite(gx).all() and gx.abs().sum() > 0


def test_resample_exact_on_nested_grids_and_close_on_others():
    grid = VMGrid((9, 6, 7), 4, generator=torch.Generator().manual_seed(0))
    x = _points(2000, 3)
    before = grid(x).detach()
    grid.resample((17, 11, 13))         # every old vertex is a new vertex: same function
    assert grid.vertices == (17, 11, 13)
    assert grid.planes[0].shape == (11, 17, 4) and grid.lines[0].shape == (13, 4)
    torch.testing.assert_close(grid(x).detach(), before, atol=1e-5, rtol=1e-5)

    smooth = VMGrid((12, 9, 10), 4)
    _smooth_(smooth)
    before = smooth(x).detach()
    smooth.resample((31, 20, 23))        # not nested: interpolation error of a smooth field only
    err = (smooth(x).detach() - before).abs().max()
    assert err < 0.02 * before.abs().max(), float(err)


def test_field_upsamples_on_schedule_and_keeps_its_values():
    cfg = TensoRFFieldConfig(init_res=10, final_res=40, upsample_at=(0.25, 0.5))
    field = TensoRFField(AABB, cfg)
    assert field.cells_schedule() == [10, 20, 40]
    # about cubic cells: 10 x 6.67 x 7.5 cells over the 1.2 x 0.8 x 0.9 m bounds
    n = field.density_vm.vertices
    assert n[0] == 11 and abs(n[1] - 7.67) <= 0.5 and abs(n[2] - 8.5) <= 0.5
    _smooth_(field.density_vm)
    _smooth_(field.app_vm)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(3000, 3, generator=g) * torch.tensor([1.2, 0.8, 0.9]) + torch.tensor(AABB[0])
    d = torch.nn.functional.normalize(torch.randn(3000, 3, generator=g), dim=-1)
    with torch.no_grad():
        sigma0, feat0 = field.density(x)
        rgb0 = field.color(feat0, d)

    assert field.before_step(0, 0.0) == {}
    assert field.before_step(5, 0.3) == {"params_changed": True}
    assert field.density_vm.vertices == field.vertices_for(20) == field.app_vm.vertices
    assert field.before_step(6, 0.4) == {}
    assert field.before_step(9, 0.9) == {"params_changed": True}
    assert field.density_vm.vertices == field.vertices_for(40)
    with torch.no_grad():
        sigma1, feat1 = field.density(x)
        rgb1 = field.color(feat1, d)
    assert float((sigma1 - sigma0).abs().max()) < 0.02 * float(sigma0.max())
    assert float((rgb1 - rgb0).abs().max()) < 0.02


def test_l1_regularizer_is_weighted_mean_abs_of_density_components():
    field = TensoRFField(AABB, TensoRFFieldConfig(init_res=8, l1_weight=1e-3))
    reg = field.regularizer()
    expected = 1e-3 * sum(p.abs().mean() + li.abs().mean()
                          for p, li in zip(field.density_vm.planes, field.density_vm.lines))
    torch.testing.assert_close(reg, expected)
    reg.backward()
    plane = field.density_vm.planes[0]
    torch.testing.assert_close(plane.grad, 1e-3 * plane.detach().sign() / plane.numel())
    assert all(p.grad is None for p in field.app_vm.parameters())

    with_tv = TensoRFField(AABB, TensoRFFieldConfig(init_res=8, l1_weight=1e-3,
                                                    tv_weight_density=0.5, tv_weight_app=0.25))
    p = with_tv.density_vm.planes[1]
    tv_one = (p[1:] - p[:-1]).square().mean() + (p[:, 1:] - p[:, :-1]).square().mean()
    assert with_tv.density_vm.tv() >= tv_one > 0
    torch.testing.assert_close(
        with_tv.regularizer(),
        1e-3 * with_tv.density_vm.l1() + 0.5 * with_tv.density_vm.tv() + 0.25 * with_tv.app_vm.tv())
    assert TensoRFField(AABB, TensoRFFieldConfig(init_res=8, l1_weight=0.0)).regularizer() is None


@pytest.mark.parametrize("shading", ["mlp", "sh"])
def test_field_outputs_and_mean_colour_start(shading):
    field = TensoRFField(AABB, TensoRFFieldConfig(init_res=8, shading=shading))
    rgb = torch.tensor([0.2, 0.5, 0.7])
    field.init_mean_color(rgb)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(500, 3, generator=g) * 2.0 - 0.5        # partly outside the bounds
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=g), dim=-1)
    sigma, feat = field.density(x)
    out = field.color(feat, d)
    inside = ((x >= torch.tensor(AABB[0])) & (x <= torch.tensor(AABB[1]))).all(-1)
    assert sigma.shape == (500,) and out.shape == (500, 3)
    assert (sigma[~inside] == 0).all() and (sigma[inside] > 0).all()
    assert ((out >= 0) & (out <= 1)).all()
    assert float((out - rgb).abs().max()) < 0.1
    # the initial density lets a ray across the cube keep about initial_transmittance
    diagonal = math.sqrt(3.0) * 1.2
    trans = math.exp(-float(sigma[inside].mean()) * diagonal)
    assert trans == pytest.approx(0.2, abs=0.05)


def test_start_along_the_training_rays(tiny_capture, tmp_path):
    """With ``initial_transmittance_path="rays"`` a ray of the training rays' median path keeps
    ``initial_transmittance``; the trainer measures that path; calling again does not move the
    start, and a field set along the diagonal is left alone."""
    g = torch.Generator().manual_seed(1)
    lo, hi = torch.tensor(AABB[0]), torch.tensor(AABB[1])
    x = lo + torch.rand(4000, 3, generator=g) * (hi - lo)

    def transmittance(field, path_m):
        with torch.no_grad():
            return math.exp(-float(field.density(x)[0].mean()) * path_m)

    rays = TensoRFField(AABB, TensoRFFieldConfig(init_res=8, initial_transmittance=0.6,
                                                 initial_transmittance_path="rays"))
    diagonal = TensoRFField(AABB, TensoRFFieldConfig(init_res=8, initial_transmittance=0.6))
    for field in (rays, diagonal):
        field.init_ray_length(0.1)
        field.init_ray_length(0.1)
    assert transmittance(rays, 0.1) == pytest.approx(0.6, abs=0.05)
    assert transmittance(diagonal, math.sqrt(3.0) * 1.2) == pytest.approx(0.6, abs=0.05)
    assert transmittance(diagonal, 0.1) > 0.95
    with pytest.raises(ValueError, match="ray length"):
        rays.init_ray_length(-1.0)

    ds = load_dataset(tiny_capture[0])
    trainer = Trainer(ds, tmp_path / "run", TrainConfig(
        method="tensorf", max_steps=1, seed=0, progress=False,
        options={"init_res": 8, "initial_transmittance": 0.6, "initial_transmittance_path": "rays"}))
    path = trainer.bank.median_ray_path(ds.aabb)
    lo, hi = (torch.as_tensor(b, dtype=torch.float32) for b in ds.aabb)
    x = lo + torch.rand(4000, 3, generator=g) * (hi - lo)
    assert transmittance(trainer.model.field, path) == pytest.approx(0.6, abs=0.05)


def test_bad_options_raise():
    for bad in ({"shading": "phong"}, {"upsample_at": [0.5, 0.2]}, {"init_res": 300},
                {"backend": "cuda"}, {"initial_transmittance": 1.0}, {"l1_weight": -1.0},
                {"initial_transmittance_path": "cube"}):
        with pytest.raises(ValueError):
            build_model("tensorf", AABB, options=bad)
    with pytest.raises(ValueError):
        build_model("tensorf", AABB, options={"log2_hashmap_size": 19})   # an ngp option


TINY = {"samples_per_batch": 8192, "grid_update_every": 8, "init_res": 16, "final_res": 48,
        "upsample_at": [0.1, 0.3]}


def test_tensorf_trains_tiny_capture_and_reloads_after_upsampling(tiny_capture, tmp_path):
    """60 steps on 16 views of 32x32 reach >= 20 dB test PSNR (measured ~24 dB; the mean-colour
    predictor scores ~11 dB), with two upsamplings on the way; the run reloads at its final
    resolution, both for evaluation (load_model) and to resume (Trainer.load)."""
    ds = load_dataset(tiny_capture[0])
    cfg = TrainConfig(method="tensorf", max_steps=60, seed=0, progress=False, options=TINY)
    trainer = Trainer(ds, tmp_path / "run", cfg)
    trainer.train()
    field = trainer.model.field
    assert field.density_vm.vertices == field.vertices_for(48)
    metrics = evaluate(trainer.model, ds, "test", with_ssim=False)
    assert metrics["psnr"] >= 20.0, metrics
    assert metrics["depth_mae_m"] < 0.15, metrics

    model, info = load_model(tmp_path / "run")
    assert info["step"] == 60
    assert model.field.density_vm.vertices == field.vertices_for(48)
    again = evaluate(model, ds, "test", with_ssim=False)
    assert again["psnr"] == pytest.approx(metrics["psnr"], abs=1e-4)

    resumed = Trainer(ds, tmp_path / "run", cfg)
    assert resumed.load()
    assert resumed.model.field.app_vm.vertices == field.vertices_for(48)
    for (name, a), b in zip(trainer.model.state_dict().items(),
                            resumed.model.state_dict().values()):
        assert torch.equal(a, b), name
