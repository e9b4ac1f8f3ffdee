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

