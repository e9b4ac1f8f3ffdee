"""PlenOctrees: the NeRF-SH field trains, its octree bakes faithfully, the fused renderer equals
the differentiable path, fine-tuning helps, and `nerfbot bake --octree` writes a loadable run."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from nerfbot.bake.plenoctree import bake_octree, finetune_octree
from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.fields.background import make_background
from nerfbot.fields.nerfsh import NeRFSHField, sh_color
from nerfbot.methods import build_model
from nerfbot.models.plenoctree import (PlenOctreeConfig, PlenOctreeModel, build_octree,
                                       octree_lookup_reference, walk_segments,
                                       walk_segments_reference)
from nerfbot.ops.cameras import Rays
from nerfbot.ops.encodings import spherical_harmonics
from nerfbot.ops.sampling import ray_aabb
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(30)  # rough single-core seconds (tests/conftest.py)

AABB = [[-0.6, -0.4, 0.0], [0.6, 0.4, 0.9]]
TINY_OPTIONS = {"samples_per_batch": 8192, "grid_update_every": 8}
BAKE_DEPTH = 6  # 64^3 leaves over the tiny scene's cube: ~1.5 cm, about a 32x32 pixel


@pytest.fixture(scope="module")
def sh_run(tiny_capture, tmp_path_factory):
    """(run folder, trained model, test PSNR) of `plenoctree` after 150 steps on the tiny capture."""
    ds = load_dataset(tiny_capture[0])
    out = tmp_path_factory.mktemp("plenoctree") / "run"
    cfg = TrainConfig(method="plenoctree", max_steps=150, seed=0, progress=False,
                      options=TINY_OPTIONS)
    trainer = Trainer(ds, out, cfg)
    trainer.train()
    trainer.model.eval()
    return out, trainer.model, evaluate(trainer.model, ds, "test", with_ssim=False)["psnr"]


@pytest.fixture(scope="module")
def baked(sh_run):
    """The tiny run baked at depth 6 (one jittered-average leaf per 1.5 cm cell)."""
    _, model, _ = sh_run
    spec = {"method": "plenoctree", "aabb": model.aabb.tolist(), "background": "learned",
            "options": TINY_OPTIONS, "seed": 0, "conditioning": None}
    return bake_octree(model, spec, BAKE_DEPTH, progress=False)


def _random_tree(depth=5, n=3000, seed=0, sh_degree=2):
    """A model holding a random octree: `n` random leaves, densities in [0, 50) 1/m."""
    rng = np.random.default_rng(seed)
    ijk = np.unique(rng.integers(0, 2 ** depth, (n, 3)), axis=0)
    child, order = build_octree(ijk, depth)
    model = PlenOctreeModel(AABB, make_background("learned"),
                            PlenOctreeConfig(depth=depth, sh_degree=sh_degree))
    n_sh = (sh_degree + 1) ** 2
    data = np.concatenate([rng.random((len(ijk), 1)) * 50, rng.normal(size=(len(ijk), 3 * n_sh))],
                          1).astype(np.float32)
    model.field.set_tree(child, data[order])
    return model.eval(), ijk, order


def _rays_towards_box(n=400, seed=0):
    """Rays from a camera 2 m in front of the box (some miss it), directions spread ~17 deg."""
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, -2.0, 0.45]) + 0.1 * torch.randn(n, 3, generator=g)
    d = torch.nn.functional.normalize(torch.tensor([0.0, 1.0, 0.0])
                                      + 0.3 * torch.randn(n, 3, generator=g), dim=-1)
    return Rays(o.contiguous(), d.contiguous(), torch.ones(n))


# -- field -----------------------------------------------------------------------------------
def test_sh_color_is_sigmoid_of_sh_dot_coefficients():
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    k = torch.randn(50, 27, generator=g)
    basis = spherical_harmonics(d, 2)
    expected = torch.sigmoid(torch.stack([(k[:, 9 * c:9 * (c + 1)] * basis).sum(-1)
                                          for c in range(3)], -1))
    torch.testing.assert_close(sh_color(k, d), expected)
    with pytest.raises(ValueError):
        sh_color(torch.zeros(5, 26), d[:5])


def test_nerfsh_field_ignores_direction_in_density_and_starts_at_mean_colour():
    field = NeRFSHField(AABB)
    rgb = torch.tensor([0.2, 0.5, 0.7])
    field.init_mean_color(rgb)
    x = torch.rand(64, 3) * 0.5 - 0.25 + torch.tensor([0.0, 0.0, 0.45])
    sigma, feat = field.density(x)
    assert feat.shape == (64, 27) and sigma.shape == (64,) and bool((sigma >= 0).all())
    outside = field.density(torch.tensor([[5.0, 0.0, 0.0]]))[0]
    assert float(outside.detach()) == 0.0
    # at initialisation only the degree-0 coefficient carries a bias: colour ~ rgb everywhere
    d = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    with torch.no_grad():
        zero_feat = field.mlp[-1].bias[1:].expand(64, 27)
    torch.testing.assert_close(field.color(zero_feat, d), rgb.expand(64, 3), atol=1e-5, rtol=0)
    with pytest.raises(ValueError):
        NeRFSHField(AABB, type(field.config)(sh_degree=5))


def test_nerfsh_sparsity_prior_is_seeded_by_the_step():
    """The prior's random points depend on the step only (resumed runs draw the same ones);
    weight 0 turns it off."""
    field = NeRFSHField(AABB)
    field.before_step(7, 0.1)
    a, loss = field.prior_points(), field.regularizer()
    assert loss.dim() == 0 and float(loss.detach()) > 0 and loss.requires_grad
    assert torch.equal(a, field.prior_points())
    lo, hi = torch.tensor(AABB)
    assert bool(((a >= lo) & (a <= hi)).all())
    field.before_step(8, 0.1)
    assert not torch.equal(a, field.prior_points())
    off = NeRFSHField(AABB, type(field.config)(sparsity_weight=0.0))
    assert off.regularizer() is None
    with pytest.raises(ValueError):
        NeRFSHField(AABB, type(field.config)(sparsity_weight=-1.0))


def test_nerfsh_trains_tiny_capture_to_threshold(sh_run):
    """150 steps on 16 views of 32x32 reach >= 20 dB test PSNR (ngp: ~23.5 dB at 120 steps;
    the mean-colour predictor scores ~11 dB)."""
    _, model, psnr = sh_run
    assert psnr >= 20.0, psnr
    assert float(model.grid.occupied.float().mean()) < 0.5


# -- octree arrays and kernels ---------------------------------------------------------------
def test_build_octree_lookup_finds_every_leaf_and_nothing_else():
    model, ijk, order = _random_tree()
    field = model.field
    cmin, size = field.normalize.cube_min, field.cube_size
    n = 2 ** 5
    centres = cmin + (torch.from_numpy(ijk).float() + 0.5) * size / n
    leaf_of_row = torch.from_numpy(np.argsort(order))
    assert torch.equal(field.leaf_index(centres), leaf_of_row)
    g = torch.Generator().manual_seed(1)
    pts = cmin - 0.05 * size + 1.1 * size * torch.rand(20000, 3, generator=g)
    fast = field.leaf_index(pts)
    assert torch.equal(fast, octree_lookup_reference(pts, field.child, cmin, size))
    occupied = set(map(tuple, ijk))
    cells = torch.floor((pts - cmin) / size * n).long().numpy()
    expect = np.array([tuple(c) in occupied and bool(((c >= 0) & (c < n)).all()) for c in cells])
    assert np.array_equal(fast.numpy() >= 0, expect)
    # leaf_cells inverts build_octree
    from nerfbot.models.plenoctree import leaf_cells

    cells_back, levels = leaf_cells(field.child)
    assert np.array_equal(cells_back, ijk[order]) and (levels == 5).all()
    # an empty tree is one root with 8 empty children
    child, order = build_octree(np.zeros((0, 3)), 4)
    assert child.shape == (1, 8) and (child == -1).all() and order.size == 0
    with pytest.raises(ValueError):
        build_octree(np.array([[0, 0, 0], [0, 0, 0]]), 3)
    with pytest.raises(ValueError):
        build_octree(np.array([[8, 0, 0]]), 3)


def test_numba_walker_matches_torch_twin():
    model, _, _ = _random_tree(seed=2)
    rays = _rays_towards_box()
    t_near, t_far, _ = ray_aabb(rays.origins, rays.directions, model.aabb)
    field = model.field
    for stop in (1e-3, 0.0):
        args = (rays.origins, rays.directions, t_near, t_far, field.child,
                field.leaf_data[:, 0].detach(), field.normalize.cube_min, field.cube_size, stop)
        fast, ref = walk_segments(*args), walk_segments_reference(*args)
        assert fast[0].numel() > 100
        assert torch.equal(fast[0], ref[0]) and torch.equal(fast[1], ref[1])
        torch.testing.assert_close(fast[2], ref[2], atol=1e-6, rtol=0)
        torch.testing.assert_close(fast[3], ref[3], atol=1e-6, rtol=0)
    # segments tile each ray's walk: contiguous within a leaf run, inside [t_near, t_far]
    ray, _, ts, te = fast
    assert bool((te >= ts).all())
    assert bool((ts >= t_near[ray] - 1e-6).all()) and bool((te <= t_far[ray] + 1e-6).all())


def _assert_same_render(model, rays, fused, ref):
    """The fused renderer reads its background from the baked table: compare with the
    differentiable path's pixels under that same background (the table's own error is
    bounded in test_background.py)."""
    assert fused.num_samples == ref.num_samples > 0
    assert torch.equal(fused.ray_indices, ref.ray_indices)
    baked = torch.from_numpy(model.baked_background(rays.directions))
    rgb = ref.rgb + (1.0 - ref.opacity)[:, None] * (baked - model.background(rays.directions))
    torch.testing.assert_close(fused.rgb, rgb.detach(), atol=2e-5, rtol=1e-5)
    for key in ("opacity", "depth", "z_depth", "median_depth", "weights", "t_starts",
                "t_ends", "sigmas"):
        torch.testing.assert_close(getattr(fused, key), getattr(ref, key).detach(), atol=2e-5,
                                   rtol=1e-5, msg=key)


@pytest.mark.parametrize("sh_degree,slots", [(0, 32), (2, 32), (4, 32), (2, 1)])
def test_fused_renderer_equals_differentiable_path_on_random_tree(sh_degree, slots, monkeypatch):
    """Same pixels, depths and packed samples; ``slots`` = 1 makes most rays overflow their
    first-pass scratch and be rendered a second time."""
    import nerfbot.models.plenoctree as plenoctree

    monkeypatch.setattr(plenoctree, "SLOT_SEGMENTS", slots)
    model, _, _ = _random_tree(seed=3, sh_degree=sh_degree)
    model.config.color_min_weight = 0.0  # shade every segment, as the torch path does
    rays = _rays_towards_box(seed=4)
    _assert_same_render(model, rays, model.render_rays(rays),
                        model.render_segments(rays, reference=True))
    # rays that miss the box: background colour, far depth, nothing NaN
    miss = Rays(torch.tensor([[0.0, -2.0, 5.0]]), torch.tensor([[0.0, 1.0, 0.0]]), torch.ones(1))
    out = model.render_rays(miss)
    torch.testing.assert_close(out.rgb, model.background(miss.directions).detach(), atol=2e-3,
                               rtol=0)
    assert float(out.opacity) == 0.0 and torch.isfinite(out.depth).all()


# -- baking ----------------------------------------------------------------------------------
def test_octree_leaves_match_the_field_at_leaf_centres(sh_run):
    """With one sample per leaf, every leaf holds exactly the field's output at its centre."""
    _, model, _ = sh_run
    spec = {"method": "plenoctree", "aabb": model.aabb.tolist(), "background": "learned",
            "options": {}, "seed": 0, "conditioning": None}
    octree, baked_spec, extra = bake_octree(model, spec, 5, progress=False, samples_per_leaf=1)
    assert baked_spec["method"] == "plenoctree_octree"
    assert baked_spec["options"] == {"depth": 5, "sh_degree": 2}
    field = octree.field
    assert extra["leaves"] == field.n_leaves > 0 and extra["nodes"] == field.n_nodes
    # the centre of every leaf: find it by walking its code back from the child table
    cmin, size = field.normalize.cube_min, field.cube_size
    n = 2 ** 5
    idx = torch.arange(n)
    cells = torch.stack(torch.meshgrid(idx, idx, idx, indexing="ij"), -1).reshape(-1, 3)
    centres = cmin + (cells.float() + 0.5) * size / n
    leaf = field.leaf_index(centres)
    hit = leaf >= 0
    assert int(hit.sum()) == field.n_leaves
    with torch.no_grad():
        sigma, coeffs = model.field.density(centres[hit])
    stored = field.leaf_data.detach()[leaf[hit]]
    torch.testing.assert_close(stored[:, 0], sigma, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(stored[:, 1:], coeffs, rtol=1e-5, atol=1e-5)
    # the octree keeps what the source renders: the dense leaves, a small part of the cube
    assert 0 < field.n_leaves < 0.5 * n ** 3


def test_baked_octree_renders_close_to_source(tiny_capture, sh_run, baked):
    _, _, source_psnr = sh_run
    octree, _, extra = baked
    ds = load_dataset(tiny_capture[0])
    metrics = evaluate(octree, ds, "test", with_ssim=False)
    assert metrics["psnr"] >= source_psnr - 1.5, (metrics["psnr"], source_psnr)
    assert extra["octree_mb"] > 0 and extra["depth"] == BAKE_DEPTH


def test_fused_renderer_equals_differentiable_path_on_baked_octree(tiny_capture, baked,
                                                                    monkeypatch):
    octree, _, _ = baked
    ds = load_dataset(tiny_capture[0])
    rays = ds.cameras(ds.indices("test")).rays(0)
    default = octree.config.color_min_weight
    monkeypatch.setattr(octree.config, "color_min_weight", 0.0)
    exact = octree.render_rays(rays)
    _assert_same_render(octree, rays, exact, octree.render_segments(rays))
    # with the default, faint segments take their ray's mean colour: each pixel moves by at
    # most their weight, and nothing else moves
    monkeypatch.setattr(octree.config, "color_min_weight", default)
    faint = octree.render_rays(rays)
    skipped = exact.weights * (exact.weights <= default)
    bound = torch.zeros(len(rays)).index_add_(0, exact.ray_indices, skipped)
    assert default > 0 and float(bound.max()) > 1e-4
    assert bool(((faint.rgb - exact.rgb).abs() <= bound[:, None] + 1e-5).all())
    for key in ("opacity", "depth", "median_depth", "weights"):
        torch.testing.assert_close(getattr(faint, key), getattr(exact, key))


def test_visibility_pruning_drops_unseen_leaves_and_keeps_the_image(tiny_capture, baked):
    """Leaves no training pixel weighs at >= 0.01 go; test renders barely change."""
    from nerfbot.bake.plenoctree import leaf_visibility, prune_leaves

    octree, spec, _ = baked
    ds = load_dataset(tiny_capture[0])
    pruned = PlenOctreeModel(octree.aabb, make_background("learned"), PlenOctreeConfig(depth=6))
    pruned.field.set_tree(octree.field.child.clone(), octree.field.leaf_data.detach().clone())
    pruned.background.load_state_dict(octree.background.state_dict())
    pruned.eval()
    seen = leaf_visibility(pruned, ds, progress=False)
    assert seen.shape == (octree.field.n_leaves,) and bool((seen >= 0).all() & (seen <= 1).all())
    keep = seen >= 0.01
    prune_leaves(pruned, keep.numpy())
    assert pruned.field.n_leaves == int(keep.sum()) < octree.field.n_leaves
    # the kept leaves carry their values into the rebuilt tree
    torch.testing.assert_close(torch.sort(pruned.field.leaf_data.detach()[:, 0]).values,
                               torch.sort(octree.field.leaf_data.detach()[keep, 0]).values)
    before = evaluate(octree, ds, "test", with_ssim=False)["psnr"]
    after = evaluate(pruned, ds, "test", with_ssim=False)["psnr"]
    assert after >= before - 0.5, (before, after)


def test_pruning_backs_off_until_the_training_views_keep_their_pixels(tiny_capture, baked):
    """A threshold that would cut visible leaves (0.5) is halved until the training views
    render within PRUNE_FIDELITY_DB of the unpruned tree; a zero-weight 'seen' prunes only
    unseen leaves at the first try."""
    from nerfbot.bake.plenoctree import PRUNE_FIDELITY_DB, leaf_visibility, prune_with_fidelity

    octree, _, _ = baked
    ds = load_dataset(tiny_capture[0])

    def copy():
        m = PlenOctreeModel(octree.aabb, make_background("learned"), PlenOctreeConfig(depth=6))
        m.field.set_tree(octree.field.child.clone(), octree.field.leaf_data.detach().clone())
        m.background.load_state_dict(octree.background.state_dict())
        return m.eval()

    model = copy()
    seen = leaf_visibility(model, ds, progress=False)
    used = prune_with_fidelity(model, seen, 0.5, ds)
    assert used < 0.5 and model.field.n_leaves == int((seen >= used).sum())
    rays = ds.cameras(ds.indices("train")[:4]).rays(0)
    with torch.no_grad():
        mse = torch.nn.functional.mse_loss(model.render_rays(rays).rgb,
                                           octree.render_rays(rays).rgb)
    assert -10 * math.log10(max(float(mse), 1e-12)) >= PRUNE_FIDELITY_DB
    # nothing the cameras see is removed when the threshold is tiny
    model = copy()
    assert prune_with_fidelity(model, seen, 1e-12, ds) == 1e-12
    assert model.field.n_leaves == int((seen >= 1e-12).sum())


def test_finetuning_lowers_the_training_loss(tiny_capture, sh_run):
    _, model, _ = sh_run
    ds = load_dataset(tiny_capture[0])
    spec = {"method": "plenoctree", "aabb": model.aabb.tolist(), "background": "learned",
            "options": {}, "seed": 0, "conditioning": None}
    octree, _, _ = bake_octree(model, spec, BAKE_DEPTH, progress=False, samples_per_leaf=1)
    before = octree.field.leaf_data.detach().clone()
    report = finetune_octree(octree, ds, 40, seed=0, progress=False)
    assert report["finetune_psnr_after"] > report["finetune_psnr_before"] + 0.3, report
    assert torch.isfinite(octree.field.leaf_data).all()
    assert not torch.equal(before, octree.field.leaf_data.detach())


def test_bake_rejects_bad_inputs(sh_run):
    _, model, _ = sh_run
    spec = {"method": "plenoctree", "aabb": model.aabb.tolist(), "background": "learned",
            "options": {}, "seed": 0, "conditioning": None}
    with pytest.raises(ValueError, match="depth"):
        bake_octree(model, spec, 0, progress=False)
    with pytest.raises(ValueError, match="samples_per_leaf"):
        bake_octree(model, spec, 4, progress=False, samples_per_leaf=5)
    with pytest.raises(ValueError, match="prune_weight"):
        bake_octree(model, spec, 4, progress=False, prune_weight=1.0)
    with pytest.raises(ValueError, match="dataset"):
        bake_octree(model, spec, 4, progress=False, finetune_steps=3)
    ngp = build_model("ngp", model.aabb.numpy())
    with pytest.raises(ValueError, match="NeRF-SH"):
        bake_octree(ngp, {**spec, "method": "ngp"}, 4, progress=False)


def test_cli_bake_octree_writes_a_run_that_eval_loads(tiny_capture, sh_run, tmp_path, capsys):
    from nerfbot.app.cli import main

    run, _, _ = sh_run
    out = tmp_path / "octree"
    assert main(["bake", str(run), "--octree", str(BAKE_DEPTH), "--finetune-steps", "5",
                 "--out", str(out), "--no-progress"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["leaves"] > 0 and printed["depth"] == BAKE_DEPTH
    assert "finetune_psnr_after" in printed
    report = json.loads((out / "bake.json").read_text())
    assert report["method"] == "plenoctree_octree" and report["leaves"] == printed["leaves"]
    model, info = load_model(out)
    assert isinstance(model, PlenOctreeModel) and model.field.n_leaves == printed["leaves"]
    assert main(["eval", str(out), "--json"]) == 0
    metrics = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert metrics["method"] == "plenoctree_octree" and metrics["psnr"] > 18.0
