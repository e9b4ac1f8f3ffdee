"""The registry of methods: a name -> how to build its model and how to train it.

This is the only place that knows which field goes with which sampler; everything else asks
the registry.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Callable

import numpy as np

from nerfbot.background import make_background
from nerfbot.conditioning import Conditioning
from nerfbot.fields.articulated import ArticulatedField, ArticulatedFieldConfig
from nerfbot.fields.dnerf import DNeRFField, DNeRFFieldConfig
from nerfbot.fields.mipnerf import (MipNeRFField, MipNeRFFieldConfig, MipNeRFModel,
                                    MipNeRFModelConfig)
from nerfbot.fields.nerf import NeRFField, NeRFFieldConfig
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.fields.tnerf import TNeRFField, TNeRFFieldConfig
from nerfbot.models import (HierarchicalModel, HierarchicalModelConfig, Model, OccupancyModel,
                            OccupancyModelConfig)


@dataclass(frozen=True)
class MethodSpec:
    """How to build and train one method.

    Attributes:
        build: (aabb (2, 3), background spec, options dict, seed, Conditioning) -> Model.
        lr: Adam learning rate.
        adam_eps: Adam epsilon (tiny for hash tables, as in Instant-NGP).
        lr_final_factor: the learning rate decays exponentially to lr * this at the end of the
            budget.
        description: one line for ``nerfbot train --help``.
        configs: the config dataclasses whose fields are the method's options.
    """

    build: Callable[..., Model]
    lr: float
    adam_eps: float
    lr_final_factor: float
    description: str
    configs: tuple = ()


def _apply(config, options: dict):
    """Dataclass ``config`` with the ``options`` whose keys match its field names."""
    names = {f.name for f in fields(config)}
    picked = {k: v for k, v in options.items() if k in names}
    return replace(config, **picked)


def _build_ngp(aabb, background, options, seed, conditioning) -> Model:
    field = NGPField(aabb, _apply(NGPFieldConfig(), options), seed=seed)
    return OccupancyModel(field, make_background(background), aabb,
                          _apply(OccupancyModelConfig(), options))


def _build_nerf(aabb, background, options, seed, conditioning) -> Model:
    cfg = _apply(NeRFFieldConfig(), options)
    return HierarchicalModel(NeRFField(aabb, cfg), NeRFField(aabb, cfg), make_background(background),
                             aabb, _apply(HierarchicalModelConfig(), options))


def _build_mipnerf(aabb, background, options, seed, conditioning) -> Model:
    field = MipNeRFField(aabb, _apply(MipNeRFFieldConfig(), options))
    return MipNeRFModel(field, make_background(background), aabb,
                        _apply(MipNeRFModelConfig(), options))


def _build_tnerf(aabb, background, options, seed, conditioning) -> Model:
    field = TNeRFField(aabb, conditioning, _apply(NGPFieldConfig(), options),
                       _apply(TNeRFFieldConfig(), options), seed=seed)
    return OccupancyModel(field, make_background(background), aabb,
                          _apply(OccupancyModelConfig(), options))


def _build_dnerf(aabb, background, options, seed, conditioning) -> Model:
    field = DNeRFField(aabb, conditioning, _apply(NGPFieldConfig(), options),
                       _apply(DNeRFFieldConfig(), options), seed=seed)
    return OccupancyModel(field, make_background(background), aabb,
                          _apply(OccupancyModelConfig(), options))


def _build_articulated(aabb, background, options, seed, conditioning) -> Model:
    field = ArticulatedField(aabb, conditioning, _apply(NGPFieldConfig(), options),
                             _apply(ArticulatedFieldConfig(), options), seed=seed)
    return OccupancyModel(field, make_background(background), aabb,
                          _apply(OccupancyModelConfig(), options))


METHODS: dict[str, MethodSpec] = {
    "ngp": MethodSpec(_build_ngp, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
                      description="Instant-NGP hash grid + occupancy-grid marching (fast default)",
                      configs=(NGPFieldConfig, OccupancyModelConfig)),
    "nerf": MethodSpec(_build_nerf, lr=5e-4, adam_eps=1e-8, lr_final_factor=0.1,
                       description="vanilla NeRF, positional encoding, coarse + fine (reference)",
                       configs=(NeRFFieldConfig, HierarchicalModelConfig)),
    "mipnerf": MethodSpec(_build_mipnerf, lr=5e-4, adam_eps=1e-8, lr_final_factor=0.1,
                          description="mip-NeRF: cones, integrated positional encoding, one MLP "
                                      "for coarse + fine (anti-aliased at lower resolutions)",
                          configs=(MipNeRFFieldConfig, MipNeRFModelConfig)),
    "tnerf": MethodSpec(_build_tnerf, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
                        description="T-NeRF: time or joints as an extra input of an NGP field",
                        configs=(NGPFieldConfig, TNeRFFieldConfig, OccupancyModelConfig)),
    "dnerf": MethodSpec(_build_dnerf, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
                        description="D-NeRF: deformation (space-time planes) into a canonical "
                                    "NGP field",
                        configs=(NGPFieldConfig, DNeRFFieldConfig, OccupancyModelConfig)),
    "articulated": MethodSpec(_build_articulated, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
                              description="one NGP field per rigid part, placed by forward "
                                          "kinematics of the joints",
                              configs=(NGPFieldConfig, ArticulatedFieldConfig,
                                       OccupancyModelConfig)),
}


def option_names(method: str) -> list[str]:
    """Names of the config fields a method accepts as ``--option key=value``."""
    return sorted(f.name for c in get_method(method).configs for f in fields(c))


def get_method(name: str) -> MethodSpec:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(METHODS))}")
    return METHODS[name]


def build_model(method: str, aabb, background="learned", options: dict | None = None,
                seed: int = 0, conditioning: Conditioning | None = None) -> Model:
    """Build the model of ``method`` for a scene with bounds ``aabb`` (2, 3) metres and
    ``conditioning`` (static when None; static methods ignore it)."""
    options = dict(options or {})
    unknown = set(options) - set(option_names(method))
    if unknown:
        raise ValueError(f"method {method!r} has no option(s) {sorted(unknown)}; "
                         f"known: {option_names(method)}")
    return get_method(method).build(np.asarray(aabb, dtype=np.float32), background, options, seed,
                                    conditioning or Conditioning())
