"""Forward kinematics of the rigid parts of an articulated scene, in torch (differentiable).

A part is moved by a chain of hinge / slide joints described at the rest configuration
``qpos0`` (world axis ``a``, anchor ``p``, rest value ``q0``; see :func:`sims.joints.joint_info`).
In the product-of-exponentials form, with every joint's axis taken at rest, a rest-frame point
goes to the world at joint values q as

    x_world = T_1(q_1) T_2(q_2) ... T_n(q_n) x_rest        (joint 1 outermost)
    hinge:  T(q) x = R(a, q - q0) (x - p) + p
    slide:  T(q) x = x + a (q - q0)

Everything is batched over N configurations: ``q`` is (N, C) in the conditioning's joint order.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


def rotate(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: rotate vectors v (N, 3) about the unit ``axis`` (3,) by ``angle`` (N,) radians."""
    c, s = torch.cos(angle)[:, None], torch.sin(angle)[:, None]
    a = axis.to(v.dtype).expand_as(v)
    return v * c + torch.cross(a, v, dim=-1) * s + a * (v * a).sum(-1, keepdim=True) * (1 - c)


class JointChain(nn.Module):
    """The joints moving one rigid part, outermost first.

    Args:
        joints: joint descriptions (dicts with ``type`` "hinge" | "slide", ``axis``, ``anchor``,
            ``qpos0``), outermost first.
        columns: index of each joint in the condition vector.
    """

    def __init__(self, joints: Sequence[dict], columns: Sequence[int]):
        super().__init__()
        for j in joints:
            if j.get("type") not in ("hinge", "slide"):
                raise ValueError(f"only hinge and slide joints move parts, got {j.get('type')!r}")
        self.kinds = [j["type"] for j in joints]
        self.columns = list(int(c) for c in columns)
        axes = torch.tensor([j["axis"] for j in joints], dtype=torch.float64).reshape(-1, 3)
        self.register_buffer("axes", axes / axes.norm(dim=-1, keepdim=True))
        self.register_buffer("anchors", torch.tensor([j["anchor"] for j in joints],
                                                     dtype=torch.float64).reshape(-1, 3))
        self.register_buffer("q0", torch.tensor([float(j["qpos0"]) for j in joints],
                                                dtype=torch.float64))

    def _steps(self, q: torch.Tensor, outer_first: bool):
        order = range(len(self.kinds)) if outer_first else reversed(range(len(self.kinds)))
        for k in order:
            yield k, q[:, self.columns[k]] - self.q0[k].to(q.dtype)

    def to_world(self, x: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """Rest-frame points x (N, 3) -> world points at joint values q (N, C)."""
        for k, dq in self._steps(q, outer_first=False):  # innermost joint acts first
            a, p = self.axes[k].to(x.dtype), self.anchors[k].to(x.dtype)
            x = rotate(x - p, a, dq) + p if self.kinds[k] == "hinge" else x + a * dq[:, None]
        return x

    def to_rest(self, x: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """World points x (N, 3) at joint values q (N, C) -> rest-frame points (N, 3)."""
        for k, dq in self._steps(q, outer_first=True):
            a, p = self.axes[k].to(x.dtype), self.anchors[k].to(x.dtype)
            x = rotate(x - p, a, -dq) + p if self.kinds[k] == "hinge" else x - a * dq[:, None]
        return x

    def dirs_to_rest(self, d: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """World directions d (N, 3) -> rest-frame directions (rotations only)."""
        for k, dq in self._steps(q, outer_first=True):
            if self.kinds[k] == "hinge":
                d = rotate(d, self.axes[k].to(d.dtype), -dq)
        return d

    def transform(self, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The rigid motion rest -> world at q (N, C): rotation (N, 3, 3) and translation (N, 3),
        x_world = R x_rest + t."""
        n, dt = q.shape[0], q.dtype
        t = self.to_world(torch.zeros(n, 3, dtype=dt, device=q.device), q)
        basis = torch.eye(3, dtype=dt, device=q.device)
        cols = [self.to_world(basis[i].expand(n, 3), q) - t for i in range(3)]
        return torch.stack(cols, dim=-1), t
