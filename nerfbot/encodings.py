"""Input encodings: frequency (positional) encoding, spherical harmonics, multiresolution hash grid."""

from __future__ import annotations

import math

import torch
from torch import nn

from nerfbot.kernels import hashgrid as _hk


class FrequencyEncoding(nn.Module):
    """NeRF's positional encoding gamma(p) = [p, sin(2^k pi p), cos(2^k pi p)], k < n_freqs.

    Input (N, D) (expected roughly in [-1, 1]); output (N, D * (1 + 2 n_freqs)).
    """

    def __init__(self, in_dim: int, n_freqs: int, include_input: bool = True):
        super().__init__()
        self.in_dim, self.n_freqs, self.include_input = in_dim, n_freqs, include_input
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(n_freqs, dtype=torch.float32),
                             persistent=False)

    @property
    def out_dim(self) -> int:
        return self.in_dim * (2 * self.n_freqs + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scaled = (x[..., None, :] * self.freqs[:, None]).flatten(-2)  # (N, F*D)
        parts = [x] if self.include_input else []
        parts += [torch.sin(scaled), torch.cos(scaled)]
        return torch.cat(parts, dim=-1)


# Real spherical-harmonic constants (the orthonormal real basis, signs as in PlenOctrees/svox2).
_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
       0.5462742152960396)
_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
       -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
_C4 = (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892,
       0.10578554691520431, -0.6690465435572892, 0.47308734787878004, -1.7701307697799304,
       0.6258357354491761)


def spherical_harmonics(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis of unit directions ``d`` (N, 3) up to ``degree`` (0..4): (N, (degree+1)^2)."""
    if not 0 <= degree <= 4:
        raise ValueError(f"spherical harmonics degree must be 0..4, got {degree}")
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [torch.full_like(x, _C0)]
    if degree >= 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [_C2[0] * xy, _C2[1] * yz, _C2[2] * (2 * zz - xx - yy), _C2[3] * xz,
                _C2[4] * (xx - yy)]
    if degree >= 3:
        out += [_C3[0] * y * (3 * xx - yy), _C3[1] * xy * z, _C3[2] * y * (4 * zz - xx - yy),
                _C3[3] * z * (2 * zz - 3 * xx - 3 * yy), _C3[4] * x * (4 * zz - xx - yy),
                _C3[5] * z * (xx - yy), _C3[6] * x * (xx - 3 * yy)]
    if degree >= 4:
        out += [_C4[0] * xy * (xx - yy), _C4[1] * yz * (3 * xx - yy), _C4[2] * xy * (7 * zz - 1),
                _C4[3] * yz * (7 * zz - 3), _C4[4] * (zz * (35 * zz - 30) + 3),
                _C4[5] * xz * (7 * zz - 3), _C4[6] * (xx - yy) * (7 * zz - 1),
                _C4[7] * xz * (xx - 3 * yy), _C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy))]
    return torch.stack(out, dim=-1)


class SHEncoding(nn.Module):
    """Spherical-harmonic encoding of unit directions: (N, 3) -> (N, (degree+1)^2)."""

    def __init__(self, degree: int = 4):
        super().__init__()
        self.degree = degree

    @property
    def out_dim(self) -> int:
        return (self.degree + 1) ** 2

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        return spherical_harmonics(d, self.degree)


def hash_encode_reference(x: torch.Tensor, table: torch.Tensor, offsets: torch.Tensor,
                          res: torch.Tensor) -> torch.Tensor:
    """Plain-torch hash encoding, the twin of the numba kernel (same arithmetic, any device).

    Args:
        x: (N, 3) positions in [0, 1]^3 (clamped).
        table: (rows, F) features of all levels; offsets: (L + 1,) int64; res: (L,) int64.
    Returns:
        (N, L * F) interpolated features, differentiable w.r.t. ``table`` and ``x``.
    """
    if x.dtype in (torch.float16, torch.bfloat16):
        # x * res in half precision is off by up to half a cell on fine levels (float16 spacing
        # is 1 between 1024 and 2048): locate cells in float32
        x = x.float()
    x = x.clamp(0.0, 1.0)
    feats = []
    for lvl in range(res.shape[0]):
        r = int(res[lvl])
        off, size = int(offsets[lvl]), int(offsets[lvl + 1] - offsets[lvl])
        res1 = r + 1
        pos = x * r
        cell = pos.detach().floor().long().clamp_(0, r - 1)
        w = pos - cell.to(pos.dtype)
        acc = 0.0
        for c in range(8):
            corner = torch.tensor([c & 1, (c >> 1) & 1, (c >> 2) & 1], device=x.device)
            v = cell + corner
            if res1**3 <= size:
                row = v[:, 0] + v[:, 1] * res1 + v[:, 2] * res1 * res1
            else:
                row = (v[:, 0] ^ (v[:, 1] * _hk.PRIME_Y) ^ (v[:, 2] * _hk.PRIME_Z)) & (size - 1)
            wc = torch.where(corner.bool(), w, 1.0 - w).prod(dim=-1, keepdim=True)
            acc = acc + wc * table[off + row]
        feats.append(acc)
    return torch.cat(feats, dim=-1)


class _HashEncodeNumba(torch.autograd.Function):
    """Fast CPU path: numba kernels for the forward pass and the table gradient."""

    @staticmethod
    def forward(ctx, x, table, offsets_np, res_np):
        x_c = x.detach().clamp(0.0, 1.0).contiguous()
        n_levels, n_feat = res_np.shape[0], table.shape[1]
        out = torch.empty(n_levels, x.shape[0], n_feat, dtype=torch.float32)
        _hk.hash_forward(x_c.numpy(), table.detach().numpy(), offsets_np, res_np, out.numpy(),
                         _n_workers())
        ctx.save_for_backward(x_c)
        ctx.layout = (offsets_np, res_np, table.shape)
        return out.permute(1, 0, 2).reshape(x.shape[0], n_levels * n_feat)

    @staticmethod
    def backward(ctx, grad_out):
        (x_c,) = ctx.saved_tensors
        offsets_np, res_np, shape = ctx.layout
        n_levels, n_feat = res_np.shape[0], shape[1]
        grad_lnf = grad_out.reshape(-1, n_levels, n_feat).permute(1, 0, 2).contiguous()
        grad_table = torch.zeros(shape, dtype=torch.float32)
        _hk.hash_backward(x_c.numpy(), grad_lnf.numpy(), offsets_np, res_np, grad_table.numpy(),
                          _n_workers())
        return None, grad_table, None, None


def _n_workers() -> int:
    import numba

    return numba.get_num_threads()


class HashEncoding(nn.Module):
    """Multiresolution hash encoding of positions in [0, 1]^3: (N, 3) -> (N, L * F).

    Args:
        n_levels: L, number of resolution levels.
        n_features: F, features per level.
        log2_size: log2 of the maximum rows per level (the hash-table size T).
        min_res, max_res: cells per axis of the coarsest and finest level.
        backend: "numba" (fast CPU kernels) or "torch" (the reference twin). The numba path is
            used only for float32 CPU inputs without NaN that do not require a gradient w.r.t.
            position; anything else goes through the reference twin, which gives the same values.
    """

    def __init__(self, n_levels: int = 16, n_features: int = 2, log2_size: int = 19,
                 min_res: int = 16, max_res: int = 2048, backend: str = "numba",
                 init_scale: float = 1e-4, seed: int | None = None):
        super().__init__()
        if backend not in ("numba", "torch"):
            raise ValueError(f"hash-encoding backend must be 'numba' or 'torch', got {backend!r}")
        res, offsets = _hk.level_layout(n_levels, log2_size, min_res, max_res)
        self.n_levels, self.n_features, self.backend = n_levels, n_features, backend
        self.register_buffer("res", torch.from_numpy(res), persistent=False)
        self.register_buffer("offsets", torch.from_numpy(offsets), persistent=False)
        self._res_np, self._offsets_np = res, offsets
        gen = torch.Generator().manual_seed(seed) if seed is not None else None
        table = (torch.rand(int(offsets[-1]), n_features, generator=gen) * 2 - 1) * init_scale
        self.table = nn.Parameter(table)

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # NaN positions must not reach the kernels: int(NaN) is -2^63 there, an out-of-bounds
        # table row (read in the forward pass, written in the backward pass). The twin gives NaN
        # features for them with in-bounds indexing.
        fast = (self.backend == "numba" and x.device.type == "cpu" and x.dtype == torch.float32
                and self.table.dtype == torch.float32 and not x.requires_grad
                and not bool(torch.isnan(x).any()))
        if fast:
            return _HashEncodeNumba.apply(x, self.table, self._offsets_np, self._res_np)
        return hash_encode_reference(x, self.table, self.offsets, self.res)
