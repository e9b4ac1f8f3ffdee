"""Rays that cross the bounds from their top face to their bottom face, and what the learned
background does on them (``floor_background``)."""

from __future__ import annotations

import math

import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.methods import build_model
from nerfbot.models.occupancy import FLOOR_SUPPORT_SHARE
from nerfbot.ops.cameras import Rays
from nerfbot.ops.sampling import crosses_top_to_bottom, ray_aabb
from nerfbot.train.trainer import TrainConfig, Trainer

BOX = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
MAT_RGB = torch.tensor([0.1, 0.2, 0.7])     # a plain blue mat on a plain wooden table
TABLE_RGB = torch.tensor([0.6, 0.4, 0.2])
TOP = 0.1                                   # the table top's height; the box's bottom at 0


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def test_top_to_bottom_rays_are_those_entering_and_leaving_on_those_faces():
    g = torch.Generator().manual_seed(0)
    origins = (torch.rand(40000, 3, generator=g) * 4 - 2).double()
    origins[:, 2] += 1.5                                   # most start above the box
    directions = _unit(torch.randn(40000, 3, generator=g)).double()
    t_near, t_far, hit = ray_aabb(origins.float(), directions.float(), BOX)
    got = crosses_top_to_bottom(origins.float(), directions.float(), t_near, t_far, hit, BOX)
    entry = origins + directions * t_near.double()[:, None]
    leave = origins + directions * t_far.double()[:, None]
    inside_xy = ((entry[:, :2].abs() <= 1 + 1e-5).all(1) & (leave[:, :2].abs() <= 1 + 1e-5).all(1))
    expected = (hit & (origins[:, 2] > 1.0) & ((entry[:, 2] - 1.0).abs() < 1e-5)
                & (leave[:, 2].abs() < 1e-5) & inside_xy)
    assert int(expected.sum()) > 200 and int((hit & ~expected).sum()) > 1000
    assert torch.equal(got, expected)
    # by hand: straight down from above; down and out through a side; down from inside the box
    # (a room's camera); in through a side and out through the bottom (under a table); a miss
    o = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.5], [-3.0, 0.0, 0.9],
                      [5.0, 5.0, 5.0]])
    d = _unit(torch.tensor([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, 0.0, -1.0],
                            [1.0, 0.0, -0.35], [1.0, 0.0, 0.0]]))
    t_near, t_far, hit = ray_aabb(o, d, BOX)
    assert crosses_top_to_bottom(o, d, t_near, t_far, hit, BOX).tolist() == [
        True, False, False, False, False]


def table_rays(n: int, gen: torch.Generator) -> tuple[Rays, torch.Tensor]:
    """n rays from cameras 2-3 m from a table top filling the box (its plain top at z =
    ``TOP``, a plain mat on its middle), 65-85 degrees above it, through random points of its
    middle: each enters the box through its top face and would go on to its bottom face; the
    colour each sees."""
    azimuth = torch.rand(n, generator=gen) * 2 * math.pi
    elevation = torch.rand(n, generator=gen) * 0.35 + 1.13          # 65-85 degrees
    distance = torch.rand(n, generator=gen) + 2.0
    towards = torch.stack([torch.cos(elevation) * torch.cos(azimuth),
                           torch.cos(elevation) * torch.sin(azimuth), torch.sin(elevation)], 1)
    targets = torch.cat([(torch.rand(n, 2, generator=gen) * 1.1 - 0.55),
                         torch.full((n, 1), TOP)], 1)
    on_mat = (targets[:, :2].abs() < 0.3).all(1)
    return (Rays(targets + distance[:, None] * towards, -towards, torch.ones(n)),
            torch.where(on_mat[:, None], MAT_RGB, TABLE_RGB))


def side_rays(n: int, gen: torch.Generator) -> tuple[Rays, torch.Tensor]:
    """n rays from 3 m beside the box, 0.5 m below its top, through random points of the table
    top: each enters the box through a side face (the sky under a table), with its colour."""
    azimuth = torch.rand(n, generator=gen) * 2 * math.pi
    origins = torch.stack([3.0 * torch.cos(azimuth), 3.0 * torch.sin(azimuth),
                           torch.full((n,), 0.5)], 1)
    targets = torch.cat([(torch.rand(n, 2, generator=gen) * 1.1 - 0.55),
                         torch.full((n, 1), TOP)], 1)
    return Rays(origins, _unit(targets - origins), torch.ones(n)), TABLE_RGB.expand(n, 3)


def _model(floor_background: str, **options):
    torch.manual_seed(0)
    return build_model("ngp", BOX, options={"log2_hashmap_size": 12,
                                            "samples_per_batch": 1 << 12,
                                            "floor_background": floor_background,
                                            "floor_random_ramp": 0.0, **options})


def _loss_gradients(rays: Rays, rgb: torch.Tensor, floor_background: str):
    """One training loss of a fresh seeded ngp on ``rays``: (rendered colours, the sum of the
    background's absolute gradients, the sum of the field's)."""
    model = _model(floor_background)
    model.train()
    loss, out = model.loss(rays, rgb, torch.Generator().manual_seed(1))
    loss.backward()
    background = sum(float(p.grad.abs().sum()) for p in model.background.parameters()
                     if p.grad is not None)
    field = sum(float(p.grad.abs().sum()) for p in model.field.parameters()
                if p.grad is not None)
    return out.rgb.detach(), background, field


@pytest.mark.parametrize("draw, crossing", [(table_rays, True), (side_rays, False)])
def test_only_rays_crossing_from_top_to_bottom_are_acted_on(draw, crossing):
    """On rays that cross the box from its top face to its bottom face (:func:`table_rays`)
    ``detached`` leaves the background exactly no gradient and the colours as ``learned``
    renders them; ``random`` leaves it no gradient either and shows other colours through
    the rays' transmittance. On rays that enter through a side (:func:`side_rays`) all three
    are the same. The field's gradient is never cut."""
    rays, rgb = draw(256, torch.Generator().manual_seed(3))
    t_near, t_far, hit = ray_aabb(rays.origins, rays.directions, BOX)
    assert bool((crosses_top_to_bottom(rays.origins, rays.directions, t_near, t_far, hit,
                                       BOX) == crossing).all())
    rgb_learned, background_learned, field_learned = _loss_gradients(rays, rgb, "learned")
    rgb_detached, background_detached, field_detached = _loss_gradients(rays, rgb, "detached")
    rgb_random, background_random, field_random = _loss_gradients(rays, rgb, "random")
    assert background_learned > 0 and min(field_learned, field_detached, field_random) > 0
    assert (background_detached == 0.0) == crossing, background_detached
    assert (background_random == 0.0) == crossing, background_random
    torch.testing.assert_close(rgb_learned, rgb_detached, rtol=0, atol=0)
    if crossing:
        assert float((rgb_random - rgb_learned).abs().mean()) > 0.05
    else:
        torch.testing.assert_close(rgb_learned, rgb_random, rtol=0, atol=0)


def _opacity_after_training(floor_background: str, steps: int) -> float:
    """Mean opacity, in eval mode, of fresh table rays after ``steps`` Adam steps on the
    plain table (every ray crossing from top to bottom)."""
    model = _model(floor_background)
    gen = torch.Generator().manual_seed(5)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    model.train()
    for _ in range(steps):
        rays, rgb = table_rays(512, gen)
        loss, _ = model.loss(rays, rgb, gen)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    model.eval()
    rays, _ = table_rays(512, torch.Generator().manual_seed(6))
    with torch.no_grad():
        return float(model.render_rays(rays).opacity.mean())


def test_random_colours_leave_the_rays_ending_inside_the_bounds():
    """Trained on a plain table whose every ray crosses the box from top to bottom, the
    field under ``random`` ends nearly every ray inside the box, while under ``learned`` the
    background, which can show the plain colours, keeps part of the light."""
    learned = _opacity_after_training("learned", 60)
    random = _opacity_after_training("random", 60)
    assert random > 0.97, random
    assert random > learned + 0.05, (learned, random)


def test_floor_background_names_its_values():
    with pytest.raises(ValueError, match="floor_background"):
        _model("sky")


def test_random_colours_fade_in_over_the_ramp():
    """With ``floor_random_ramp`` R the crossing rays see the learned background's colour at
    the start of the budget, the random one from R on, and a mix in between."""
    rays, rgb = table_rays(256, torch.Generator().manual_seed(3))

    def colours(mode: str, progress: float) -> torch.Tensor:
        model = _model(mode, floor_random_ramp=0.5)
        model.train()
        model.before_step(0, torch.Generator().manual_seed(2), progress=progress)
        with torch.no_grad():
            return model.render_rays(rays, torch.Generator().manual_seed(1)).rgb

    learned = colours("learned", 0.0)
    torch.testing.assert_close(colours("random", 0.0), learned, rtol=0, atol=0)
    late = colours("random", 0.5)
    assert float((late - learned).abs().mean()) > 0.05
    torch.testing.assert_close(colours("random", 0.9), late, rtol=0, atol=0)
    middle = colours("random", 0.25)
    torch.testing.assert_close(middle, 0.5 * (learned + late), rtol=0, atol=1e-5)


def test_auto_chooses_from_the_share_of_crossing_rays(tiny_capture, tmp_path):
    """The bank's share of rays crossing top to bottom is the share over every training
    pixel's centre ray (the tiny capture has no more pixels than the spread takes); ``auto``
    trains the tabletop, whose rays mostly enter through the sides or miss, as ``learned``,
    and would give random colours to a capture whose rays nearly all cross."""
    ds = load_dataset(tiny_capture[0])
    trainer = Trainer(ds, tmp_path / "auto", TrainConfig(method="ngp", max_steps=1, seed=0,
                                                         progress=False,
                                                         options={"floor_background": "auto"}))
    bank = trainer.bank
    rays = bank.centre_rays(torch.arange(len(bank)))
    for box in (ds.aabb, [[-3.0, -3.0, -1.0], [3.0, 3.0, 0.5]]):
        box = torch.as_tensor(box, dtype=torch.float32)
        t_near, t_far, hit = ray_aabb(rays.origins, rays.directions, box)
        expected = float(crosses_top_to_bottom(rays.origins, rays.directions, t_near, t_far,
                                               hit, box).float().mean())
        assert bank.top_to_bottom_share(box) == pytest.approx(expected, abs=1e-6)
    assert bank.top_to_bottom_share(ds.aabb) < FLOOR_SUPPORT_SHARE
    assert trainer.model.floor_mode == "learned"
    trainer.model.init_floor_share(0.95)
    assert trainer.model.floor_mode == "random"
    fixed = _model("detached")
    fixed.init_floor_share(0.95)
    assert fixed.floor_mode == "detached"
