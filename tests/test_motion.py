"""Scene flow of deformation fields (``nerfbot.query.motion``): an analytic moving blob, the
consistency of the two directions, and fields that have no deformation."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.dnerf import DNeRFField, DNeRFFieldConfig
from nerfbot.fields.kplanes import KPlanesField
from nerfbot.query.motion import point_motion, scene_flow

AABB = [[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]]
TIME = Conditioning("time", ("time",), ((0.0, 1.0),))
START = torch.tensor([-0.3, 0.1, 0.5])  # the blob's centre at t = 0, metres
VELOCITY = torch.tensor([0.2, 0.05, -0.1])  # metres per unit time
WIDTH = 0.3  # the blob's Gaussian width, metres


def _blob_field():
    """A dnerf field whose warp is an analytic blob moving at ``VELOCITY``: near its centre
    c(t) = START + VELOCITY t the material is the canonical (t = 0) blob's, far away nothing
    moves; dx(x, t) = -VELOCITY t g(x - c(t)) with g a unit Gaussian bump."""
    field = DNeRFField(AABB, TIME)

    def deformation(x, cond=None):
        t = torch.zeros(len(x), 1) if cond is None else cond[:, :1]
        centre = START + VELOCITY * t
        bump = torch.exp(-((x - centre) ** 2).sum(-1, keepdim=True) / (2 * WIDTH ** 2))
        return -VELOCITY * t * bump

    field.deformation = deformation
    return SimpleNamespace(field=field)


def test_the_blob_centre_moves_with_the_blob():
    model = _blob_field()
    for t0, t1 in ((0.0, 1.0), (0.2, 0.7), (0.9, 0.1)):
        moved = point_motion(model, (START + VELOCITY * t0)[None], t0, t1)
        assert torch.allclose(moved.points[0], START + VELOCITY * t1, atol=1e-5)
        assert float(moved.residual[0]) < 1e-5
    flow = scene_flow(model, START[None], 0.0, 0.5)
    assert torch.allclose(flow.points[0], 0.5 * VELOCITY, atol=1e-5)
    far = torch.tensor([[0.9, -0.9, 0.05]])  # 3.5 widths away: it stays
    assert float(scene_flow(model, far, 0.0, 1.0).points.norm()) < 1e-3


def test_forward_then_backward_flow_returns_every_point():
    """Cycle consistency: t0 -> t1 -> t0 gives back the points (the blob's, and those of a
    dnerf field with a random small warp)."""
    gen = torch.Generator().manual_seed(0)
    points = START + 0.4 * (torch.rand(300, 3, generator=gen) - 0.5)
    blob = _blob_field()
    there = point_motion(blob, points, 0.1, 0.8)
    back = point_motion(blob, there.points, 0.8, 0.1)
    assert (back.points - points).norm(dim=-1).max() < 1e-4
    assert there.residual.max() < 1e-4 and back.residual.max() < 1e-4
    assert (there.points - points).norm(dim=-1).max() > 0.05  # they did move

    torch.manual_seed(0)
    field = DNeRFField(AABB, TIME, dconfig=DNeRFFieldConfig(deform_encoding="frequency"))
    for p in field.deform_mlp.parameters():
        torch.nn.init.normal_(p, std=0.01)
    warped = SimpleNamespace(field=field)
    there = point_motion(warped, points, 0.2, 0.9)
    back = point_motion(warped, there.points, 0.9, 0.2)
    assert (there.points - points).norm(dim=-1).max() > 1e-3
    assert (back.points - points).norm(dim=-1).max() < 1e-4


def test_fields_without_a_deformation_have_no_scene_flow():
    model = SimpleNamespace(field=KPlanesField(AABB, TIME))
    with pytest.raises(ValueError, match="KPlanesField has no deformation: scene flow needs"):
        point_motion(model, torch.zeros(1, 3), 0.0, 1.0)
