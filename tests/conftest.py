"""Shared fixtures (one tiny real MuJoCo capture per test session) and the suite's scheduling.

The suite runs under pytest-xdist, one worker per core (``addopts`` in pyproject.toml). Each
worker then computes with one thread: the tests' tensors are small, so two threads in one
process gained little (with warm caches on a 2-core machine, the suite took 12:35 with 2
threads in one process and 8:00 with 2 single-thread workers). Modules marked
``slow(seconds)`` go first, costliest first, so a long module does not start last and leave the
other workers idle at the end (``--no-loadscope-reorder`` in pyproject.toml keeps this order:
xdist would otherwise hand out the modules with the most tests first). Each tutorial notebook
has its own module, so that two of them can run side by side.
"""

from __future__ import annotations

import os

if os.environ.get("PYTEST_XDIST_WORKER"):  # before torch / numba are imported
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(_var, "1")

import sims  # noqa: E402,F401  (sets MUJOCO_GL=egl before mujoco is imported)

import pytest  # noqa: E402

TINY_SIZE = 32
TINY_VIEWS = 16
TINY_TEST_VIEWS = 4


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "slow(seconds): a module that trains fields or runs notebooks; seconds is its "
        "rough single-core cost, used to start the costliest modules first")


def _cost_s(item) -> float:
    marker = item.get_closest_marker("slow")
    return float(marker.args[0]) if marker is not None and marker.args else 0.0


def pytest_collection_modifyitems(config, items):
    # stable: tests keep their order inside a module, and equal-cost modules their file order
    items.sort(key=lambda item: -_cost_s(item))


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory):
    """(dataset folder, train rig) of a 32x32 tabletop capture: 16 train + 4 test views."""
    from sims.capture import capture
    from sims.rigs import default_rig, make_test_rig

    out = tmp_path_factory.mktemp("tiny") / "tabletop"
    rig = default_rig("tabletop", count=TINY_VIEWS, width=TINY_SIZE, height=TINY_SIZE, seed=0)
    capture("tabletop", rig, make_test_rig(rig, TINY_TEST_VIEWS), out, progress=False)
    return out, rig


#: The look of the toy MJCF scenes of the tests: a gradient sky, a checkered 1 m floor, red and
#: blue materials, one light from above and a headlight with its ambient term only (static
#: lighting). ``{model}``, ``{custom}``, ``{bodies}`` and ``{extra}`` are filled by
#: :func:`toy_scene`.
_TOY_SCENE = """
<mujoco model="{model}">
  {options}
  <custom>{custom}</custom>
  <visual>
    <headlight active="1" ambient="0.35 0.35 0.35" diffuse="0 0 0" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.45 0.65 0.9" rgb2="0.9 0.9 0.95"
             width="64" height="64"/>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.8 0.8 0.8" rgb2="0.55 0.55 0.55"
             width="64" height="64"/>
    <material name="grid" texture="grid" texrepeat="4 4" specular="0"/>
    <material name="red" rgba="0.9 0.15 0.1 1" specular="0"/>
    <material name="blue" rgba="0.1 0.25 0.9 1" specular="0"/>
  </asset>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true" diffuse="0.6 0.6 0.6" specular="0 0 0"/>
    <geom name="floor" type="box" size="0.5 0.5 0.01" pos="0 0 -0.01" material="grid"/>
    {bodies}
  </worldbody>
  {extra}
</mujoco>
"""


def toy_scene(model: str, bodies: str, custom: str = "", options: str = "",
              extra: str = "") -> str:
    """MJCF text of a toy scene with the tests' look (:data:`_TOY_SCENE`): ``bodies`` in the
    worldbody beside the floor, ``custom`` inside <custom>, ``options`` before it (e.g.
    <option .../>), ``extra`` after the worldbody (e.g. a keyframe)."""
    return _TOY_SCENE.format(model=model, bodies=bodies, custom=custom, options=options,
                             extra=extra)


@pytest.fixture(scope="session")
def toy_mjcf():
    """:func:`toy_scene`, for tests that write their own small MJCF scene."""
    return toy_scene
