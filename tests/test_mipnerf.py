"""mip-NeRF: integrated positional encoding, frustum Gaussians, pixel radii, training, and
evaluation at lower resolutions."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from nerfbot.app.cli import main
from nerfbot.data import load_dataset
from nerfbot.data.pixels import PixelBank
from nerfbot.eval.evaluation import downscale_area, downscale_depth, evaluate
from nerfbot.fields.mipnerf import (MipNeRFField, MipNeRFFieldConfig, conical_frustum_gaussian,
                                    integrated_pos_enc, lift_gaussian)
from nerfbot.methods import build_model
from nerfbot.models.mipnerf import blurred_weights
from nerfbot.ops.cameras import PIXEL_RADIUS, Cameras, Rays, look_at
from nerfbot.ops.encodings import FrequencyEncoding
from nerfbot.ops.metrics import psnr
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

# A small mip-NeRF: 100 steps of this take seconds on the 32x32 capture.
TINY_MIP = {"width": 64, "depth": 4, "skip": 2, "color_width": 32, "coarse_samples": 16,
            "fine_samples": 16, "rays_per_batch": 256}
TINY_STEPS = 100


# -- integrated positional encoding -----------------------------------------------------------

def test_ipe_with_zero_variance_is_the_positional_encoding():
    x = torch.rand(50, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    pe = FrequencyEncoding(3, 7)(x)
    torch.testing.assert_close(integrated_pos_enc(x, torch.zeros_like(x), 7), pe)
    torch.testing.assert_close(integrated_pos_enc(x, None, 7), pe)
    field = MipNeRFField([[-1, -1, -1], [1, 1, 1]], MipNeRFFieldConfig(width=32, depth=3, skip=1))
    sigma, feat = field.density(x * 0.9)
    sigma_g, feat_g = field.density_gaussian(x * 0.9, torch.zeros_like(x))
    torch.testing.assert_close(sigma, sigma_g)
    torch.testing.assert_close(feat, feat_g)


def test_ipe_attenuates_high_frequencies_and_matches_monte_carlo():
    """E[sin(a x)], E[cos(a x)] of x ~ N(mu, s^2) against 10^6 samples (float64, standard error
    <= 1e-3), and the amplitude of each level falls with the variance and with the level."""
    levels = 6
    gen = torch.Generator().manual_seed(1)
    z = torch.randn(1_000_000, generator=gen, dtype=torch.float64)
    freqs = math.pi * 2.0 ** torch.arange(levels, dtype=torch.float64)
    mu = torch.tensor([[0.3, -0.7, 0.05]], dtype=torch.float64)
    amplitudes = []
    for std in (0.0, 0.01, 0.05, 0.2):
        var = torch.full_like(mu, std ** 2)
        enc = integrated_pos_enc(mu, var, levels)[0]
        assert enc.dtype == torch.float64
        torch.testing.assert_close(enc[:3], mu[0])  # the mean itself is its own expectation
        sin, cos = enc[3:3 + 3 * levels].view(levels, 3), enc[3 + 3 * levels:].view(levels, 3)
        for k in range(levels):
            samples = (mu[0, 0] + std * z) * freqs[k]
            assert abs(float(sin[k, 0]) - float(torch.sin(samples).mean())) < 5e-3
            assert abs(float(cos[k, 0]) - float(torch.cos(samples).mean())) < 5e-3
        amp = torch.sqrt(sin ** 2 + cos ** 2)  # (levels, 3), = exp(-a^2 s^2 / 2)
        torch.testing.assert_close(amp, torch.exp(-0.5 * freqs[:, None] ** 2 * std ** 2)
                                   .expand(levels, 3))
        amplitudes.append(amp[:, 0])
    amps = torch.stack(amplitudes)  # (variances, levels)
    assert torch.all(amps[0] == 1.0)
    assert torch.all(amps[1:] <= amps[:-1]) and torch.all(amps[:, 1:] <= amps[:, :-1])
    assert float(amps[1, 0]) > 0.99 and float(amps[2, -1]) < 1e-3  # fine levels fade first


# -- frustum Gaussians ------------------------------------------------------------------------

def _frustum_moments_quadrature(t0: float, t1: float, radius: float):
    """Mean and variance along the axis, and per-axis perpendicular variance, of a point
    uniform in the frustum, by trapezoidal integration of the t^2 cross-section (float64)."""
    t = np.linspace(t0, t1, 200_001)
    w = t ** 2
    mass = np.trapezoid(w, t)
    mean = np.trapezoid(w * t, t) / mass
    var = np.trapezoid(w * (t - mean) ** 2, t) / mass  # centred: no cancellation
    r_var = np.trapezoid(w * (radius * t) ** 2 / 4.0, t) / mass  # a disk of radius R: R^2 / 4
    return mean, var, r_var


@pytest.mark.parametrize("t0, t1", [(0.0, 1.0), (0.5, 0.7), (0.1, 3.0), (2.0, 2.001),
                                    (40.0, 40.0005)])
def test_frustum_gaussian_matches_numerical_integration(t0, t1):
    radius = 0.003
    mean, var, r_var = conical_frustum_gaussian(torch.tensor(t0, dtype=torch.float64),
                                                torch.tensor(t1, dtype=torch.float64),
                                                torch.tensor(radius, dtype=torch.float64))
    ref_mean, ref_var, ref_r_var = _frustum_moments_quadrature(t0, t1, radius)
    assert float(mean) == pytest.approx(ref_mean, rel=1e-9)
    assert float(var) == pytest.approx(ref_var, rel=1e-6)
    assert float(r_var) == pytest.approx(ref_r_var, rel=1e-6)


def test_lifted_gaussian_matches_monte_carlo_frustum():
    """World mean and diagonal covariance of a tilted frustum against 10^6 uniform points in it."""
    rng = np.random.default_rng(2)
    origin = np.array([0.2, -0.4, 1.1])
    d = np.array([0.3, -0.5, -0.8])
    d /= np.linalg.norm(d)
    t0, t1, radius = 0.6, 1.4, 0.08
    n = 1_000_000
    t = np.cbrt(t0 ** 3 + rng.random(n) * (t1 ** 3 - t0 ** 3))  # density ~ t^2
    rho = radius * t * np.sqrt(rng.random(n))  # uniform in the disk of radius r t
    phi = rng.random(n) * 2 * np.pi
    e1 = np.cross(d, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    pts = origin + t[:, None] * d + rho[:, None] * (np.cos(phi)[:, None] * e1
                                                    + np.sin(phi)[:, None] * e2)
    tm, tv, rv = conical_frustum_gaussian(torch.tensor(t0, dtype=torch.float64),
                                          torch.tensor(t1, dtype=torch.float64),
                                          torch.tensor(radius, dtype=torch.float64))
    mean, var = lift_gaussian(torch.from_numpy(origin), torch.from_numpy(d), tm, tv, rv)
    std_err = pts.std(0) / math.sqrt(n)
    assert np.all(np.abs(mean.numpy() - pts.mean(0)) < 6 * std_err)
    np.testing.assert_allclose(var.numpy(), pts.var(0), rtol=0.01)


def test_blurred_weights_widen_peaks_and_pad():
    w = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])
    out = blurred_weights(w, 0.01)
    torch.testing.assert_close(out, torch.tensor([[0.01, 0.51, 1.01, 0.51, 0.01, 0.01]]))


# -- pixel radii ------------------------------------------------------------------------------

def _camera() -> Cameras:
    return Cameras.pinhole(look_at([1.0, -0.5, 0.6], [0.0, 0.0, 0.1]), 50.0, 32, 24)


def test_radii_are_the_pixel_footprint_and_scale_with_downscale():
    cams = _camera()
    rays = cams.rays(0)
    f = float(cams.fy[0])
    torch.testing.assert_close(rays.radii, PIXEL_RADIUS / f * rays.z_per_t)
    for k in (2, 4):
        small = cams.scaled(1.0 / k)
        assert int(small.width[0]) == 32 // k and int(small.height[0]) == 24 // k
        coarse = small.rays(0)
        same = cams.rays(0, downscale=k)  # the other path to a low-resolution image
        torch.testing.assert_close(coarse.directions, same.directions, atol=1e-6, rtol=0)
        torch.testing.assert_close(coarse.radii, same.radii)
        # a coarse pixel's footprint is k fine pixels wide: radius k times that of a fine
        # pixel in the same direction (the centre of the image, where z_per_t is 1)
        torch.testing.assert_close(coarse.radii / coarse.z_per_t,
                                   torch.full_like(coarse.radii, k * PIXEL_RADIUS / f))
    # slicing and moving rays keep their radii; hand-made rays have none
    assert torch.equal(rays[3:5].radii, rays.radii[3:5]) and rays.to("cpu").radii is not None
    assert Rays(rays.origins, rays.directions, rays.z_per_t).radii is None


def test_training_rays_carry_the_radii_of_their_pixels(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    idx = ds.indices("train")
    bank = PixelBank(ds, idx)
    rays, _, slot = bank.sample(64, torch.Generator().manual_seed(0))
    cams = ds.cameras(idx)
    local = bank.last_pixels - bank.offsets[slot]
    for j in range(8):
        ref = cams.rays(int(slot[j]))
        torch.testing.assert_close(rays.radii[j], ref.radii[int(local[j])])
        torch.testing.assert_close(rays.directions[j], ref.directions[int(local[j])])


# -- the model --------------------------------------------------------------------------------

def test_model_renders_empty_and_radius_free_rays_finitely(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    model = build_model("mipnerf", ds.aabb, "white", TINY_MIP).eval()
    cams = ds.cameras(ds.indices("test"))
    rays = cams.rays(0)[:64]
    far = torch.tensor([[100.0, 100.0, 100.0]])
    away = Rays(rays.origins + far, rays.directions, rays.z_per_t, rays.radii)  # miss the box
    with torch.no_grad():
        out = model.render_rays(away)
        thin = model.render_rays(Rays(rays.origins, rays.directions, rays.z_per_t))
        cone = model.render_rays(rays)
    torch.testing.assert_close(out.rgb, torch.ones_like(out.rgb))
    assert torch.isfinite(out.depth).all() and torch.all(out.opacity == 0)
    for o in (thin, cone):
        assert torch.isfinite(o.rgb).all() and torch.isfinite(o.depth).all()
    with pytest.raises(ValueError, match="fine_samples"):
        build_model("mipnerf", ds.aabb, "white", {"fine_samples": 0})


@pytest.fixture(scope="module")
def tiny_mip_run(tiny_capture, tmp_path_factory):
    run = tmp_path_factory.mktemp("mip") / "run"
    args = ["train", "--data", str(tiny_capture[0]), "--method", "mipnerf", "--max-steps",
            str(TINY_STEPS), "--out", str(run), "--no-progress", "--lr", "3e-3"]
    for k, v in TINY_MIP.items():
        args += ["--option", f"{k}={v}"]
    assert main(args) == 0
    return run


def test_mipnerf_trains_tiny_capture_to_threshold(tiny_capture, tiny_mip_run):
    """100 steps of a small mip-NeRF reach >= 18 dB test PSNR (measured 21.7 dB; the mean-colour
    predictor scores ~11 dB) and depth within 15 cm (measured 7.6 cm)."""
    ds = load_dataset(tiny_capture[0])
    model, info = load_model(tiny_mip_run)
    assert info["step"] == TINY_STEPS
    metrics = evaluate(model, ds, "test", with_ssim=False)
    assert metrics["psnr"] >= 18.0, metrics
    assert metrics["depth_mae_m"] is not None and metrics["depth_mae_m"] < 0.15, metrics


def test_evaluate_at_half_resolution(tiny_capture, tiny_mip_run):
    ds = load_dataset(tiny_capture[0])
    model, _ = load_model(tiny_mip_run)
    idx = ds.indices("test")
    half = ds.cameras(idx).scaled(0.5)
    img = render_image(model, half, 0)
    assert img["rgb"].shape == (16, 16, 3) and img["z_depth"].shape == (16, 16)
    gt = downscale_area(ds.image_float(idx[0]), 16, 16)
    assert gt.shape == (16, 16, 3)
    np.testing.assert_allclose(gt.mean((0, 1)), ds.image_float(idx[0]).mean((0, 1)), atol=1e-5)
    metrics = evaluate(model, ds, "test", with_ssim=False, downscale=2)
    assert metrics["downscale"] == 2 and metrics["num_images"] == len(idx)
    assert math.isfinite(metrics["psnr"]) and metrics["psnr"] == pytest.approx(
        np.mean([psnr(render_image(model, half, s)["rgb"],
                      downscale_area(ds.image_float(i), 16, 16)) for s, i in enumerate(idx)]),
        abs=1e-4)
    assert metrics["depth_mae_m"] is not None and math.isfinite(metrics["depth_mae_m"])
    with pytest.raises(ValueError, match="downscale"):
        evaluate(model, ds, "test", downscale=0)


def test_downscaled_depth_keeps_only_fully_valid_blocks():
    depth = np.array([[1.0, 3.0, 5.0, np.inf],
                      [1.0, 3.0, 5.0, 5.0]], np.float32)
    valid = np.isfinite(depth)
    low, ok = downscale_depth(depth, valid, 2, 1)
    assert ok.tolist() == [[True, False]]
    assert float(low[0, 0]) == pytest.approx(2.0) and np.isnan(low[0, 1])


def test_eval_cli_downscale(tiny_mip_run, capsys):
    capsys.readouterr()
    results = {}
    for k in (1, 2):
        assert main(["eval", str(tiny_mip_run), "--json", "--downscale", str(k)]) == 0
        results[k] = json.loads(capsys.readouterr().out)
    assert results[1]["downscale"] == 1 and results[2]["downscale"] == 2
    assert results[2]["method"] == "mipnerf"
    assert all(math.isfinite(r["psnr"]) for r in results.values())
    with pytest.raises(SystemExit) as refused:  # the parser's own one-line error
        main(["eval", str(tiny_mip_run), "--downscale", "0"])
    assert refused.value.code == 2
    assert "--downscale" in capsys.readouterr().err
