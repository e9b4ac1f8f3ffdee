"""Deterministic physics rollouts of a MuJoCo scene, recorded at evenly spaced times.

A rollout starts from the model's keyframe named :data:`INIT_KEY` (``"init"``) when it has one,
else from the model's default state (``qpos0``, zero velocity), and steps the physics with the
model's own timestep. Recording times are whole numbers of steps, so the normalised time of
snapshot ``i`` is exactly ``steps[i] / steps[-1]`` in [0, 1]. MuJoCo is deterministic for a given
model, build and machine, so the same call gives the same snapshots.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

#: Name of the keyframe a rollout starts from, when the model has one.
INIT_KEY = "init"


@dataclass
class Rollout:
    """States recorded during one rollout.

    Attributes:
        steps: (N,) int64 physics step index of each snapshot (first 0, last = total steps).
        time_s: (N,) float64 simulated time of each snapshot, seconds.
        time: (N,) float64 normalised time ``steps / steps[-1]`` in [0, 1].
        qpos: (N, nq) float64 joint positions of each snapshot.
        qvel: (N, nv) float64 joint velocities of each snapshot.
        duration_s: simulated duration, seconds (``steps[-1] * timestep``).
    """

    steps: np.ndarray
    time_s: np.ndarray
    time: np.ndarray
    qpos: np.ndarray
    qvel: np.ndarray
    duration_s: float

    def __len__(self) -> int:
        return len(self.steps)


def reset_to_initial_state(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Reset ``data`` to the :data:`INIT_KEY` keyframe if the model has one, else to ``qpos0``;
    then run ``mj_forward``."""
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, INIT_KEY)
    if key >= 0:
        mujoco.mj_resetDataKeyframe(model, data, key)
    else:
        mujoco.mj_resetData(model, data)
    mujoco.mj_forward(model, data)


def rollout(model: mujoco.MjModel, data: mujoco.MjData, duration_s: float,
            n_frames: int) -> Rollout:
    """Step the physics for ``duration_s`` seconds and record ``n_frames`` evenly spaced states.

    Args:
        model, data: the compiled scene; ``data`` is reset (see :func:`reset_to_initial_state`)
            and left at the final state.
        duration_s: simulated seconds (rounded to a whole number of ``model.opt.timestep``).
        n_frames: snapshots, >= 2; the first is the initial state, the last the final one.

    Raises:
        ValueError: ``n_frames < 2``, a non-positive duration, fewer steps than frames, or a
            state that went non-finite (MuJoCo's warnings are in the message).
    """
    if n_frames < 2:
        raise ValueError(f"a rollout needs at least 2 frames, got {n_frames}")
    if not duration_s > 0.0:
        raise ValueError(f"rollout duration must be positive, got {duration_s}")
    dt = float(model.opt.timestep)
    total = int(round(duration_s / dt))
    if total < n_frames - 1:
        raise ValueError(f"{n_frames} frames over {duration_s} s need a timestep below "
                         f"{duration_s / (n_frames - 1):.3g} s; the model's is {dt} s")
    steps = np.round(np.linspace(0, total, n_frames)).astype(np.int64)
    reset_to_initial_state(model, data)
    qpos = np.empty((n_frames, model.nq))
    qvel = np.empty((n_frames, model.nv))
    done = 0
    for i, target in enumerate(steps):
        while done < target:
            mujoco.mj_step(model, data)
            done += 1
        if not (np.all(np.isfinite(data.qpos)) and np.all(np.isfinite(data.qvel))):
            raise ValueError(f"the rollout diverged by step {done} (t = {done * dt:.3f} s): "
                             f"non-finite state; MuJoCo warnings: {_warnings(data)}")
        qpos[i], qvel[i] = data.qpos, data.qvel
    return Rollout(steps=steps, time_s=steps * dt, time=steps / float(total), qpos=qpos,
                   qvel=qvel, duration_s=total * dt)


def _warnings(data: mujoco.MjData) -> str:
    names = [w.name for w in mujoco.mjtWarning if w.name != "mjNWARNING"]
    found = [f"{n} x{data.warning[i].number}" for i, n in enumerate(names)
             if i < len(data.warning) and data.warning[i].number > 0]
    return ", ".join(found) or "none"


def joint_motion(model: mujoco.MjModel, qpos: np.ndarray) -> dict[str, float]:
    """How far each joint moved over the snapshots ``qpos`` (N, nq), from the first snapshot.

    Returns joint name -> largest displacement: metres for slide joints and for the position
    part of free joints; radians for hinge joints and the rotation of ball / free joints (the
    largest of the two for a free joint, so metres and radians compare as "about 1 cm" ~
    "about 0.01 rad"). Unnamed joints are called ``joint_<id>``.
    """
    qpos = np.asarray(qpos, dtype=np.float64)
    out = {}
    for j in range(model.njnt):
        adr = int(model.jnt_qposadr[j])
        kind = model.jnt_type[j]
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            trans = np.linalg.norm(qpos[:, adr:adr + 3] - qpos[0, adr:adr + 3], axis=1).max()
            rot = _max_rotation(qpos[:, adr + 3:adr + 7])
            moved = max(float(trans), rot)
        elif kind == mujoco.mjtJoint.mjJNT_BALL:
            moved = _max_rotation(qpos[:, adr:adr + 4])
        else:
            moved = float(np.abs(qpos[:, adr] - qpos[0, adr]).max())
        out[joint_name(model, j)] = moved
    return out


def _max_rotation(quats: np.ndarray) -> float:
    """Largest rotation angle (radians) of unit quaternions (N, 4) relative to the first."""
    q = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    dots = np.clip(np.abs(q @ q[0]), 0.0, 1.0)
    return float(2.0 * np.arccos(dots).max())


def joint_name(model: mujoco.MjModel, j: int) -> str:
    """Name of joint ``j``, or ``joint_<j>`` when unnamed."""
    return model.joint(j).name or f"joint_{j}"


def moving_joints(model: mujoco.MjModel, qpos: np.ndarray, threshold: float = 1e-3) -> list[str]:
    """Names of the joints whose :func:`joint_motion` exceeds ``threshold`` (metres / radians),
    in model order."""
    return [name for name, moved in joint_motion(model, qpos).items() if moved > threshold]
