"""The registry of methods: a name -> how to build its model and how to train it.

This is the only place that knows which field goes with which sampler; everything else asks
the registry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Callable, Optional

import numpy as np

from nerfbot.background import make_background
from nerfbot.conditioning import Conditioning
from nerfbot.fields.articulated import ArticulatedField, ArticulatedFieldConfig
from nerfbot.fields.dnerf import DNeRFField, DNeRFFieldConfig
from nerfbot.fields.fastnerf import FastNeRFField, FastNeRFFieldConfig
from nerfbot.fields.fastnerf_cache import FastNeRFCacheConfig, FastNeRFCacheModel
from nerfbot.fields.kilonerf import (KILONERF_OCCUPANCY_DEFAULTS, KiloNeRFConfig, KiloNeRFField,
                                      KiloNeRFFieldConfig, KiloNeRFModel)
from nerfbot.fields.mipnerf import (MipNeRFField, MipNeRFFieldConfig, MipNeRFModel,
                                    MipNeRFModelConfig)
from nerfbot.fields.nerf import NeRFField, NeRFFieldConfig
from nerfbot.fields.nerfsh import NeRFSHField, NeRFSHFieldConfig
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.fields.plenoxels import PlenoxelField, PlenoxelFieldConfig
from nerfbot.fields.tensorf import TensoRFField, TensoRFFieldConfig
from nerfbot.fields.tnerf import TNeRFField, TNeRFFieldConfig
from nerfbot.models import (HierarchicalModel, HierarchicalModelConfig, Model, OccupancyModel,
                            OccupancyModelConfig)
from nerfbot.plenoctree import PlenOctreeConfig, PlenOctreeModel


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
    baked_from: Optional["BakeRecipe"] = None
    """Set for renderers made by ``nerfbot bake`` from a trained run rather than trained."""


@dataclass(frozen=True)
class BakeRecipe:
    """How a baked method is made: train ``source``, then ``bake`` the trained model.

    ``bake(model, spec, dataset, options, seed, progress) -> (baked model, baked spec, extra)``
    takes the baked method's own options (e.g. ``np``, ``nd`` or ``depth``); ``extra`` is a
    JSON-able report (sizes, counts) written to the baked run's ``bake.json``.
    """

    source: str
    bake: Callable[..., tuple]


def _typed(name: str, value, default):
    """``value`` of option ``name`` as the type of its ``default`` (an integral float is an
    int, an int a float, a list a tuple); ValueError naming the option otherwise. Tuple
    options may also come as a string or a number, which their config parses."""
    def bad(kind):
        return ValueError(f"option {name}: expected {kind} (the default is {default!r}), got "
                          f"{value!r}")

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    if default is None:
        return value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        if not number(value) or value != int(value):
            raise bad("an integer")
        return int(value)
    if isinstance(default, float):
        if not number(value):
            raise bad("a finite number")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad("a string")
        return value
    if isinstance(default, (tuple, list)) and isinstance(value, (tuple, list)):
        if not all(number(v) for v in value):
            raise bad("a list of finite numbers")
        return type(default)(value)
    return value  # other spellings (e.g. "16,32" for a tuple) are the config's to parse


def _apply(config, options: dict):
    """Dataclass ``config`` with the ``options`` whose keys match its field names, each checked
    against the type of its default (the config's own checks then run on the new values)."""
    names = {f.name for f in fields(config)}
    picked = {k: _typed(k, v, getattr(config, k)) for k, v in options.items() if k in names}
    return replace(config, **picked)


def _static_occupancy(field_cls, config_cls, occupancy_defaults: dict | None = None):
    """Build function of a static field (built as ``field_cls(aabb, config, seed=seed)``)
    marched over an occupancy grid (``occupancy_defaults``: the method's own defaults of
    :class:`OccupancyModelConfig` fields)."""
    def build(aabb, background, options, seed, conditioning) -> Model:
        field = field_cls(aabb, _apply(config_cls(), options), seed=seed)
        return OccupancyModel(field, make_background(background), aabb,
                              _apply(OccupancyModelConfig(**(occupancy_defaults or {})), options))
    return build


#: ngp's own renderer defaults: 2 x 2 rays per pixel from half the budget on. On the tabletop in
#: 180 s: +1.2 dB test PSNR and the objects' depth error 2.80 -> 2.0-2.4 cm; from the start, the
#: large box of a capture without a manifest lost 2 dB (BENCHMARKS.md, issue 2, session 10).
#: Log-density noise 1.0: uniformly coloured objects become surfaces instead of veils
#: (BENCHMARKS.md, issue 2, session 12). 2^15 samples per step, not 2^17: on a CPU a time
#: budget buys few steps, and small objects need steps more than large batches (180 s on the
#: tabletop: 1183 steps, 35.8 dB, objects 0.9 cm, against 439 steps, 33.6 dB, 2.0 cm; session 13).
NGP_OCCUPANCY_DEFAULTS = {"supersample": 2, "supersample_from": 0.5, "density_noise": 1.0,
                          "samples_per_batch": 1 << 15}

_build_ngp = _static_occupancy(NGPField, NGPFieldConfig, NGP_OCCUPANCY_DEFAULTS)


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


def _build_kilonerf(aabb, background, options, seed, conditioning) -> Model:
    field = KiloNeRFField(aabb, _apply(KiloNeRFFieldConfig(), options), seed=seed)
    return KiloNeRFModel(field, make_background(background), aabb,
                         _apply(OccupancyModelConfig(**KILONERF_OCCUPANCY_DEFAULTS), options),
                         _apply(KiloNeRFConfig(), options))


def _build_fastnerf_cache(aabb, background, options, seed, conditioning) -> Model:
    return FastNeRFCacheModel(aabb, make_background(background),
                              _apply(FastNeRFCacheConfig(), options))


def _bake_fastnerf_cache(model, spec, dataset, options, seed, progress):
    from nerfbot.fields.fastnerf import bake_cache

    cfg = _apply(FastNeRFCacheConfig(), options)
    return bake_cache(model, spec, cfg.np, cfg.nd, progress=progress)


def _bake_plenoctree_octree(model, spec, dataset, options, seed, progress):
    from nerfbot.plenoctree import bake_octree

    cfg = _apply(PlenOctreeConfig(), options)
    return bake_octree(model, spec, cfg.depth, dataset=dataset, seed=seed, progress=progress)


def _build_plenoctree_octree(aabb, background, options, seed, conditioning) -> Model:
    return PlenOctreeModel(aabb, make_background(background),
                           _apply(PlenOctreeConfig(), options))


METHODS: dict[str, MethodSpec] = {
    "ngp": MethodSpec(_build_ngp, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
                      description="Instant-NGP hash grid + occupancy-grid marching (fast default)",
                      configs=(NGPFieldConfig, OccupancyModelConfig)),
    "plenoxels": MethodSpec(
        _static_occupancy(PlenoxelField, PlenoxelFieldConfig),
        lr=1e-1, adam_eps=1e-15, lr_final_factor=0.1,
        description="Plenoxels: sparse voxel grid of density + SH colour, "
                    "no network, coarse-to-fine with pruning",
        configs=(PlenoxelFieldConfig, OccupancyModelConfig)),
    "nerf": MethodSpec(_build_nerf, lr=5e-4, adam_eps=1e-8, lr_final_factor=0.1,
                       description="vanilla NeRF, positional encoding, coarse + fine (reference)",
                       configs=(NeRFFieldConfig, HierarchicalModelConfig)),
    "mipnerf": MethodSpec(_build_mipnerf, lr=5e-4, adam_eps=1e-8, lr_final_factor=0.1,
                          description="mip-NeRF: cones, integrated positional encoding, one MLP "
                                      "for coarse + fine (anti-aliased at lower resolutions)",
                          configs=(MipNeRFFieldConfig, MipNeRFModelConfig)),
    "tensorf": MethodSpec(
        _static_occupancy(TensoRFField, TensoRFFieldConfig),
        lr=2e-2, adam_eps=1e-15, lr_final_factor=0.1,
        description="TensoRF: vector-matrix factorised grids, coarse-to-fine "
                    "upsampling + occupancy-grid marching",
        configs=(TensoRFFieldConfig, OccupancyModelConfig)),
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
    "plenoctree": MethodSpec(
        _static_occupancy(NeRFSHField, NeRFSHFieldConfig),
        lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
        description="PlenOctrees' NeRF-SH: hash grid -> density + SH colour "
                    "(no direction input); bake with `nerfbot bake --octree`",
        configs=(NeRFSHFieldConfig, OccupancyModelConfig)),
    "plenoctree_octree": MethodSpec(_build_plenoctree_octree, lr=1e-2, adam_eps=1e-15,
                                    lr_final_factor=0.1,
                                    description="a baked PlenOctree (made by `nerfbot bake "
                                                "--octree` from a plenoctree run; not trained "
                                                "from scratch)",
                                    configs=(PlenOctreeConfig,),
                                    baked_from=BakeRecipe("plenoctree", _bake_plenoctree_octree)),
    "fastnerf": MethodSpec(
        _static_occupancy(FastNeRFField, FastNeRFFieldConfig),
        lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
        description="FastNeRF: position net (hash grid) x direction net, "
                    "colour = sigmoid(sum_i beta_i(d) u_i(x)); cacheable "
                    "with `nerfbot bake --cache`",
        configs=(FastNeRFFieldConfig, OccupancyModelConfig)),
    "kilonerf": MethodSpec(_build_kilonerf, lr=5e-3, adam_eps=1e-8, lr_final_factor=0.1,
                           description="KiloNeRF: a 16^3 grid of tiny MLPs, distilled from a "
                                       "trained run (option teacher_run) then fine-tuned",
                           configs=(KiloNeRFFieldConfig, KiloNeRFConfig,
                                    OccupancyModelConfig)),
    "fastnerf_cache": MethodSpec(_build_fastnerf_cache, lr=1e-2, adam_eps=1e-15,
                                 lr_final_factor=0.1,
                                 description="baked FastNeRF cache (made by `nerfbot bake "
                                             "--cache NP,ND`; not trainable)",
                                 configs=(FastNeRFCacheConfig,),
                                 baked_from=BakeRecipe("fastnerf", _bake_fastnerf_cache)),
}


def option_names(method: str) -> list[str]:
    """Names of the config fields a method accepts as ``--option key=value``."""
    return sorted(f.name for c in get_method(method).configs for f in fields(c))


def sweep_option_names(method: str) -> list[str]:
    """Options a bench point of ``method`` takes: its own and, for a baked method, those of
    the method it is baked from (used to train the source)."""
    recipe = get_method(method).baked_from
    names = set(option_names(method))
    if recipe is not None:
        names |= set(option_names(recipe.source))
    return sorted(names)


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
