"""Scene flow (``nerfbot.query.motion``) of deformation fields (an analytic moving blob) and of
rigid parts (a cube on a known track), the consistency of the two directions, and fields that
have no deformation."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.dnerf import DNeRFField, DNeRFFieldConfig
from nerfbot.fields.kplanes import KPlanesField
from nerfbot.fields.rigid import RigidField
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


def _rigid_cube():
    """A rigid field whose one part (a 10 cm cube, made opaque) is carried along a known track:
    steps at t = 0, 0.5, 1 with centres along +x and turns of 0, 45 and 90 degrees about z."""
    track = {"name": "cube", "times": [0.0, 0.5, 1.0], "extent": 0.1,
             "centres": [[-0.3, 0.0, 0.5], [0.0, 0.1, 0.5], [0.3, 0.0, 0.5]],
             "rotations": [[0.0, 0.0, 0.0], [0.0, 0.0, math.pi / 4], [0.0, 0.0, math.pi / 2]]}
    cond = Conditioning("time", ("time",), ((0.0, 1.0),), object_tracks=[track])
    field = RigidField(AABB, cond)
    field.parts[0].density_bias += 20.0                 # the body's material fills its cube
    return SimpleNamespace(field=field)


def _turn_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_rigid_parts_move_their_material_along_the_track_and_nothing_else():
    model = _rigid_cube()
    offset = torch.tensor([0.05, 0.02, -0.03])          # a point of the body, in its frame
    x0 = torch.stack([torch.tensor([-0.3, 0.0, 0.5]) + offset, torch.tensor([0.5, -0.6, 0.2])])
    for t1, centre, angle in ((0.5, [0.0, 0.1, 0.5], math.pi / 4),
                              (1.0, [0.3, 0.0, 0.5], math.pi / 2),
                              (0.25, [-0.15, 0.05, 0.5], math.pi / 8)):   # between two steps
        moved = point_motion(model, x0, 0.0, t1)
        expected = torch.tensor(centre) + _turn_z(angle) @ offset
        assert torch.allclose(moved.points[0], expected, atol=1e-5), t1
        assert torch.equal(moved.points[1], x0[1])      # empty space far from the body stays
        assert float(moved.residual.abs().max()) == 0.0
    flow = scene_flow(model, x0[:1], 0.0, 1.0).points[0]
    assert torch.allclose(flow, torch.tensor([0.3, 0.0, 0.5]) + _turn_z(math.pi / 2) @ offset
                          - x0[0], atol=1e-5)


def test_rigid_forward_then_backward_flow_returns_every_point():
    """The body's material comes back from t0 -> t1 -> t0; a point of empty space clear of the
    body at both times stays put both ways."""
    model = _rigid_cube()
    gen = torch.Generator().manual_seed(1)
    centre, turn = torch.tensor([0.0, 0.1, 0.5]), _turn_z(math.pi / 4)   # the pose at t = 0.5
    body = centre + (0.198 * (torch.rand(300, 3, generator=gen) - 0.5)) @ turn.T
    empty = torch.tensor([0.0, -0.4, 0.5]) + 0.2 * (torch.rand(100, 3, generator=gen) - 0.5)
    points = torch.cat([body, empty])
    there = point_motion(model, points, 0.5, 0.9)
    back = point_motion(model, there.points, 0.9, 0.5)
    assert (back.points - points).norm(dim=-1).max() < 1e-5
    assert (there.points[:300] - body).norm(dim=-1).min() > 0.1      # the body moved
    assert torch.equal(there.points[300:], empty)
