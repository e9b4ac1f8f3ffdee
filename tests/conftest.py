"""Shared fixtures (one tiny real MuJoCo capture per test session) and the suite's scheduling.

The suite runs under pytest-xdist, one worker per core (``addopts`` in pyproject.toml). Each
worker then computes with one thread: the tests' tensors are small, so two threads in one
process gained little (with warm caches on a 2-core machine, the suite took 12:35 with 2
threads in one process and 8:00 with 2 single-thread workers). Modules marked
``slow(seconds)`` go first, costliest first, so a long module does not start last and leave the
other workers idle at the end.
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
