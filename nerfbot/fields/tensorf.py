"""TensoRF field (Chen et al. 2022): vector-matrix (VM) factorised density and appearance grids.

A VM tensor holds three (plane, line) pairs - an XY plane with a Z line, XZ with Y, YZ with X -
of R components each; a point's value of component r of pair m is ``plane_m(x_a, x_b)[r] *
line_m(x_c)[r]`` (bilinear and linear interpolation). Density sums these over pairs and
components and goes through a shifted softplus; appearance concatenates them (3 R_app values),
maps them with a linear "basis matrix" B to ``app_dim`` features and shades them with a small
MLP on (features, view direction and their positional encodings), the paper's "MLP" render
mode, or reads B's output as spherical-harmonic coefficients ("sh" mode).

Training is coarse to fine: the grids start at ``init_res`` cells along the longest edge of the
scene bounds and are resampled (bilinear / linear interpolation of the parameters) up to
``final_res`` at fractions ``upsample_at`` of the budget, as the paper does; each upsampling
asks the trainer for a new optimiser. Resolutions live only in the parameters' shapes, so a
checkpoint of an upsampled field reloads into a freshly built one
(:func:`nerfbot.models.base.resize_like_state_dict`).

The grids cover the scene bounds per axis (not the enclosing cube), with cells of about the same
size along every axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numba
import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.fields.base import Field, mlp
from nerfbot.kernels import use_kernels
from nerfbot.kernels import vm as _vk
from nerfbot.kernels.vm import VM_AXES
from nerfbot.ops.encodings import FrequencyEncoding, spherical_harmonics


def _unit_box(x: torch.Tensor) -> torch.Tensor:
    """NaN read as 0, then clamped to [0, 1] (so +-inf go to the border)."""
    return torch.nan_to_num(x, nan=0.0).clamp(0.0, 1.0)


def _lerp_stencil(u: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell index (N,) int64 in [0, n - 2] and local weight (N, 1) of coordinates u (N,) in
    [0, 1] on n vertices (the kernels' ``_axis``)."""
    p = u * (n - 1)
    i = p.detach().floor().long().clamp_(0, n - 2)
    return i, (p - i.to(p.dtype))[:, None]


def vm_reference(x: torch.Tensor, planes: Sequence[torch.Tensor],
                 lines: Sequence[torch.Tensor]) -> torch.Tensor:
    """Plain-torch VM lookup, the twin of :func:`nerfbot.kernels.vm.vm_forward` (any device).

    Args:
        x: (N, 3) points in [0, 1]^3 (NaN read as 0, then clamped).
        planes: three (n_b, n_a, C) planes of the pairs in :data:`VM_AXES` order.
        lines: three (n_c, C) lines.
    Returns:
        (N, 3, C): ``plane_m * line_m`` per pair and channel, differentiable w.r.t. the planes,
        the lines and ``x``.
    """
    if x.dtype in (torch.float16, torch.bfloat16):
        x = x.float()  # locate cells in float32
    x = _unit_box(x)
    outs = []
    for (a, b, c), plane, line in zip(VM_AXES, planes, lines):
        n_b, n_a, ch = plane.shape
        ia, wa = _lerp_stencil(x[:, a], n_a)
        ib, wb = _lerp_stencil(x[:, b], n_b)
        ic, wc = _lerp_stencil(x[:, c], line.shape[0])
        flat = plane.reshape(-1, ch)
        r0 = ia + ib * n_a
        r1 = r0 + n_a
        pv = ((1 - wa) * flat[r0] + wa * flat[r0 + 1]) * (1 - wb) \
            + ((1 - wa) * flat[r1] + wa * flat[r1 + 1]) * wb
        outs.append(pv * ((1 - wc) * line[ic] + wc * line[ic + 1]))
    return torch.stack(outs, dim=1)


class _VMNumba(torch.autograd.Function):
    """Fast CPU path: numba kernels for the forward pass and the grid gradients (none for x)."""

    @staticmethod
    def forward(ctx, x, in_box, p0, p1, p2, l0, l1, l2):
        x_c = (x.detach() if in_box else _unit_box(x.detach())).contiguous()
        grids = (p0, p1, p2, l0, l1, l2)
        out = torch.empty(x.shape[0], 3, p0.shape[2], dtype=torch.float32)
        _vk.vm_forward(x_c.numpy(), *[g.detach().numpy() for g in grids], out.numpy())
        ctx.save_for_backward(x_c, *grids)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        x_c, *grids = ctx.saved_tensors
        grads = [torch.zeros_like(g, memory_format=torch.contiguous_format) for g in grids]
        n_blocks = max(1, min(numba.get_num_threads(), grad_out.shape[2]))
        _vk.vm_backward(x_c.numpy(), *[g.detach().numpy() for g in grids],
                        grad_out.float().contiguous().numpy(), *[g.numpy() for g in grads],
                        n_blocks)
        return (None, None, *grads)


class VMGrid(nn.Module):
    """One VM tensor: three (plane, line) pairs of C components over [0, 1]^3.

    Args:
        vertices: (n_x, n_y, n_z) vertices per axis (>= 2 each).
        components: C.
        init_scale: parameters start as ``init_scale * N(0, 1)`` (the paper's 0.1).
        backend: "numba" (fast CPU kernels) or "torch" (the twin). The kernels serve float32 CPU
            points that need no position gradient; anything else goes through the twin.
    """

    def __init__(self, vertices: Sequence[int], components: int, init_scale: float = 0.1,
                 generator: Optional[torch.Generator] = None, backend: str = "numba"):
        super().__init__()
        if backend not in ("numba", "torch"):
            raise ValueError(f"VM backend must be 'numba' or 'torch', got {backend!r}")
        if len(vertices) != 3 or min(vertices) < 2 or components < 1:
            raise ValueError(f"bad VM grid: vertices {tuple(vertices)}, components {components}")
        self.backend = backend
        n = [int(v) for v in vertices]
        self.planes = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(n[b], n[a], components, generator=generator))
             for a, b, _ in VM_AXES])
        self.lines = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(n[c], components, generator=generator))
             for _, _, c in VM_AXES])

    @property
    def components(self) -> int:
        return self.planes[0].shape[2]

    @property
    def vertices(self) -> tuple[int, int, int]:
        """(n_x, n_y, n_z) vertices per axis, read from the lines' shapes."""
        n = [0, 0, 0]
        for (_, _, c), line in zip(VM_AXES, self.lines):
            n[c] = line.shape[0]
        return n[0], n[1], n[2]

    def forward(self, x: torch.Tensor, in_box: bool = False) -> torch.Tensor:
        """x: (N, 3) in [0, 1]^3 -> (N, 3, C) per-pair products plane * line. ``in_box``: the
        caller guarantees x is finite and within [0, 1]^3 (skips the clamp)."""
        grids = [*self.planes, *self.lines]
        fast = use_kernels(x, *grids, backend=self.backend) and not x.requires_grad
        if fast:
            return _VMNumba.apply(x, in_box, *grids)
        return vm_reference(x, self.planes, self.lines)

    @torch.no_grad()
    def resample(self, vertices: Sequence[int]) -> None:
        """Resize every plane and line to ``vertices`` (n_x, n_y, n_z) by (bi)linear
        interpolation of the parameters over [0, 1] (end vertices stay on the box faces). The
        parameters are replaced: an optimiser over the old ones must be rebuilt."""
        n = [int(v) for v in vertices]
        if len(n) != 3 or min(n) < 2:
            raise ValueError(f"VM grid needs >= 2 vertices per axis, got {tuple(vertices)}")
        for m, (a, b, c) in enumerate(VM_AXES):
            p = self.planes[m].permute(2, 0, 1)[None]                     # (1, C, n_b, n_a)
            p = F.interpolate(p, size=(n[b], n[a]), mode="bilinear", align_corners=True)
            self.planes[m] = nn.Parameter(p[0].permute(1, 2, 0).contiguous())
            line = self.lines[m].t()[None]                                # (1, C, n_c)
            line = F.interpolate(line, size=n[c], mode="linear", align_corners=True)
            self.lines[m] = nn.Parameter(line[0].t().contiguous())

    def l1(self) -> torch.Tensor:
        """TensoRF's sparsity term: the sum over pairs of mean |plane| + mean |line|."""
        return sum(p.abs().mean() + li.abs().mean() for p, li in zip(self.planes, self.lines))

    def tv(self) -> torch.Tensor:
        """Squared total variation of the planes: mean squared difference of neighbouring
        vertices along both plane axes, summed over planes."""
        return sum((p[1:] - p[:-1]).square().mean() + (p[:, 1:] - p[:, :-1]).square().mean()
                   for p in self.planes)


@dataclass
class TensoRFFieldConfig:
    init_res: int = 64
    """Cells along the longest edge of the scene bounds at the start (other axes in proportion)."""
    final_res: int = 256
    """Cells along the longest edge after the last upsampling."""
    upsample_at: tuple = (0.04, 0.08, 0.12, 0.18, 0.25)
    """Fractions of the training budget at which the grids are upsampled; the resolutions in
    between grow geometrically (in voxel count, as the paper) from init_res to final_res."""
    density_components: int = 16
    """R_sigma: density components per (plane, line) pair."""
    app_components: int = 48
    """R_app: appearance components per pair."""
    app_dim: int = 27
    """Output width of the basis matrix B in "mlp" shading."""
    shading: str = "mlp"
    """"mlp": a ReLU MLP on B's features and the view direction (the paper's MLP_Fea mode);
    "sh": B outputs 3 (sh_degree + 1)^2 spherical-harmonic coefficients of the colour."""
    sh_degree: int = 2
    """Degree of the colour's spherical harmonics in "sh" shading."""
    mlp_hidden: int = 64
    """Width of the shading MLP (two hidden layers; the paper's 128 costs 1.4x the field's
    time per sample on the CPU here)."""
    view_pe: int = 2
    """Frequencies of the view direction's positional encoding (the raw direction is always in)."""
    feature_pe: int = 2
    """Frequencies of the appearance features' positional encoding (0: raw features only)."""
    density_shift: float = -10.0
    """sigma = softplus(f + density_shift) * scale: components at zero (where the L1 term pulls
    them) mean empty space (the paper's -10)."""
    initial_transmittance: float = 0.2
    """Transmittance at initialisation along ``initial_transmittance_path``: the density
    components start at a constant offset (plus noise) that makes f this dense. From f = 0 (the
    paper's zero-mean start) the softplus passes almost no gradient (4.5e-5 of it), and with a
    learned background explaining the first batches the density never grows."""
    initial_transmittance_path: str = "diagonal"
    """What ``initial_transmittance`` is measured along: "diagonal", the diagonal of the cube
    enclosing the bounds; "rays", the training rays' median path through the bounds (measured
    from the data before the first step, :meth:`TensoRFField.init_ray_length`), so bounds shaped
    as a slab do not start nearly transparent. A field trained outside the trainer starts along
    the diagonal."""
    density_scale: float = 75.0
    """sigma (1/m) = softplus(...) * density_scale / (longest edge of the bounds in m). The
    paper's 25 per unit on its 3-unit Blender box is 75 per box length."""
    init_scale: float = 0.1
    """Grid parameters start as init_scale * N(0, 1)."""
    l1_weight: float = 8e-5
    """Weight of the L1 sparsity of the density components (mean |plane| + mean |line|)."""
    tv_weight_density: float = 0.0
    """Weight of the total variation of the density planes (0: off; the paper uses it only for
    forward-facing scenes)."""
    tv_weight_app: float = 0.0
    """Weight of the total variation of the appearance planes."""
    mlp_lr_scale: float = 0.05
    """Learning rate of B and the shading MLP relative to the grids' (paper: 1e-3 vs 0.02)."""
    backend: str = "numba"
    """VM lookups: "numba" (fast CPU kernels) or "torch" (the reference twin)."""


_WARM = False


class TensoRFField(Field):
    """sigma = softplus(sum VM_sigma(x) + shift) * scale; rgb = S(B VM_app(x), d).

    The geometry features passed from :meth:`density` to :meth:`color` are the normalised
    positions (N, 3): appearance is only looked up for the samples that get coloured (the
    trainer's density-only pass over all samples skips it). Points outside the scene bounds have
    zero density.
    """

    def __init__(self, aabb, config: TensoRFFieldConfig | None = None, seed: int = 0):
        super().__init__()
        self.config = cfg = config or TensoRFFieldConfig()
        self._validate(cfg)
        aabb = torch.as_tensor(aabb, dtype=torch.float32)
        extent = aabb[1] - aabb[0]
        if not bool((extent > 0).all()):
            raise ValueError(f"scene bounds must have positive extent, got {aabb.tolist()}")
        self.register_buffer("aabb", aabb.clone())
        self._edge_ratio = (extent / extent.max()).tolist()
        self.sigma_scale = cfg.density_scale / float(extent.max())

        gen = torch.Generator().manual_seed(seed)
        start = self.vertices_for(cfg.init_res)
        self.density_vm = VMGrid(start, cfg.density_components, cfg.init_scale, gen, cfg.backend)
        #: the constant in every density plane and line entry (:meth:`_initial_offset`)
        self._start_offset = self._initial_offset(self._cube_diagonal())
        with torch.no_grad():
            for t in self.density_vm.parameters():
                t.add_(self._start_offset)
        self.app_vm = VMGrid(start, cfg.app_components, cfg.init_scale, gen, cfg.backend)
        if cfg.shading == "mlp":
            self.basis = nn.Linear(3 * cfg.app_components, cfg.app_dim, bias=False)
            self.view_enc = FrequencyEncoding(3, cfg.view_pe)
            self.feat_enc = FrequencyEncoding(cfg.app_dim, cfg.feature_pe)
            self.shader = mlp(self.view_enc.out_dim + self.feat_enc.out_dim, cfg.mlp_hidden, 2, 3)
        else:
            self.basis = nn.Linear(3 * cfg.app_components, 3 * (cfg.sh_degree + 1) ** 2)
        global _WARM
        if use_kernels(backend=cfg.backend) and not _WARM:
            _vk.warm_up()  # compile / load the kernels outside any training clock
            _WARM = True

    @staticmethod
    def _validate(cfg: TensoRFFieldConfig) -> None:
        if not 2 <= cfg.init_res <= cfg.final_res:
            raise ValueError(f"need 2 <= init_res <= final_res, got {cfg.init_res}, {cfg.final_res}")
        fractions = list(cfg.upsample_at)
        if any(not 0.0 < f < 1.0 for f in fractions) or fractions != sorted(fractions):
            raise ValueError(f"upsample_at must be increasing fractions in (0, 1), got {fractions}")
        if min(cfg.density_components, cfg.app_components, cfg.app_dim, cfg.mlp_hidden) < 1:
            raise ValueError("density_components, app_components, app_dim and mlp_hidden must be >= 1")
        if cfg.shading not in ("mlp", "sh"):
            raise ValueError(f"shading must be 'mlp' or 'sh', got {cfg.shading!r}")
        if not 0 <= cfg.sh_degree <= 4:
            raise ValueError(f"sh_degree must be 0..4, got {cfg.sh_degree}")
        if min(cfg.view_pe, cfg.feature_pe) < 0:
            raise ValueError("view_pe and feature_pe must be >= 0")
        if min(cfg.l1_weight, cfg.tv_weight_density, cfg.tv_weight_app) < 0:
            raise ValueError("regulariser weights must be >= 0")
        if not (cfg.density_scale > 0 and cfg.init_scale > 0 and cfg.mlp_lr_scale > 0):
            raise ValueError("density_scale, init_scale and mlp_lr_scale must be > 0")
        if not 0.0 < cfg.initial_transmittance < 1.0:
            raise ValueError(f"initial_transmittance must be in (0, 1), got "
                             f"{cfg.initial_transmittance}")
        if cfg.initial_transmittance_path not in ("diagonal", "rays"):
            raise ValueError(f"initial_transmittance_path must be 'diagonal' or 'rays', got "
                             f"{cfg.initial_transmittance_path!r}")
        if cfg.backend not in ("numba", "torch"):
            raise ValueError(f"backend must be 'numba' or 'torch', got {cfg.backend!r}")

    def _cube_diagonal(self) -> float:
        """Diagonal (m) of the cube enclosing the bounds."""
        return math.sqrt(3.0) * float((self.aabb[1] - self.aabb[0]).max())

    def _initial_offset(self, path_m: float) -> float:
        """Constant a added to every density plane and line entry so that f = 3 R a^2 gives a
        density of -ln(initial_transmittance) / path_m (1/m)."""
        cfg = self.config
        sigma0 = -math.log(cfg.initial_transmittance) / path_m
        f0 = math.log(math.expm1(sigma0 / self.sigma_scale)) - cfg.density_shift
        return math.sqrt(max(f0, 0.0) / (3 * cfg.density_components))

    def init_ray_length(self, length_m: float) -> None:
        """With ``initial_transmittance_path="rays"``: start with ``initial_transmittance``
        along ``length_m`` metres instead of the cube's diagonal, by moving the constant in
        every density plane and line entry (the noise around it stays); a checkpoint keeps it.
        Calling again replaces the earlier start."""
        if self.config.initial_transmittance_path != "rays":
            return
        if not (math.isfinite(length_m) and length_m > 0):
            raise ValueError(f"ray length must be a positive number of metres, got {length_m}")
        offset = self._initial_offset(length_m)
        with torch.no_grad():
            for t in self.density_vm.parameters():
                t.add_(offset - self._start_offset)
        self._start_offset = offset

    # -- resolution schedule -----------------------------------------------------------------
    def vertices_for(self, cells: int) -> tuple[int, int, int]:
        """Vertices per axis for ``cells`` cells along the longest edge (cubic cells)."""
        return tuple(max(1, round(cells * r)) + 1 for r in self._edge_ratio)

    def cells_schedule(self) -> list[int]:
        """Cells along the longest edge in each stage (before the first upsampling, then after
        each): geometric in voxel count from init_res to final_res."""
        cfg = self.config
        k = len(cfg.upsample_at)
        if k == 0:
            return [cfg.init_res]
        lo, hi = math.log(cfg.init_res), math.log(cfg.final_res)
        return [round(math.exp(lo + (hi - lo) * i / k)) for i in range(k + 1)]

    def before_step(self, step: int, progress: float) -> dict:
        stage = sum(progress >= f for f in self.config.upsample_at)
        target = self.vertices_for(self.cells_schedule()[stage])
        if target == self.density_vm.vertices:
            return {}
        self.density_vm.resample(target)
        self.app_vm.resample(target)
        return {"params_changed": True}

    # -- field -------------------------------------------------------------------------------
    def _normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.aabb[0]) / (self.aabb[1] - self.aabb[0])

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        u = self._normalize(x)
        inside = ((u >= 0) & (u <= 1)).all(-1)
        u = _unit_box(u)
        f = self.density_vm(u, in_box=True).sum(dim=(1, 2))
        sigma = F.softplus(f + self.config.density_shift) * self.sigma_scale
        sigma = torch.where(inside, sigma, torch.zeros_like(sigma))
        return sigma, u

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        """feat: (N, 3) normalised positions from :meth:`density`; d: (N, 3) unit directions."""
        h = self.basis(self.app_vm(feat).reshape(feat.shape[0], -1))
        if self.config.shading == "mlp":
            return torch.sigmoid(self.shader(torch.cat([self.feat_enc(h), self.view_enc(d)], -1)))
        coeffs = h.view(h.shape[0], 3, -1)                                # (N, 3, K)
        sh = spherical_harmonics(d, self.config.sh_degree)                # (N, K)
        return torch.sigmoid((coeffs * sh[:, None, :]).sum(-1))

    def regularizer(self) -> Optional[torch.Tensor]:
        cfg = self.config
        terms = []
        if cfg.l1_weight > 0:
            terms.append(cfg.l1_weight * self.density_vm.l1())
        if cfg.tv_weight_density > 0:
            terms.append(cfg.tv_weight_density * self.density_vm.tv())
        if cfg.tv_weight_app > 0:
            terms.append(cfg.tv_weight_app * self.app_vm.tv())
        return sum(terms) if terms else None

    # -- training hooks ----------------------------------------------------------------------
    def color_head(self) -> nn.Linear:
        return self.shader[-1] if self.config.shading == "mlp" else self.basis

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        if self.config.shading == "mlp":
            return super().init_mean_color(rgb)
        # sh: only the constant (degree-0) coefficient of each channel carries the mean colour
        k = (self.config.sh_degree + 1) ** 2
        bias = torch.zeros(3, k)
        bias[:, 0] = torch.logit(rgb.clamp(0.02, 0.98)) / spherical_harmonics(
            torch.tensor([[0.0, 0.0, 1.0]]), 0)[0, 0]
        with torch.no_grad():
            self.basis.bias.copy_(bias.reshape(-1).to(self.basis.bias))

    def param_groups(self) -> list[dict]:
        """Grids at the method's learning rate, B and the shading MLP at ``mlp_lr_scale``."""
        grids = [*self.density_vm.parameters(), *self.app_vm.parameters()]
        ids = {id(p) for p in grids}
        rest = [p for p in self.parameters() if id(p) not in ids]
        return [{"params": grids, "lr_scale": 1.0},
                {"params": rest, "lr_scale": self.config.mlp_lr_scale}]
