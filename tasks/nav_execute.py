"""Drive the mobile base along a planned path in MuJoCo physics.

A pure-pursuit controller: every control period it takes the robot's pose (true, or estimated
by a localiser from the robot's own camera and carried forward by the commanded velocity in
between), steers the base towards the path point one look-ahead distance ahead, slows down
before the goal and turns the camera to face the direction of travel. Contacts between the
base and anything but the floor are read from MuJoCo each physics step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import mujoco
import numpy as np

from sims.robot import RobotIds, command_velocity, robot_contacts, robot_pose
from tasks.nav_planner import resample

#: The path is followed through points this far apart, metres.
FOLLOW_SPACING = 0.02

#: A pose source: called with (model, data, predicted pose (3,)) every ``localise_every``
#: control periods; returns the pose estimate (x, y, yaw) to steer by.
PoseSource = Callable[[mujoco.MjModel, mujoco.MjData, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class DriveConfig:
    """Controller settings.

    Attributes:
        speed: cruise speed, m/s.
        lookahead: pure-pursuit look-ahead distance along the path, metres.
        control_period: seconds between control updates.
        goal_tolerance: the drive ends when the robot is this close to the goal, metres.
        yaw_gain: yaw-rate command per radian of heading error, 1/s.
        timeout_factor: the drive gives up after this many times the path's length at cruise
            speed (plus 5 s).
        localise_every: control periods between pose estimates (poses in between are
            predicted from the commanded velocities).
        gate_distance, gate_angle: an estimate farther than this from the predicted pose
            (metres, or degrees of yaw) is rejected and the prediction kept, as a Kalman
            filter's innovation gate would; 0 accepts every estimate.
        gate_patience: after this many rejected estimates in a row the next one is accepted
            whatever its distance (the prediction may be the wrong one).
    """

    speed: float = 0.4
    lookahead: float = 0.25
    control_period: float = 0.05
    goal_tolerance: float = 0.05
    yaw_gain: float = 2.0
    timeout_factor: float = 3.0
    localise_every: int = 10
    gate_distance: float = 0.15
    gate_angle: float = 10.0
    gate_patience: int = 3


@dataclass
class DriveLog:
    """What happened: the true poses at each control update (K, 3), the estimates steered
    by (K, 3), the geom names touched (each contact episode once), seconds simulated,
    whether the goal was reached, and how many estimates the gate rejected."""

    poses: np.ndarray
    estimates: np.ndarray
    contacts: list[str] = field(default_factory=list)
    seconds: float = 0.0
    reached: bool = False
    rejected: int = 0

    @property
    def collided(self) -> bool:
        return bool(self.contacts)

    def estimate_errors(self, every: int) -> dict:
        """Median and largest position error (metres) and median yaw error (degrees) of the
        estimates steered by, at the control updates where they were made (every ``every``-th,
        :attr:`DriveConfig.localise_every`); empty for a drive without updates."""
        if not len(self.poses):
            return {}
        est, true = self.estimates[::every], self.poses[::every]
        dxy = np.linalg.norm(est[:, :2] - true[:, :2], axis=1)
        dyaw = np.degrees(np.abs((est[:, 2] - true[:, 2] + np.pi) % (2 * np.pi) - np.pi))
        return {"estimate_error_m_median": float(np.median(dxy)),
                "estimate_error_m_max": float(dxy.max()),
                "estimate_error_deg_median": float(np.median(dyaw))}


def _lookahead_point(path: np.ndarray, xy: np.ndarray, lookahead: float,
                     progress: int) -> tuple[np.ndarray, int]:
    """The point ``lookahead`` metres along the path beyond the path vertex nearest to ``xy``
    (searching from ``progress`` on, so the robot never turns back); returns it and the new
    progress index."""
    d = np.linalg.norm(path[progress:] - xy, axis=1)
    nearest = progress + int(np.argmin(d))
    remaining = lookahead
    k = nearest
    point = path[k]
    while k < len(path) - 1:
        seg = path[k + 1] - path[k]
        length = float(np.linalg.norm(seg))
        if length >= remaining:
            point = path[k] + seg * (remaining / max(length, 1e-9))
            break
        remaining -= length
        k += 1
        point = path[k]
    return point, nearest


def within_gate(estimate: np.ndarray, predicted: np.ndarray, config: DriveConfig) -> bool:
    """True when the estimate (x, y, yaw) is close enough to the predicted pose to be used
    (:attr:`DriveConfig.gate_distance`, :attr:`DriveConfig.gate_angle`; 0 disables a test)."""
    dxy = float(np.linalg.norm(np.asarray(estimate[:2]) - predicted[:2]))
    dyaw = abs(math.degrees((estimate[2] - predicted[2] + math.pi) % (2 * math.pi) - math.pi))
    return ((config.gate_distance <= 0 or dxy <= config.gate_distance)
            and (config.gate_angle <= 0 or dyaw <= config.gate_angle))


def drive(model: mujoco.MjModel, data: mujoco.MjData, ids: RobotIds, path: np.ndarray,
          config: DriveConfig = DriveConfig(), pose_source: Optional[PoseSource] = None,
          floor_geoms: tuple[int, ...] = ()) -> DriveLog:
    """Follow ``path`` (N, 2) world points from the robot's current pose to the path's last
    point. ``pose_source`` None steers by the true pose; otherwise by its estimates that pass
    the gate (:func:`within_gate`), predicted forward by the commanded velocity between them.
    Contacts with geoms other than ``floor_geoms`` are logged by name."""
    path = resample(np.asarray(path, float), FOLLOW_SPACING)
    goal = path[-1]
    length = float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())
    timeout = config.timeout_factor * length / config.speed + 5.0
    substeps = max(int(round(config.control_period / model.opt.timestep)), 1)
    period = substeps * model.opt.timestep
    estimate = robot_pose(data, ids)
    command = np.zeros(3)
    # the actuators clip commands to their control ranges: predict with what they apply
    limited = model.actuator_ctrllimited[list(ids.actuators)].astype(bool)
    ranges = model.actuator_ctrlrange[list(ids.actuators)]
    low = np.where(limited, ranges[:, 0], -np.inf)
    high = np.where(limited, ranges[:, 1], np.inf)
    poses, estimates, touched = [], [], []
    progress, t, update, rejected, in_a_row = 0, 0.0, 0, 0, 0
    reached = False
    in_contact: set[int] = set()
    while t < timeout:
        true = robot_pose(data, ids)
        if pose_source is None:
            estimate = true
        elif update % config.localise_every == 0:
            measured = np.asarray(pose_source(model, data, estimate), float)
            if in_a_row >= config.gate_patience or within_gate(measured, estimate, config):
                estimate, in_a_row = measured, 0
            else:
                rejected, in_a_row = rejected + 1, in_a_row + 1
        poses.append(true)
        estimates.append(estimate.copy())
        if np.linalg.norm(estimate[:2] - goal) <= config.goal_tolerance:
            reached = np.linalg.norm(true[:2] - goal) <= 2 * config.goal_tolerance
            break
        target, progress = _lookahead_point(path, estimate[:2], config.lookahead, progress)
        to_target = target - estimate[:2]
        dist_goal = float(np.linalg.norm(goal - estimate[:2]))
        speed = min(config.speed, 1.5 * dist_goal + 0.05)
        direction = to_target / max(float(np.linalg.norm(to_target)), 1e-9)
        heading = np.arctan2(direction[1], direction[0])
        yaw_err = (heading - estimate[2] + np.pi) % (2 * np.pi) - np.pi
        command = np.array([*(speed * direction), config.yaw_gain * yaw_err])
        command_velocity(data, ids, *command)
        for _ in range(substeps):
            mujoco.mj_step(model, data)
            now = set(robot_contacts(model, data, ids, floor_geoms))
            for g in now - in_contact:
                touched.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or str(g))
            in_contact = now
        t += period
        update += 1
        # predict the estimate forward by what was commanded (odometry)
        estimate = estimate + np.clip(command, low, high) * period
    command_velocity(data, ids, 0.0, 0.0, 0.0)
    return DriveLog(np.asarray(poses), np.asarray(estimates), touched, t, reached, rejected)
