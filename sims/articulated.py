"""Capture an articulated scene at many joint configurations, holding out unseen ones for test.

The scene (declared ``<custom><text name="nerfbot_capture" data="articulated"/>``, e.g. the
built-in ``articulated`` cabinet) has hinge / slide joints with limits: those named by
``<custom><text name="nerfbot_joints">``, else all limited hinge and slide joints. A capture
never steps physics: for each configuration it sets the joint positions in ``qpos`` (the rest
at ``qpos0``), runs ``mj_forward`` and renders K views (:func:`sims.sequence.stratified_views`:
evenly spaced azimuths rotated at random per configuration, random elevations).

Configuration schedule (:func:`config_schedule`), per joint of span ``hi - lo``:

- training configurations fill the inner *training range* ``lo + train_range * span`` (default
  15 %..85 % of the span), stratified (a Latin hypercube: each joint's training range is cut into
  N equal bins and each bin gets one configuration);
- test configurations are new random configurations: a share ``1 - outside_fraction`` inside
  the training range (interpolation), the others with one or all joints *outside* it by at least
  ``margin * span`` (default 10 %: values in 0..5 % or 95..100 % of the span; extrapolation),
  cycling through which joints go out and to which side; the other joints stay inside.

Every frame carries ``joints`` {name: position} (radians / metres). The manifest lists
``moving_joints``, ``joint_bodies``, ``joint_info`` (type, axis, anchor, range, ...; see
:func:`sims.joints.joint_info`), ``part_bounds`` (the rigid parts and their rest bounds, see
:func:`sims.joints.rigid_parts`), ``joint_train_range`` {name: [lo, hi]}, ``body_rest_poses`` of
the moved bodies, and ``capture`` (with each test configuration and the joints it holds
outside the training range); ``time_varying`` is false. ``states.npz`` holds the body poses of
every configuration (see :func:`capture_articulated`).
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import mujoco
import numpy as np

from nerfbot.data.outputs import check_output_folder
from sims.capture import (View, _scene_source, set_lighting, check_views,
                          write_views)
from sims.joints import (JOINT_TYPES, body_rest_poses, joint_bodies, joint_id, joint_info,
                         rigid_parts, set_joints)
from sims.manifest import scene_manifest
from sims.rollout import joint_name
from sims.sensor import DepthSensorModel
from sims.sequence import (SequenceRig, load_sequence_scene, custom_text, state_arrays,
                           stratified_views, union_bounds)

log = logging.getLogger(__name__)

DEFAULT_CONFIGS = 40
DEFAULT_TEST_CONFIGS = 8
DEFAULT_VIEWS_PER_CONFIG = 4
#: Training configurations stay within these fractions of each joint's span.
DEFAULT_TRAIN_RANGE = (0.15, 0.85)
#: Extrapolating test configurations lie at least this fraction of the span outside it.
DEFAULT_MARGIN = 0.10
DEFAULT_OUTSIDE_FRACTION = 0.5
STATE_FILE = "states.npz"
#: Random configurations (besides the captured ones and the limit corners) the manifest bounds
#: are taken over.
_BOUNDS_SAMPLES = 64


def articulated_joints(model: mujoco.MjModel) -> list[str]:
    """The joints an articulated capture varies: ``<custom><text name="nerfbot_joints">`` (names
    separated by spaces), else every limited hinge / slide joint, in model order.

    Raises:
        ValueError: a listed joint is unknown, not hinge / slide, or unlimited; or no joint.
    """
    declared = custom_text(model, "nerfbot_joints")
    if declared:
        names = declared.split()
        for name in names:
            j = joint_id(model, name)
            kind = JOINT_TYPES[int(model.jnt_type[j])]
            if kind not in ("hinge", "slide"):
                raise ValueError(f"nerfbot_joints: joint '{name}' is a {kind} joint; an "
                                 "articulated capture varies hinge and slide joints")
            if not model.jnt_limited[j]:
                raise ValueError(f"nerfbot_joints: joint '{name}' has no range (limited=\"true\" "
                                 "range=\"LO HI\" in the MJCF)")
        return names
    names = [joint_name(model, j) for j in range(model.njnt)
             if JOINT_TYPES[int(model.jnt_type[j])] in ("hinge", "slide") and model.jnt_limited[j]]
    if not names:
        raise ValueError("the scene has no limited hinge or slide joint to articulate")
    return names


@dataclass
class ConfigSchedule:
    """Which joint configurations a capture renders.

    Attributes:
        joints: the varied joints, in column order.
        limits: (J, 2) joint limits [lo, hi] (radians / metres).
        train_range: (J, 2) training range [lo, hi] of each joint.
        train: (N, J) training configurations, inside ``train_range``.
        test: (M, J) test configurations.
        test_outside: per test configuration, the joints outside the training range (each by
            at least ``margin`` of its span); [] for interpolating configurations.
        margin: that fraction.
    """

    joints: list[str]
    limits: np.ndarray
    train_range: np.ndarray
    train: np.ndarray
    test: np.ndarray
    test_outside: list[list[str]]
    margin: float

    def as_dicts(self, configs: np.ndarray) -> list[dict[str, float]]:
        """Rows of ``configs`` (K, J) as {joint name: position} dicts."""
        return [{n: float(v) for n, v in zip(self.joints, row)} for row in configs]


def config_schedule(model: mujoco.MjModel, joints: Sequence[str], n_train: int, n_test: int,
                    train_range: tuple[float, float] = DEFAULT_TRAIN_RANGE,
                    margin: float = DEFAULT_MARGIN,
                    outside_fraction: float = DEFAULT_OUTSIDE_FRACTION,
                    seed: int = 0) -> ConfigSchedule:
    """Training and test configurations of ``joints`` (see the module docstring).

    ``round(n_test * outside_fraction)`` test configurations extrapolate (at least one when
    ``n_test > 0`` and ``outside_fraction > 0``). Extrapolating configuration ``k`` moves the
    joints of pattern ``k mod P`` outside, where the patterns are each joint alone, then all
    joints together; joint ``i`` goes below the training range when ``k + i`` is even, else
    above it.

    Raises:
        ValueError: ``n_train < 1``, ``n_test < 0``, a training range outside [margin,
            1 - margin] (no room to extrapolate by ``margin``) or empty, or a fraction outside
            [0, 1].
    """
    if n_train < 1 or n_test < 0:
        raise ValueError(f"need >= 1 training and >= 0 test configurations, got {n_train}, "
                         f"{n_test}")
    f_lo, f_hi = (float(v) for v in train_range)
    if not 0.0 <= f_lo < f_hi <= 1.0:
        raise ValueError(f"training range must be fractions 0 <= lo < hi <= 1 of each joint's "
                         f"span, got {train_range}")
    if not 0.0 <= outside_fraction <= 1.0 or not margin >= 0.0:
        raise ValueError(f"outside_fraction must be in [0, 1] and margin >= 0, got "
                         f"{outside_fraction}, {margin}")
    n_out = int(round(n_test * outside_fraction))
    if n_test > 0 and outside_fraction > 0.0:
        n_out = max(n_out, 1)
    if n_out and (f_lo < margin - 1e-12 or f_hi > 1.0 - margin + 1e-12):
        raise ValueError(f"training range {train_range} leaves less than {margin:.0%} of the "
                         "span on each side for test configurations outside it")
    limits = np.array([model.jnt_range[joint_id(model, n)] for n in joints], dtype=np.float64)
    span = limits[:, 1] - limits[:, 0]
    inner = np.stack([limits[:, 0] + f_lo * span, limits[:, 0] + f_hi * span], axis=1)
    n_joints = len(joints)

    rng = np.random.default_rng([int(seed), 0])
    strata = (np.stack([rng.permutation(n_train) for _ in range(n_joints)], axis=1)
              + rng.uniform(0.0, 1.0, (n_train, n_joints))) / n_train
    train = inner[:, 0] + strata * (inner[:, 1] - inner[:, 0])

    rng = np.random.default_rng([int(seed), 1])
    test = inner[:, 0] + rng.uniform(0.0, 1.0, (n_test, n_joints)) * (inner[:, 1] - inner[:, 0])
    patterns = [[i] for i in range(n_joints)] + ([list(range(n_joints))] if n_joints > 1 else [])
    outside: list[list[str]] = [[] for _ in range(n_test)]
    for k in range(n_out):
        row = n_test - n_out + k  # the extrapolating configurations come last
        for i in patterns[k % len(patterns)]:
            u = rng.uniform(0.0, 1.0)
            if (k + i) % 2 == 0:  # below: [lo, lo + (f_lo - margin) * span]
                test[row, i] = limits[i, 0] + u * (f_lo - margin) * span[i]
            else:                 # above: [lo + (f_hi + margin) * span, hi]
                test[row, i] = limits[i, 1] - u * (1.0 - f_hi - margin) * span[i]
            outside[row].append(joints[i])
    return ConfigSchedule(list(joints), limits, inner, train, test, outside, float(margin))


def _bounds_configs(schedule: ConfigSchedule, seed: int) -> np.ndarray:
    """Captured configurations, every corner of the joint limits, and random ones within them."""
    corners = np.array(list(itertools.product(*schedule.limits)), dtype=np.float64)
    rng = np.random.default_rng([int(seed), 2])
    lo, hi = schedule.limits[:, 0], schedule.limits[:, 1]
    samples = lo + rng.uniform(0.0, 1.0, (_BOUNDS_SAMPLES, len(lo))) * (hi - lo)
    return np.concatenate([schedule.train, schedule.test, corners, samples])


def capture_articulated(scene: str | Path, rig: SequenceRig, out_dir: Path,
                        configs: int = DEFAULT_CONFIGS, test_configs: int = DEFAULT_TEST_CONFIGS,
                        train_range: tuple[float, float] = DEFAULT_TRAIN_RANGE,
                        margin: float = DEFAULT_MARGIN,
                        outside_fraction: float = DEFAULT_OUTSIDE_FRACTION,
                        joints: Optional[Sequence[str]] = None, fmt: str = "nerfstudio",
                        manifest: bool = True, progress: bool = True,
                        sensor: Optional[DepthSensorModel] = None,
                        overwrite: bool = False, headlight: bool = False) -> Path:
    """Render ``scene`` at ``configs`` training and ``test_configs`` test joint configurations.

    Args:
        scene: an articulated scene: built-in name (``"articulated"``) or MJCF path.
        rig: the cameras (:func:`sims.sequence.sequence_rig`): ``rig.views_per_step`` views per
            configuration (monocular: 1), fresh for every configuration; train and test
            configurations draw their views from independent random streams.
        out_dir: dataset folder to create (missing or empty), or with ``overwrite`` to
            replace (a dataset captured there before).
        configs, test_configs, train_range, margin, outside_fraction: see
            :func:`config_schedule` (``rig.seed`` seeds it).
        joints: the joints to vary (default :func:`articulated_joints`).
        fmt, manifest, progress, sensor, overwrite, headlight: as :func:`sims.capture.capture`.

    Returns:
        ``out_dir`` (absolute). Frames are written training configurations first, then test
        ones, the views of one configuration together; each frame carries ``joints``.
        ``states.npz``: per configuration ``c`` (train then test) ``joint_names`` (J,),
        ``joint_values`` (C, J), ``is_test`` (C,), ``qpos`` (C, nq), ``body_names`` (nbody,),
        ``body_pos`` (C, nbody, 3), ``body_quat`` (C, nbody, 4) (world, w-x-y-z); per frame
        ``state_of_frame`` (F,).

    Raises:
        ValueError: not an articulated scene or bad parameters (before anything is written);
            FileExistsError / RuntimeError as :func:`sims.capture.capture`.
    """
    model, data, name = load_sequence_scene(scene, "articulated")
    check_output_folder(out_dir, "dataset", overwrite=overwrite)  # before the long part
    lighting = set_lighting(model, headlight)
    names = list(joints) if joints is not None else articulated_joints(model)
    schedule = config_schedule(model, names, configs, test_configs, train_range, margin,
                               outside_fraction, rig.seed)

    all_configs = np.concatenate([schedule.train, schedule.test])
    is_test = np.array([False] * configs + [True] * test_configs)
    qpos = np.stack([set_joints(model, model.qpos0, d) for d in schedule.as_dicts(all_configs)])
    poses = stratified_views(rig, configs, stream=0) + stratified_views(rig, test_configs,
                                                                        stream=1)
    views, state_of_frame = [], []
    for c, values in enumerate(schedule.as_dicts(all_configs)):
        split = "test" if is_test[c] else "train"
        index = c - configs if is_test[c] else c
        for j, pose in enumerate(poses[c]):
            views.append(View(split, pose, qpos=qpos[c], joints=values,
                              where=f"{split} configuration {index} view {j}"))
            state_of_frame.append(c)
    check_views(views)

    data.qpos[:] = model.qpos0
    mujoco.mj_forward(model, data)
    meta = scene_manifest(model, data, name, _scene_source(scene), moving_joints=names,
                          time_varying=False)
    bounds_q = np.stack([set_joints(model, model.qpos0, d)
                         for d in schedule.as_dicts(_bounds_configs(schedule, rig.seed))])
    meta["bounds"] = union_bounds(model, data, bounds_q).tolist()
    meta["lighting"] = lighting
    bodies = joint_bodies(model, names)
    meta["joint_bodies"] = bodies
    meta["joint_info"] = joint_info(model, names)
    meta["part_bounds"] = rigid_parts(model, names)
    meta["joint_train_range"] = {n: schedule.train_range[i].tolist() for i, n in enumerate(names)}
    meta["body_rest_poses"] = body_rest_poses(model, sorted({b for v in bodies.values()
                                                             for b in v}))
    meta["capture"] = {
        "kind": "articulated", "rig": rig.kind, "views_per_frame": rig.views_per_step,
        "configs": configs, "test_configs": test_configs,
        "train_range_fraction": [float(v) for v in train_range],
        "extrapolation_margin": float(margin),
        "test": [{"joints": d, "outside_train_range": out}
                 for d, out in zip(schedule.as_dicts(schedule.test), schedule.test_outside)],
        "state_file": STATE_FILE,
    }
    states = state_arrays(model, data, qpos)
    states.update(joint_names=np.array(names), joint_values=all_configs, is_test=is_test,
                  state_of_frame=np.asarray(state_of_frame, dtype=np.int64))

    out = write_views(model, data, views, out_dir, rig.width, rig.height, rig.fov_deg, meta,
                      fmt=fmt, manifest=manifest, progress=progress, sensor=sensor,
                      extra_files=lambda root: np.savez(root / STATE_FILE, **states),
                      overwrite=overwrite)
    log.info("wrote %d views of '%s' at %d training and %d test configurations to %s",
             len(views), name, configs, test_configs, out)
    return out
