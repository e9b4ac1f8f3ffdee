"""KiloNeRF's field (Reiser et al. 2021): a regular grid of thousands of tiny MLPs, one per cell.

Network ``k`` owns one cell of a G^3 grid over the cube enclosing the scene bounds and sees the
positional encoding of the point in the cell's local coordinates ([-1, 1]^3). All networks'
weights are stacked in tensors with a leading network axis; samples are grouped by network into
padded chunks of C rows (:func:`nerfbot.kernels.kilonerf.chunk_layout`) so that every layer of
every network is one batched matmul (``torch.baddbmm``), never a Python loop over networks.
Its renderer and training phases are :class:`nerfbot.models.kilonerf.KiloNeRFModel`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from nerfbot.fields.base import BoxNormalizer, Field, trunc_exp
from nerfbot.kernels import kilonerf as _kk
from nerfbot.kernels import use_kernels
from nerfbot.ops.encodings import FrequencyEncoding


#: Scratch room per ray of the fused renderer's first pass (rays average two samples here).
FUSED_SLOT_SAMPLES = 8


#: The stacked per-network tensors, each with the network axis first.
PARAMETER_NAMES = ("w_in", "b_in", "w_hid", "b_hid", "w_sigma", "b_sigma", "w_color", "b_color",
                   "w_rgb", "b_rgb")


@dataclass
class KiloNeRFFieldConfig:
    network_resolution: int = 16
    """G: networks per axis of the cube enclosing the bounds (G^3 networks before pruning)."""
    hidden: int = 32
    """Width H of every tiny network."""
    hidden_layers: int = 1
    """ReLU layers of width H before the density output; one more follows where the view
    direction is injected (the paper's networks have 4 in all). Distilled from the tabletop's
    ngp run, 1 (2 in all) rendered 7% faster than 2 at the same test PSNR (32.8 dB)."""
    pos_freqs: int = 6
    """Frequencies L of the positional encoding of the *local* coordinates in [-1, 1]^3. A cell
    is 1/G of the cube, so with G = 16, L = 6 local reaches the same finest frequency as the
    paper's L = 10 on global coordinates."""
    dir_freqs: int = 4
    """Frequencies of the positional encoding of the view direction (paper: 4)."""
    chunk_rows: int = 64
    """Largest C, the rows per chunk of the batched matmuls. Each call picks the power of two
    nearest to its samples per network within [8, chunk_rows]: every network's samples are
    padded to a multiple of C, so a C much above that count is mostly padding."""
    initial_transmittance: float = 0.2
    """Transmittance of a ray crossing the whole cube at initialisation (sets a density bias,
    as in the ngp field, so untrained networks start nearly empty)."""
    layout_backend: str = "numba"
    """Chunk layout and encodings: "numba" (kernels) or "torch" (the twins)."""


def chunk_layout_reference(slots: torch.Tensor, n_nets: int, chunk: int
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Plain-torch twin of :func:`nerfbot.kernels.kilonerf.chunk_layout` (same outputs).

    Args:
        slots: (N,) int64 network of each sample, -1 for none. n_nets: K. chunk: C.
    Returns:
        pos (N,) int64 padded row of each sample (-1 for none); chunk_net (n_chunks,) int64.
    """
    device = slots.device
    valid = torch.nonzero(slots >= 0).squeeze(-1)
    s = slots[valid]
    counts = torch.bincount(s, minlength=n_nets)
    n_ch = (counts + chunk - 1) // chunk
    first = torch.cumsum(n_ch, 0) - n_ch
    chunk_net = torch.repeat_interleave(torch.arange(n_nets, device=device), n_ch)
    order = torch.sort(s, stable=True).indices
    sorted_s = s[order]
    rank = torch.arange(s.shape[0], device=device) - (torch.cumsum(counts, 0) - counts)[sorted_s]
    pos_valid = torch.empty_like(s)
    pos_valid[order] = first[sorted_s] * chunk + rank
    pos = torch.full_like(slots, -1)
    pos[valid] = pos_valid
    return pos, chunk_net


class Layout:
    """Samples grouped by network for the batched matmuls.

    Attributes:
        pos: (M,) int64 padded row of each sample (every sample has a network); None for a
            layout that only runs matmuls (e.g. a selection of another layout's chunks).
        chunk_net: (n_chunks,) int64 network of each chunk. chunk: C. rows: n_chunks * C.
    """

    def __init__(self, pos: Optional[torch.Tensor], chunk_net: torch.Tensor, chunk: int):
        self.pos, self.chunk_net, self.chunk = pos, chunk_net, chunk
        self.rows = int(chunk_net.shape[0]) * chunk

    def padded(self, rows: torch.Tensor) -> torch.Tensor:
        """Per-sample rows (M, D) -> padded (rows, D), zero padding (differentiable)."""
        return rows.new_zeros(self.rows, rows.shape[1]).index_copy(0, self.pos, rows)

    def bmm(self, xp: torch.Tensor, w: torch.Tensor, b: Optional[torch.Tensor] = None
            ) -> torch.Tensor:
        """One layer of every network: padded xp (rows, in) -> (rows, out); chunk c is
        multiplied by w[chunk_net[c]] (in, out) and offset by b[chunk_net[c]] (out,)."""
        nc = self.chunk_net.shape[0]
        x3 = xp.reshape(nc, self.chunk, -1)
        wc = w[self.chunk_net]
        if b is None:
            y = torch.bmm(x3, wc)
        else:
            y = torch.baddbmm(b[self.chunk_net].unsqueeze(1), x3, wc)
        return y.reshape(self.rows, -1)


def _uniform(gen: torch.Generator, shape, fan_in: int) -> torch.Tensor:
    """nn.Linear's default initialisation: U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    bound = 1.0 / math.sqrt(fan_in)
    return (torch.rand(shape, generator=gen) * 2.0 - 1.0) * bound


class KiloNeRFField(Field):
    """Per network k: h = relu(W_l ... relu(W_in gamma(x_local) + b_in)),
    sigma = trunc_exp(w_sigma . h + b_sigma + bias), rgb = sigmoid(W_rgb relu(W_color [h, gamma(d)]
    + b_color) + b_rgb) (the view direction enters before the last layers, as in the paper).

    ``net_index`` (G^3,) maps every grid cell to its network's slot in the stacked tensors, or
    -1 when the cell has no network (pruned: empty space); points there, and outside the scene
    bounds, have zero density. All sizes derive from tensor shapes, so checkpoints of pruned
    fields load into a freshly built one (:func:`nerfbot.models.base.resize_like_state_dict`).

    The geometry features are ``[h, slot]`` (N, H + 1): the network's slot travels with the
    features so that :meth:`color` evaluates the same network.
    """

    def __init__(self, aabb, config: KiloNeRFFieldConfig | None = None, seed: int = 0):
        super().__init__()
        self.config = cfg = config or KiloNeRFFieldConfig()
        for name in ("network_resolution", "hidden", "hidden_layers", "chunk_rows"):
            if int(getattr(cfg, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(cfg, name)}")
        if cfg.pos_freqs < 0 or cfg.dir_freqs < 0:
            raise ValueError(f"pos_freqs and dir_freqs must be >= 0, got {cfg.pos_freqs}, "
                             f"{cfg.dir_freqs}")
        if cfg.layout_backend not in ("numba", "torch"):
            raise ValueError(f"layout_backend must be 'numba' or 'torch', got "
                             f"{cfg.layout_backend!r}")
        if not 0.0 < cfg.initial_transmittance < 1.0:
            raise ValueError(f"initial_transmittance must be in (0, 1), got "
                             f"{cfg.initial_transmittance}")
        self.normalize = BoxNormalizer(aabb)
        self.pos_enc = FrequencyEncoding(3, cfg.pos_freqs)
        self.dir_enc = FrequencyEncoding(3, cfg.dir_freqs)
        g, h, n_hid = cfg.network_resolution, cfg.hidden, cfg.hidden_layers - 1
        k = g ** 3
        self.register_buffer("net_index", torch.arange(k, dtype=torch.long))
        gen = torch.Generator().manual_seed(seed)
        d_in, d_dir = self.pos_enc.out_dim, self.dir_enc.out_dim
        shapes = {"w_in": ((k, d_in, h), d_in), "b_in": ((k, h), d_in),
                  "w_hid": ((k, n_hid, h, h), h), "b_hid": ((k, n_hid, h), h),
                  "w_sigma": ((k, h, 1), h), "b_sigma": ((k, 1), h),
                  "w_color": ((k, h + d_dir, h), h + d_dir), "b_color": ((k, h), h + d_dir),
                  "w_rgb": ((k, h, 3), h), "b_rgb": ((k, 3), h)}
        for name in PARAMETER_NAMES:
            shape, fan_in = shapes[name]
            setattr(self, name, nn.Parameter(_uniform(gen, shape, fan_in)))
        diagonal = math.sqrt(3.0) * float(self.normalize.cube_size)
        self.density_bias = math.log(-math.log(cfg.initial_transmittance) / diagonal)

    # -- layout ------------------------------------------------------------------------------
    @property
    def resolution(self) -> int:
        """G, from the shape of ``net_index``."""
        return int(round(self.net_index.numel() ** (1.0 / 3.0)))

    @property
    def num_networks(self) -> int:
        """Networks that exist (after pruning), from the stacked tensors' shape."""
        return int(self.w_in.shape[0])

    def cells(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (N, 3) world points -> flat grid cell (N,) int64 in [0, G^3), local coordinates
        (N, 3) in [-1, 1] within that cell."""
        g = self.resolution
        p = self.normalize(x) * g
        ijk = p.detach().floor().long().clamp(0, g - 1)  # clamp after the cast: NaN stays in range
        local = (p - ijk.to(p.dtype)) * 2.0 - 1.0
        return (ijk[:, 0] * g + ijk[:, 1]) * g + ijk[:, 2], local

    def slots(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (N, 3) -> network slot (N,) int64 (-1 outside the bounds or in a cell without a
        network) and local coordinates (N, 3)."""
        cell, local = self.cells(x)
        slot = self.net_index[cell]
        return torch.where(self.normalize.inside(x), slot, torch.full_like(slot, -1)), local

    def layout(self, slots: torch.Tensor) -> Layout:
        """(M,) slots, all >= 0 -> their :class:`Layout` (C adapted to the samples per network)."""
        per_net = max(slots.shape[0] / max(self.num_networks, 1), 1.0)
        chunk = int(min(max(2 ** round(math.log2(per_net)), 8), self.config.chunk_rows))
        if use_kernels(slots, backend=self.config.layout_backend):
            pos, chunk_net = _kk.chunk_layout(slots.contiguous().numpy(), self.num_networks, chunk)
            pos, chunk_net = torch.from_numpy(pos), torch.from_numpy(chunk_net)
        else:
            pos, chunk_net = chunk_layout_reference(slots, self.num_networks, chunk)
        return Layout(pos, chunk_net, chunk)

    def encoded_rows(self, values: torch.Tensor, layout: Layout, enc: FrequencyEncoding,
                     out: Optional[torch.Tensor] = None, col: int = 0) -> torch.Tensor:
        """The encoding of ``values`` (M, D) on the padded rows of ``layout``: (rows, D_enc);
        with ``out`` (rows, >= col + D_enc), written into its columns from ``col`` instead."""
        if use_kernels(values, backend=self.config.layout_backend) and not values.requires_grad:
            if out is None:
                out, col = torch.zeros(layout.rows, enc.out_dim), 0
            v = values.contiguous()
            angle = math.pi * v.double()
            _kk.encode_rows(v.numpy(), torch.sin(angle).numpy(), torch.cos(angle).numpy(),
                            layout.pos.numpy(), enc.n_freqs, out.numpy(), col)
            return out
        rows = layout.padded(enc(values))
        if out is None:
            return rows
        out[:, col:col + rows.shape[1]] = rows
        return out

    # -- the networks ------------------------------------------------------------------------
    def weights(self, dtype: Optional[torch.dtype] = None) -> dict:
        """The stacked parameters by name, in ``dtype``: the parameters themselves for None or
        their own dtype, else detached copies, cached until any parameter changes (rendering in
        bfloat16 converts them once, not per image)."""
        params = {name: getattr(self, name) for name in PARAMETER_NAMES}
        if dtype is None or dtype == self.w_in.dtype:
            return params
        key = (dtype,) + tuple((p.data_ptr(), p._version) for p in params.values())
        cache = self.__dict__.get("_cast_cache")
        if cache is None or cache[0] != key:
            cache = (key, {n: p.detach().to(dtype) for n, p in params.items()})
            self.__dict__["_cast_cache"] = cache
        return cache[1]

    def trunk(self, xp: torch.Tensor, layout: Layout, w: Optional[dict] = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """Padded encoded points (rows, D_in) -> padded hidden features (rows, H) and raw
        density (rows, 1) (before the bias and the activation). ``w``: the weights to use
        (default: the parameters; see :meth:`weights`)."""
        w = w or self.weights()
        h = torch.relu_(layout.bmm(xp, w["w_in"], w["b_in"]))
        for layer in range(w["w_hid"].shape[1]):
            h = torch.relu_(layout.bmm(h, w["w_hid"][:, layer], w["b_hid"][:, layer]))
        return h, layout.bmm(h, w["w_sigma"], w["b_sigma"])

    def head(self, hp: torch.Tensor, dp: torch.Tensor, layout: Layout, w: Optional[dict] = None
             ) -> torch.Tensor:
        """Padded hidden features (rows, H) and encoded directions (rows, D_dir) -> padded rgb
        (rows, 3) in [0, 1]. W_color [h, gamma(d)] is computed as two matmuls (no concatenated
        copy of the inputs)."""
        w = w or self.weights()
        hdim = hp.shape[1]
        c = layout.bmm(dp, w["w_color"][:, hdim:], w["b_color"])
        c = torch.relu_(c.add_(layout.bmm(hp, w["w_color"][:, :hdim])))
        return torch.sigmoid(layout.bmm(c, w["w_rgb"], w["b_rgb"]))

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        """x: (N, 3) -> sigma (N,) >= 0 (1/m), features (N, H + 1): [h, slot] (slot -1: none)."""
        n, hdim = x.shape[0], self.w_in.shape[-1]
        slot, local = self.slots(x)
        idx = torch.nonzero(slot >= 0).squeeze(-1)
        sigma = x.new_zeros(n)
        feat = torch.cat([x.new_zeros(n, hdim), x.new_full((n, 1), -1.0)], -1)
        if idx.numel() == 0:
            return sigma, feat
        s = slot[idx]
        lay = self.layout(s)
        h, raw = self.trunk(self.encoded_rows(local[idx], lay, self.pos_enc), lay)
        sig = trunc_exp(raw[lay.pos, 0] + self.density_bias)
        f = torch.cat([h[lay.pos], s.to(x.dtype)[:, None]], -1)
        if idx.numel() == n:
            return sig, f
        return sigma.index_copy(0, idx, sig), feat.index_copy(0, idx, f)

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        """feat (N, H + 1) from :meth:`density`, d (N, 3) unit directions -> rgb (N, 3) in [0, 1]
        (0 where there is no network: those samples have zero density)."""
        n = feat.shape[0]
        slot = feat[:, -1].detach().round().long()
        idx = torch.nonzero(slot >= 0).squeeze(-1)
        rgb = feat.new_zeros(n, 3)
        if idx.numel() == 0:
            return rgb
        lay = self.layout(slot[idx])
        out = self.head(lay.padded(feat[idx, :-1]), self.encoded_rows(d[idx], lay, self.dir_enc),
                        lay)[lay.pos]
        return out if idx.numel() == n else rgb.index_copy(0, idx, out)

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """Every network starts predicting ``rgb`` (3,): its last bias is logit(rgb)."""
        with torch.no_grad():
            logit = torch.logit(rgb.clamp(0.02, 0.98)).to(self.b_rgb)
            self.b_rgb.copy_(logit.expand_as(self.b_rgb))

    # -- pruning -----------------------------------------------------------------------------
    @torch.no_grad()
    def keep_networks(self, cells: torch.Tensor) -> int:
        """Keep only the networks of the grid cells where ``cells`` (G^3,) bool is True (and
        that still have one); the others are deleted and their cells map to -1. Replaces the
        parameters (the optimiser must be rebuilt). Returns the number of networks kept."""
        if cells.shape != self.net_index.shape:
            raise ValueError(f"cells must have shape {tuple(self.net_index.shape)}, got "
                             f"{tuple(cells.shape)}")
        keep = torch.nonzero(cells.to(self.net_index.device) & (self.net_index >= 0)).squeeze(-1)
        old = self.net_index[keep]
        index = torch.full_like(self.net_index, -1)
        index[keep] = torch.arange(keep.numel(), device=index.device)
        self.net_index.copy_(index)
        for name in PARAMETER_NAMES:
            setattr(self, name, nn.Parameter(getattr(self, name).data[old].clone()))
        return int(keep.numel())
