"""Direct image alignment to a rendered RGB-D reference (nerfbot.query.direct_alignment)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.ops.cameras import look_at
from nerfbot.ops.lie import se3_exp
from nerfbot.query.direct_alignment import (AlignConfig, _Level, _pose_derivatives, align,
                                            level_size, render_reference)
from nerfbot.query.localise import perturb, planar_update, pose_error
from painted_room import PaintedRoom, painted_room_view


def _planar(start, q):
    return planar_update(start[None], q[None])[0]


def _six_dof(start, q):
    return start @ se3_exp(q)


def _reference(model, c2w, intr, scale=1.0, size=64):
    return render_reference(model, torch.as_tensor(c2w, dtype=torch.float32), intr,
                            level_size(size, size, scale), scale)


@pytest.mark.parametrize("update,parameters", [(_planar, 3), (_six_dof, 6)],
                         ids=["planar", "6dof"])
def test_pixel_jacobian_matches_finite_differences(update, parameters):
    model = PaintedRoom()
    c2w = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, c2w)
    level = _Level(_reference(model, c2w, intr), torch.as_tensor(image), intr, 1.0,
                   AlignConfig())
    start = torch.as_tensor(c2w, dtype=torch.float32)
    q = torch.tensor([0.02, -0.01, 0.03, 0.01, 0.02, -0.02][:parameters])
    pose, derivatives = _pose_derivatives(update, start, q)
    jac = level.pixel_jacobian(pose, derivatives)                       # (N, 2, P)
    eps = 1e-3
    for k in range(parameters):
        step = torch.zeros(parameters)
        step[k] = eps
        plus, minus = (torch.stack(level.project(
            update(start.double(), (q + sign * step).double()).float())[:2], -1)
            for sign in (1, -1))
        numeric = (plus - minus) / (2 * eps)
        assert torch.allclose(jac[:, :, k], numeric, rtol=2e-2, atol=2e-2), k


@pytest.mark.parametrize("planar", [True, False], ids=["planar", "6dof"])
def test_alignment_to_a_reference_at_another_pose_finds_the_camera(planar):
    """The reference is rendered where the start is, 8 cm and 6 degrees from the camera (a
    sixth of its pixels leave the view): the pyramid's alignment lands on the truth."""
    model = PaintedRoom()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    start = perturb(truth, 0.08, 6.0, np.random.default_rng(1), planar=planar)
    reference = _reference(model, start, intr)
    pose, cost = align(reference, torch.as_tensor(image), intr,
                       torch.as_tensor(start, dtype=torch.float32),
                       _planar if planar else _six_dof, 3 if planar else 6, (0.25, 0.5, 1.0))
    dt, dr = pose_error(pose.numpy(), truth)
    # observed: planar 0.1 mm / 0.01 degrees, 6-DoF 0.2 mm / 0.01 degrees
    assert dt < 0.005 and dr < 0.2, (dt, dr)
    assert np.isfinite(cost)


def test_alignment_at_the_reference_pose_stays_there():
    model = PaintedRoom()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    start = torch.as_tensor(truth, dtype=torch.float32)
    pose, cost = align(_reference(model, truth, intr), torch.as_tensor(image), intr, start,
                       _six_dof, 6, (0.5, 1.0))
    dt, dr = pose_error(pose.numpy(), truth)
    assert dt < 1e-4 and dr < 1e-2 and cost < 1e-6


def test_a_reference_without_opaque_pixels_leaves_the_start():
    """A render where nothing is opaque has no depth to warp by: the start comes back."""

    class _Empty(PaintedRoom):
        def render_rays_differentiable(self, rays):
            out = super().render_rays_differentiable(rays)
            out.opacity = torch.zeros_like(out.opacity)
            return out

    model = _Empty()
    truth = look_at([0.3, -0.4, 0.45], [2.0, 0.2, 0.6])
    image, intr = painted_room_view(model, truth)
    start = torch.as_tensor(perturb(truth, 0.05, 3.0, np.random.default_rng(0)),
                            dtype=torch.float32)
    pose, _ = align(_reference(model, start, intr), torch.as_tensor(image), intr, start,
                    _six_dof, 6, (0.5, 1.0))
    assert torch.allclose(pose, start, atol=1e-6)
