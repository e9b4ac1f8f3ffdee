"""Input encodings: frequency (positional) encoding, spherical harmonics, multiresolution hash grid,
factorised (K-Planes) plane grid."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import nn

from nerfbot.kernels import hashgrid as _hk
from nerfbot.kernels import planes as _pk
from nerfbot.kernels import use_kernels
from nerfbot.kernels.sh import check_sh_degree, sh_encode, spherical_harmonics_reference


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


def spherical_harmonics(d: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis of unit directions ``d`` (N, 3) up to ``degree`` (0..4): (N, (degree+1)^2)."""
    check_sh_degree(degree)
    if (use_kernels(d) and d.dim() == 2
            and not (d.requires_grad and torch.is_grad_enabled())):
        # no gradient wanted: one numba pass instead of ~60 elementwise torch ops (the learned
        # background of a 128x128 image took 4 ms here, most of a baked renderer's time)
        out = torch.empty(d.shape[0], (degree + 1) ** 2)
        sh_encode(d.detach().contiguous().numpy(), degree, out.numpy())
        return out
    return spherical_harmonics_reference(d, degree)


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
    """Fast CPU path: numba kernels for the forward pass, the table gradient and the position
    gradient.

    The position gradient follows the twin's autograd: zero for a coordinate outside [0, 1]
    (where the clamp is active), the one-sided derivative from inside the cube exactly on 0 or 1
    (``torch.clamp`` passes the gradient at its bounds), and on inner cell faces the derivative
    inside the cell ``floor(x * res)`` picks. The kernels are not differentiable themselves:
    when a position gradient is asked for with ``create_graph=True`` (grad mode is on during the
    backward pass), the backward pass rebuilds both gradients with the twin, so second-order
    gradients (Eikonal or normal losses) stay right, at the twin's speed.
    """

    @staticmethod
    def forward(ctx, x, table, offsets_np, res_np):
        x_c = x.detach().clamp(0.0, 1.0).contiguous()
        n_levels, n_feat = res_np.shape[0], table.shape[1]
        out = torch.empty(n_levels, x.shape[0], n_feat, dtype=torch.float32)
        _hk.hash_forward(x_c.numpy(), table.detach().numpy(), offsets_np, res_np, out.numpy(),
                         _n_workers())
        # x and the table are kept only for the position gradient (the table gradient needs
        # neither, so without it they may still be changed in place before the backward pass)
        need_x = ctx.needs_input_grad[0]
        ctx.save_for_backward(x_c, x if need_x else None, table if need_x else None)
        ctx.layout = (offsets_np, res_np, table.shape)
        return out.permute(1, 0, 2).reshape(x.shape[0], n_levels * n_feat)

    @staticmethod
    def backward(ctx, grad_out):
        x_c, x, table = ctx.saved_tensors
        offsets_np, res_np, shape = ctx.layout
        need_x, need_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if need_x and torch.is_grad_enabled():
            return _HashEncodeNumba._differentiable_backward(ctx, grad_out, x, table)
        n_levels, n_feat = res_np.shape[0], shape[1]
        grad_lnf = grad_out.reshape(-1, n_levels, n_feat).permute(1, 0, 2).contiguous()
        grad_x = grad_table = None
        if need_table:
            grad_table = torch.empty(shape, dtype=torch.float32)  # the kernel zeroes it
            _hk.hash_backward(x_c.numpy(), grad_lnf.numpy(), offsets_np, res_np,
                              grad_table.numpy(), _n_workers())
        if need_x:
            grad_x = torch.empty(x_c.shape, dtype=torch.float32)
            _hk.hash_backward_input(x_c.numpy(), table.detach().contiguous().numpy(),
                                    grad_lnf.numpy(), offsets_np, res_np, grad_x.numpy(),
                                    _n_workers())
            # the clamp: no gradient where it moved x (NaN never gets here, see HashEncoding)
            grad_x.masked_fill_((x < 0) | (x > 1), 0.0)
        return grad_x, grad_table, None, None

    @staticmethod
    def _differentiable_backward(ctx, grad_out, x, table):
        """Both gradients through the twin's autograd, with a graph (for create_graph=True)."""
        offsets_np, res_np, _ = ctx.layout
        need = ctx.needs_input_grad[:2]
        y = hash_encode_reference(x, table, torch.from_numpy(offsets_np),
                                  torch.from_numpy(res_np))
        wanted = [t for t, n in zip((x, table), need) if n]
        grads = iter(torch.autograd.grad(y, wanted, grad_out, create_graph=True))
        return tuple(next(grads) if n else None for n in need) + (None, None)


def _n_workers() -> int:
    return numba.get_num_threads()


#: The largest hash table an option may ask for: 2^24 rows per level is 2 GB of parameters at
#: 16 levels x 2 features (and twice that again for Adam's moments).
MAX_LOG2_HASHMAP_SIZE = 24


@dataclass
class HashGridConfig:
    """The hash-grid fields of every field config built on :class:`HashEncoding` (ngp,
    fastnerf, plenoctree's NeRF-SH): they subclass this, so each takes the same
    ``--option`` names with the same defaults."""

    n_levels: int = 16
    """L, hash-grid resolution levels."""
    n_features: int = 2
    """F, features per level."""
    log2_hashmap_size: int = 17
    """log2 of the hash-table size T per level (2^17 rows x F floats = 1 MB: fits in L2)."""
    min_res: int = 16
    """Cells per axis of the coarsest level (over the cube enclosing the bounds)."""
    max_res: int = 512
    """Cells per axis of the finest level."""
    backend: str = "numba"
    """Hash-encoding implementation: "numba" (fast CPU) or "torch" (reference twin)."""

    def __post_init__(self):
        for name in ("n_levels", "n_features", "min_res"):
            if getattr(self, name) < 1:
                raise ValueError(f"option {name}: must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.log2_hashmap_size <= MAX_LOG2_HASHMAP_SIZE:
            raise ValueError(f"option log2_hashmap_size: must be 0 to {MAX_LOG2_HASHMAP_SIZE} "
                             f"(2^{MAX_LOG2_HASHMAP_SIZE} rows per level), got "
                             f"{self.log2_hashmap_size}")
        if self.max_res < self.min_res:
            raise ValueError(f"option max_res: must be >= min_res ({self.min_res}), got "
                             f"{self.max_res}")
        if self.backend not in ("numba", "torch"):
            raise ValueError(f"option backend: 'numba' or 'torch', got {self.backend!r}")

    def hash_encoding(self, seed: int | None = None) -> "HashEncoding":
        """A :class:`HashEncoding` with these settings."""
        return HashEncoding(self.n_levels, self.n_features, self.log2_hashmap_size,
                            self.min_res, self.max_res, backend=self.backend, seed=seed)


class HashEncoding(nn.Module):
    """Multiresolution hash encoding of positions in [0, 1]^3: (N, 3) -> (N, L * F).

    Args:
        n_levels: L, number of resolution levels.
        n_features: F, features per level.
        log2_size: log2 of the maximum rows per level (the hash-table size T).
        min_res, max_res: cells per axis of the coarsest and finest level.
        backend: "numba" (fast CPU kernels) or "torch" (the reference twin). The numba path is
            used for float32 CPU inputs without NaN, with or without a gradient w.r.t. position
            (deformation fields, inverse rendering); anything else goes through the reference
            twin, which gives the same values and gradients.
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

    def check_table(self, shape, where: str = "table") -> None:
        """ValueError unless a table of ``shape`` fits this encoding's levels: (offsets[-1], F)
        rows and features. The kernels index rows up to ``offsets[-1]`` unchecked, so a smaller
        table would be read and written out of bounds."""
        rows = int(self._offsets_np[-1])
        if tuple(shape) != (rows, self.n_features):
            have = " x ".join(str(int(n)) for n in shape) or "a scalar"
            raise ValueError(
                f"{where}: hash table is {have} (rows x features), but the encoding's "
                f"{self.n_levels} levels need {rows} x {self.n_features}; it was made with other "
                "hash-grid options (e.g. log2_hashmap_size)")

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        table = state_dict.get(prefix + "table")
        if table is not None:
            self.check_table(table.shape, prefix + "table")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.table.shape != (int(self._offsets_np[-1]), self.n_features):
            self.check_table(self.table.shape)  # never let the kernels see a mismatched table
        # NaN positions must not reach the kernels: int(NaN) is -2^63 there, an out-of-bounds
        # table row (read by the forward pass and the position gradient, written by the table
        # gradient). The twin gives NaN features for them with in-bounds indexing.
        fast = (use_kernels(x, self.table, backend=self.backend)
                and not bool(torch.isnan(x).any()))
        if fast:
            return _HashEncodeNumba.apply(x, self.table, self._offsets_np, self._res_np)
        return hash_encode_reference(x, self.table, self.offsets, self.res)


# ----------------------------------------------------------------------------- factorised planes

def _unit_box(x: torch.Tensor) -> torch.Tensor:
    """NaN read as 0, then clamped to [0, 1] (so +-inf go to the border)."""
    return torch.nan_to_num(x, nan=0.0).clamp(0.0, 1.0)


def plane_encode_reference(x: torch.Tensor, table: torch.Tensor, offsets: torch.Tensor,
                           res: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """Plain-torch plane encoding, the twin of the numba kernels (same arithmetic, any device).

    Args:
        x: (N, D) points in [0, 1]^D (NaN read as 0, then clamped).
        table: (rows, F) features of all planes of all levels.
        offsets: (L * P + 1,) int64, plane p of level l starts at row ``offsets[l * P + p]``.
        res: (L, D) int64 cells per axis of each level; pairs: (P, 2) int64 axes of each plane.
    Returns:
        (N, L * F): per level, the product over the P planes of their bilinearly interpolated
        features (layout in :mod:`nerfbot.kernels.planes`), differentiable w.r.t. ``table``
        and ``x``.
    """
    if x.dtype in (torch.float16, torch.bfloat16):
        x = x.float()  # locate cells in float32 (see hash_encode_reference)
    x = _unit_box(x)
    offs, pairs_l = offsets.tolist(), pairs.tolist()
    feats = []
    for lvl, r in enumerate(res.tolist()):
        acc = 1.0
        for p, (a, b) in enumerate(pairs_l):
            pa, pb = x[:, a] * r[a], x[:, b] * r[b]
            ia = pa.detach().floor().long().clamp_(0, r[a] - 1)
            ib = pb.detach().floor().long().clamp_(0, r[b] - 1)
            wa = (pa - ia.to(pa.dtype))[:, None]
            wb = (pb - ib.to(pb.dtype))[:, None]
            row0 = offs[lvl * len(pairs_l) + p] + ia + ib * (r[a] + 1)   # corner (i, j)
            row1 = row0 + r[a] + 1                                        # corner (i, j + 1)
            acc = acc * (((1 - wa) * table[row0] + wa * table[row0 + 1]) * (1 - wb)
                         + ((1 - wa) * table[row1] + wa * table[row1 + 1]) * wb)
        feats.append(acc)
    return torch.cat(feats, dim=-1)


class _PlaneEncodeNumba(torch.autograd.Function):
    """Fast CPU path: numba kernels for the forward pass and the table gradient (none for x)."""

    @staticmethod
    def forward(ctx, x, table, offsets_np, res_np, pairs_np):
        x_c = _unit_box(x.detach()).contiguous()
        out = torch.empty(x.shape[0], res_np.shape[0] * table.shape[1], dtype=torch.float32)
        _pk.plane_forward(x_c.numpy(), pairs_np, table.detach().contiguous().numpy(), offsets_np,
                          res_np, out.numpy())
        ctx.save_for_backward(x_c, table)
        ctx.layout = (offsets_np, res_np, pairs_np)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x_c, table = ctx.saved_tensors
        offsets_np, res_np, pairs_np = ctx.layout
        grads = torch.zeros(_n_workers(), *table.shape, dtype=torch.float32)  # one per worker
        _pk.plane_backward(x_c.numpy(), pairs_np, table.detach().contiguous().numpy(), offsets_np,
                           res_np, grad_out.float().contiguous().numpy(), grads.numpy())
        return None, grads.sum(0), None, None, None


def plane_pairs(in_dim: int) -> list[tuple[int, int]]:
    """Axis pairs of the planes: the spatial ones first, then (axis, t) for t = 3 .. in_dim - 1.

    For in_dim 4: (0, 1), (0, 2), (1, 2), (0, 3), (1, 3), (2, 3).
    """
    spatial = [(a, b) for b in range(min(in_dim, 3)) for a in range(b)]
    return spatial + [(a, t) for t in range(3, in_dim) for a in range(t)]


class PlaneEncoding(nn.Module):
    """Factorised plane encoding (K-Planes / HexPlane): points (..., D) in [0, 1]^D -> (..., L * F).

    Each of the P = D (D - 1) / 2 axis-aligned planes (:func:`plane_pairs`) holds, per level, a
    grid of F features that is interpolated bilinearly; a level's features are the Hadamard
    product over its P planes and the L levels are concatenated. Points outside the unit box get
    the border value, NaN coordinates are read as 0.

    Args:
        in_dim: D, 3 (space) or 4 (space-time: axis 3 is time or any other condition).
        n_levels: L, number of resolution levels.
        n_features: F, features per level.
        spatial_res: cells per spatial axis of each level (L values).
        time_res: cells along axis 3 of each level (L values; unused when in_dim is 3).
        init: "ones": every feature uniform in [0.9, 1.1] (products start near 1); "kplanes":
            spatial planes uniform in [0.1, 0.5], time planes exactly 1, so the space-time
            product starts as the spatial one (the K-Planes initialisation).
        backend: "numba" (fast CPU kernels) or "torch" (the reference twin). The numba path is
            used only for float32 CPU inputs that do not require a gradient w.r.t. position;
            anything else goes through the reference twin, which gives the same values.
    """

    def __init__(self, in_dim: int = 4, n_levels: int = 2, n_features: int = 8,
                 spatial_res: tuple[int, ...] = (32, 64), time_res: tuple[int, ...] = (16, 24),
                 init: str = "ones", backend: str = "numba", seed: int | None = None):
        super().__init__()
        if backend not in ("numba", "torch"):
            raise ValueError(f"plane-encoding backend must be 'numba' or 'torch', got {backend!r}")
        if init not in ("ones", "kplanes"):
            raise ValueError(f"plane-encoding init must be 'ones' or 'kplanes', got {init!r}")
        if in_dim not in (3, 4) or len(spatial_res) != n_levels or (
                in_dim == 4 and len(time_res) != n_levels):
            raise ValueError(f"bad plane encoding: in_dim={in_dim}, n_levels={n_levels}, "
                             f"spatial_res={spatial_res}, time_res={time_res}")
        self.in_dim, self.n_levels, self.n_features = in_dim, n_levels, n_features
        self.backend = backend
        pairs = plane_pairs(in_dim)
        self.spatial_planes = [p for p, (_, b) in enumerate(pairs) if b < 3]
        self.time_planes = [p for p, (_, b) in enumerate(pairs) if b >= 3]
        res = [[s] * 3 for s in spatial_res]
        if in_dim == 4:
            res = [r + [t] for r, t in zip(res, time_res)]
        self._res_np = np.array(res, dtype=np.int64)
        self._pairs_np = np.array(pairs, dtype=np.int64)
        self._offsets_np = _pk.plane_layout(self._res_np, self._pairs_np)
        for name in ("res", "pairs", "offsets"):
            self.register_buffer(name, torch.from_numpy(getattr(self, f"_{name}_np")),
                                 persistent=False)
        gen = torch.Generator().manual_seed(seed) if seed is not None else None
        table = torch.rand(int(self._offsets_np[-1]), n_features, generator=gen)
        self.table = nn.Parameter(table * 0.2 + 0.9 if init == "ones" else table * 0.4 + 0.1)
        if init == "kplanes":
            with torch.no_grad():
                for lvl in range(n_levels):
                    for p in self.time_planes:
                        self.plane(lvl, p).fill_(1.0)

    @property
    def out_dim(self) -> int:
        return self.n_levels * self.n_features

    def plane(self, level: int, p: int) -> torch.Tensor:
        """View of plane ``p`` of ``level`` in the table: (res_b + 1, res_a + 1, F) for axes (a, b).

        Entry [j, i] is vertex (i, j); for a time plane (a, 3) the first dimension is time.
        """
        a, b = self._pairs_np[p]
        n_a, n_b = self._res_np[level, a] + 1, self._res_np[level, b] + 1
        start = int(self._offsets_np[level * len(self._pairs_np) + p])
        return self.table[start:start + n_a * n_b].view(int(n_b), int(n_a), self.n_features)

    def tv_loss(self) -> torch.Tensor:
        """Squared total variation of the spatial planes (K-Planes' plane TV): the mean squared
        difference of neighbouring vertices along each plane axis, summed over planes and levels."""
        total = self.table.new_zeros(())
        for lvl in range(self.n_levels):
            for p in self.spatial_planes:
                g = self.plane(lvl, p)
                total = (total + (g[1:] - g[:-1]).square().mean()
                         + (g[:, 1:] - g[:, :-1]).square().mean())
        return total

    def smoothness_loss(self) -> torch.Tensor:
        """Temporal smoothness (K-Planes): mean squared second difference along time of the time
        planes, summed over planes and levels; zero when in_dim is 3."""
        total = self.table.new_zeros(())
        for lvl in range(self.n_levels):
            for p in self.time_planes:
                g = self.plane(lvl, p)
                if g.shape[0] > 2:
                    total = total + (g[2:] - 2 * g[1:-1] + g[:-2]).square().mean()
        return total

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.in_dim:
            raise ValueError(f"expected points (..., {self.in_dim}), got {tuple(x.shape)}")
        if x.dim() != 2:
            return self(x.reshape(-1, self.in_dim)).reshape(*x.shape[:-1], self.out_dim)
        fast = use_kernels(x, self.table, backend=self.backend) and not x.requires_grad
        if fast:
            return _PlaneEncodeNumba.apply(x, self.table, self._offsets_np, self._res_np,
                                           self._pairs_np)
        return plane_encode_reference(x, self.table, self.offsets, self.res, self.pairs)
