"""Shared fixtures: one tiny real MuJoCo capture per test session."""

from __future__ import annotations

import sims  # noqa: F401  (sets MUJOCO_GL=egl before mujoco is imported)

import pytest

TINY_SIZE = 32
TINY_VIEWS = 16
TINY_TEST_VIEWS = 4


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory):
    """(dataset folder, train rig) of a 32x32 tabletop capture: 16 train + 4 test views."""
    from sims.capture import capture
    from sims.cli import default_rig
    from sims.rigs import make_test_rig

    out = tmp_path_factory.mktemp("tiny") / "tabletop"
    rig = default_rig("tabletop", count=TINY_VIEWS, width=TINY_SIZE, height=TINY_SIZE, seed=0)
    capture("tabletop", rig, make_test_rig(rig, TINY_TEST_VIEWS), out, progress=False)
    return out, rig
