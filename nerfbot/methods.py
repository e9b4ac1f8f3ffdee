"""The registry of methods: a name -> its complete defaults, how to build its model and how to
train it.

This is the only place that knows which field goes with which sampler, and the only place a
method's option defaults are set: each entry holds instantiated configs (dataclasses) whose
values are the method's effective defaults (:func:`method_defaults`); ``--option key=value``
replaces a value by its field name. An option name may belong to one config of a method only
(:func:`register_method` refuses a second). Everything else asks the registry.

Adding a variant: a field in ``nerfbot/fields/`` (and a model in :mod:`nerfbot.models.base` if no
existing renderer fits) and one :func:`register_method` entry; for the command line, also its
line in :mod:`nerfbot.method_names`, which lists the methods without importing any of this.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, is_dataclass, replace
from typing import Callable, Optional

import numpy as np

from nerfbot.bake.fastnerf_cache import bake_cache
from nerfbot.bake.plenoctree import OctreeBakeConfig, bake_octree
from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.articulated import ArticulatedField, ArticulatedFieldConfig
from nerfbot.fields.background import make_background
from nerfbot.fields.dnerf import DNeRFField, DNeRFFieldConfig
from nerfbot.fields.fastnerf import FastNeRFField, FastNeRFFieldConfig
from nerfbot.fields.kilonerf import KiloNeRFField, KiloNeRFFieldConfig
from nerfbot.fields.kplanes import KPlanesField, KPlanesFieldConfig
from nerfbot.fields.mipnerf import MipNeRFField, MipNeRFFieldConfig
from nerfbot.fields.nerf import NeRFField, NeRFFieldConfig
from nerfbot.fields.nerfsh import NeRFSHField, NeRFSHFieldConfig
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.fields.plenoxels import PlenoxelField, PlenoxelFieldConfig
from nerfbot.fields.rigid import RigidField, RigidFieldConfig
from nerfbot.fields.tensorf import TensoRFField, TensoRFFieldConfig
from nerfbot.fields.tnerf import TNeRFField, TNeRFFieldConfig
from nerfbot.models.base import Model
from nerfbot.models.fastnerf_cache import FastNeRFCacheConfig, FastNeRFCacheModel
from nerfbot.models.hierarchical import HierarchicalModel, HierarchicalModelConfig
from nerfbot.models.kilonerf import KiloNeRFConfig, KiloNeRFModel
from nerfbot.models.mipnerf import MipNeRFModel, MipNeRFModelConfig
from nerfbot.models.occupancy import OccupancyModel, OccupancyModelConfig
from nerfbot.models.plenoctree import PlenOctreeConfig, PlenOctreeModel


@dataclass(frozen=True)
class BakeRecipe:
    """How a baked method is made: train ``source``, then ``bake`` the trained model.

    Attributes:
        source: the method whose trained runs are baked.
        bake: (trained model, its run spec, dataset, configs, seed, progress) -> (baked model,
            baked spec, extra); ``configs`` are the baked method's ``configs`` followed by the
            recipe's own, with the bake options applied; ``extra`` is a JSON-able report
            (sizes, counts) written to the baked run's ``bake.json``.
        reads: the options of the baked method's ``configs`` that the bake sets (e.g. ``np``,
            ``depth``); the baked renderer's other options come from the source run or keep
            their defaults, so they are not bake options.
        configs: instantiated configs of options of the bake alone (e.g. fine-tuning steps),
            which the baked renderer does not keep.
    """

    source: str
    bake: Callable[..., tuple]
    reads: tuple = ()
    configs: tuple = ()


@dataclass(frozen=True)
class MethodSpec:
    """How to build and train one method.

    Attributes:
        build: (aabb (2, 3), background spec, configs, seed, Conditioning) -> Model, where
            ``configs`` are this entry's ``configs`` in their order, with the options applied.
        lr: Adam learning rate.
        adam_eps: Adam epsilon (tiny for hash tables, as in Instant-NGP).
        lr_final_factor: the learning rate decays exponentially to lr * this at the end of the
            budget.
        configs: instantiated config dataclasses: their fields are the method's options, their
            values its defaults.
        baked_from: set for renderers made by ``nerfbot bake`` from a trained run rather than
            trained.
    """

    build: Callable[..., Model]
    lr: float
    adam_eps: float
    lr_final_factor: float
    configs: tuple = ()
    baked_from: Optional[BakeRecipe] = None


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
    """A copy of dataclass ``config`` with the ``options`` whose keys match its field names,
    each checked against the type of its value in ``config`` (the config's own checks then run
    on the new values)."""
    names = {f.name for f in fields(config)}
    picked = {k: _typed(k, v, getattr(config, k)) for k, v in options.items() if k in names}
    return replace(config, **picked)


# -- build functions ---------------------------------------------------------------------------
def occupancy_build(field_cls, contractible: bool = False) -> Callable[..., Model]:
    """Build function of a static field, ``field_cls(aabb, field config, seed=seed)``, marched
    over an occupancy grid; its entry's configs are (field config, OccupancyModelConfig).
    A ``contractible`` field also takes ``contract=`` (the renderer's ``contraction``)."""
    def build(aabb, background, configs, seed, conditioning) -> Model:
        field_config, renderer = configs
        extra = {"contract": renderer.contraction} if contractible else {}
        return OccupancyModel(field_cls(aabb, field_config, seed=seed, **extra),
                              make_background(background), aabb, renderer)
    return build


def _conditioned_ngp_build(field_cls) -> Callable[..., Model]:
    """Build function of an ngp field conditioned on time or joints, ``field_cls(aabb,
    conditioning, NGPFieldConfig, its own config, seed=seed)``, marched over an occupancy grid;
    its entry's configs are (NGPFieldConfig, its own config, OccupancyModelConfig)."""
    def build(aabb, background, configs, seed, conditioning) -> Model:
        ngp_config, own_config, renderer = configs
        field = field_cls(aabb, conditioning, ngp_config, own_config, seed=seed)
        return OccupancyModel(field, make_background(background), aabb, renderer)
    return build


def _rigid_build(aabb, background, configs, seed, conditioning) -> Model:
    ngp_config, kplanes_config, rigid_config, renderer = configs
    field = RigidField(aabb, conditioning, ngp_config, kplanes_config, rigid_config, seed=seed)
    return OccupancyModel(field, make_background(background), aabb, renderer)


def _build_nerf(aabb, background, configs, seed, conditioning) -> Model:
    field_config, renderer = configs
    return HierarchicalModel(NeRFField(aabb, field_config), NeRFField(aabb, field_config),
                             make_background(background), aabb, renderer)


def _build_mipnerf(aabb, background, configs, seed, conditioning) -> Model:
    field_config, renderer = configs
    return MipNeRFModel(MipNeRFField(aabb, field_config), make_background(background), aabb,
                        renderer)


def _build_kilonerf(aabb, background, configs, seed, conditioning) -> Model:
    field_config, kilo_config, renderer = configs
    field = KiloNeRFField(aabb, field_config, seed=seed)
    return KiloNeRFModel(field, make_background(background), aabb, renderer, kilo_config)


def _build_fastnerf_cache(aabb, background, configs, seed, conditioning) -> Model:
    (cache_config,) = configs
    return FastNeRFCacheModel(aabb, make_background(background), cache_config)


def _build_plenoctree_octree(aabb, background, configs, seed, conditioning) -> Model:
    (octree_config,) = configs
    return PlenOctreeModel(aabb, make_background(background), octree_config)


def _bake_fastnerf_cache(model, spec, dataset, configs, seed, progress):
    (cache_config,) = configs
    return bake_cache(model, spec, cache_config.np, cache_config.nd, progress=progress)


def _bake_plenoctree_octree(model, spec, dataset, configs, seed, progress):
    octree_config, bake_config = configs
    return bake_octree(model, spec, octree_config.depth, dataset=dataset,
                       finetune_steps=bake_config.finetune_steps, seed=seed, progress=progress)


# -- defaults shared by several entries --------------------------------------------------------
#: ngp's own renderer defaults: 2 x 2 rays per pixel from half the budget on. On the tabletop in
#: 180 s: +1.2 dB test PSNR and the objects' depth error 2.80 -> 2.0-2.4 cm; from the start, the
#: large box of a capture without a manifest lost 2 dB. Log-density noise 1.0: uniformly
#: coloured objects become surfaces instead of veils (whole-scene depth error 1.3 -> 1.0 cm in
#: 180 s). 2^15 samples per step, not 2^17: on a CPU a time budget buys few steps, and small
#: objects need steps more than large batches (180 s on the tabletop: 1183 steps, 35.8 dB,
#: objects 0.9 cm, against 439 steps, 33.6 dB, 2.0 cm). The carving prior at 1e-4: in 180 s,
#: +0.5 dB on the tabletop, +2.5 and +1.8 dB on two workspace seeds with 3-6x less depth error,
#: within 0.3 dB on two bins seeds and a room (BENCHMARKS.md, section 10). The current figures:
#: BENCHMARKS.md, sections 1 and 10.
NGP_RENDERER = OccupancyModelConfig(supersample=2, supersample_from=0.5, density_noise=1.0,
                                    samples_per_batch=1 << 15, carving_weight=1e-4)

#: ngp's field defaults: the start's transmittance is set along the training rays' median path
#: through the bounds (0.6, about what the tabletop's and the rooms' rays kept when it was 0.2
#: along the cube's diagonal); along the diagonal, slab-shaped bounds (bins, workspaces) start
#: 90 % transparent and stall (BENCHMARKS.md, section 10, "The initial density").
NGP_FIELD = NGPFieldConfig(initial_transmittance=0.6, initial_transmittance_path="rays")

#: The renderer defaults of the conditioned ngp family (tnerf, dnerf, articulated) differ from
#: ngp's in exactly these five values (tests/test_registry.py holds them to it): one ray per
#: pixel throughout, no log-density noise, 2^17 samples per step, no carving prior. Their
#: field defaults differ only in the start's density (``NGPFieldConfig()``'s, along the cube's
#: diagonal, not ngp's NGP_FIELD). Their results in BENCHMARKS.md (section 4) were measured with
#: these; whether ngp's values help them is unmeasured.
CONDITIONED_NGP_RENDERER = OccupancyModelConfig(supersample=1, supersample_from=0.0,
                                                density_noise=0.0, samples_per_batch=1 << 17)

#: kilonerf's renderer defaults. Its speed comes from skipping empty space, so its occupancy grid
#: is finer (128^3) and stricter (a cell counts when one marching step through it is >= 15%
#: opaque, or denser than average) than ngp's, and its steps are twice as long (128 per cube
#: diagonal). Distilled from the 180 s ngp run of the 128x128 tabletop (32.8 dB) for 500 steps,
#: ngp's settings (256 steps, 64^3 grid at 0.01) gave 33.2 dB test PSNR with 91k samples per
#: image, these 32.8 dB with 31k.
KILONERF_RENDERER = OccupancyModelConfig(render_steps=128, grid_resolution=128,
                                         grid_threshold=0.15)


#: kplanes' renderer defaults: the conditioned family's, with ngp's 2^15 samples per step: small
#: moving objects need steps more than large batches (BENCHMARKS.md, section 4).
KPLANES_RENDERER = replace(CONDITIONED_NGP_RENDERER, samples_per_batch=1 << 15)


def conditioned_ngp_method(field_cls, own_config) -> MethodSpec:
    """The entry of a conditioned ngp variant: ``field_cls`` (see
    :func:`_conditioned_ngp_build`) with ngp's field defaults, ``own_config`` (an instance) and
    :data:`CONDITIONED_NGP_RENDERER`, trained with ngp's optimiser settings."""
    return MethodSpec(_conditioned_ngp_build(field_cls), lr=1e-2, adam_eps=1e-15,
                      lr_final_factor=0.1,
                      configs=(NGPFieldConfig(), own_config, CONDITIONED_NGP_RENDERER))


# -- the registry ------------------------------------------------------------------------------
METHODS: dict[str, MethodSpec] = {}


def _all_configs(spec: MethodSpec) -> tuple:
    """The entry's configs and, for a baked method, its recipe's."""
    return spec.configs + (spec.baked_from.configs if spec.baked_from else ())


def register_method(name: str, spec: MethodSpec) -> MethodSpec:
    """Add ``spec`` to the registry as method ``name`` (returned).

    ValueError when ``name`` is taken, a config is a class rather than an instance, an option
    name belongs to two of its configs (an option would silently set both), or a bake recipe
    reads an option its method does not have.
    """
    if name in METHODS:
        raise ValueError(f"method {name!r} is already registered")
    owner: dict[str, str] = {}
    for config in _all_configs(spec):
        if not is_dataclass(config) or isinstance(config, type):
            raise ValueError(f"method {name!r}: configs must be dataclass instances (their "
                             f"values are the defaults), got {config!r}")
        for f in fields(config):
            if f.name in owner:
                raise ValueError(f"method {name!r}: option {f.name!r} is in both "
                                 f"{owner[f.name]} and {type(config).__name__}")
            owner[f.name] = type(config).__name__
    if spec.baked_from:
        missing = set(spec.baked_from.reads) - {f.name for c in spec.configs for f in fields(c)}
        if missing:
            raise ValueError(f"method {name!r}: its bake recipe reads unknown option(s) "
                             f"{sorted(missing)}")
    METHODS[name] = spec
    return spec


register_method("ngp", MethodSpec(
    occupancy_build(NGPField, contractible=True), lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(NGP_FIELD, NGP_RENDERER)))
register_method("plenoxels", MethodSpec(
    occupancy_build(PlenoxelField), lr=1e-1, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(PlenoxelFieldConfig(), OccupancyModelConfig())))
#: nerf's and mipnerf's MLPs and sample counts sized for a 2-core CPU: the papers' 8x256 trunks
#: with 64 + 128 (nerf) or 128 + 128 (mipnerf) samples per ray run at 0.07-0.1 steps/s here,
#: this 4x64 trunk with 16 + 32 (32 + 32) samples at 3-4 steps/s, and reaches 29.1 dB (29.7)
#: on the 128x128 tabletop in 3000 steps (BENCHMARKS.md, section 2). The papers' settings:
#: ``--option width=256 depth=8 skip=4 color_width=128 coarse_samples=64 fine_samples=128
#: rays_per_batch=1024 --lr 5e-4`` (mipnerf: 128 + 128 samples).
SMALL_MLP = dict(width=64, depth=4, skip=2, color_width=32)

register_method("nerf", MethodSpec(
    _build_nerf, lr=2e-3, adam_eps=1e-8, lr_final_factor=0.1,
    configs=(NeRFFieldConfig(**SMALL_MLP),
             HierarchicalModelConfig(coarse_samples=16, fine_samples=32, rays_per_batch=256))))
register_method("mipnerf", MethodSpec(
    _build_mipnerf, lr=2e-3, adam_eps=1e-8, lr_final_factor=0.1,
    configs=(MipNeRFFieldConfig(**SMALL_MLP),
             MipNeRFModelConfig(coarse_samples=32, fine_samples=32, rays_per_batch=256))))
register_method("tensorf", MethodSpec(
    occupancy_build(TensoRFField), lr=2e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(TensoRFFieldConfig(), OccupancyModelConfig())))
register_method("tnerf", conditioned_ngp_method(TNeRFField, TNeRFFieldConfig()))
register_method("dnerf", conditioned_ngp_method(DNeRFField, DNeRFFieldConfig()))
register_method("kplanes", MethodSpec(
    _conditioned_ngp_build(KPlanesField), lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(NGPFieldConfig(), KPlanesFieldConfig(), KPLANES_RENDERER)))
register_method("rigid", MethodSpec(
    _rigid_build, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(NGPFieldConfig(), KPlanesFieldConfig(), RigidFieldConfig(), KPLANES_RENDERER)))
register_method("articulated",
                conditioned_ngp_method(ArticulatedField, ArticulatedFieldConfig()))
register_method("plenoctree", MethodSpec(
    occupancy_build(NeRFSHField), lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(NeRFSHFieldConfig(), OccupancyModelConfig())))
register_method("plenoctree_octree", MethodSpec(
    _build_plenoctree_octree, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(PlenOctreeConfig(),),
    baked_from=BakeRecipe("plenoctree", _bake_plenoctree_octree, reads=("depth",),
                          configs=(OctreeBakeConfig(),))))
register_method("fastnerf", MethodSpec(
    occupancy_build(FastNeRFField), lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(FastNeRFFieldConfig(), OccupancyModelConfig())))
register_method("kilonerf", MethodSpec(
    _build_kilonerf, lr=5e-3, adam_eps=1e-8, lr_final_factor=0.1,
    configs=(KiloNeRFFieldConfig(), KiloNeRFConfig(), KILONERF_RENDERER)))
register_method("fastnerf_cache", MethodSpec(
    _build_fastnerf_cache, lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
    configs=(FastNeRFCacheConfig(),),
    baked_from=BakeRecipe("fastnerf", _bake_fastnerf_cache, reads=("np", "nd"))))


# -- queries -----------------------------------------------------------------------------------
def get_method(name: str) -> MethodSpec:
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(METHODS))}")
    return METHODS[name]


def method_defaults(method: str) -> dict:
    """Every option of ``method`` -> its effective default (for a baked method, its bake
    recipe's options too)."""
    out = {}
    for config in _all_configs(get_method(method)):
        out.update(asdict(config))
    return out


def option_names(method: str) -> list[str]:
    """Names of the config fields a method is built with (``--option key=value``)."""
    return sorted(f.name for c in get_method(method).configs for f in fields(c))


def bake_option_names(method: str) -> list[str]:
    """Options a baked ``method`` is baked with (those its recipe reads, and its own); [] for a
    method that is trained."""
    recipe = get_method(method).baked_from
    if recipe is None:
        return []
    return sorted(set(recipe.reads) | {f.name for c in recipe.configs for f in fields(c)})


def sweep_option_names(method: str) -> list[str]:
    """Options a bench point of ``method`` takes: its own and, for a baked method, its bake
    options and those of the method it is baked from (used to train the source)."""
    recipe = get_method(method).baked_from
    if recipe is None:
        return option_names(method)
    return sorted(set(bake_option_names(method)) | set(option_names(recipe.source)))


def build_model(method: str, aabb, background="learned", options: dict | None = None,
                seed: int = 0, conditioning: Conditioning | None = None) -> Model:
    """Build the model of ``method`` for a scene with bounds ``aabb`` (2, 3) metres and
    ``conditioning`` (static when None; static methods ignore it)."""
    spec = get_method(method)
    options = dict(options or {})
    unknown = set(options) - set(option_names(method))
    if unknown:
        raise ValueError(f"method {method!r} has no option(s) {sorted(unknown)}; "
                         f"known: {option_names(method)}")
    configs = tuple(_apply(c, options) for c in spec.configs)
    return spec.build(np.asarray(aabb, dtype=np.float32), background, configs, seed,
                      conditioning or Conditioning())


def bake_model(method: str, model: Model, spec: dict, dataset, options: dict | None = None,
               seed: int = 0, progress: bool = True) -> tuple:
    """Bake ``model``, a trained run of the source of baked ``method`` with run ``spec``, by
    the method's recipe with ``options`` (:func:`bake_option_names`); ``dataset``: the
    training data (fine-tuning and pruning use it). Returns (baked model, baked spec, extra)."""
    recipe = get_method(method).baked_from
    if recipe is None:
        raise ValueError(f"method {method!r} is trained, not baked")
    if spec.get("method") != recipe.source:
        raise ValueError(f"method {method!r} is baked from a {recipe.source!r} run, not a "
                         f"{spec.get('method')!r} one")
    options = dict(options or {})
    unknown = set(options) - set(bake_option_names(method))
    if unknown:
        raise ValueError(f"method {method!r} is baked with option(s) "
                         f"{bake_option_names(method)}, not {sorted(unknown)}")
    configs = tuple(_apply(c, options) for c in _all_configs(get_method(method)))
    return recipe.bake(model, spec, dataset, configs, seed, progress)
