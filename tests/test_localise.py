"""Pose estimation through a frozen field: the exponential map, interest pixels, and iNeRF
recovering a known perturbation of a test camera of a trained tiny capture."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.ops.cameras import Rays, look_at
from nerfbot.ops.lie import se3_exp
from nerfbot.query.direct_alignment import blur
from nerfbot.query.localise import (InerfConfig, WideConfig, _hypotheses,
                                    _Observation, _photometric, across_rays, inerf,
                                    interest_pixels, localise_wide, perturb, planar_update,
                                    pose_error)
from nerfbot.train.trainer import TrainConfig, Trainer
from painted_room import PaintedRoom, painted_room_view

pytestmark = pytest.mark.slow(100)


def _twist_matrix(xi: torch.Tensor) -> torch.Tensor:
    w, v = xi[:3], xi[3:]
    m = torch.zeros(4, 4, dtype=xi.dtype)
    m[0, 1], m[0, 2], m[1, 2] = -w[2], w[1], -w[0]
    m[1, 0], m[2, 0], m[2, 1] = w[2], -w[1], w[0]
    m[:3, 3] = v
    return m


@pytest.mark.parametrize("scale", [0.0, 1e-5, 0.3, 2.5])
def test_se3_exp_matches_the_matrix_exponential(scale):
    g = torch.Generator().manual_seed(0)
    for _ in range(5):
        xi = torch.randn(6, generator=g, dtype=torch.float64) * scale
        assert torch.allclose(se3_exp(xi), torch.linalg.matrix_exp(_twist_matrix(xi)),
                              atol=1e-10)
    batch = torch.randn(3, 6, generator=g, dtype=torch.float64)
    assert se3_exp(batch).shape == (3, 4, 4)


def test_se3_exp_has_finite_gradients_at_zero():
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: se3_exp(x), (xi,), eps=1e-6, atol=1e-6)


def test_interest_pixels_lie_on_texture():
    img = np.zeros((64, 64, 3), np.uint8)
    img[16:48:4, 16:48] = 255                 # stripes in the middle, flat elsewhere
    px = interest_pixels(img, dilate=2)
    assert len(px) > 0
    assert np.all((px >= 10) & (px < 54))
    assert len(interest_pixels(np.full((32, 32, 3), 128, np.uint8))) == 0


def test_perturb_moves_by_exactly_the_requested_amount():
    rng = np.random.default_rng(0)
    c2w = np.eye(4)
    c2w[:3, 3] = [1.0, 2.0, 0.5]
    moved = perturb(c2w, 0.1, 5.0, rng)
    dt, dr = pose_error(moved, c2w)
    assert dt == pytest.approx(0.1, abs=1e-9) and dr == pytest.approx(5.0, abs=1e-6)


def test_planar_perturbation_is_horizontal_and_about_the_vertical():
    rng = np.random.default_rng(2)
    c2w = perturb(np.eye(4), 0.0, 30.0, np.random.default_rng(0))      # a tilted camera
    c2w[:3, 3] = [1.0, 2.0, 0.45]
    for _ in range(5):
        moved = perturb(c2w, 0.2, 10.0, rng, planar=True)
        dt, dr = pose_error(moved, c2w)
        assert dt == pytest.approx(0.2, abs=1e-9) and dr == pytest.approx(10.0, abs=1e-6)
        assert moved[2, 3] == pytest.approx(0.45, abs=1e-12)            # height kept
        # a turn about the vertical keeps each axis' angle to it (roll and pitch)
        assert np.allclose(moved[2, :3], c2w[2, :3], atol=1e-12)


def test_planar_update_turns_about_the_camera_centre_and_moves_horizontally():
    c2w = torch.as_tensor(perturb(np.eye(4), 0.5, 25.0, np.random.default_rng(1)),
                          dtype=torch.float64)[None]
    q = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64)
    out = planar_update(c2w, q)[0]
    c, s = np.cos(0.3), np.sin(0.3)
    rz = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(out[:3, :3], rz @ c2w[0, :3, :3], atol=1e-12)
    assert torch.allclose(out[:3, 3], c2w[0, :3, 3] + torch.tensor([0.1, -0.2, 0.0],
                                                                   dtype=torch.float64))
    assert torch.equal(planar_update(c2w, torch.zeros(1, 3, dtype=torch.float64)), c2w)
    q = q.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: planar_update(c2w, x), (q,), eps=1e-6, atol=1e-6)


def test_hypothesis_grids_start_at_the_guess():
    for planar, n, dof in ((True, 45, 3), (False, 31, 6)):
        grid = _hypotheses(WideConfig(planar=planar))
        assert grid.shape == (n, dof) and torch.all(grid[0] == 0)
        assert len(torch.unique(grid, dim=0)) == n                    # no duplicates


def test_gaussian_blur_keeps_flat_images_and_the_mean():
    flat = torch.full((2, 3, 8, 8), 0.4)
    assert torch.allclose(blur(flat, 1.0), flat)
    spot = torch.zeros(1, 1, 15, 15)
    spot[0, 0, 7, 7] = 1.0
    blurred = blur(spot, 1.0)
    assert blurred.sum() == pytest.approx(1.0, abs=1e-5) and blurred.max() < 0.2


@pytest.fixture(scope="module")
def trained_tiny(tmp_path_factory):
    """ngp trained 400 steps on a 64x64 tabletop capture of 24 views (+ 2 test views)."""
    from sims.capture import capture
    from sims.rigs import default_rig, make_test_rig

    folder = tmp_path_factory.mktemp("loc") / "tabletop"
    rig = default_rig("tabletop", count=24, width=64, height=64, seed=0)
    capture("tabletop", rig, make_test_rig(rig, 2), folder, progress=False)
    ds = load_dataset(folder)
    trainer = Trainer(ds, folder.parent / "run", TrainConfig(
        method="ngp", max_steps=400, seed=0, progress=False,
        options={"samples_per_batch": 8192, "grid_update_every": 4, "supersample": 1}))
    trainer.train()
    trainer.model.eval()
    return trainer.model, ds


def _observation(model, ds, index):
    """A test view's real image, its intrinsics and its true pose."""
    cams = ds.cameras([index])
    intr = tuple(float(getattr(cams, k)[0]) for k in ("fx", "fy", "cx", "cy"))
    return ds.images[index][..., :3], intr, cams.c2w[0].cpu().numpy().astype(float)


def _whole_image_loss(model, image, intr, poses) -> list[float]:
    """The mean squared colour error over every pixel of ``image`` at each of ``poses``."""
    obs = _Observation(image, intr, InerfConfig(interest=False), torch.Generator(), "cpu")
    ys, xs = np.mgrid[0:obs.h, 0:obs.w]
    with torch.no_grad():
        return _photometric(model, obs, torch.as_tensor(np.stack(poses), dtype=torch.float32),
                            torch.as_tensor(xs.ravel()), torch.as_tensor(ys.ravel())).tolist()


def test_inerf_reaches_the_fields_own_optimum_on_a_tiny_capture(trained_tiny):
    """A briefly trained field's best-fitting pose is not the true one: on this capture
    (64 px, the scene 2-4 m away) poses 1-7 cm from the truth fit the test views as well as
    the truth does, so iNeRF is judged by the fit it reaches, and by the rotation, which the
    image pins down (3 degrees is 6 px at this focal length). iNeRF's basin is not certain
    even from 5 cm and 3 degrees (80 % in the rooms, BENCHMARKS.md section 9), so the test
    asks for most of eight starts."""
    model, ds = trained_tiny
    reached = []
    for index in ds.indices("test"):
        image, intr, truth = _observation(model, ds, index)
        for seed in range(1, 5):
            start = perturb(truth, 0.05, 3.0, np.random.default_rng(seed))
            est = inerf(model, image, intr, start, InerfConfig(iterations=100, rays=512))
            at_estimate, at_truth, at_start = _whole_image_loss(model, image, intr,
                                                                [est.c2w, truth, start])
            reached.append(at_estimate < 1.15 * at_truth and at_estimate < 0.25 * at_start
                           and pose_error(est.c2w, truth)[1] < 0.6 * 3.0)
    # observed: 8 of 8 (two threads) and 7 of 8 (one thread) starts reach 0.97-1.07 of the
    # truth's error and 0.06-0.12 of the start's, 0.5-1.2 degrees from the truth; the eighth
    # turned 11 degrees away
    assert sum(reached) >= 5, reached


def test_inerf_recovers_a_small_perturbation_of_the_painted_room():
    """Where the truth is the colours' optimum (an analytic field), iNeRF recovers the pose."""
    model = PaintedRoom()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    for seed in range(3):
        start = perturb(truth, 0.05, 3.0, np.random.default_rng(seed))
        est = inerf(model, image, intr, start, InerfConfig(iterations=100, rays=512))
        dt, dr = pose_error(est.c2w, truth)
        # observed: 2.0, 2.1 and 0.3 cm; 0.62, 0.52 and 0.08 degrees
        assert dt < 0.5 * 0.05 and dr < 0.3 * 3.0, (seed, dt, dr)


def test_coarse_levels_widen_inerfs_basin_on_the_painted_room():
    """From 10 cm / 10 degrees (planar) plain iNeRF's pixels say nothing about the pose; two
    blurred whole-image levels first bring every start within 2 cm and 1 degree."""
    model = PaintedRoom()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    for seed in range(3):
        start = perturb(truth, 0.1, 10.0, np.random.default_rng(seed), planar=True)
        plain = pose_error(inerf(model, image, intr, start, InerfConfig(planar=True)).c2w,
                           truth)
        est = inerf(model, image, intr, start, InerfConfig(planar=True, coarse_levels=2))
        dt, dr = pose_error(est.c2w, truth)
        assert plain[0] > 0.02 or plain[1] > 1.0, (seed, plain)
        assert dt < 0.02 and dr < 1.0, (seed, dt, dr)
        assert len(est.losses) == 2 * InerfConfig().coarse_iterations + InerfConfig().iterations


def test_supersampled_coarse_renders_match_the_area_averaged_image_better():
    """At the true pose a 16 x 16 render whose pixels average 4 x 4 rays is closer to the
    observed image's area average than one ray per pixel (sub-rays in the wrong pixels
    would be farther)."""
    from nerfbot.query.localise import _LowRes, _Observation
    model = PaintedRoom()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    obs = _Observation(image, intr, InerfConfig(interest=False), torch.Generator(), "cpu")
    c2w = torch.as_tensor(truth, dtype=torch.float32)[None]
    with torch.no_grad():
        errors = [float(_LowRes(model, obs, 16, 0.0, supersample=s)(c2w)[0]) for s in (1, 4)]
    assert errors[1] < 0.5 * errors[0], errors


def test_inerf_config_rejects_bad_coarse_levels():
    with pytest.raises(ValueError, match="coarse_levels"):
        InerfConfig(coarse_levels=-1)
    with pytest.raises(ValueError, match="coarse_iterations"):
        InerfConfig(coarse_levels=1, coarse_iterations=0)


def test_origin_gradients_cross_the_rays():
    g = torch.Generator().manual_seed(0)
    origins = torch.randn(6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    directions = torch.nn.functional.normalize(torch.randn(6, 3, generator=g,
                                                           dtype=torch.float64), dim=-1)
    rays = across_rays(Rays(origins, directions, torch.ones(6, dtype=torch.float64)))
    assert torch.equal(rays.origins, origins)
    upstream = torch.randn(6, 3, generator=g, dtype=torch.float64)
    (rays.origins * upstream).sum().backward()
    along = (upstream * directions).sum(-1, keepdim=True)
    assert torch.allclose(origins.grad, upstream - along * directions, atol=1e-12)
    assert torch.allclose((origins.grad * directions).sum(-1), torch.zeros(6, dtype=torch.float64),
                          atol=1e-12)


def test_evaluation_with_pose_refinement_recovers_a_misplaced_test_camera(trained_tiny):
    model, ds = trained_tiny
    c2w = ds.c2w.copy()
    index = ds.indices("test")[0]
    c2w[index] = perturb(ds.c2w[index], 0.02, 1.0, np.random.default_rng(3))
    misplaced = replace(ds, c2w=c2w, splits={"train": [], "test": [index]})
    exact = evaluate(model, replace(ds, splits={"train": [], "test": [index]}), "test")
    plain = evaluate(model, misplaced, "test")
    refined = evaluate(model, misplaced, "test",
                       refine_poses=InerfConfig(iterations=100, rays=1024, lr=2e-3))
    assert plain["psnr"] < exact["psnr"] - 1.0         # the misplaced camera costs PSNR
    assert refined["psnr"] > plain["psnr"] + 0.5 * (exact["psnr"] - plain["psnr"])
    assert refined["pose_refinement"]["rotation_deg_median"] > 0.2


@pytest.mark.parametrize("planar", [True, False], ids=["planar", "6dof"])
def test_the_wide_estimator_converges_where_inerf_does_not(planar):
    model = PaintedRoom()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    start = perturb(truth, 0.3, 20.0, np.random.default_rng(4), planar=planar)
    plain = pose_error(inerf(model, image, intr, start, InerfConfig(planar=planar)).c2w, truth)
    dt, dr = pose_error(localise_wide(model, image, intr, start,
                                      WideConfig(planar=planar)).c2w, truth)
    assert plain[0] > 0.1 or plain[1] > 5.0, plain           # outside iNeRF's basin
    # observed from 30 cm / 20 degrees: planar 0.01 mm / 0.0003 degrees, 6-DoF 0.04 mm /
    # 0.0007 degrees (iNeRF 32 cm / 8.8 degrees planar)
    assert dt < 0.005 and dr < 0.2, (dt, dr)
