"""A holonomic mobile base for MuJoCo scenes: a cylinder on the floor, velocity-controlled in the
world's x, y and yaw, with a forward-looking camera.

The base (:func:`add_robot`) is a body on three world-frame joints (slide x, slide y, hinge z)
driven by velocity actuators, so ``data.ctrl`` holds the commanded (vx m/s, vy m/s, yaw rate
rad/s) and physics makes it so, stopped by whatever it hits. Its collision body is one cylinder
(the planner's :class:`tasks.nav_map.RobotBody`), in geom group :data:`ROBOT_GEOM_GROUP`, which
captures do not draw, so the robot's camera never sees its own body. Contacts are MuJoCo's:
:func:`robot_contacts` lists every geom the body touches except the floor.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

#: Geom group of the robot's geoms: hidden by captures (MuJoCo draws groups 0-2 by default).
ROBOT_GEOM_GROUP = 3


@dataclass(frozen=True)
class RobotConfig:
    """Dimensions and drive of the base.

    Attributes:
        radius: cylinder radius, metres.
        height: cylinder height (its top above the floor), metres.
        mass: kg.
        camera_height: the camera's height above the floor, metres.
        camera_fovy: vertical field of view, degrees.
        camera_pitch: downward tilt of the camera, degrees.
        max_speed: largest commanded speed, m/s (actuator control range).
        max_yaw_rate: largest commanded yaw rate, rad/s.
        gain: velocity-servo gain per kg, 1/s (how fast the base reaches the commanded speed).
    """

    radius: float = 0.18
    height: float = 0.5
    mass: float = 10.0
    camera_height: float = 0.45
    camera_fovy: float = 70.0
    camera_pitch: float = 5.0
    max_speed: float = 0.6
    max_yaw_rate: float = 1.5
    gain: float = 20.0


@dataclass(frozen=True)
class RobotIds:
    """Indices of the robot's elements in a compiled model."""

    body: int
    geom: int
    qpos: tuple[int, int, int]    # x, y, yaw addresses in qpos
    dof: tuple[int, int, int]     # their addresses in qvel
    actuators: tuple[int, int, int]
    camera: int


def _names(name: str) -> dict[str, str]:
    return {"body": name, "geom": f"{name}_body", "x": f"{name}_x", "y": f"{name}_y",
            "yaw": f"{name}_yaw", "vx": f"{name}_vx", "vy": f"{name}_vy", "wz": f"{name}_wz",
            "camera": f"{name}_camera"}


def add_robot(spec: mujoco.MjSpec, config: RobotConfig = RobotConfig(), name: str = "robot",
                floor_z: float = 0.0) -> None:
    """Add the base called ``name`` to ``spec`` (in place), on the floor at ``floor_z``, at the
    world origin (place it with :func:`set_robot_pose`).

    Adds a body ``name`` with joints ``<name>_x``, ``<name>_y`` (slides along the world axes)
    and ``<name>_yaw`` (hinge about z), velocity actuators ``<name>_vx``, ``<name>_vy``,
    ``<name>_wz``, the cylinder geom ``<name>_body`` and the camera ``<name>_camera`` (looking
    along the body's +x, ``camera_pitch`` degrees down). Raises ValueError when a name is taken.
    """
    names = _names(name)
    taken = ({b.name for b in spec.bodies} | {g.name for g in spec.geoms}
             | {j.name for j in spec.joints} | {a.name for a in spec.actuators}
             | {c.name for c in spec.cameras})
    clash = sorted(set(names.values()) & taken)
    if clash:
        raise ValueError(f"cannot add robot: the scene already uses the name(s) {clash}")
    c = config
    body = spec.worldbody.add_body(name=names["body"], pos=[0.0, 0.0, floor_z])
    body.add_joint(name=names["x"], type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[1, 0, 0],
                   damping=0.0)
    body.add_joint(name=names["y"], type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 1, 0],
                   damping=0.0)
    body.add_joint(name=names["yaw"], type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 0, 1],
                   damping=0.0)
    body.add_geom(name=names["geom"], type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                  size=[c.radius, c.height / 2.0, 0.0], pos=[0.0, 0.0, c.height / 2.0 + 0.005],
                  mass=c.mass, rgba=[0.2, 0.3, 0.8, 1.0], group=ROBOT_GEOM_GROUP,
                  contype=1, conaffinity=1, friction=[0.0, 0.0, 0.0], condim=1)
    pitch = np.radians(c.camera_pitch)
    # camera frame: x right, y up, looking along -z; here looking along the body's +x
    forward = np.array([np.cos(pitch), 0.0, -np.sin(pitch)])
    up = np.array([np.sin(pitch), 0.0, np.cos(pitch)])
    right = np.cross(forward, up)
    body.add_camera(name=names["camera"], pos=[0.0, 0.0, c.camera_height],
                    fovy=c.camera_fovy, xyaxes=[*right, *up])
    gain = c.gain * c.mass
    for key, joint, limit in (("vx", "x", c.max_speed), ("vy", "y", c.max_speed),
                              ("wz", "yaw", c.max_yaw_rate)):
        act = spec.add_actuator(name=names[key], target=names[joint],
                                trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_velocity(kv=gain if key != "wz" else gain * c.radius ** 2)
        act.ctrllimited = True
        act.ctrlrange = [-limit, limit]


def robot_ids(model: mujoco.MjModel, name: str = "robot") -> RobotIds:
    """Indices of the robot ``name`` in ``model``; ValueError when it has none."""
    names = _names(name)
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, names["body"])
    if body < 0:
        raise ValueError(f"the model has no robot called {name!r} (see sims.robot.add_robot)")
    joints = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, names[k])
              for k in ("x", "y", "yaw")]
    return RobotIds(
        body=body, geom=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, names["geom"]),
        qpos=tuple(int(model.jnt_qposadr[j]) for j in joints),
        dof=tuple(int(model.jnt_dofadr[j]) for j in joints),
        actuators=tuple(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, names[k])
                        for k in ("vx", "vy", "wz")),
        camera=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, names["camera"]))


def set_robot_pose(data: mujoco.MjData, ids: RobotIds, x: float, y: float, yaw: float) -> None:
    """Place the robot at (x, y) metres, yaw radians, at rest (call ``mj_forward`` after)."""
    for adr, v in zip(ids.qpos, (x, y, yaw)):
        data.qpos[adr] = v
    for adr in ids.dof:
        data.qvel[adr] = 0.0


def robot_pose(data: mujoco.MjData, ids: RobotIds) -> np.ndarray:
    """(3,) the robot's (x, y metres, yaw radians)."""
    return np.array([data.qpos[a] for a in ids.qpos], float)


def command_velocity(data: mujoco.MjData, ids: RobotIds, vx: float, vy: float, wz: float) -> None:
    """Command world-frame velocity (m/s, m/s, rad/s); the actuators clip it to their ranges."""
    for adr, v in zip(ids.actuators, (vx, vy, wz)):
        data.ctrl[adr] = v


def robot_contacts(model: mujoco.MjModel, data: mujoco.MjData, ids: RobotIds,
                   ignore: tuple[int, ...] = ()) -> list[int]:
    """Geoms in contact with the robot's body now (penetration or touching), except the geoms
    in ``ignore`` (the floor)."""
    out = []
    for k in range(data.ncon):
        con = data.contact[k]
        if con.dist > 0:
            continue
        if con.geom1 == ids.geom and con.geom2 not in ignore:
            out.append(int(con.geom2))
        elif con.geom2 == ids.geom and con.geom1 not in ignore:
            out.append(int(con.geom1))
    return out
