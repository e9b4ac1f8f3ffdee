"""Rays that cross the bounds from their top face to their bottom face, and the learned
background they may not train (``floor_trains_background``)."""

from __future__ import annotations

import math

import pytest
import torch

from nerfbot.methods import build_model
from nerfbot.ops.cameras import Rays
from nerfbot.ops.sampling import crosses_top_to_bottom, ray_aabb

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


def _loss_gradients(rays: Rays, rgb: torch.Tensor, trains: bool):
    """One training loss of a fresh seeded ngp on ``rays``: (rendered colours, the sum of the
    background's absolute gradients, the sum of the field's)."""
    torch.manual_seed(0)
    model = build_model("ngp", BOX, options={"log2_hashmap_size": 12,
                                             "samples_per_batch": 1 << 12,
                                             "floor_trains_background": trains})
    model.train()
    loss, out = model.loss(rays, rgb, torch.Generator().manual_seed(1))
    loss.backward()
    background = sum(float(p.grad.abs().sum()) for p in model.background.parameters())
    field = sum(float(p.grad.abs().sum()) for p in model.field.parameters()
                if p.grad is not None)
    return out.rgb.detach(), background, field


@pytest.mark.parametrize("draw, crossing", [(table_rays, True), (side_rays, False)])
def test_only_rays_crossing_from_top_to_bottom_are_kept_from_the_background(draw, crossing):
    """Without ``floor_trains_background`` the background's gradient from rays that cross the
    box from its top face to its bottom face (:func:`table_rays`) is exactly zero, and from
    rays that enter through a side (:func:`side_rays`) it is not; with it, both train it. The
    field's gradient is never cut and the rays render the same."""
    rays, rgb = draw(256, torch.Generator().manual_seed(3))
    t_near, t_far, hit = ray_aabb(rays.origins, rays.directions, BOX)
    assert bool((crosses_top_to_bottom(rays.origins, rays.directions, t_near, t_far, hit,
                                       BOX) == crossing).all())
    rgb_on, background_on, field_on = _loss_gradients(rays, rgb, True)
    rgb_off, background_off, field_off = _loss_gradients(rays, rgb, False)
    assert background_on > 0 and field_on > 0 and field_off > 0
    assert (background_off == 0.0) == crossing, background_off
    torch.testing.assert_close(rgb_on, rgb_off, rtol=0, atol=0)
