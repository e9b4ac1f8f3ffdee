"""Where the points of a moving scene go: scene flow of a deformation field (``dnerf``) or of
rigid parts carried along their tracks (``rigid``).

A deformation field renders the scene at time t as a canonical scene seen through a warp,
``canonical(x) = x + dx(x, t)``. The material at point ``x0`` at time ``t0`` is the canonical
point ``c = x0 + dx(x0, t0)``; at time ``t1`` it is wherever the warp sends to ``c``, the
solution ``x1`` of ``x1 + dx(x1, t1) = c``, found by the fixed-point iteration
``x1 <- c - dx(x1, t1)`` (it converges where the warp moves neighbouring points by less than
their distance, as a rigid motion does). Going from ``t1`` back to ``t0`` returns ``x0``: the
two directions are consistent by construction, up to the iteration's tolerance, which is
reported.

A field that moves points itself (``rigid``: a point of a body's material goes with the body's
pose, :meth:`nerfbot.fields.rigid.RigidField.move_points`) answers directly and exactly. Fields
without either (``kplanes`` and ``tnerf`` model what moves by its density at each time, not by
where it goes) have no scene flow; :func:`point_motion` says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerfbot.models.base import Model


@dataclass
class Motion:
    """Where points went: ``points`` (N, 3) world metres at the target time, and ``residual``
    (N,) metres, the distance by which the warp misses the points' canonical positions there
    (large where the iteration did not converge)."""

    points: torch.Tensor
    residual: torch.Tensor


def _deformation(model: Model):
    field = getattr(model, "field", None)
    deform = getattr(field, "deformation", None)
    if deform is None:
        name = type(field).__name__ if field is not None else type(model).__name__
        raise ValueError(f"{name} has no deformation: scene flow needs a deformation field "
                         "(a dnerf run) or rigid parts (a rigid run)")
    return deform


@torch.no_grad()
def point_motion(model: Model, points: torch.Tensor, t0: float, t1: float,
                 iterations: int = 50, tolerance: float = 1e-5) -> Motion:
    """Move world ``points`` (N, 3, metres) of time ``t0`` to time ``t1`` (both in [0, 1])
    through the model's deformation. Stops when every point moves by less than ``tolerance``
    metres in an iteration, or after ``iterations``; a field with its own ``move_points``
    (``rigid``) moves them itself."""
    x0 = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3)
    mover = getattr(getattr(model, "field", None), "move_points", None)
    if mover is not None:
        return Motion(*mover(x0, float(t0), float(t1)))
    deform = _deformation(model)
    tt0 = x0.new_full((len(x0), 1), float(t0))
    tt1 = x0.new_full((len(x0), 1), float(t1))
    canonical = x0 + deform(x0, tt0)
    x1 = canonical - deform(canonical, tt1)
    for _ in range(iterations):
        nxt = canonical - deform(x1, tt1)
        step = (nxt - x1).norm(dim=-1)
        x1 = nxt
        if bool((step < tolerance).all()):
            break
    residual = (x1 + deform(x1, tt1) - canonical).norm(dim=-1)
    return Motion(x1, residual)


def scene_flow(model: Model, points: torch.Tensor, t: float, dt: float) -> Motion:
    """Forward scene flow: the displacement (N, 3, metres) of ``points`` at time ``t`` over
    ``dt`` (negative: backward flow), with the iteration's residual."""
    moved = point_motion(model, points, t, t + dt)
    return Motion(moved.points - torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3),
                  moved.residual)
