"""The simulated parallel-jaw gripper (sims.gripper) and the grasp executor (tasks.execute)."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from sims.camera import capture_scene_option
from sims.gl import make_renderer
from sims.gripper import (GRIPPER, GRIPPER_GEOM_GROUP, PARK_POSITION, add_gripper, gripper_ids,
                          gripper_opening, park_gripper, teleport_gripper)
from sims.manifest import rendered_geoms
from tasks.execute import ExecutionResult, execute_grasp, settle
from tasks.grasp_pose import Grasp

TABLE_TOP = 0.75
#: A table (top at z = 0.75 m), a 5 x 5 x 8 cm box of 0.2 kg and a cylinder r = 3.5 cm,
#: h = 12 cm of 0.2 kg standing on it, 20 cm apart, and a camera looking at both.
SCENE = f"""
<mujoco model="grasp_test">
  <worldbody>
    <light pos="0 -0.5 2" dir="0 0.25 -1"/>
    <camera name="view" pos="0 -0.7 1.1" xyaxes="1 0 0 0 0.45 0.9" fovy="45"/>
    <geom name="table" type="box" size="0.4 0.3 0.02" pos="0 0 {TABLE_TOP - 0.02}"
          rgba="0.6 0.45 0.3 1"/>
    <body name="box" pos="-0.1 0 {TABLE_TOP + 0.04}">
      <freejoint/>
      <geom name="box" type="box" size="0.025 0.025 0.04" mass="0.2" rgba="0.8 0.2 0.2 1"/>
    </body>
    <body name="cylinder" pos="0.1 0 {TABLE_TOP + 0.06}">
      <freejoint/>
      <geom name="cylinder" type="cylinder" size="0.035 0.06" mass="0.2" rgba="0.2 0.3 0.8 0.5"/>
    </body>
  </worldbody>
</mujoco>
"""
X = np.array([1.0, 0.0, 0.0])


def build(geometry=GRIPPER) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The test scene with a gripper, objects settled."""
    spec = mujoco.MjSpec.from_string(SCENE)
    add_gripper(spec, geometry)
    model = spec.compile()
    data = mujoco.MjData(model)
    settle(model, data)
    return model, data


@pytest.fixture(scope="module")
def scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    """(model, settled data); tests copy the data, never modify it."""
    return build()


def fresh(scene) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model, settled = scene
    data = mujoco.MjData(model)
    mujoco.mj_copyData(data, model, settled)
    return model, data


def top_grasp(data: mujoco.MjData, body: str, width: float, up: float,
              offset=(0.0, 0.0, 0.0), axis=X) -> Grasp:
    """A top-down grasp ``up`` metres above the body origin (its centre), closing along ``axis``."""
    center = data.body(body).xpos + np.array([0.0, 0.0, up]) + np.asarray(offset)
    return Grasp(center=center, axis=np.asarray(axis, dtype=np.float64), width=width)


def test_lifts_the_box(scene):
    model, data = fresh(scene)
    result = execute_grasp(model, data, top_grasp(data, "box", 0.05, 0.02), "box")
    assert isinstance(result, ExecutionResult)
    assert result.success, result
    assert result.reason == "lifted"
    assert result.lift_height >= 0.10
    assert result.min_hold_height >= 0.10
    assert result.fingers_on_object == 2
    assert result.final_opening == pytest.approx(0.05, abs=0.003)   # pads on the box faces
    assert result.object_z_start == pytest.approx(TABLE_TOP + 0.04, abs=0.002)
    assert result.object_z_end - result.object_z_start == pytest.approx(result.lift_height)
    assert result.sim_seconds > 3.0


def test_lifts_the_cylinder(scene):
    model, data = fresh(scene)
    result = execute_grasp(model, data, top_grasp(data, "cylinder", 0.07, 0.03), "cylinder")
    assert result.success, result
    assert result.lift_height >= 0.10
    assert result.final_opening == pytest.approx(0.07, abs=0.003)


def test_lifts_the_cylinder_closing_along_y_and_off_centre(scene):
    model, data = fresh(scene)
    grasp = top_grasp(data, "cylinder", 0.07, 0.03, offset=(0.01, 0.01, 0.0), axis=(0, 1, 0))
    result = execute_grasp(model, data, grasp, "cylinder")
    assert result.success, result


def test_lifts_with_a_side_approach(scene):
    model, data = fresh(scene)
    center = data.body("cylinder").xpos.copy()
    grasp = Grasp(center=center, axis=X, width=0.07, approach=np.array([0.0, 1.0, 0.0]))
    result = execute_grasp(model, data, grasp, "cylinder")
    assert result.success, result


def test_a_grasp_beside_the_object_closes_on_air(scene):
    model, data = fresh(scene)
    grasp = top_grasp(data, "box", 0.05, 0.02, offset=(0.0, 0.10, 0.0))
    result = execute_grasp(model, data, grasp, "box")
    assert not result.success
    assert result.reason == "not lifted (fingers closed on nothing)"
    assert result.fingers_on_object == 0
    assert result.final_opening < 0.001
    assert abs(result.lift_height) < 1e-3


def test_a_weak_grip_lets_the_object_slip():
    # 0.5 N per finger with friction 1 holds at most 1 N; the box weighs 0.2 kg x 9.81 = 2 N.
    weak = dataclasses.replace(GRIPPER, grip_force=0.5)
    model, data = build(weak)
    result = execute_grasp(model, data, top_grasp(data, "box", 0.05, 0.02), "box", geometry=weak)
    assert not result.success
    assert result.fingers_on_object == 2
    assert result.reason.startswith("not lifted")
    assert result.lift_height < 0.05


def test_slippery_pads_cannot_lift():
    slippery = dataclasses.replace(GRIPPER, pad_friction=0.02)
    model, data = build(slippery)
    result = execute_grasp(model, data, top_grasp(data, "box", 0.05, 0.02), "box",
                           geometry=slippery)
    assert not result.success
    assert result.lift_height < 0.05


def test_a_fingertip_landing_on_the_object_aborts(scene):
    # Opening 8 cm, 3 cm off-centre along the closing axis: one fingertip comes down on the box.
    model, data = fresh(scene)
    grasp = top_grasp(data, "box", 0.05, 0.02, offset=(0.03, 0.0, 0.0))
    result = execute_grasp(model, data, grasp, "box")
    assert not result.success
    assert result.reason.startswith("gripper collided with 'box' during the approach")


def test_a_grasp_too_low_hits_the_table(scene):
    model, data = fresh(scene)
    center = data.body("box").xpos.copy()
    center[2] = TABLE_TOP + GRIPPER.tcp_height - 0.01   # fingertips 1 cm below the table top
    result = execute_grasp(model, data, Grasp(center=center, axis=X, width=0.05), "box")
    assert not result.success
    assert result.reason.startswith("gripper collided with 'table'")


def test_a_pre_grasp_pose_in_collision_is_refused(scene):
    # A side approach closing vertically on a box standing on the table: the lower finger of
    # the open gripper is already inside the table top at the pre-grasp pose.
    model, data = fresh(scene)
    grasp = Grasp(center=data.body("box").xpos.copy(), axis=np.array([0.0, 0.0, 1.0]),
                  width=0.05, approach=np.array([-1.0, 0.0, 0.0]))
    before = data.qpos.copy()
    result = execute_grasp(model, data, grasp, "box")
    assert not result.success
    assert result.reason.startswith("gripper collided with 'table'")
    assert "pre-grasp pose" in result.reason
    assert result.sim_seconds == 0.0
    np.testing.assert_array_equal(data.qpos, before)   # parked again, nothing simulated


def test_execution_is_deterministic_and_survives_a_reset(scene):
    model, data = fresh(scene)
    grasp = top_grasp(data, "cylinder", 0.07, 0.03, offset=(0.005, -0.005, 0.0))
    first = execute_grasp(model, data, grasp, "cylinder", hold_seconds=0.5)
    mujoco.mj_resetData(model, data)
    settle(model, data)
    second = execute_grasp(model, data, grasp, "cylinder", hold_seconds=0.5)
    assert first == second


def test_recorder_sees_every_phase_in_order(scene):
    model, data = fresh(scene)
    phases: list[str] = []
    execute_grasp(model, data, top_grasp(data, "box", 0.05, 0.02), "box", hold_seconds=0.2,
                  recorder=lambda m, d, phase: phases.append(phase), record_fps=20)
    order = list(dict.fromkeys(phases))
    assert order == ["pregrasp", "approach", "close", "lift", "hold"]
    assert 20 * 1.5 <= len(phases) <= 20 * 3.0   # about 20 calls per simulated second


def test_errors_name_the_problem(scene):
    model, data = fresh(scene)
    grasp = top_grasp(data, "box", 0.05, 0.02)
    with pytest.raises(ValueError, match="'mug'"):
        execute_grasp(model, data, grasp, "mug")
    with pytest.raises(ValueError, match="'world'"):
        execute_grasp(model, data, grasp, "world")
    with pytest.raises(ValueError, match="'hand'"):
        execute_grasp(model, data, grasp, "box", gripper="hand")
    with pytest.raises(ValueError, match="parallel"):
        execute_grasp(model, data, Grasp(center=grasp.center, axis=np.array([0.0, 0.0, 1.0]),
                                         width=0.05), "box")
    with pytest.raises(ValueError, match="lift"):
        execute_grasp(model, data, grasp, "box", lift=0.0)
    spec = mujoco.MjSpec.from_string(SCENE)
    add_gripper(spec)
    with pytest.raises(ValueError, match="gripper"):
        add_gripper(spec)


def test_park_and_fingers(scene):
    model, data = fresh(scene)
    ids = gripper_ids(model)
    assert ids.max_opening == pytest.approx(GRIPPER.max_opening)
    assert ids.park_position == PARK_POSITION
    assert gripper_opening(data, ids) == pytest.approx(GRIPPER.max_opening)
    assert data.xpos[ids.body, 2] > 10.0   # parked far above the scene
    # The finger pads' inner faces are at +-opening/2 along the gripper x axis, as the planner
    # assumes.
    teleport_gripper(data, ids, np.array([0.0, 0.0, 1.5]), np.eye(3))
    mujoco.mj_forward(model, data)
    left, right = ids.finger_geoms
    inner = [data.geom_xpos[left, 0] + GRIPPER.finger_thickness / 2,
             data.geom_xpos[right, 0] - GRIPPER.finger_thickness / 2]
    assert inner == pytest.approx([-0.07, 0.07])
    bottom = data.geom_xpos[left, 2] - GRIPPER.finger_length / 2
    assert bottom == pytest.approx(1.5 - GRIPPER.tcp_height)
    park_gripper(model, data)
    assert data.xpos[ids.body, 2] > 10.0


def test_gripper_geoms_are_never_rendered(scene):
    plain = mujoco.MjModel.from_xml_string(SCENE)
    plain_data = mujoco.MjData(plain)
    mujoco.mj_forward(plain, plain_data)
    model, data = fresh(scene)
    mujoco.mj_resetData(model, data)   # the same state as plain_data, plus the parked gripper
    mujoco.mj_forward(model, data)
    ids = gripper_ids(model)
    assert all(model.geom_group[g] == GRIPPER_GEOM_GROUP for g in ids.geoms)
    assert model.stat.extent == pytest.approx(plain.stat.extent)   # same clipping planes
    # Hover the open gripper just above the box, in the middle of the camera's view.
    teleport_gripper(data, ids, data.body("box").xpos + np.array([0.0, 0.0, 0.1]), np.eye(3))
    mujoco.mj_forward(model, data)
    assert not {int(g.objid) for g in rendered_geoms(model, data)} & ids.geoms

    def render(m, d, option):
        renderer = make_renderer(m, 64, 96)
        try:
            renderer.update_scene(d, camera="view", scene_option=option)
            return renderer.render().copy()
        finally:
            renderer.close()

    without = render(plain, plain_data, capture_scene_option())
    hidden = render(model, data, capture_scene_option())
    np.testing.assert_array_equal(hidden, without)
    shown_option = capture_scene_option()
    shown_option.geomgroup[GRIPPER_GEOM_GROUP] = 1
    shown = render(model, data, shown_option)
    assert np.abs(shown.astype(int) - without.astype(int)).sum(axis=2).astype(bool).mean() > 0.01
