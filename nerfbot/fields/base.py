"""The one interface every radiance field implements."""

from __future__ import annotations

import abc
from typing import Optional

import torch
from torch import nn

from nerfbot.ops.contraction import CONTRACTED_HALF, contract, step_scale


def _trunc_exp_limit(dtype: torch.dtype) -> float:
    """Largest argument of :func:`trunc_exp`: 15, or 11 in float16, whose largest finite value
    (65504) is below exp(15) = 3.3e6 (exp(11) = 6.0e4 fits)."""
    return 11.0 if dtype == torch.float16 else 15.0


class TruncExp(torch.autograd.Function):
    """exp(x) with its argument clamped to <= 15 in the forward pass and to [-15, 15] in the
    gradient (Instant-NGP's ``trunc_exp``): density stays finite (<= 3.3e6 /m) and gradients
    never overflow, yet saturated densities still receive a gradient. In float16 the limit is
    11 instead of 15 (see :func:`_trunc_exp_limit`)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp_max(_trunc_exp_limit(x.dtype)))

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        limit = _trunc_exp_limit(x.dtype)
        return grad * torch.exp(x.clamp(-limit, limit))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return TruncExp.apply(x)


class Field(nn.Module, metaclass=abc.ABCMeta):
    """A radiance field: density and view-dependent colour at world points (metres).

    ``cond`` carries what the scene needs beyond position and direction (time, joints) and is
    None for static scenes. Every variant implements both methods; samplers, renderers,
    trainers and queries only ever call these.
    """

    @abc.abstractmethod
    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (N, 3) world points -> sigma (N,) >= 0 in 1/m, geometry features (N, C)."""

    @abc.abstractmethod
    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None
              ) -> torch.Tensor:
        """feat: (N, C) from :meth:`density`, d: (N, 3) unit view directions -> rgb (N, 3) in [0, 1]."""

    def forward(self, x: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        sigma, feat = self.density(x, cond)
        return sigma, self.color(feat, d, cond)

    @property
    def uses_footprint(self) -> bool:
        """Whether :meth:`density_at_scale` uses the sample's footprint (renderers compute
        the radii only then). Default: False."""
        return False

    def density_at_scale(self, x: torch.Tensor, radius: Optional[torch.Tensor],
                         cond: Optional[torch.Tensor] = None
                         ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`density` of the samples of a pixel's cone: x (N, 3) world points, radius (N,)
        the cone's radius at each point in metres (``t * Rays.radii``; None: points). A field
        whose encoding knows the footprint fades out detail finer than it, so a far camera and a
        near one that see the same surface each get the detail their pixels resolve. Default:
        the radius is ignored."""
        return self.density(x, cond)

    def occupancy_density(self, x: torch.Tensor, generator: Optional[torch.Generator] = None
                          ) -> torch.Tensor:
        """x: (N, 3) -> (N,) density for occupancy-grid updates: a cell must count as occupied
        if it is occupied under *any* condition. Static fields: :meth:`density`. Conditioned
        fields draw conditions at random over their whole range (each update a new draw; the
        grid keeps a decaying maximum over updates)."""
        return self.density(x)[0]

    def before_step(self, step: int, progress: float) -> dict:
        """Field upkeep before training step ``step`` at ``progress`` in [0, 1] of the budget
        (e.g. coarse-to-fine upsampling); ``{"params_changed": True}`` asks the trainer for a
        new optimiser. Default: nothing."""
        return {}

    def training_time_limit(self, progress: float) -> Optional[float]:
        """The latest time (a time-conditioned field's condition, in [0, 1]) whose frames train
        at ``progress`` in [0, 1] of the budget, for a field that learns a scene forward in
        time; None: every frame trains. Default: None."""
        return None

    def regularizer(self) -> Optional[torch.Tensor]:
        """A scalar added to the training loss (e.g. smoothness of a space-time grid), or None."""
        return None

    def prunable(self) -> bool:
        """Whether an occupancy grid may prune empty cells now (the field's last
        :meth:`before_step` decides); False while part of the field has yet to grow where it
        will live. Default: always."""
        return True

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """Start predicting the colour ``rgb`` (3,) in (0, 1) everywhere (before training).

        Default: set the bias of the last layer of :meth:`color_head` to logit(rgb). Starting
        from the data's mean colour makes the first colour gradients zero-mean across pixels; from
        grey, they all agree ("brighter" against a sky) and Adam drives the colour MLP into
        sigmoid saturation before any structure forms."""
        head = self.color_head()
        with torch.no_grad():
            head.bias.copy_(torch.logit(rgb.clamp(0.02, 0.98)).to(head.bias))

    def init_ray_length(self, length_m: float) -> None:
        """Before training: the training rays cross the scene bounds over a median of
        ``length_m`` metres (:meth:`~nerfbot.data.pixels.PixelBank.median_ray_path`). Fields
        whose initial density is set along that path adjust it here. Default: nothing."""

    def color_head(self) -> nn.Linear:
        """The last linear layer of the colour branch (its output goes through a sigmoid)."""
        raise TypeError(f"{type(self).__name__} has no colour head; override init_mean_color")

    def param_groups(self) -> list[dict]:
        """Optimiser groups: dicts with ``params`` and an ``lr_scale`` relative to the method's
        learning rate. Default: one group of everything at scale 1."""
        return [{"params": list(self.parameters()), "lr_scale": 1.0}]


def mlp(in_dim: int, hidden: int, n_hidden_layers: int, out_dim: int) -> nn.Sequential:
    """Plain ReLU MLP: in -> [hidden] * n_hidden_layers -> out (no output activation)."""
    layers: list[nn.Module] = []
    d = in_dim
    for _ in range(n_hidden_layers):
        layers += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


#: Rows of a reduced-precision MLP batch are padded to a multiple of this: oneDNN compiles a
#: bfloat16 matmul for each new shape (about a millisecond each), and training batches and
#: render chunks change their row count every call; padded, a few shapes recur.
MLP_ROW_BUCKET = 2048


def run_mlp(net: nn.Module, x: torch.Tensor, precision: str = "fp32") -> torch.Tensor:
    """``net(x)`` for x (N, D): (N, out) float32. ``precision`` "bf16": under bfloat16 autocast
    (AMX / AVX-512 BF16 matmuls on CPU, tensor cores on GPU; weights and their gradients stay
    float32), the rows padded to a multiple of :data:`MLP_ROW_BUCKET` with zeros and the
    padding dropped from the output; "fp32": plain float32."""
    if precision != "bf16":
        return net(x)
    n = x.shape[0]
    pad = -n % MLP_ROW_BUCKET
    if pad:
        x = torch.nn.functional.pad(x, (0, 0, 0, pad))
    with torch.autocast(x.device.type, dtype=torch.bfloat16):
        out = net(x)
    return out[:n].float()


class BoxNormalizer(nn.Module):
    """Maps world points into [0, 1]^3 of the cube enclosing the scene bounds (isotropic)."""

    contracted = False

    def __init__(self, aabb):
        super().__init__()
        aabb = torch.as_tensor(aabb, dtype=torch.float32)
        center = 0.5 * (aabb[0] + aabb[1])
        half = 0.5 * (aabb[1] - aabb[0]).max()
        self.register_buffer("aabb", aabb.clone())
        self.register_buffer("cube_min", center - half)
        self.register_buffer("cube_size", 2.0 * half)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.cube_min) / self.cube_size

    def inside(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the point lies within the scene bounds (not just the cube)."""
        return ((x >= self.aabb[0]) & (x <= self.aabb[1])).all(-1)

    @property
    def extent(self) -> float:
        """Edge of the modelled cube, metres."""
        return float(self.cube_size)

    def unit_scale(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) lengths at world points x (N, 3) in metres -> lengths in [0, 1]^3 units."""
        return (1.0 / self.cube_size).expand(x.shape[0])


class ContractedNormalizer(BoxNormalizer):
    """Maps all of space into [0, 1]^3 through the scene contraction
    (:mod:`nerfbot.ops.contraction`): the cube enclosing the scene bounds (the inner cube) to
    [1/4, 3/4]^3, everything beyond it into the shell around that.

    Attributes are :class:`BoxNormalizer`'s (``cube_min``, ``cube_size`` are the inner cube's)
    plus its ``centre``.
    """

    contracted = True

    def __init__(self, aabb):
        super().__init__(aabb)
        self.register_buffer("centre", self.cube_min + 0.5 * self.cube_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        half = 0.5 * self.cube_size
        c = contract((x - self.centre) / half)
        return (c + CONTRACTED_HALF) / (2.0 * CONTRACTED_HALF)

    def inside(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) bool: every finite point is modelled."""
        return torch.isfinite(x).all(-1)

    def density_scale(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) factor from density per unit of contracted length (what a field over the
        contracted cube learns) to density per metre: ``1 / max(1, |y|_inf^2)``. A field of
        uniform contracted density is then equally opaque over every cell of the contracted
        grid, and the far shell has a finite optical depth."""
        return 1.0 / step_scale((x - self.centre) / (0.5 * self.cube_size))

    def unit_scale(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) lengths at world points x (N, 3) in metres -> lengths in [0, 1]^3 units: the
        contraction's isotropic scale at x (the cube root of its Jacobian's determinant: radial
        factor 1 / n^2, tangential (2 - 1 / n) / n at ``n = |y|_inf > 1``), times the unit
        cube's size per half-size."""
        n = ((x - self.centre) / (0.5 * self.cube_size)).abs().amax(-1).clamp_min(1.0)
        jacobian = ((2.0 - 1.0 / n) ** 2 / n ** 4) ** (1.0 / 3.0)
        return jacobian / (CONTRACTED_HALF * self.cube_size)

    @property
    def extent(self) -> float:
        """Edge of the modelled cube, metres of contracted space."""
        return float(CONTRACTED_HALF * self.cube_size)
