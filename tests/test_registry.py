"""The method registry: each method's complete defaults as instantiated configs, no option name
in two configs of a method, the conditioned ngp family's deliberate renderer difference, a new
variant as one field and one registry entry, `nerfbot bake` through the bench's recipes, and a
`nerfbot --help` that imports nothing heavy."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from nerfbot import method_names
from nerfbot.app.cli import build_parser, main
from nerfbot.data import load_dataset
from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.base import BoxNormalizer, Field, mlp, trunc_exp
from nerfbot.fields.ngp import NGPFieldConfig
from nerfbot.methods import (METHODS, MethodSpec, bake_model, bake_option_names, build_model,
                             method_defaults, occupancy_build, option_names, register_method,
                             sweep_option_names)
from nerfbot.models.occupancy import OccupancyModelConfig
from nerfbot.ops.encodings import FrequencyEncoding
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(70)  # rough single-core seconds (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[1]
AABB = [[-0.5, -0.4, 0.0], [0.5, 0.4, 0.6]]
JOINTS = Conditioning(
    "joints", ("a",), ((0.0, 2.0),),
    joint_info={"a": {"type": "hinge", "axis": [0, 0, 1], "anchor": [0, 0, 0.1], "qpos0": 0.0}},
    part_bounds=[{"joints": ["a"], "bodies": ["lid"],
                  "bounds": [[-0.1, -0.1, 0.0], [0.1, 0.1, 0.2]]}])
CONDITIONING = {"tnerf": Conditioning("time", ("time",), ((0.0, 1.0),)),
                "dnerf": Conditioning("time", ("time",), ((0.0, 1.0),)),
                "kplanes": Conditioning("time", ("time",), ((0.0, 1.0),)), "articulated": JOINTS,
                "rigid": Conditioning("time", ("time",), ((0.0, 1.0),), object_tracks=[
                    {"name": "box", "geoms": [0], "times": [0.0, 1.0],
                     "centres": [[0.0, 0.0, 0.2], [0.1, 0.0, 0.2]], "extent": 0.1}])}
#: The renderer defaults in which tnerf, dnerf and articulated differ from ngp (the registry's
#: CONDITIONED_NGP_RENDERER says why they are kept).
CONDITIONED_RENDERER_DIFFERENCES = {"supersample", "supersample_from", "density_noise",
                                    "samples_per_batch", "carving_weight"}
#: ...and the field defaults in which they differ (ngp's NGP_FIELD: the start's density).
CONDITIONED_FIELD_DIFFERENCES = {"initial_transmittance", "initial_transmittance_path"}


def _all_configs(name: str) -> tuple:
    spec = METHODS[name]
    return spec.configs + (spec.baked_from.configs if spec.baked_from else ())


def _model_configs(model: nn.Module) -> list:
    """Every config dataclass instance held by ``model`` or its submodules."""
    return [value for module in model.modules() for value in vars(module).values()
            if dataclasses.is_dataclass(value) and not isinstance(value, type)]


# -- defaults ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(METHODS))
def test_every_method_holds_its_complete_defaults_and_builds_with_them(name):
    """The registry's config instances are what a model built without options holds: no
    default is set anywhere else."""
    configs = _all_configs(name)
    assert configs and all(dataclasses.is_dataclass(c) and not isinstance(c, type)
                           for c in configs)
    defaults = method_defaults(name)
    assert list(defaults) == [f.name for c in configs for f in dataclasses.fields(c)]
    assert set(option_names(name)) | set(bake_option_names(name)) <= set(defaults)
    model = build_model(name, AABB, conditioning=CONDITIONING.get(name))
    held = _model_configs(model)
    for config in METHODS[name].configs:
        assert config in held, (name, config)


@pytest.mark.parametrize("name", sorted(METHODS))
def test_no_option_name_is_in_two_configs_of_a_method(name):
    names = [f.name for c in _all_configs(name) for f in dataclasses.fields(c)]
    assert len(names) == len(set(names)), sorted(n for n in set(names) if names.count(n) > 1)


def test_register_method_refuses_shared_option_names_classes_and_taken_names():
    build = METHODS["ngp"].build
    with pytest.raises(ValueError, match="'grid_resolution' is in both OccupancyModelConfig and "
                                         "OccupancyModelConfig"):
        register_method("clash", MethodSpec(build, 1e-2, 1e-15, 0.1,
                                            configs=(OccupancyModelConfig(),
                                                     OccupancyModelConfig())))
    with pytest.raises(ValueError, match="dataclass instances"):
        register_method("classes", MethodSpec(build, 1e-2, 1e-15, 0.1,
                                              configs=(NGPFieldConfig, OccupancyModelConfig())))
    with pytest.raises(ValueError, match="already registered"):
        register_method("ngp", METHODS["ngp"])
    assert not {"clash", "classes"} & set(METHODS)


def test_the_command_line_table_lists_the_registry():
    assert list(method_names.DESCRIPTIONS) == list(METHODS)
    assert method_names.BAKED == {name: spec.baked_from.source for name, spec in METHODS.items()
                                  if spec.baked_from}


@pytest.mark.parametrize("name", ["tnerf", "dnerf", "articulated"])
def test_the_conditioned_ngp_family_differs_from_ngp_only_in_its_renderer_and_start(name):
    ngp, own = method_defaults("ngp"), method_defaults(name)
    assert set(ngp) <= set(own)
    assert {k for k in ngp if ngp[k] != own[k]} == \
        CONDITIONED_RENDERER_DIFFERENCES | CONDITIONED_FIELD_DIFFERENCES
    assert METHODS[name].build.__qualname__ == METHODS["tnerf"].build.__qualname__  # one factory


def test_bake_options_reach_the_bench():
    assert bake_option_names("plenoctree_octree") == ["depth", "finetune_steps"]
    assert bake_option_names("fastnerf_cache") == ["nd", "np"] and bake_option_names("ngp") == []
    sweep = sweep_option_names("plenoctree_octree")
    assert {"depth", "finetune_steps", "log2_hashmap_size"} <= set(sweep)
    assert "color_min_weight" not in sweep  # the baked renderer's, but no bake sets it


# -- a new variant -----------------------------------------------------------------------------
@dataclasses.dataclass
class ToyFieldConfig:
    toy_freqs: int = 4
    """Frequencies of the positional encoding."""
    toy_hidden: int = 32
    """Width of the MLPs."""


class ToyField(Field):
    """A variant the registry has never seen: positional encoding and two small MLPs."""

    def __init__(self, aabb, config: ToyFieldConfig, seed: int = 0):
        super().__init__()
        self.config = config
        self.normalize = BoxNormalizer(aabb)
        self.encoding = FrequencyEncoding(3, config.toy_freqs)
        self.density_net = mlp(self.encoding.out_dim, config.toy_hidden, 1, 1 + 8)
        self.color_net = mlp(8 + 3, config.toy_hidden, 1, 3)

    def density(self, x, cond=None):
        out = self.density_net(self.encoding(self.normalize(x)))
        sigma = trunc_exp(out[:, 0] - 2.0) * self.normalize.inside(x)
        return sigma, out[:, 1:]

    def color(self, feat, d, cond=None):
        return torch.sigmoid(self.color_net(torch.cat([feat, d], -1)))

    def color_head(self) -> nn.Linear:
        return self.color_net[-1]


@pytest.fixture
def toy_method():
    """The toy variant registered as "toy" for one test, removed afterwards."""
    register_method("toy", MethodSpec(
        occupancy_build(ToyField), lr=1e-2, adam_eps=1e-15, lr_final_factor=0.1,
        configs=(ToyFieldConfig(), OccupancyModelConfig(samples_per_batch=1 << 12))))
    yield "toy"
    del METHODS["toy"]


def test_a_new_variant_is_one_field_and_one_registry_entry(toy_method, tiny_capture, tmp_path):
    assert method_defaults("toy")["toy_hidden"] == 32
    assert method_defaults("toy")["samples_per_batch"] == 1 << 12
    ds = load_dataset(tiny_capture[0])
    config = TrainConfig(method="toy", max_steps=6, seed=0, progress=False,
                         options={"toy_hidden": 16, "grid_update_every": 2})
    config.validate()
    trainer = Trainer(ds, tmp_path / "run", config)
    summary = trainer.train()
    assert summary["steps"] == 6
    model, _ = load_model(tmp_path / "run")  # built again from the run's spec
    assert isinstance(model.field, ToyField) and model.field.config.toy_hidden == 16
    img = render_image(model, ds.cameras(ds.indices("test")), 0)
    assert img["rgb"].shape == (32, 32, 3) and np.isfinite(img["rgb"]).all()


# -- nerfbot bake through the recipes -----------------------------------------------------------
@pytest.fixture(scope="module")
def plenoctree_run(tiny_capture, tmp_path_factory):
    """A `plenoctree` run trained 30 steps on the tiny capture."""
    run = tmp_path_factory.mktemp("registry") / "plenoctree"
    assert main(["train", "--data", str(tiny_capture[0]), "--method", "plenoctree",
                 "--max-steps", "30", "--out", str(run), "--no-progress",
                 "--option", "samples_per_batch=8192", "--option", "grid_update_every=8"]) == 0
    return run


def test_bake_goes_through_the_bench_recipe(plenoctree_run, tiny_capture, tmp_path, capsys):
    """`nerfbot bake --method plenoctree_octree --option ...` and its `--octree` spelling bake
    the octree a bench point bakes with the same options, fine-tuning included."""
    source, info = load_model(plenoctree_run)
    ds = load_dataset(tiny_capture[0])
    cases = [({"depth": 5}, ["--method", "plenoctree_octree", "--option", "depth=5"]),
             ({"depth": 5, "finetune_steps": 3}, ["--octree", "5", "--finetune-steps", "3"])]
    for k, (options, flags) in enumerate(cases):
        bench, spec, extra = bake_model("plenoctree_octree", source, info["spec"], ds, options,
                                        seed=0, progress=False)
        out = tmp_path / f"octree{k}"
        assert main(["bake", str(plenoctree_run), *flags, "--out", str(out),
                     "--no-progress"]) == 0
        printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert printed["source_method"] == "plenoctree" and printed["leaves"] == extra["leaves"]
        baked, baked_info = load_model(out)
        assert baked_info["spec"]["options"] == spec["options"] == {"depth": 5, "sh_degree": 2}
        assert torch.equal(baked.field.child, bench.field.child)
        leaves, expected = baked.field.leaf_data.detach(), bench.field.leaf_data.detach()
        if "finetune_steps" in options:
            # fine-tuning differs in the last float bits between two runs of one process
            assert printed["finetune_steps"] == extra["finetune_steps"] == 3
            assert torch.allclose(leaves, expected, atol=1e-4)
        else:
            assert torch.equal(leaves, expected)


@pytest.mark.parametrize("flags, message", [
    ([], "give the baked method"),
    (["--cache", "16,8", "--octree", "5"], "--cache / --octree: these name different"),
    (["--method", "plenoctree_octree", "--cache", "16,8"], "name different baked methods"),
    (["--cache", "16,8", "--finetune-steps", "3"],
     "--finetune-steps: fastnerf_cache is baked with option(s) nd, np"),
    (["--method", "plenoctree_octree", "--option", "sh_degree=1"], "--option sh_degree:"),
    (["--octree", "5", "--option", "depth=6"], "--option depth: given twice"),
    (["--cache", "16"], "--cache wants NP,ND"),
])
def test_bake_refuses_flags_that_name_no_recipe_or_an_option_it_ignores(flags, message, tmp_path,
                                                                         capsys):
    assert main(["bake", str(tmp_path / "run"), "--out", str(tmp_path / "out"), *flags]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


def test_bake_model_refuses_the_wrong_source_and_unknown_options(plenoctree_run):
    source, info = load_model(plenoctree_run)
    with pytest.raises(ValueError, match="baked from a 'fastnerf' run, not a 'plenoctree'"):
        bake_model("fastnerf_cache", source, info["spec"], None, {"np": 16})
    with pytest.raises(ValueError, match=r"baked with option\(s\) \['depth', 'finetune_steps'\]"):
        bake_model("plenoctree_octree", source, info["spec"], None, {"color_min_weight": 0.0})
    with pytest.raises(ValueError, match="trained, not baked"):
        bake_model("plenoctree", source, info["spec"], None, {})


# -- nerfbot --help ----------------------------------------------------------------------------
HEAVY = ("torch", "numba", "mujoco")


def _imported(argv: list[str]) -> list[str]:
    """The modules ``python -m nerfbot.app.cli ARGV`` imports, in the order their imports finish
    (``-X importtime``); the command must exit 0."""
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "nerfbot.app.cli", *argv],
                          cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return [line.rsplit("|", 1)[1].strip() for line in done.stderr.splitlines()
            if line.startswith("import time:") and "|" in line]


def _commands() -> list[str]:
    import argparse

    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sorted(action.choices)


@pytest.mark.parametrize("argv", [["--help"]] + [[c, "--help"] for c in _commands()
                                                  if c != "capture"])
def test_help_imports_no_torch_numba_or_mujoco(argv):
    modules = _imported(argv)
    assert "nerfbot.method_names" in modules  # the parser was built
    assert not [m for m in modules if m.split(".")[0] in HEAVY]


def test_capture_help_sets_the_gl_backend_before_mujoco_is_imported():
    modules = _imported(["capture", "--help"])
    assert modules.index("sims.gl") < modules.index("mujoco")
