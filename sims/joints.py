"""Joints of a MuJoCo scene described for manifests: which bodies each moves, and its kinematics.

Everything here is plain JSON-ready data (names, lists of floats). Angles are radians, lengths
metres, quaternions w-x-y-z, all in the world frame of the reference configuration ``qpos0``
(the joint positions of ``model.qpos0``: a hinge or slide joint at ``qpos0`` is "at rest").

Forward kinematics from a description (what a field with per-part motion needs): for a body
moved by a single hinge joint with world ``axis`` a and ``anchor`` p at rest, and joint value q,

    pose(q) = Translate(p) . Rotate(a, q - qpos0) . Translate(-p) . rest_pose

and for a slide joint ``pose(q) = Translate(a * (q - qpos0)) . rest_pose``. For chains, apply the
joints from the innermost (closest to the body) outwards, each about its own rest axis moved by
the joints outside it, as MuJoCo does.
"""

from __future__ import annotations

from typing import Iterable

import mujoco
import numpy as np

from sims.manifest import content_bounds, rendered_geoms
from sims.rollout import joint_name

JOINT_TYPES = {int(mujoco.mjtJoint.mjJNT_FREE): "free", int(mujoco.mjtJoint.mjJNT_BALL): "ball",
               int(mujoco.mjtJoint.mjJNT_SLIDE): "slide", int(mujoco.mjtJoint.mjJNT_HINGE): "hinge"}


def body_name(model: mujoco.MjModel, b: int) -> str:
    """Name of body ``b``, or ``body_<b>`` when unnamed."""
    return model.body(b).name or f"body_{b}"


def joint_id(model: mujoco.MjModel, name: str) -> int:
    """Id of the joint called ``name`` (or ``joint_<id>``); ValueError listing the joints."""
    j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if j < 0 and name.startswith("joint_") and name[6:].isdigit() and int(name[6:]) < model.njnt:
        j = int(name[6:])
    if j < 0:
        known = [joint_name(model, i) for i in range(model.njnt)]
        raise ValueError(f"the model has no joint '{name}' (joints: {', '.join(known) or 'none'})")
    return j


def subtree_bodies(model: mujoco.MjModel, root: int) -> list[int]:
    """Body ``root`` and all its descendants, in model (depth-first) order."""
    inside = {root}
    for b in range(root + 1, model.nbody):  # parents always precede their children
        if int(model.body_parentid[b]) in inside:
            inside.add(b)
    return sorted(inside)


def joint_bodies(model: mujoco.MjModel, names: Iterable[str]) -> dict[str, list[str]]:
    """Joint name -> names of the bodies it moves: the joint's body and its descendants."""
    out = {}
    for name in names:
        body = int(model.jnt_bodyid[joint_id(model, name)])
        out[str(name)] = [body_name(model, b) for b in subtree_bodies(model, body)]
    return out


def body_geoms(model: mujoco.MjModel, bodies: Iterable[str]) -> dict[str, list[int]]:
    """Body name -> ids of the geoms attached to that body itself (not its descendants), in
    model order; bodies without geoms are left out."""
    out = {}
    for name in bodies:
        b = next(i for i in range(model.nbody) if body_name(model, i) == name)
        ids = [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) == b]
        if ids:
            out[str(name)] = ids
    return out


def joint_range(model: mujoco.MjModel, name: str) -> tuple[float, float] | None:
    """(lo, hi) limits of a hinge / slide joint (radians / metres), None if it is unlimited."""
    j = joint_id(model, name)
    if not model.jnt_limited[j]:
        return None
    lo, hi = (float(v) for v in model.jnt_range[j])
    return lo, hi


def _rest_data(model: mujoco.MjModel) -> mujoco.MjData:
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    mujoco.mj_kinematics(model, data)
    return data


def joint_info(model: mujoco.MjModel, names: Iterable[str]) -> dict[str, dict]:
    """Joint name -> kinematic description at the reference configuration ``qpos0``.

    Keys: ``type`` ("hinge", "slide", "ball", "free"); ``body`` (the body it moves directly) and
    ``parent`` (that body's parent); ``bodies`` (see :func:`joint_bodies`); ``qpos0`` (the joint's
    rest position: a float for hinge / slide, a list for ball / free); for hinge / slide also
    ``axis`` and ``anchor`` (world, at rest), ``axis_local`` and ``pos_local`` (in the body
    frame, as in the MJCF), and ``range`` ([lo, hi], or null when unlimited).
    """
    rest = _rest_data(model)
    out = {}
    for name in names:
        j = joint_id(model, name)
        kind = JOINT_TYPES[int(model.jnt_type[j])]
        body = int(model.jnt_bodyid[j])
        adr = int(model.jnt_qposadr[j])
        info = {"type": kind, "body": body_name(model, body),
                "parent": body_name(model, int(model.body_parentid[body])),
                "bodies": [body_name(model, b) for b in subtree_bodies(model, body)]}
        if kind in ("hinge", "slide"):
            info.update(qpos0=float(model.qpos0[adr]),
                        axis=rest.xaxis[j].tolist(), anchor=rest.xanchor[j].tolist(),
                        axis_local=model.jnt_axis[j].tolist(), pos_local=model.jnt_pos[j].tolist(),
                        range=list(joint_range(model, name)) if model.jnt_limited[j] else None)
        else:
            size = 7 if kind == "free" else 4
            info["qpos0"] = model.qpos0[adr:adr + size].tolist()
        out[str(name)] = info
    return out


def body_rest_poses(model: mujoco.MjModel, bodies: Iterable[str]) -> dict[str, dict]:
    """Body name -> {"pos": [x, y, z], "quat": [w, x, y, z]}: world pose at ``qpos0``."""
    rest = _rest_data(model)
    out = {}
    for name in bodies:
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if b < 0:
            raise ValueError(f"the model has no body '{name}'")
        out[str(name)] = {"pos": rest.xpos[b].tolist(), "quat": rest.xquat[b].tolist()}
    return out


def set_joints(model: mujoco.MjModel, qpos: np.ndarray, values: dict[str, float]) -> np.ndarray:
    """A copy of ``qpos`` (nq,) with the hinge / slide joints of ``values`` (name -> position)
    set; ValueError for other joint types or unknown names."""
    out = np.array(qpos, dtype=np.float64, copy=True)
    for name, value in values.items():
        j = joint_id(model, name)
        kind = JOINT_TYPES[int(model.jnt_type[j])]
        if kind not in ("hinge", "slide"):
            raise ValueError(f"joint '{name}' is a {kind} joint; only hinge and slide joints "
                             "take a single position")
        out[int(model.jnt_qposadr[j])] = float(value)
    return out


def rigid_parts(model: mujoco.MjModel, names: Iterable[str]) -> list[dict]:
    """The rigid parts the joints ``names`` define, for fields that move one sub-field per part.

    Bodies moved by the same set of these joints form one part. Each part is a dict with
    ``joints`` (the joints that move it, outermost first: apply the innermost first to go from
    the rest pose to the current one), ``bodies`` and ``bounds`` [[min], [max]]: the world AABB of
    its rendered geoms at the rest configuration ``qpos0`` (metres). Bodies no joint moves (the
    static part) are not listed. Parts without rendered geoms are dropped.
    """
    names = [str(n) for n in names]
    moved = {n: set(joint_bodies(model, [n])[n]) for n in names}
    # outer joints move more bodies than the joints nested inside them
    order = sorted(names, key=lambda n: -len(moved[n]))
    groups: dict[tuple, list[str]] = {}
    for b in range(model.nbody):
        bname = body_name(model, b)
        chain = tuple(n for n in order if bname in moved[n])
        if chain:
            groups.setdefault(chain, []).append(bname)
    rest = _rest_data(model)
    drawn = {int(g.objid) for g in rendered_geoms(model, rest)}
    parts = []
    for chain, bodies in groups.items():
        ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, bn) for bn in bodies]
        geoms = [g for g in sorted(drawn) if int(model.geom_bodyid[g]) in ids]
        if not geoms:
            continue
        box = content_bounds(model, rest, geoms)
        parts.append({"joints": list(chain), "bodies": bodies, "bounds": box.tolist()})
    return parts
