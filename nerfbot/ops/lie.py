"""Rotations and rigid motions from their Lie algebra: skew matrices, so(3) and se(3)
exponentials, differentiable and exact at zero (series near it)."""

from __future__ import annotations

import torch


def hat(w: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) skew-symmetric matrices of vectors (..., 3)."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([z, -w[..., 2], w[..., 1]], -1),
                        torch.stack([w[..., 2], z, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations exp(hat(w)) of axis-angle vectors w (..., 3) in radians
    (Rodrigues); differentiable, exact at w = 0 (series near zero)."""
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2.clamp_min(1e-20))
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-20))
    k = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def so3_log(rot: torch.Tensor) -> torch.Tensor:
    """(..., 3) axis-angle vectors of rotations (..., 3, 3) with angles below pi (the inverse of
    :func:`so3_exp` there); differentiable, finite at the identity."""
    v = 0.5 * torch.stack([rot[..., 2, 1] - rot[..., 1, 2], rot[..., 0, 2] - rot[..., 2, 0],
                           rot[..., 1, 0] - rot[..., 0, 1]], -1)
    sin = torch.sqrt((v * v).sum(-1, keepdim=True) + 1e-24)
    cos = 0.5 * (rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2] - 1.0)[..., None]
    theta = torch.atan2(sin, cos)
    return v * torch.where(sin < 1e-6, 1.0 + theta * theta / 6.0, theta / sin)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) rigid transforms exp(xi) of twists xi (..., 6) = (rotation w in radians,
    translation v in metres); differentiable, exact at xi = 0 (series near zero)."""
    w, v = xi[..., :3], xi[..., 3:]
    theta2 = (w * w).sum(-1, keepdim=True)[..., None]
    theta = torch.sqrt(theta2.clamp_min(1e-20))
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-20))
    c = torch.where(small, 1.0 / 6 - theta2 / 120, (theta - torch.sin(theta)) /
                    (theta2 * theta).clamp_min(1e-30))
    k = hat(w)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(k)
    rot = eye + a * k + b * k2
    vmat = eye + b * k + c * k2
    top = torch.cat([rot, (vmat @ v[..., None])], -1)
    bottom = torch.zeros(*xi.shape[:-1], 1, 4, dtype=xi.dtype, device=xi.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)

