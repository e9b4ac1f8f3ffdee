"""Carry out a :class:`~tasks.grasp_pose.Grasp` with the simulated parallel-jaw gripper.

The gripper (:func:`sims.gripper.add_gripper`) follows a kinematically moved target (a mocap body
it is stiffly welded to, like a position-controlled arm); the hand, the fingers and the object are
simulated, so the object is lifted only if the two finger pads hold it by friction against
gravity. The sequence:

1. ``pregrasp``: teleport the open gripper to the pre-grasp pose, ``pregrasp_distance`` back
   along the approach from the grasp centre, oriented by :meth:`Grasp.rotation`; open to
   ``min(width + opening_margin, max_opening)``.
2. ``approach``: move the TCP to the grasp centre along the approach (minimum-jerk profile at
   ``approach_speed`` on average). A contact force on the gripper above ``max_contact_force``
   (e.g. a fingertip driven into the table or onto the object's rim) aborts the grasp.
3. ``close``: close at ``closing_speed`` and squeeze with the full grip force until the fingers
   stop.
4. ``lift``: raise the gripper straight up (world +z) by ``lift`` in ``lift_seconds``.
5. ``hold``: keep still for ``hold_seconds``.

Success: the object's body origin is at least ``min_lift`` above its starting height during the
whole hold (so at its start and at its end).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import mujoco
import numpy as np

from sims.gripper import (GRIPPER, GripperGeometry, GripperIds, gripper_ids, gripper_opening,
                          park_gripper, place_fingers, set_gripper_target, set_opening,
                          teleport_gripper)
from tasks.grasp_pose import Grasp

#: ``recorder(model, data, phase)``: called during execution (e.g. to render video frames).
Recorder = Callable[[mujoco.MjModel, mujoco.MjData, str], None]

#: Finger speed below which the fingers count as stopped while closing, m/s.
_STOPPED_SPEED = 0.002
#: How long the fingers must stay stopped to end the closing phase, seconds.
_STOPPED_FOR = 0.05
#: Commanded opening at the end of closing, metres: 2 cm past closed, so the servo saturates at
#: the grip force (see :attr:`sims.gripper.GripperGeometry.servo_gain`).
_SQUEEZE_OPENING = -0.02
#: Opening below which the fingers count as closed on nothing, metres.
_CLOSED_ON_NOTHING = 0.001


@dataclass(frozen=True)
class ExecutionResult:
    """Outcome of one executed grasp.

    Attributes:
        success: the object stayed at least ``min_lift`` above its start during the whole hold.
        lift_height: object z at the end minus object z at the start, metres.
        object_z_start: object body z before the grasp, metres (world).
        object_z_end: object body z at the end, metres (world).
        min_hold_height: lowest (object z - object_z_start) during the hold, metres
            (``-inf`` if the hold was never reached).
        reason: "lifted" on success; otherwise e.g. "not lifted", "dropped", or
            "gripper collided with '<geom>' ...", with details on the finger contacts.
        sim_seconds: simulated time spent, seconds.
        final_opening: distance between the finger pads after closing, metres (nan if the
            grasp was aborted before closing).
        fingers_on_object: how many finger pads touched the object after closing (0, 1 or 2).
    """

    success: bool
    lift_height: float
    object_z_start: float
    object_z_end: float
    min_hold_height: float
    reason: str
    sim_seconds: float
    final_opening: float = float("nan")
    fingers_on_object: int = 0


def object_body_id(model: mujoco.MjModel, object_body: str) -> int:
    """Body id of ``object_body``.

    Raises:
        ValueError: no body has that name (the message lists the free bodies), or the body is
            welded to the world.
    """
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, object_body)
    if bid < 0:
        free = [model.body(int(model.jnt_bodyid[j])).name for j in range(model.njnt)
                if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE]
        raise ValueError(f"unknown object body {object_body!r}; free bodies: {free}")
    if int(model.body_weldid[bid]) == 0:
        raise ValueError(f"object body {object_body!r} is fixed to the world (no joint): "
                         "it cannot be lifted")
    return int(bid)


def settle(model: mujoco.MjModel, data: mujoco.MjData, seconds: float = 0.5,
           gripper: str = "gripper") -> None:
    """Park the gripper (open, far above the scene) and step physics for ``seconds`` so that
    the objects come to rest (e.g. after ``mujoco.mj_resetData``)."""
    park_gripper(model, data, gripper)
    for _ in range(int(round(seconds / model.opt.timestep))):
        mujoco.mj_step(model, data)


class _Runner:
    """Steps physics, keeps time and calls the recorder every ``every`` steps."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData,
                 recorder: Recorder | None, record_fps: float) -> None:
        self.model, self.data, self.recorder = model, data, recorder
        self.every = max(1, int(round(1.0 / (record_fps * model.opt.timestep))))
        self.steps = 0

    def step(self, phase: str) -> None:
        mujoco.mj_step(self.model, self.data)
        self.steps += 1
        if self.recorder is not None and self.steps % self.every == 0:
            self.recorder(self.model, self.data, phase)

    def steps_for(self, seconds: float) -> int:
        return max(1, int(round(seconds / self.model.opt.timestep)))

    @property
    def seconds(self) -> float:
        return self.steps * float(self.model.opt.timestep)


def _min_jerk(s: float) -> float:
    """Minimum-jerk position profile on [0, 1] (zero velocity and acceleration at both ends)."""
    s = min(max(s, 0.0), 1.0)
    return s * s * s * (10.0 + s * (-15.0 + 6.0 * s))


def _subtree_bodies(model: mujoco.MjModel, root: int) -> set[int]:
    """Ids of ``root`` and all its descendant bodies."""
    bodies = {root}
    for b in range(root + 1, model.nbody):
        if int(model.body_parentid[b]) in bodies:
            bodies.add(b)
    return bodies


def _worst_contact(model: mujoco.MjModel, data: mujoco.MjData,
                   gripper_geoms: frozenset[int]) -> tuple[float, int, float]:
    """(largest normal force N, other geom id, its penetration m) over contacts between the
    gripper and anything else; (0, -1, 0) if none."""
    worst = (0.0, -1, 0.0)
    force = np.zeros(6)
    for i in range(data.ncon):
        c = data.contact[i]
        g1, g2 = int(c.geom1), int(c.geom2)
        if (g1 in gripper_geoms) == (g2 in gripper_geoms):
            continue
        other = g2 if g1 in gripper_geoms else g1
        mujoco.mj_contactForce(model, data, i, force)
        if worst[1] < 0 or force[0] > worst[0]:
            worst = (float(force[0]), other, float(-c.dist))
    return worst


def _fingers_touching(data: mujoco.MjData, ids: GripperIds, object_geoms: set[int]) -> int:
    """How many finger pads are in contact with one of ``object_geoms``."""
    touching = set()
    for i in range(data.ncon):
        c = data.contact[i]
        pair = (int(c.geom1), int(c.geom2))
        for finger in ids.finger_geoms:
            if finger in pair and (pair[0] in object_geoms or pair[1] in object_geoms):
                touching.add(finger)
    return len(touching)


def _geom_label(model: mujoco.MjModel, gid: int) -> str:
    name = model.geom(gid).name or f"geom_{gid}"
    body = model.body(int(model.geom_bodyid[gid])).name
    return f"'{name}'" + (f" (body '{body}')" if body and body != name else "")


def execute_grasp(model: mujoco.MjModel, data: mujoco.MjData, grasp: Grasp, object_body: str, *,
                  lift: float = 0.15, hold_seconds: float = 2.0, min_lift: float = 0.10,
                  gripper: str = "gripper", geometry: GripperGeometry = GRIPPER,
                  recorder: Recorder | None = None, record_fps: float = 30.0,
                  pregrasp_distance: float = 0.15, opening_margin: float = 0.03,
                  approach_speed: float = 0.4, closing_speed: float = 0.2,
                  close_seconds: float = 1.0,
                  lift_seconds: float = 1.0, max_contact_force: float = 30.0) -> ExecutionResult:
    """Execute ``grasp`` on the free body ``object_body`` from the current state of ``data``
    (objects at rest, gripper anywhere: it is teleported) and report whether the object was
    lifted and held. Deterministic: the same model, state and arguments give the same result.

    Args:
        lift: how far the gripper rises after closing, metres.
        hold_seconds: how long the lifted gripper stays still, seconds.
        min_lift: how far above its start the object must stay during the hold, metres.
        gripper: name given to :func:`sims.gripper.add_gripper`.
        geometry: the geometry the gripper was built with (its ``max_opening`` must match).
        recorder: optional ``recorder(model, data, phase)`` called ``record_fps`` times per
            simulated second (and once at the pre-grasp pose); phase is one of "pregrasp",
            "approach", "close", "lift", "hold".
        pregrasp_distance: distance of the pre-grasp TCP from the grasp centre, metres.
        opening_margin: pre-grasp opening beyond ``grasp.width``, metres.
        approach_speed: mean TCP speed of the approach, m/s.
        closing_speed: rate at which the commanded opening shrinks, m/s (each finger moves at
            half of it).
        close_seconds: longest wait for the fingers to stop after the closing ramp, seconds.
        lift_seconds: duration of the lift, seconds.
        max_contact_force: gripper contact force that aborts the approach, newtons.

    The gripper is left where the grasp ended (holding the object, if it did; parked if the
    pre-grasp pose was already in collision); use :func:`settle` or
    :func:`sims.gripper.park_gripper` to put it away.

    Raises:
        ValueError: unknown or immovable ``object_body``, no gripper ``gripper`` in the model, a
            gripper whose opening differs from ``geometry``, a degenerate grasp, or a
            non-positive distance, speed or duration.
    """
    body = object_body_id(model, object_body)
    ids = gripper_ids(model, gripper)
    if abs(ids.max_opening - geometry.max_opening) > 1e-9:
        raise ValueError(f"gripper {gripper!r} opens to {ids.max_opening} m but geometry says "
                         f"{geometry.max_opening} m: pass the geometry it was built with")
    rotation = _checked_rotation(grasp)
    center = np.asarray(grasp.center, dtype=np.float64)
    approach = -rotation[:, 2]
    _check_positive(lift=lift, min_lift=min_lift, record_fps=record_fps, width=grasp.width,
                    approach_speed=approach_speed, closing_speed=closing_speed,
                    lift_seconds=lift_seconds, pregrasp_distance=pregrasp_distance)
    if hold_seconds < 0 or close_seconds < 0:
        raise ValueError(f"hold_seconds ({hold_seconds}) and close_seconds ({close_seconds}) "
                         "must be >= 0")
    bodies = _subtree_bodies(model, body)
    object_geoms = {g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in bodies}
    z0 = float(data.xpos[body, 2])
    run = _Runner(model, data, recorder, record_fps)

    def result(success: bool, reason: str, min_hold: float = -np.inf, opening: float = np.nan,
               touching: int = 0) -> ExecutionResult:
        z = float(data.xpos[body, 2])
        return ExecutionResult(success=success, lift_height=z - z0, object_z_start=z0,
                               object_z_end=z, min_hold_height=float(min_hold), reason=reason,
                               sim_seconds=run.seconds, final_opening=float(opening),
                               fingers_on_object=touching)

    # 1. Pre-grasp: teleport, open, check that the gripper appeared in free space.
    start = center - approach * pregrasp_distance
    teleport_gripper(data, ids, start, rotation)
    place_fingers(data, ids, min(grasp.width + opening_margin, ids.max_opening))
    mujoco.mj_forward(model, data)
    if recorder is not None:
        recorder(model, data, "pregrasp")
    force, other, depth = _worst_contact(model, data, ids.geoms)
    if other >= 0:
        park_gripper(model, data, gripper)  # nothing was simulated: leave the scene as it was
        return result(False, f"gripper collided with {_geom_label(model, other)} at the "
                             f"pre-grasp pose (penetration {depth * 1000:.1f} mm)")

    # 2. Approach along the approach direction.
    n = run.steps_for(pregrasp_distance / approach_speed)
    for k in range(1, n + 1):
        set_gripper_target(data, ids, start + (center - start) * _min_jerk(k / n))
        run.step("approach")
        force, other, _ = _worst_contact(model, data, ids.geoms)
        if force > max_contact_force:
            return result(False, f"gripper collided with {_geom_label(model, other)} during the "
                                 f"approach ({force:.0f} N)")

    # 3. Close: ramp the commanded opening down past zero (the servo then squeezes with the full
    # grip force on whatever is in between), then wait until the fingers stop.
    open_width = gripper_opening(data, ids)
    n = run.steps_for((open_width - _SQUEEZE_OPENING) / closing_speed)
    for k in range(1, n + 1):
        set_opening(data, ids, open_width + (_SQUEEZE_OPENING - open_width) * k / n)
        run.step("close")
    still = 0
    for _ in range(run.steps_for(close_seconds)):
        run.step("close")
        speed = max(abs(float(data.qvel[d])) for d in ids.dof)
        still = still + 1 if speed < _STOPPED_SPEED else 0
        if still >= run.steps_for(_STOPPED_FOR):
            break
    opening = gripper_opening(data, ids)
    touching = _fingers_touching(data, ids, object_geoms)

    # 4. Lift straight up.
    n = run.steps_for(lift_seconds)
    up = np.array([0.0, 0.0, lift])
    for k in range(1, n + 1):
        set_gripper_target(data, ids, center + up * _min_jerk(k / n))
        run.step("lift")

    # 5. Hold still.
    heights = [float(data.xpos[body, 2]) - z0]
    for _ in range(run.steps_for(hold_seconds)):
        run.step("hold")
        heights.append(float(data.xpos[body, 2]) - z0)
    min_hold = min(heights)
    if min_hold >= min_lift:
        return result(True, "lifted", min_hold, opening, touching)
    reason = "dropped" if heights[0] >= min_lift else "not lifted"
    if opening < _CLOSED_ON_NOTHING:
        reason += " (fingers closed on nothing)"
    elif touching < 2:
        reason += f" ({touching} finger(s) touched the object after closing)"
    else:
        reason += " (the object slipped between the fingers)"
    return result(False, reason, min_hold, opening, touching)


def _check_positive(**values: float) -> None:
    """Raise ValueError naming the first of ``values`` that is not a finite number > 0."""
    for key, value in values.items():
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{key} must be > 0, got {value}")


def _checked_rotation(grasp: Grasp) -> np.ndarray:
    """The grasp's gripper-to-world rotation, validated.

    Raises:
        ValueError: non-finite centre, or axis (nearly) parallel to the approach.
    """
    center = np.asarray(grasp.center, dtype=np.float64)
    axis = np.asarray(grasp.axis, dtype=np.float64)
    approach = np.asarray(grasp.approach, dtype=np.float64)
    if center.shape != (3,) or not np.all(np.isfinite(center)):
        raise ValueError(f"grasp centre must be 3 finite numbers, got {grasp.center!r}")
    na, nb = np.linalg.norm(axis), np.linalg.norm(approach)
    if not (na > 0 and nb > 0) or np.linalg.norm(np.cross(axis / na, approach / nb)) < 1e-3:
        raise ValueError(f"grasp axis {axis.tolist()} must be non-zero and not parallel to the "
                         f"approach {approach.tolist()}")
    return grasp.rotation()


__all__ = ["ExecutionResult", "Recorder", "execute_grasp", "object_body_id", "settle"]
