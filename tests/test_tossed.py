"""The ``tossed`` zoo family (sims/zoo/tossed.py): a seeded dynamic scene of props thrown onto a
table, generated, rolled out in real MuJoCo physics and captured over time at 32x32."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco renders)
from nerfbot.data import load_dataset
from sims.dynamic import capture_dynamic
from sims.manifest import declared_objects
from sims.rollout import rollout
from sims.scene import builtin_scenes, load_model
from sims.sequence import capture_kind, sequence_rig
from sims.zoo import tossed
from sims.zoo.tossed import tossed_scene

pytestmark = pytest.mark.slow(5)

SEEDS = (0, 1, 7)


@pytest.fixture(scope="module", autouse=True)
def scene_cache(tmp_path_factory):
    """Generated scenes go to a fresh cache folder for this module."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NERFBOT_CACHE", str(tmp_path_factory.mktemp("cache")))
        yield


def _table_half(model: mujoco.MjModel) -> np.ndarray:
    return model.geom_size[model.geom("table_top").id, :2]


def test_tossed_is_a_dynamic_scene_name_and_the_seed_changes_it():
    assert "tossed" in builtin_scenes()
    starts = []
    for seed in SEEDS:
        model = load_model(f"tossed:{seed}")
        assert capture_kind(model) == "dynamic"
        objects = declared_objects(model)
        assert objects[0].startswith("sphere_")                  # a ball rolls in every scene
        assert tossed.PROP_COUNT[0] <= sum(o != "pendulum_bob" for o in objects) <= \
            tossed.PROP_COUNT[1]
        starts.append(model.key("init").qpos.copy())
    for a in range(len(SEEDS)):
        for b in range(a + 1, len(SEEDS)):
            assert starts[a].shape != starts[b].shape or not np.allclose(starts[a], starts[b])
    assert tossed_scene(3).xml == tossed_scene(3).xml


@pytest.mark.parametrize("seed", range(6))
def test_every_prop_stays_on_the_table_and_something_moves_to_the_end(seed):
    """The recorded rollout a capture takes: props inside the rim and above the top at every
    snapshot, each prop moved, and a prop or the bob still moving over the last quarter."""
    model = load_model(f"tossed:{seed}")
    data = mujoco.MjData(model)
    roll = rollout(model, data, tossed.DURATION_S, 41)
    props = [o for o in declared_objects(model) if o != "pendulum_bob"]
    half = _table_half(model)
    centres = []
    for qpos in roll.qpos:
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        centres.append(np.array([data.xpos[model.body(p).id] for p in props]))
    centres = np.stack(centres)                                   # (T, P, 3)
    assert (np.abs(centres[..., :2]) < half - tossed.RIM_WIDTH).all()
    assert (centres[..., 2] > tossed.TABLE_TOP).all()
    assert (np.linalg.norm(centres[-1] - centres[0], axis=-1) > 0.05).all()
    late = np.abs(np.diff(roll.qpos[-11:], axis=0)).max()
    assert late > 1e-3, "nothing moves in the last quarter"


def test_a_tiny_multiview_capture_loads_with_its_moving_bodies(tmp_path):
    rig = sequence_rig("tossed:2", "multiview", size=32, views_per_step=3)
    out = capture_dynamic("tossed:2", rig, tmp_path / "data", frames=6, test_every=4,
                          progress=False)
    ds = load_dataset(out)
    assert len(ds) == 18 and len(ds.indices("test")) == 3
    manifest = ds.manifest
    props = [o for o in manifest["objects"] if o != "pendulum_bob"]
    assert set(props) <= set(manifest["moving_bodies"])
    seen = set()
    for seg in ds.segmentations:
        seen |= set(np.unique(seg).tolist())
    for body in props:
        assert set(manifest["moving_bodies"][body]) & seen, f"{body} in no view"
    assert sorted(set(np.round(ds.times, 6))) == pytest.approx(np.linspace(0, 1, 6))
