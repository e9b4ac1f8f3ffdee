"""The scene contraction: the map, the grid over contracted space, and `ngp` trained with it on a
scene whose content reaches beyond the bounds it is given."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.fields.base import ContractedNormalizer
from nerfbot.methods import build_model
from nerfbot.ops.cameras import Rays
from nerfbot.ops.contraction import contract, disparity_distance, step_scale, uncontract
from nerfbot.ops.sampling import OccupancyGrid
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(65)


def _directions(n: int, g: torch.Generator) -> torch.Tensor:
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


def test_identity_inside_and_far_points_inside_the_contracted_cube():
    g = torch.Generator().manual_seed(0)
    inner = torch.rand(2000, 3, generator=g, dtype=torch.float64) * 2 - 1
    assert torch.equal(contract(inner), inner)
    radii = torch.logspace(0, 9, 2000, dtype=torch.float64)[:, None]
    far = _directions(2000, g) * radii * 1.8          # L-inf norms from about 1 to 1e9
    c = contract(far)
    assert bool((c.abs().amax(-1) < 2.0).all())
    # directions are kept, and the contracted norm grows with the distance
    cos = (torch.nn.functional.normalize(c, dim=-1) * torch.nn.functional.normalize(far, dim=-1))
    assert bool((cos.sum(-1) > 1 - 1e-12).all())
    n = c.abs().amax(-1)
    order = far.abs().amax(-1).argsort()
    assert bool((n[order].diff() >= 0).all())
    # continuous at the inner cube's surface
    edge = torch.tensor([[1.0, 0.3, -0.2]], dtype=torch.float64)
    assert torch.allclose(contract(edge * (1 + 1e-9)), edge, atol=1e-8)


def test_uncontract_inverts_contract():
    g = torch.Generator().manual_seed(1)
    y = _directions(1000, g) * torch.logspace(-2, 3, 1000, dtype=torch.float64)[:, None]
    assert torch.allclose(uncontract(contract(y)), y, rtol=1e-9, atol=1e-12)


def test_step_scale_and_disparity_distance():
    y = torch.tensor([[0.5, 0.0, 0.0], [0.0, -3.0, 1.0], [10.0, 10.0, 10.0]])
    assert torch.equal(step_scale(y), torch.tensor([1.0, 9.0, 100.0]))
    t = torch.tensor([0.0, 1.0, 2.0, 4.0, 1e9])
    s = disparity_distance(t, 2.0)
    assert torch.allclose(s, torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0]), atol=1e-6)
    assert bool((s.diff() >= 0).all()) and float(s.max()) <= 4.0


def test_contracted_normalizer_maps_the_bounds_cube_to_the_middle_of_the_unit_cube():
    aabb = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 1.0]])
    norm = ContractedNormalizer(aabb)
    corners = torch.tensor([[-1.0, -1.0, -0.5], [1.0, 1.0, 1.5]])   # the enclosing cube
    assert torch.allclose(norm(corners), torch.tensor([[0.25] * 3, [0.75] * 3]))
    far = torch.tensor([[1e6, -1e6, 3.0], [0.0, 0.0, -50.0]])
    u = norm(far)
    assert bool(((u > 0) & (u < 1)).all()) and bool(norm.inside(far).all())


def test_contracted_grid_covers_far_space_and_marching_reaches_it():
    """A ray from the centre towards an occupied far cell gets samples in that cell and nowhere
    else, and crosses all of space in a finite number of steps."""
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = OccupancyGrid(aabb, 64, contract=True)
    assert bool(grid.inside.all())
    world = grid.cell_points(torch.full((64 ** 3, 3), 0.5))
    assert float(world.abs().max()) == pytest.approx(32.0)  # outer cell centres: c = 1.97
    assert torch.allclose(grid.lookup_points(world),
                          grid.cube_min + (grid._cell_index + 0.5) * grid.cell_size, atol=1e-4)
    # the cell holding x = 6 half-sizes spans contracted x in [1.8125, 1.875): x in [5.33, 8)
    target = torch.tensor([[6.0, 0.01, 0.01]])
    cell = ((grid.lookup_points(target) - grid.cube_min) / grid.cell_size).floor().long()[0]
    grid.occupied.zero_()
    grid.occupied[cell[0], cell[1], cell[2]] = 1
    d = torch.tensor([[1.0, 0.0, 0.0]])
    origin = torch.tensor([[0.0, 0.01, 0.01]])
    s = grid.march(origin, d, torch.zeros(1), torch.full((1,), 1000.0), 0.01, 0.01)
    assert len(s) > 0
    mids = 0.5 * (s.t_starts + s.t_ends)                    # the marcher tests midpoints
    assert float(mids.min()) >= 16 / 3 and float(mids.max()) < 8.0
    assert float(s.t_stop[0]) >= 1000.0
    grid.occupied.fill_(1)
    everywhere = grid.march(origin, d, torch.zeros(1), torch.full((1,), 1000.0), 0.01, 0.01)
    # 100 steps to the inner cube's face, about 100 more to 1000 half-sizes (1 / n^2 decay)
    assert 150 < len(everywhere) < 260


def test_contraction_refused_by_fields_without_contracted_coordinates():
    aabb = np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="contraction"):
        build_model("plenoxels", aabb, "learned", {"contraction": True}, seed=0)


def test_contracted_ngp_renders_finite_and_far(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    model = build_model("ngp", ds.aabb, "learned", {"contraction": True}, seed=0).eval()
    g = torch.Generator().manual_seed(2)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    rays = Rays(torch.as_tensor(ds.aabb.mean(0), dtype=torch.float32).expand(64, 3), d,
                torch.ones(64))
    out = model.render_rays(rays)
    assert bool(torch.isfinite(out.rgb).all()) and bool(torch.isfinite(out.depth).all())


@pytest.mark.parametrize("shrink", [0.45])
def test_contraction_models_content_beyond_the_bounds(tiny_capture, tmp_path, shrink):
    """Given bounds that cut the table in half, the box model cannot represent what lies
    outside them; the contracted model can, and fits the test views better at equal steps."""
    folder = tiny_capture[0]
    full = load_dataset(folder)
    centre = full.aabb.mean(0)
    half = shrink * (full.aabb[1] - full.aabb[0]).max() / 2
    small = np.stack([centre - half, centre + half])
    ds = load_dataset(folder, aabb=small)
    scores = {}
    for contraction in (False, True):
        cfg = TrainConfig(method="ngp", max_steps=150, seed=0, progress=False,
                          options={"samples_per_batch": 8192, "grid_update_every": 8,
                                   "contraction": contraction})
        trainer = Trainer(ds, tmp_path / f"run_{contraction}", cfg)
        trainer.train()
        scores[contraction] = evaluate(trainer.model, full, "test", with_ssim=False,
                                       supersample=1)
    box, contracted = scores[False], scores[True]
    # observed, one ray per pixel: box 16.9 dB, contracted 20.7 dB
    assert contracted["psnr"] >= 19.0, scores
    assert contracted["psnr"] >= box["psnr"] + 1.0, scores


def _look_at(origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(N, 4, 4) OpenGL camera-to-world poses at ``origins`` looking at ``targets``."""
    poses = []
    for o, t in zip(origins, targets):
        back = o - t
        back = back / np.linalg.norm(back)
        right = np.cross([0.0, 0.0, 1.0], back)
        right = right / np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(back, right), back, o
        poses.append(pose)
    return np.stack(poses)


def _ring(n: int, radius: float, height: float) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(a), radius * np.sin(a), np.full(n, height)], -1)


def test_choose_space_from_manifest_bounds_and_cameras():
    from nerfbot.data.bounds import choose_space

    ring = _ring(24, 4.0, 1.5)
    inward = _look_at(ring, np.zeros_like(ring))
    table = np.array([[-0.7, -0.7, 0.0], [0.7, 0.7, 0.8]])
    assert not choose_space(table, "manifest", inward).contraction
    yard = np.array([[-150.0, -150.0, -1.0], [150.0, 150.0, 30.0]])
    space = choose_space(yard, "manifest", inward)
    assert space.contraction and "unbounded" in space.reason
    lo, hi = space.aabb
    assert np.all(lo <= ring.min(0)) and np.all(hi >= ring.max(0)) and (hi - lo).max() < 12
    assert not choose_space(yard, "user", inward).contraction
    # seen from inside: cameras spread over a room, each looking outwards at a wall
    rng = np.random.default_rng(0)
    spots = np.c_[rng.uniform(-2, 2, (30, 2)), rng.uniform(0.4, 1.6, 30)]
    away = spots + np.c_[np.cos(a := rng.uniform(0, 2 * np.pi, 30)), np.sin(a), np.zeros(30)]
    outward = _look_at(spots, away)
    space = choose_space(table, "cameras", outward)
    assert not space.contraction and "inside" in space.reason   # the box around the cameras
    lo, hi = space.aabb
    assert np.all(lo <= spots.min(0)) and np.all(hi >= spots.max(0))
    assert not choose_space(table, "cameras", inward).contraction
