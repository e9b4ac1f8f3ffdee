"""pixelNeRF's renderer: NeRF's coarse stratified + fine pdf samples through one image-conditioned
field (:class:`~nerfbot.fields.pixelnerf.PixelNeRFField`), within the bounds of the scene the
field is conditioned on.

Unlike every other model, one trained pixelNeRF model serves many scenes: :meth:`PixelNeRFModel.
set_scene` gives it a scene's source views and bounds, after which it renders that scene like
any model (``render_rays``, :func:`nerfbot.eval.evaluation.evaluate`, ...).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from nerfbot.fields.base import BoxNormalizer
from nerfbot.fields.pixelnerf import PixelNeRFField, SourceViews
from nerfbot.models.hierarchical import HierarchicalModel


@dataclass
class PixelNeRFModelConfig:
    coarse_samples: int = 32
    """Stratified samples per ray (the paper: 64)."""
    fine_samples: int = 16
    """Extra samples per ray drawn from the coarse weights (the paper: 32)."""
    rays_per_batch: int = 256
    """Target rays per training step."""


class PixelNeRFModel(HierarchicalModel):
    """Coarse and fine passes through the same pixelNeRF field (one network, as it must
    generalise rather than specialise); both passes are trained."""

    def __init__(self, field: PixelNeRFField, background: nn.Module, aabb,
                 config: PixelNeRFModelConfig | None = None):
        nn.Module.__init__(self)
        self.config = config or PixelNeRFModelConfig()
        self.field, self.background = field, background
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).clone())

    @property
    def coarse(self) -> PixelNeRFField:
        return self.field

    def set_scene(self, sources: SourceViews, aabb=None) -> None:
        """Condition on ``sources`` (:class:`SourceViews`) and, when given, render within the
        scene bounds ``aabb`` (2, 3) metres."""
        if aabb is not None:
            aabb = torch.as_tensor(aabb, dtype=torch.float32, device=self.aabb.device)
            self.aabb.copy_(aabb)
            self.field.normalize = BoxNormalizer(aabb).to(self.aabb.device)
        self.field.set_sources(sources)
