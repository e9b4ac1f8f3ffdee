"""FastNeRF: the factorised field trains, its cache reproduces it, the fused renderer matches its
torch twin, and `nerfbot bake --cache` writes a run that loads and evaluates."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nerfbot.app.cli import main
from nerfbot.bake.fastnerf_cache import bake_cache
from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.fields.fastnerf import FastNeRFField, FastNeRFFieldConfig
from nerfbot.methods import build_model
from nerfbot.models.fastnerf_cache import FastNeRFCacheConfig, FastNeRFCacheModel
from nerfbot.ops.octahedral import direction_grid, octahedral_decode, octahedral_encode
from nerfbot.query.render import depth, render_image
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(30)  # rough single-core seconds (tests/conftest.py)

# Marching in rounds throughout (full_march_kept_fraction=1): the baked-renderer twin test
# below is held to exact agreement on the cache of this training run; with ngp's default
# (training every marched sample while the field is translucent) the trained field differs
# and one test ray of the baked cache disagrees between the numba and torch renderers by
# 2e-3 (BENCHMARKS.md, open points).
TINY = {"samples_per_batch": 8192, "grid_update_every": 8, "full_march_kept_fraction": 1.0}


@pytest.fixture(scope="module")
def trained(tiny_capture, tmp_path_factory):
    """(trainer, dataset) of fastnerf trained 120 steps on the tiny capture."""
    ds = load_dataset(tiny_capture[0])
    cfg = TrainConfig(method="fastnerf", max_steps=120, seed=0, progress=False, options=TINY)
    trainer = Trainer(ds, tmp_path_factory.mktemp("fastnerf") / "run", cfg)
    trainer.train()
    trainer.model.eval()
    return trainer, ds


@pytest.fixture(scope="module")
def baked(trained):
    """(baked model, spec, extra) of the trained model at NP = 64, ND = 16."""
    trainer, _ = trained
    return bake_cache(trainer.model, trainer.spec, 64, 16, progress=False)


def test_fastnerf_trains_tiny_capture_to_threshold(trained):
    """>= 20 dB test PSNR after 120 steps (measured ~23 dB; the mean-colour predictor scores
    ~11 dB), and the occupancy grid pruned most of the cube."""
    trainer, ds = trained
    metrics = evaluate(trainer.model, ds, "test", with_ssim=False)
    assert metrics["psnr"] >= 20.0, metrics
    assert float(trainer.model.grid.occupied.float().mean()) < 0.5


def test_colour_is_sigmoid_of_weighted_components():
    field = FastNeRFField([[-1, -1, -1], [1, 1, 1]], FastNeRFFieldConfig(components=4))
    g = torch.Generator().manual_seed(0)
    x = torch.rand(50, 3, generator=g) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    sigma, u = field.density(x)
    beta = field.direction_weights(d)
    expected = torch.sigmoid((beta[:, :, None] * u.reshape(50, 4, 3)).sum(1))
    torch.testing.assert_close(field.color(u, d), expected)
    assert sigma.shape == (50,) and bool((sigma >= 0).all())
    # the mean-colour start: with the output layers' weights at zero, every point and direction
    # renders exactly the given colour
    rgb = torch.tensor([0.2, 0.5, 0.7])
    field.init_mean_color(rgb)
    with torch.no_grad():
        field.position_net[-1].weight.zero_()
        field.direction_net[-1].weight.zero_()
        torch.testing.assert_close(field.color(field.density(x)[1], d), rgb.expand(50, 3))


def test_frequency_variant_and_bad_options():
    aabb = [[-1, -1, -1], [1, 1, 1]]
    model = build_model("fastnerf", aabb, "white", {"position_encoding": "frequency",
                                                     "freq_width": 32, "components": 3})
    x = torch.rand(64, 3) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    sigma, u = model.field.density(x)
    rgb = model.field.color(u, d)
    (sigma.sum() + rgb.sum()).backward()
    grads = [p.grad for p in model.field.parameters() if p.grad is not None]
    assert grads and all(bool(torch.isfinite(g).all()) for g in grads)
    assert u.shape == (64, 9) and len(model.field.position_net.layers) == 8
    with pytest.raises(ValueError, match="position_encoding"):
        build_model("fastnerf", aabb, "white", {"position_encoding": "grid"})
    with pytest.raises(ValueError, match="components"):
        build_model("fastnerf", aabb, "white", {"components": 0})


def test_octahedral_map_round_trips():
    g = torch.Generator().manual_seed(1)
    d = torch.randn(2000, 3, generator=g, dtype=torch.float64)
    d[:4] = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, -1.0, 0]])
    d = torch.nn.functional.normalize(d, dim=-1)
    uv = octahedral_encode(d)
    assert bool((uv.abs() <= 1 + 1e-12).all())
    torch.testing.assert_close(octahedral_decode(uv), d, atol=1e-9, rtol=0)
    # grid vertices are unit directions, and the mirrored border holds equal directions
    grid = direction_grid(9)
    torch.testing.assert_close(grid.norm(dim=-1), torch.ones(9, 9))
    torch.testing.assert_close(grid[-1, :], grid[-1, :].flip(0), atol=1e-6, rtol=0)
    torch.testing.assert_close(grid[:, 0], grid[:, 0].flip(0), atol=1e-6, rtol=0)


def test_cache_matches_field_at_grid_points(trained, baked):
    """At grid vertices of stored bricks, the cache gives the field's density and, for
    directions on the direction grid, its colour (up to the quantisation: 16 bits for the
    density, 8 for the colour components)."""
    trainer, _ = trained
    model, spec, extra = baked
    src, cache = trainer.model.field, model.field
    assert spec["method"] == "fastnerf_cache" and spec["options"] == {"np": 64, "nd": 16}
    assert extra["occupied_cells"] > 0 and extra["cache_mb"] > 0
    nc, bs = cache.cells_per_axis, cache.brick_size
    assert nc == 64 and tuple(cache.dir_weights.shape) == (16, 16, 8)
    assert extra["bricks"] == cache.density_codes.shape[0]
    assert extra["occupied_cells"] <= 64 * extra["bricks"]
    h = float(src.normalize.cube_size) / nc
    ijk = torch.stack(torch.meshgrid(*[torch.arange(nc)] * 3, indexing="ij"), -1).reshape(-1, 3)
    stored = cache.bricks[ijk[:, 0] // bs, ijk[:, 1] // bs, ijk[:, 2] // bs] >= 0
    cells = ijk[stored]
    pick = cells[torch.randperm(len(cells), generator=torch.Generator().manual_seed(0))[:300]]
    # the cache looks up float64 points a hair inside the cell (a float32 vertex can round into
    # the neighbouring cell, which may not be stored); the field gets the float32 vertex
    x64 = src.normalize.cube_min.double() + (pick.double() + 1e-9) * h
    x64 = x64[src.normalize.inside(x64.float())]
    assert len(x64) > 100
    with torch.no_grad():
        sigma_src, u_src = src.density(x64.float())
        sigma_c, u_c = cache.density(x64)
        torch.testing.assert_close(sigma_c, sigma_src, rtol=2e-3, atol=1e-4)
        # each component is off by at most half its 8-bit step, the logit by sum_i |beta_i|
        # step_i / 2, and the sigmoid's slope is at most 1/4
        step = cache.scale[1:].reshape(-1, 3).amax(1)
        dirs = direction_grid(16)[[0, 3, 8, 12, 15], [5, 15, 8, 2, 0]]
        for d in dirs:
            dd = d.expand(len(x64), 3)
            beta = cache.direction_weights(d[None])[0]
            bound = float((beta.abs() * step).sum()) / 8
            assert bound < 1e-2  # under 2.6 / 255
            torch.testing.assert_close(cache.color(u_c, dd), src.color(u_src, dd),
                                       atol=bound + 1e-3, rtol=0)
    # the cache marches only where the source's occupancy grid had density
    occ_src, occ_cache = trainer.model.grid.occupied.bool(), cache.occupancy.bool()
    assert occ_cache.shape == occ_src.shape and bool(occ_cache.any())
    assert not bool((occ_cache & ~occ_src).any())


def _test_rays(ds, index=0):
    cams = ds.cameras(ds.indices("test"))
    return cams.rays(index)


@pytest.mark.parametrize("stop", [0.0, 1e-3])
def test_fused_renderer_matches_torch_reference(trained, baked, stop):
    """The numba renderer and the torch twin render the same cache alike: exactly (up to float
    rounding) without early termination, within the terminated transmittance with it."""
    _, ds = trained
    model = baked[0]
    model.config.early_stop_transmittance = stop
    model.config.color_min_weight = 0.0
    try:
        rays = _test_rays(ds)
        fused, ref = model.render_fused(rays), model.render_reference(rays)
    finally:
        model.config.early_stop_transmittance = 1e-3
        model.config.color_min_weight = FastNeRFCacheConfig.color_min_weight
    tol = 3e-4 if stop == 0 else 3e-3
    torch.testing.assert_close(fused.rgb, ref.rgb.float(), atol=tol, rtol=0)
    torch.testing.assert_close(fused.opacity, ref.opacity.float(), atol=tol, rtol=0)
    hit = ref.opacity > 0.5
    assert int(hit.sum()) > 50
    torch.testing.assert_close(fused.depth[hit], ref.depth[hit].float(), atol=5e-3, rtol=0)
    close = (fused.median_depth - ref.median_depth).abs() < 1e-4
    assert float(close[hit].float().mean()) > 0.97
    # the packed samples are consistent with the per-ray results
    assert fused.num_samples > 0 and fused.ray_indices.shape == (fused.num_samples,)
    assert bool((fused.ray_indices[1:] >= fused.ray_indices[:-1]).all())
    sums = torch.zeros(len(rays)).index_add_(0, fused.ray_indices, fused.weights)
    torch.testing.assert_close(sums, fused.opacity, atol=1e-4, rtol=0)
    if stop == 0:
        assert fused.num_samples == int((ref.sigmas > 0).sum())


def test_faint_samples_take_their_rays_mean_colour(trained, baked):
    """With ``color_min_weight``, samples of at most that weight are not looked up: each pixel
    moves by at most the weight of its skipped samples, opacity and depth do not move, and
    fewer colour lookups are the point (most of a ray's samples are faint)."""
    _, ds = trained
    model = baked[0]
    rays = _test_rays(ds)
    min_w = FastNeRFCacheConfig.color_min_weight
    assert min_w > 0 and model.config.color_min_weight == min_w
    faint = model.render_fused(rays)
    model.config.color_min_weight = 0.0
    try:
        exact = model.render_fused(rays)
    finally:
        model.config.color_min_weight = min_w
    skipped = exact.weights * (exact.weights <= min_w)
    bound = torch.zeros(len(rays)).index_add_(0, exact.ray_indices, skipped)
    assert float(bound.max()) > 1e-4  # some rays do skip samples
    assert bool(((faint.rgb - exact.rgb).abs() <= bound[:, None] + 1e-5).all())
    for name in ("opacity", "depth", "median_depth", "weights"):
        torch.testing.assert_close(getattr(faint, name), getattr(exact, name))


def test_fused_renderer_handles_long_rays_and_empty_caches(trained, baked):
    """Rays with more samples than the first pass keeps are rendered again with room; an
    unbaked (empty) cache renders the background; the cache cannot be trained."""
    _, ds = trained
    model = baked[0]
    rays = _test_rays(ds, 1)
    import nerfbot.models.fastnerf_cache as fc

    default = fc.SLOT_SAMPLES
    full = model.render_fused(rays)
    try:
        fc.SLOT_SAMPLES = 2
        small = model.render_fused(rays)
    finally:
        fc.SLOT_SAMPLES = default
        model._scratch.arrays = None
    assert int(torch.bincount(full.ray_indices).max()) > 2
    for name in ("rgb", "opacity", "depth", "median_depth", "ray_indices", "t_starts", "sigmas",
                 "weights"):
        torch.testing.assert_close(getattr(small, name), getattr(full, name))

    empty = build_model("fastnerf_cache", baked[1]["aabb"], "white", {"np": 64, "nd": 16})
    empty.eval()
    out = empty.render_rays(rays)
    torch.testing.assert_close(out.rgb, torch.ones(len(rays), 3))
    assert out.num_samples == 0 and bool(torch.isfinite(out.depth).all())
    empty.train()
    with pytest.raises(RuntimeError, match="cannot be trained"):
        empty.render_rays(rays)
    with pytest.raises(RuntimeError, match="cannot be trained"):
        empty.rays_for_next_batch(None, 100)


def test_bake_rejects_other_methods_and_bad_sizes(trained, tiny_capture):
    trainer, _ = trained
    ngp = build_model("ngp", trainer.spec["aabb"])
    with pytest.raises(ValueError, match="fastnerf"):
        bake_cache(ngp, {**trainer.spec, "method": "ngp"}, 32, 8, progress=False)
    with pytest.raises(ValueError, match="NP >= 1"):
        bake_cache(trainer.model, trainer.spec, 0, 8, progress=False)


def test_bake_cli_end_to_end(tiny_capture, tmp_path, capsys):
    """train -> bake --cache -> eval: the baked run loads, renders like its source, reports its
    size, and answers density and threshold-depth queries."""
    run, out = tmp_path / "run", tmp_path / "cache"
    assert main(["train", "--data", str(tiny_capture[0]), "--method", "fastnerf", "--max-steps",
                 "60", "--out", str(run), "--no-progress", "--option", "samples_per_batch=8192",
                 "--option", "grid_update_every=8"]) == 0
    capsys.readouterr()
    assert main(["bake", str(run), "--cache", "96,32", "--out", str(out), "--no-progress"]) == 0
    printed = json.loads(capsys.readouterr().out)
    report = json.loads((out / "bake.json").read_text())
    assert report["method"] == "fastnerf_cache" and report["cache_mb"] > 0
    assert report["np"] == 96 and report["nd"] == 32 and printed["cache_mb"] == report["cache_mb"]
    assert main(["eval", str(run), "--json"]) == 0
    src = json.loads(capsys.readouterr().out)
    assert main(["eval", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["method"] == "fastnerf_cache"
    assert res["psnr"] > src["psnr"] - 0.5, (res, src)

    model, info = load_model(out)
    assert isinstance(model, FastNeRFCacheModel) and model.field.cells_per_axis == 96
    ds = load_dataset(tiny_capture[0])
    cams = ds.cameras(ds.indices("test"))
    img = render_image(model, cams, 0)
    assert img["rgb"].shape == (32, 32, 3) and np.isfinite(img["depth"]).all()
    # threshold depth (from the packed samples) agrees with the source's
    source, _ = load_model(run)
    thr = float(source.render_rays(cams.rays(0)).sigmas.median())
    z_src = depth(source, cams, 0, mode="threshold", threshold=thr)
    z = depth(model, cams, 0, mode="threshold", threshold=thr)
    both = np.isfinite(z_src) & np.isfinite(z)
    assert both.mean() > 0.5 * np.isfinite(z_src).mean() > 0
    assert np.median(np.abs(z[both] - z_src[both])) < 0.02
    sigma, _ = model.field.density(torch.rand(100, 3) * 0.1)
    assert sigma.shape == (100,) and bool(torch.isfinite(sigma).all())


def test_empty_distance_is_the_capped_chebyshev_distance_to_occupied_cells():
    """The renderer jumps out of the (2k - 1)^3 cells around a cell at distance k: they must
    all be empty, so the distance may never exceed the true one."""
    from nerfbot.kernels.fastnerf_cache import empty_distance

    occ = np.zeros((12, 12, 12), np.uint8)
    occ[2, 3, 4] = occ[10, 9, 1] = occ[5, 5, 5] = 1
    dist = empty_distance(occ, cap=6)
    ijk = np.stack(np.meshgrid(*[np.arange(12)] * 3, indexing="ij"), -1).reshape(-1, 3)
    full = np.abs(ijk[:, None, :] - np.argwhere(occ)[None]).max(-1).min(1).reshape(occ.shape)
    assert np.array_equal(dist, np.minimum(full, 6)) and dist.max() == 6
    assert np.array_equal(empty_distance(np.zeros((4, 4, 4), np.uint8), cap=3), np.full((4,) * 3, 3))
    assert not empty_distance(np.ones((3, 3, 3), np.uint8)).any()


def test_a_cache_baked_by_an_older_nerfbot_asks_to_be_baked_again():
    from nerfbot.models.fastnerf_cache import CachedField

    field = CachedField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    with pytest.raises(ValueError, match="bake it again"):
        field.load_state_dict({"values": torch.zeros(1, 5, 5, 5, 25, dtype=torch.int16)},
                              strict=False)
