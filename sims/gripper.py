"""A parallel-jaw gripper for MuJoCo scenes: its geometry (shared with the grasp planner) and MJCF.

Gripper frame (see :meth:`tasks.grasp_pose.Grasp.rotation`): origin at the tool-centre point
(TCP, midway between the finger pads at the middle of the pad height), x = closing axis,
z = up from the fingertips towards the palm, y = z × x.

The simulated gripper (:func:`add_gripper`) is a hand body (the gripper frame) welded to a mocap
target whose pose is set kinematically, like a stiff position-controlled arm. The hand carries the
palm and two finger bodies on slide joints along x, kept symmetric by a joint equality and driven
together by one force-limited position actuator on the tendon ``q_left + q_right`` (how far the
fingers have closed). Each finger therefore squeezes with at most
:attr:`GripperGeometry.grip_force`, and an object is held only by the pads' friction. All gripper
geoms are in geom group :data:`GRIPPER_GEOM_GROUP`, which captures do not draw, and the gripper is
parked at :data:`PARK_POSITION` (by default), far above any scene, whenever it is not grasping.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

#: Geom group of all gripper geoms: hidden by MuJoCo's default ``MjvOption`` (groups 0-2 drawn),
#: hence by :func:`sims.camera.capture_scene_option`. Collisions do not depend on groups.
GRIPPER_GEOM_GROUP = 3
#: Default place where the gripper TCP waits when not in use, world frame, metres (out of every
#: scene).
PARK_POSITION = (0.0, 0.0, 20.0)


@dataclass(frozen=True)
class GripperGeometry:
    """Dimensions and physical parameters of the gripper. The planner's collision model uses
    exactly the dimensions.

    Attributes:
        max_opening: largest distance between the two finger pads (fully open), metres.
        finger_length: finger length from the palm's underside to the fingertip (along z), metres.
        finger_thickness: finger size along the closing axis (x), metres.
        finger_width: finger size along y, metres.
        tcp_height: height of the TCP above the fingertips (z); the pad centre, metres.
        palm_height: palm size along z (above the fingers), metres.
        palm_width: palm size along y, metres.
        grip_force: largest squeezing force of each finger, newtons (the actuator's force limit).
        pad_friction: sliding friction coefficient of the finger pads (used for every pad
            contact: the pads have contact priority over other geoms), dimensionless.
        pad_torsional_friction: torsional friction of the pads, metres (torque / normal force);
            resists the object pivoting about the closing axis.
        finger_mass: mass of each finger, kg.
        finger_damping: viscous damping of each finger slide joint, N s/m (friction in the
            finger drive; the servo itself is critically damped).
        finger_armature: reflected motor inertia of each finger slide, kg (keeps the light
            fingers' joint limit and equality stiff).
        servo_gain: stiffness of the finger position servo, N/m; at least 50 x ``grip_force``
            so that the servo squeezes with the full grip force when commanded 2 cm past
            closed (see :func:`set_opening`).
        hand_mass: mass of the palm, kg (gravity-compensated; matters in collisions).
    """

    max_opening: float = 0.14
    finger_length: float = 0.10
    finger_thickness: float = 0.012
    finger_width: float = 0.03
    tcp_height: float = 0.02
    palm_height: float = 0.04
    palm_width: float = 0.05
    grip_force: float = 20.0
    pad_friction: float = 1.0
    pad_torsional_friction: float = 0.01
    finger_mass: float = 0.05
    finger_damping: float = 1.0
    finger_armature: float = 0.1
    servo_gain: float = 2000.0
    hand_mass: float = 0.5


GRIPPER = GripperGeometry()

# Contact parameters of the gripper geoms: a stiffer, harder contact than MuJoCo's default
# (solref 0.02 1) so that the pads do not visibly sink into the object under the grip force.
_SOLREF = (0.01, 1.0)
_SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)
# The weld holding the hand to its mocap target: as stiff as the default timestep (2 ms) allows.
_WELD_SOLREF = (0.005, 1.0)
#: How far past closed (negative opening, metres) the servo may be commanded to squeeze.
_SQUEEZE_PAST_CLOSED = 0.02
_PAD_RGBA = (0.15, 0.15, 0.17, 1.0)
_PALM_RGBA = (0.55, 0.56, 0.6, 1.0)


@dataclass(frozen=True)
class GripperIds:
    """Indices of one gripper in a compiled model.

    Attributes:
        mocap: index of the target (mocap) body into ``data.mocap_pos`` / ``data.mocap_quat``.
        body: body id of the hand.
        hand_qpos: ``qpos`` address of the hand's free joint (position, then quaternion).
        hand_dof: ``qvel`` address of the hand's free joint.
        finger_bodies: body ids of the (left, right) fingers.
        qpos: ``qpos`` addresses of the (left, right) finger slide joints.
        dof: ``qvel`` addresses of the (left, right) finger slide joints.
        actuator: id of the finger actuator (ctrl = closure, metres, see :func:`set_opening`).
        geoms: ids of all gripper geoms (palm and fingers).
        finger_geoms: geom ids of the (left, right) finger pads.
        max_opening: the fingers' largest pad distance in this model, metres.
        park_position: where the TCP waits when not in use, world frame, metres.
    """

    mocap: int
    body: int
    hand_qpos: int
    hand_dof: int
    finger_bodies: tuple[int, int]
    qpos: tuple[int, int]
    dof: tuple[int, int]
    actuator: int
    geoms: frozenset[int]
    finger_geoms: tuple[int, int]
    max_opening: float
    park_position: tuple[float, float, float]


def _names(name: str) -> dict[str, str]:
    """Element names of the gripper called ``name``."""
    return {
        "body": name, "target": f"{name}_target", "free": f"{name}_free", "palm": f"{name}_palm",
        "weld": f"{name}_weld", "symmetry": f"{name}_symmetry",
        "left": f"{name}_left_finger", "right": f"{name}_right_finger",
        "left_joint": f"{name}_left_slide", "right_joint": f"{name}_right_slide",
        "tendon": f"{name}_closure", "actuator": f"{name}_grip",
    }


def add_gripper(spec: mujoco.MjSpec, geometry: GripperGeometry = GRIPPER,
                name: str = "gripper",
                park_position: tuple[float, float, float] = PARK_POSITION) -> None:
    """Add a parked, open parallel-jaw gripper called ``name`` to ``spec`` (modified in place).

    The gripper starts (and, after ``mj_resetData``, restarts) at ``park_position`` (3,), world
    frame, metres, upright; give each gripper its own park position if a scene has several.
    Its geoms collide with every geom whose ``contype`` / ``conaffinity`` has bit 0 set (MuJoCo's
    default).

    Adds to the world body:

    - a mocap body ``<name>_target`` (no geoms): the commanded gripper frame;
    - a free body ``name`` (the hand, gravity-compensated) welded to the target by a stiff weld
      equality ``<name>_weld``, with the palm geom ``<name>_palm``. The hand follows the target
      like a stiff arm, but as a dynamic body: its contacts have proper velocities (a finger
      moved by a mocap body directly would slide through the object without friction) and it is
      stopped by the table instead of passing through it;
    - two finger bodies ``<name>_left_finger`` / ``<name>_right_finger`` with one box geom each
      (same names), on slide joints ``<name>_left_slide`` / ``<name>_right_slide`` (0 = fully
      open, positive = closing, metres), kept symmetric by a joint equality, summed by the tendon
      ``<name>_closure`` and driven by the position actuator ``<name>_grip`` on that tendon,
      force-limited to ``geometry.grip_force`` (the squeezing force of each finger).

    Scene-wide changes: the scene's ``<statistic>`` center/extent are pinned to their values
    without the gripper (so a far-parked gripper does not change the renderer's clipping planes
    or shadows), and the friction cone becomes elliptic with ``impratio`` 10 (the usual MuJoCo
    setting for grasping: pads grip without creeping).

    Raises:
        ValueError: a gripper element name is already used in the spec, or the spec does not
            compile (MuJoCo's message is included).
    """
    if geometry.servo_gain * _SQUEEZE_PAST_CLOSED < geometry.grip_force:
        raise ValueError(f"servo_gain {geometry.servo_gain} N/m is too low for grip_force "
                         f"{geometry.grip_force} N: it must be >= {1 / _SQUEEZE_PAST_CLOSED:g} x "
                         "grip_force")
    names = _names(name)
    _check_free_names(spec, names)
    _pin_statistic(spec)
    g = geometry
    half_open = g.max_opening / 2.0
    common = dict(group=GRIPPER_GEOM_GROUP, contype=1, conaffinity=1,
                  solref=list(_SOLREF), solimp=list(_SOLIMP))

    park = [float(v) for v in park_position]
    spec.worldbody.add_body(name=names["target"], pos=park, mocap=True)
    hand = spec.worldbody.add_body(name=names["body"], pos=park, gravcomp=1.0)
    hand.add_freejoint(name=names["free"])
    palm_half = [half_open + g.finger_thickness, g.palm_width / 2.0, g.palm_height / 2.0]
    palm_z = g.finger_length - g.tcp_height + g.palm_height / 2.0
    hand.add_geom(name=names["palm"], type=mujoco.mjtGeom.mjGEOM_BOX, size=palm_half,
                  pos=[0.0, 0.0, palm_z], mass=g.hand_mass, rgba=list(_PALM_RGBA), **common)
    spec.add_equality(name=names["weld"], type=mujoco.mjtEq.mjEQ_WELD,
                      objtype=mujoco.mjtObj.mjOBJ_BODY, name1=names["body"],
                      name2=names["target"], solref=list(_WELD_SOLREF),
                      data=[0.0] * 6 + [1.0, 0.0, 0.0, 0.0, 1.0, 0.0])

    finger_half = [g.finger_thickness / 2.0, g.finger_width / 2.0, g.finger_length / 2.0]
    finger_z = g.finger_length / 2.0 - g.tcp_height
    for side, sign in (("left", -1.0), ("right", 1.0)):
        finger = hand.add_body(name=names[side], gravcomp=1.0,
                               pos=[sign * (half_open + g.finger_thickness / 2.0), 0.0, finger_z])
        finger.add_joint(name=names[f"{side}_joint"], type=mujoco.mjtJoint.mjJNT_SLIDE,
                         axis=[-sign, 0.0, 0.0], range=[0.0, half_open], limited=True,
                         damping=g.finger_damping, armature=g.finger_armature,
                         solref_limit=[0.005, 1.0])
        finger.add_geom(name=names[side], type=mujoco.mjtGeom.mjGEOM_BOX, size=finger_half,
                        mass=g.finger_mass, rgba=list(_PAD_RGBA), condim=4, priority=1,
                        friction=[g.pad_friction, g.pad_torsional_friction, 0.0001], **common)
    spec.add_exclude(bodyname1=names["left"], bodyname2=names["right"])

    tendon = spec.add_tendon(name=names["tendon"])
    tendon.wrap_joint(names["left_joint"], 1.0)
    tendon.wrap_joint(names["right_joint"], 1.0)
    spec.add_equality(name=names["symmetry"], type=mujoco.mjtEq.mjEQ_JOINT,
                      name1=names["left_joint"], name2=names["right_joint"],
                      data=[0.0, 1.0] + [0.0] * 10, solref=[0.005, 1.0])
    act = spec.add_actuator(name=names["actuator"], target=names["tendon"],
                            trntype=mujoco.mjtTrn.mjTRN_TENDON)
    act.set_to_position(kp=g.servo_gain, dampratio=1.0)
    act.ctrllimited = True
    act.ctrlrange = [0.0, g.max_opening + _SQUEEZE_PAST_CLOSED]
    act.forcelimited = True
    act.forcerange = [-g.grip_force, g.grip_force]

    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = max(float(spec.option.impratio), 10.0)


def _check_free_names(spec: mujoco.MjSpec, names: dict[str, str]) -> None:
    """Raise ValueError if a body, geom, joint, tendon, actuator or equality of the gripper
    would reuse an existing name."""
    taken = ({b.name for b in spec.bodies} | {g.name for g in spec.geoms}
             | {j.name for j in spec.joints} | {t.name for t in spec.tendons}
             | {a.name for a in spec.actuators} | {e.name for e in spec.equalities})
    clash = sorted(set(names.values()) & taken)
    if clash:
        raise ValueError(f"cannot add gripper: the scene already uses the name(s) {clash}")


def _pin_statistic(spec: mujoco.MjSpec) -> None:
    """Fix the spec's statistic center/extent to the values MuJoCo computes without the gripper
    (unless the scene already sets them)."""
    if np.isfinite(spec.stat.extent) and np.all(np.isfinite(spec.stat.center)):
        return
    try:
        model = spec.compile()
    except ValueError as err:
        raise ValueError(f"cannot add gripper: the scene does not compile: {err}") from err
    if not np.isfinite(spec.stat.extent):
        spec.stat.extent = float(model.stat.extent)
    if not np.all(np.isfinite(spec.stat.center)):
        spec.stat.center = [float(v) for v in model.stat.center]


def gripper_ids(model: mujoco.MjModel, name: str = "gripper") -> GripperIds:
    """Indices of the gripper ``name`` in ``model``.

    Raises:
        ValueError: the model has no gripper called ``name`` (see :func:`add_gripper`).
    """
    names = _names(name)
    target = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, names["target"])
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, names["body"])
    if target < 0 or body < 0 or model.body_mocapid[target] < 0:
        raise ValueError(f"the model has no gripper called {name!r} (add it with add_gripper)")
    free = model.joint(names["free"])
    fingers = tuple(int(model.body(names[s]).id) for s in ("left", "right"))
    joints = [model.joint(names[f"{s}_joint"]) for s in ("left", "right")]
    finger_geoms = tuple(int(model.geom(names[s]).id) for s in ("left", "right"))
    geoms = frozenset(int(i) for i in
                      np.flatnonzero(np.isin(model.geom_bodyid, [body, *fingers])))
    return GripperIds(
        mocap=int(model.body_mocapid[target]), body=int(body),
        hand_qpos=int(free.qposadr[0]), hand_dof=int(free.dofadr[0]),
        finger_bodies=(fingers[0], fingers[1]),
        qpos=(int(joints[0].qposadr[0]), int(joints[1].qposadr[0])),
        dof=(int(joints[0].dofadr[0]), int(joints[1].dofadr[0])),
        actuator=int(model.actuator(names["actuator"]).id),
        geoms=geoms, finger_geoms=(finger_geoms[0], finger_geoms[1]),
        max_opening=2.0 * float(joints[0].range[1]),
        park_position=tuple(float(v) for v in model.body_pos[target]))


def rotation_to_quat(rotation: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion (w, x, y, z) of a (3, 3) rotation matrix."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation, dtype=np.float64).reshape(-1))
    return quat


def set_gripper_target(data: mujoco.MjData, ids: GripperIds, position: np.ndarray,
                       rotation: np.ndarray | None = None) -> None:
    """Command the gripper TCP to ``position`` (3,) metres, world frame, with gripper-to-world
    ``rotation`` (3, 3) (unchanged if None). The hand follows during the next steps."""
    data.mocap_pos[ids.mocap] = np.asarray(position, dtype=np.float64)
    if rotation is not None:
        data.mocap_quat[ids.mocap] = rotation_to_quat(rotation)


def teleport_gripper(data: mujoco.MjData, ids: GripperIds, position: np.ndarray,
                     rotation: np.ndarray) -> None:
    """Put the hand and its target at TCP ``position`` (3,) metres with gripper-to-world
    ``rotation`` (3, 3), at rest. Run ``mj_forward`` (or step) for it to take effect."""
    set_gripper_target(data, ids, position, rotation)
    data.qpos[ids.hand_qpos:ids.hand_qpos + 3] = data.mocap_pos[ids.mocap]
    data.qpos[ids.hand_qpos + 3:ids.hand_qpos + 7] = data.mocap_quat[ids.mocap]
    data.qvel[ids.hand_dof:ids.hand_dof + 6] = 0.0


def gripper_pose(data: mujoco.MjData, ids: GripperIds) -> tuple[np.ndarray, np.ndarray]:
    """(TCP position (3,) metres, gripper-to-world rotation (3, 3)) of the hand now."""
    return data.xpos[ids.body].copy(), data.xmat[ids.body].reshape(3, 3).copy()


def set_opening(data: mujoco.MjData, ids: GripperIds, opening: float) -> None:
    """Command the distance between the finger pads, metres, from ``max_opening`` down to
    -0.02 (2 cm past closed: the servo then squeezes whatever is in between with the full
    :attr:`GripperGeometry.grip_force`). Values outside are clipped by the actuator."""
    data.ctrl[ids.actuator] = ids.max_opening - float(opening)


def place_fingers(data: mujoco.MjData, ids: GripperIds, opening: float) -> None:
    """Teleport the fingers to ``opening`` (metres, clipped to [0, max_opening]) at rest and
    command that opening."""
    opening = float(np.clip(opening, 0.0, ids.max_opening))
    closure = (ids.max_opening - opening) / 2.0
    for q, v in zip(ids.qpos, ids.dof):
        data.qpos[q] = closure
        data.qvel[v] = 0.0
    set_opening(data, ids, opening)


def gripper_opening(data: mujoco.MjData, ids: GripperIds) -> float:
    """Current distance between the finger pads, metres."""
    return ids.max_opening - float(data.qpos[ids.qpos[0]] + data.qpos[ids.qpos[1]])


def park_gripper(model: mujoco.MjModel, data: mujoco.MjData, name: str = "gripper") -> None:
    """Put the gripper back at its park position (see :func:`add_gripper`), upright, at rest and
    fully open, and run ``mj_forward``."""
    ids = gripper_ids(model, name)
    teleport_gripper(data, ids, np.asarray(ids.park_position), np.eye(3))
    place_fingers(data, ids, ids.max_opening)
    mujoco.mj_forward(model, data)
