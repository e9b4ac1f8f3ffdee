"""Models: a field (or two), a sampling strategy and a background, rendering rays.

A model turns :class:`~nerfbot.ops.cameras.Rays` into a :class:`~nerfbot.ops.rendering.RenderOutput`
and knows its own training loss and per-step upkeep (:class:`Model`). The renderers:

* :class:`~nerfbot.models.occupancy.OccupancyModel` - occupancy-grid marching over packed
  samples, early termination (Instant-NGP and every grid-like field);
* :class:`~nerfbot.models.hierarchical.HierarchicalModel` - coarse stratified + fine pdf sampling
  with two fields (NeRF);
* :mod:`~nerfbot.models.mipnerf`, :mod:`~nerfbot.models.kilonerf` and the baked
  :mod:`~nerfbot.models.fastnerf_cache` and :mod:`~nerfbot.models.plenoctree`, each for its
  variant.
"""

from __future__ import annotations

import abc
from typing import Callable, Optional

import numpy as np
import torch
from torch import nn

from nerfbot.fields.background import BakedBackground
from nerfbot.fields.base import Field
from nerfbot.ops.cameras import Rays
from nerfbot.ops.rendering import RenderOutput


def pixel_mean(values: torch.Tensor, rays_per_pixel: int) -> torch.Tensor:
    """(P * K, ...) per-ray values, K = ``rays_per_pixel`` consecutive rays per pixel ->
    (P, ...) their means per pixel (the input itself when K = 1)."""
    if rays_per_pixel == 1:
        return values
    if values.shape[0] % rays_per_pixel:
        raise ValueError(f"{values.shape[0]} rays are not a whole number of pixels of "
                         f"{rays_per_pixel} rays")
    return values.reshape(-1, rays_per_pixel, *values.shape[1:]).mean(1)


def photometric_loss(rgb: torch.Tensor, target_rgb: torch.Tensor, rays_per_pixel: int = 1,
                     pixel_weights: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean squared error of rendered colours (P * K, 3), K = ``rays_per_pixel`` rays per pixel
    averaged first, against ``target_rgb`` (P, 3); each pixel's error times its weight in
    ``pixel_weights`` (P,) when given (importance-sampling corrections, mean about 1)."""
    err = (pixel_mean(rgb, rays_per_pixel) - target_rgb).square()
    if pixel_weights is None:
        return err.mean()
    return (err.mean(-1) * pixel_weights).mean()


#: The colour span (max - min in some channel, colours in [0, 1]) of a pixel's centre and corner
#: rays above which the "adaptive" supersampling pattern casts the S x S grid through it
#: (:func:`nerfbot.query.render.render_image`; chosen in BENCHMARKS.md, section 7).
ADAPTIVE_TOLERANCE = 0.2


class Model(nn.Module, metaclass=abc.ABCMeta):
    """Common surface of every model: render rays, compute the training loss, upkeep."""

    field: Field
    background: nn.Module
    aabb: torch.Tensor

    #: Whether the renderer keeps sample features for a label head.
    supports_labels: bool = False

    @property
    def label_head(self) -> Optional[nn.Module]:
        """Semantic-NeRF's label branch (:mod:`nerfbot.models.labels`; set by assigning a
        module, which registers it), None without labels."""
        return self._modules.get("label_head")

    @abc.abstractmethod
    def render_rays(self, rays: Rays, generator: Optional[torch.Generator] = None,
                    cond: Optional[torch.Tensor] = None) -> RenderOutput:
        """Render (R,) rays; in eval mode without randomness."""

    def render_geometry(self, rays: Rays, cond: Optional[torch.Tensor] = None) -> RenderOutput:
        """Render (R,) rays in eval mode for what depends on density alone (opacity, depths,
        the samples' densities); ``rgb`` may be left black. Renderers that can skip the colour
        evaluation override this; by default it is :meth:`render_rays`."""
        return self.render_rays(rays, None, cond)

    def render_rays_differentiable(self, rays: Rays, cond: Optional[torch.Tensor] = None
                                   ) -> RenderOutput:
        """Render (R,) rays as in eval mode (no randomness) but with gradients w.r.t. the
        rays' origins and directions, for estimating camera poses through a frozen model
        (:mod:`nerfbot.query.localise`). Models whose rendering cannot carry such gradients
        raise NotImplementedError."""
        raise NotImplementedError(
            f"{type(self).__name__} cannot render with gradients w.r.t. its rays; pose "
            "estimation needs a method rendered by the occupancy-grid marcher (ngp, plenoxels, "
            "tensorf, ...)")

    #: Rays per pixel axis when training and rendering colour: S x S rays through each pixel,
    #: their colours averaged (see :func:`nerfbot.train.trainer.batch_loss`); 1: the pixel centre.
    supersample: int = 1

    #: With S = 1, training rays go through a uniformly random point of their pixel instead of
    #: its centre (:meth:`nerfbot.data.pixels.PixelBank.sample`).
    pixel_jitter: bool = False

    #: Where a render with S > 1 casts its rays over a pixel: "grid", "corners" or "adaptive"
    #: (:func:`nerfbot.query.render.render_image`).
    supersample_pattern: str = "grid"

    #: The "adaptive" pattern's colour span above which a pixel gets the S x S grid.
    adaptive_tolerance: float = ADAPTIVE_TOLERANCE

    #: Rendering casts the S x S rays only through pixels whose 3 x 3 neighbourhood of centre-ray
    #: colours spans more than this (:func:`nerfbot.query.render.render_image`); 0: every pixel.
    supersample_tolerance: float = 0.0

    def training_supersample(self, progress: float) -> int:
        """Rays per pixel axis of the training batch at ``progress`` in [0, 1] of the budget."""
        return self.supersample

    def loss(self, rays: Rays, target_rgb: torch.Tensor,
             generator: Optional[torch.Generator] = None,
             cond: Optional[torch.Tensor] = None,
             rays_per_pixel: int = 1, pixel_weights: Optional[torch.Tensor] = None
             ) -> tuple[torch.Tensor, RenderOutput]:
        """Photometric MSE of the rendered rays against ``target_rgb`` (P, 3), P pixels; the
        (P * rays_per_pixel,) rays come pixel after pixel and their colours are averaged per
        pixel first (:func:`photometric_loss`, with the pixels' ``pixel_weights`` (P,))."""
        out = self.render_rays(rays, generator, cond)
        return photometric_loss(out.rgb, target_rgb, rays_per_pixel, pixel_weights), out

    def before_step(self, step: int, generator: Optional[torch.Generator] = None,
                    progress: float = 0.0) -> dict:
        """Upkeep before optimisation step ``step``, ``progress`` in [0, 1] of the budget (e.g.
        occupancy updates, grid upsampling); returns log values. A model whose parameters
        changed shape or identity returns ``{"params_changed": True}``: the trainer then builds
        a new optimiser (as TensoRF and Plenoxels do after upsampling)."""
        return {}

    def training_time_limit(self, progress: float) -> Optional[float]:
        """The latest frame time that trains at ``progress`` (the field's
        :meth:`~nerfbot.fields.base.Field.training_time_limit`); None: every frame."""
        field = getattr(self, "field", None)
        return None if field is None else field.training_time_limit(progress)

    def use_run_loader(self, loader: Callable[..., tuple]) -> None:
        """Give the model a way to open other trained runs, ``loader(run_dir, device=...) ->
        (model, info)``, for methods that learn from one (a distillation teacher); the trainer
        passes :func:`nerfbot.train.runs.load_model`. Kept outside the module tree."""
        self.__dict__["run_loader"] = loader

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """Make every field and the background start at the data's mean colour ``rgb`` (3,)."""
        for m in self.modules():
            if m is not self and hasattr(m, "init_mean_color"):
                m.init_mean_color(rgb)

    def init_ray_length(self, length_m: Optional[float]) -> None:
        """Tell every field how far the training rays cross the bounds (median, metres;
        :meth:`~nerfbot.fields.base.Field.init_ray_length`); None (no ray meets them): nothing."""
        if length_m is None:
            return
        for m in self.modules():
            if m is not self and hasattr(m, "init_ray_length"):
                m.init_ray_length(length_m)

    def init_floor_share(self, share: float) -> None:
        """Tell the model which share of the training rays cross the bounds from their top
        face to their bottom face (:meth:`~nerfbot.data.pixels.PixelBank.top_to_bottom_share`),
        for options chosen from the data; most models take nothing from it."""

    def param_groups(self) -> list[dict]:
        """Optimiser groups (``params``, ``lr_scale``): the fields' own groups, then every other
        parameter (background, second field, ...) at scale 1."""
        groups, seen = [], set()
        fields = [self.field] + [m for m in self.children() if isinstance(m, Field) and m is not self.field]
        for f in fields:
            for g in f.param_groups():
                groups.append(g)
                seen.update(id(p) for p in g["params"])
        rest = [p for p in self.parameters() if id(p) not in seen]
        if rest:
            groups.append({"params": rest, "lr_scale": 1.0})
        return groups

    def baked_background(self, directions: torch.Tensor) -> np.ndarray:
        """(R, 3) CPU unit directions -> (R, 3) float32 numpy: the background read from an
        octahedral table of it (:class:`~nerfbot.fields.background.BakedBackground`, rebuilt
        when the background changes). The baked renderers' background; its error is bounded by
        a test."""
        baked = self.__dict__.get("_baked_background")
        if baked is None or baked.module is not self.background:
            baked = self.__dict__["_baked_background"] = BakedBackground(self.background)
        return baked(directions)

    @abc.abstractmethod
    def rays_for_next_batch(self, last_samples: Optional[int], n_rays: int) -> int:
        """How many rays the next training batch should hold, given the previous batch's sample
        count (None before the first batch) and ray count."""


def resize_like_state_dict(module: nn.Module, state_dict: dict) -> None:
    """Give every parameter and buffer of ``module`` the shape and dtype it has in
    ``state_dict``, so it can be loaded. Fields whose tensors change size (upsampled grids,
    sparse baked caches, octrees) are built at their initial size and take the stored size
    here; they must derive any size they need from their tensors' shapes."""
    for name, value in state_dict.items():
        owner_name, _, attr = name.rpartition(".")
        owner = module.get_submodule(owner_name) if owner_name else module
        if attr in owner._parameters and owner._parameters[attr] is not None:
            p = owner._parameters[attr]
            if p.shape != value.shape or p.dtype != value.dtype:
                p.data = torch.empty(value.shape, dtype=value.dtype, device=p.device)
        elif attr in owner._buffers:
            b = owner._buffers[attr]
            if b is None or b.shape != value.shape or b.dtype != value.dtype:
                device = value.device if b is None else b.device
                owner._buffers[attr] = torch.empty(value.shape, dtype=value.dtype, device=device)


def num_params(model: nn.Module) -> int:
    """Number of trainable scalars."""
    return int(sum(p.numel() for p in model.parameters()))
