"""Octahedral maps of directions: the unit sphere unfolded onto the square [-1, 1]^2, so a
function of direction can be tabulated on a regular grid and read back with bilinear
interpolation (FastNeRF's direction cache, the baked renderers' background).
The numba twins of the lookups are in :mod:`nerfbot.kernels.octahedral`."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def octahedral_encode(d: torch.Tensor) -> torch.Tensor:
    """Unit directions (N, 3) -> octahedral coordinates (N, 2) in [-1, 1]^2.

    The upper hemisphere (z >= 0) fills the diamond |u| + |v| <= 1, the lower one the four
    corners, folded across the diamond's edges; every direction has one point, and the square's
    border is mirrored (``(1, v)`` and ``(1, -v)`` are the same direction), so bilinear lookups
    on a vertex grid symmetric about 0 are continuous on the sphere.
    """
    p = d / d.abs().sum(-1, keepdim=True).clamp_min(1e-30)
    x, y, z = p.unbind(-1)
    sx = torch.where(x >= 0, 1.0, -1.0)
    sy = torch.where(y >= 0, 1.0, -1.0)
    lower = z < 0
    u = torch.where(lower, (1.0 - y.abs()) * sx, x)
    v = torch.where(lower, (1.0 - x.abs()) * sy, y)
    return torch.stack([u, v], -1)


def octahedral_decode(uv: torch.Tensor) -> torch.Tensor:
    """Octahedral coordinates (N, 2) in [-1, 1]^2 -> unit directions (N, 3)."""
    u, v = uv.unbind(-1)
    z = 1.0 - u.abs() - v.abs()
    lower = z < 0
    x = torch.where(lower, (1.0 - v.abs()) * torch.where(u >= 0, 1.0, -1.0), u)
    y = torch.where(lower, (1.0 - u.abs()) * torch.where(v >= 0, 1.0, -1.0), v)
    return F.normalize(torch.stack([x, y, z], -1), dim=-1)


def octahedral_lookup(table: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of ``table`` (ND, ND, C), values at the vertices of
    :func:`direction_grid`, at unit directions ``d`` (N, 3): (N, C). The plain-torch twin of
    :func:`nerfbot.kernels.octahedral.lookup` (any device, differentiable w.r.t. the table)."""
    nd = table.shape[0]
    uv = octahedral_encode(d.double())
    f = (uv + 1.0) * 0.5 * (nd - 1)
    i = torch.floor(f).long().clamp(0, nd - 2)
    w = (f - i).float()
    wu, wv = w[:, 0:1], w[:, 1:2]
    return ((1 - wu) * (1 - wv) * table[i[:, 0], i[:, 1]]
            + wu * (1 - wv) * table[i[:, 0] + 1, i[:, 1]]
            + (1 - wu) * wv * table[i[:, 0], i[:, 1] + 1]
            + wu * wv * table[i[:, 0] + 1, i[:, 1] + 1])


def direction_grid(nd: int) -> torch.Tensor:
    """The ND x ND unit directions (ND, ND, 3) at the vertices of the octahedral grid: vertex
    (i, j) at (u, v) = (-1 + 2i / (ND - 1), -1 + 2j / (ND - 1))."""
    t = torch.linspace(-1.0, 1.0, nd, dtype=torch.float64)
    uv = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    return octahedral_decode(uv).float().reshape(nd, nd, 3)
