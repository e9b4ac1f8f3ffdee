"""Rays that leave the bounds through their bottom face, and the learned background they may not
train (``floor_trains_background``)."""

from __future__ import annotations

import math

import pytest
import torch

from nerfbot.methods import build_model
from nerfbot.ops.cameras import Rays
from nerfbot.ops.sampling import leaves_through_bottom, ray_aabb
from nerfbot.query.render import render_rays_chunked
from ray_training import train_on_rays

BOX = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]])
MAT_RGB = torch.tensor([0.1, 0.2, 0.7])     # a plain blue mat on a plain wooden table
TABLE_RGB = torch.tensor([0.6, 0.4, 0.2])
TOP = 0.1                                   # the table top's height; the box's bottom at 0


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def test_bottom_face_rays_are_the_ones_whose_exit_point_lies_on_it():
    g = torch.Generator().manual_seed(0)
    origins = (torch.rand(20000, 3, generator=g) * 4 - 2).double()
    directions = _unit(torch.randn(20000, 3, generator=g)).double()
    t_near, t_far, hit = ray_aabb(origins.float(), directions.float(), BOX)
    got = leaves_through_bottom(origins.float(), directions.float(), t_far, hit, BOX)
    exit_point = origins + directions * t_far.double()[:, None]
    on_bottom = (exit_point[:, 2] - 0.0).abs() < 1e-5
    inside_xy = (exit_point[:, :2].abs() <= 1 + 1e-5).all(1)
    expected = hit & on_bottom & inside_xy & (directions[:, 2] < 0)
    assert int(expected.sum()) > 500 and int((hit & ~expected).sum()) > 1000
    assert torch.equal(got, expected)
    # by hand: straight down from above; down and out through a side; up; along the floor; a miss
    o = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.5], [-3.0, 0.0, 0.5],
                      [5.0, 5.0, 5.0]])
    d = _unit(torch.tensor([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, 0.1, 1.0],
                            [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
    _, t_far, hit = ray_aabb(o, d, BOX)
    assert leaves_through_bottom(o, d, t_far, hit, BOX).tolist() == [True, False, False, False,
                                                                      False]


def table_rays(n: int, gen: torch.Generator) -> tuple[Rays, torch.Tensor]:
    """n rays from cameras 1.5-2.5 m from a table top filling the box (its plain top at z =
    ``TOP``, a plain mat on its middle), through random points of its middle, from where they
    go on to the box's bottom face; the colour each sees."""
    azimuth = torch.rand(n, generator=gen) * 2 * math.pi
    elevation = torch.rand(n, generator=gen) * 0.6 + 0.7            # 40-75 degrees
    radius = torch.rand(n, generator=gen) + 1.5
    origins = torch.stack([radius * torch.cos(elevation) * torch.cos(azimuth),
                           radius * torch.cos(elevation) * torch.sin(azimuth),
                           radius * torch.sin(elevation)], 1)
    targets = torch.cat([(torch.rand(n, 2, generator=gen) * 1.2 - 0.6),
                         torch.full((n, 1), TOP)], 1)
    on_mat = (targets[:, :2].abs() < 0.3).all(1)
    return (Rays(origins, _unit(targets - origins), torch.ones(n)),
            torch.where(on_mat[:, None], MAT_RGB, TABLE_RGB))


@pytest.mark.slow(40)
@pytest.mark.parametrize("trains", [True, False])
def test_a_plain_mat_is_held_by_the_field_when_the_floor_does_not_train_the_background(trains):
    """Every ray of :func:`table_rays` meets the table and, through an empty field, would leave
    through the bottom face. Trained by them, the background paints the plain mat and the field
    leaves it empty (the failure the option exists for); without their gradients the background
    stays as it started and the field holds the mat."""
    rays, _ = table_rays(20000, torch.Generator().manual_seed(1))
    _, t_far, hit = ray_aabb(rays.origins, rays.directions, BOX)
    assert bool(leaves_through_bottom(rays.origins, rays.directions, t_far, hit, BOX).all())
    torch.manual_seed(0)
    model = build_model("ngp", BOX, options={
        "log2_hashmap_size": 14, "samples_per_batch": 1 << 13, "supersample": 1,
        "floor_trains_background": trains})
    before = [p.detach().clone() for p in model.background.parameters()]
    train_on_rays(model, table_rays, 300)
    changed = any(not torch.equal(a, b) for a, b in zip(before, model.background.parameters()))
    assert changed == trains
    rays, rgb = table_rays(2048, torch.Generator().manual_seed(5))
    with torch.no_grad():
        out = render_rays_chunked(model, rays)
    on_mat = torch.isclose(rgb, MAT_RGB).all(1)
    psnr = -10 * math.log10(float(((out["rgb"] - rgb) ** 2).mean()))
    assert psnr > 30.0, psnr                                          # both fit the images
    mat_opacity = float(out["opacity"][on_mat].mean())
    assert float(out["opacity"][~on_mat].mean()) > 0.95
    if trains:
        assert mat_opacity < 0.2, mat_opacity
    else:
        assert mat_opacity > 0.95, mat_opacity
