"""Capture a dynamic scene over time: a physics rollout rendered by a monocular or multi-view rig.

The scene (declared ``<custom><text name="nerfbot_capture" data="dynamic"/>``, e.g. the built-in
``dynamic``) is stepped from its ``init`` keyframe for ``duration`` seconds
(:func:`sims.rollout.rollout`) and recorded at ``frames`` evenly spaced time steps. Each time
step is rendered by:

- ``monocular``: one camera, moving along a smooth spiral around the scene (or, with
  ``camera_path="random"``, jumping to a random view each step as in D-NeRF's synthetic scenes);
- ``multiview``: the same K cameras every step (a fixed multi-camera rig).

Every frame carries ``time`` = step / last step in [0, 1]. Held-out time steps form the test
split (:func:`held_out_steps`: every ``test_every``-th step, starting at ``test_every // 2``, so
they are interior times never seen in training; a monocular camera at a held-out time is also a
view never seen in training). The manifest says ``time_varying: true`` and lists the
``moving_joints`` (joints that moved more than :data:`MOTION_THRESHOLD`), ``joint_bodies`` (joint
-> the bodies it moves), ``moving_bodies`` (each of those bodies -> the ids of its own geoms,
for reading the segmentation per rigid body), ``joint_info`` (see
:func:`sims.joints.joint_info`) and ``capture`` (how it was captured); its ``bounds`` cover
the content over the whole rollout. ``states.npz`` next to ``transforms.json`` holds the
recorded states (see :func:`capture_dynamic`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional

import numpy as np

from nerfbot.data.outputs import check_output_folder
from sims.capture import (View, _scene_source, set_lighting, check_views,
                          write_views)
from sims.joints import body_geoms, joint_bodies, joint_info
from sims.manifest import scene_manifest
from sims.rollout import moving_joints, reset_to_initial_state, rollout
from sims.sensor import DepthSensorModel
from sims.sequence import (SequenceRig, load_sequence_scene, custom_numeric, fixed_ring, spiral_path,
                           state_arrays, stratified_views, union_bounds)

log = logging.getLogger(__name__)

DEFAULT_FRAMES = 100
DEFAULT_TEST_EVERY = 8
#: Rollout length of scenes that do not declare ``nerfbot_duration``, seconds.
DEFAULT_DURATION_S = 2.5
#: A joint "moves" when it travels more than this (metres, or radians) over the rollout.
MOTION_THRESHOLD = 1e-3
#: File of the recorded states, next to the transforms JSON.
STATE_FILE = "states.npz"


def held_out_steps(n_steps: int, test_every: int) -> list[int]:
    """Test time steps: ``test_every // 2, test_every // 2 + test_every, ...`` below ``n_steps``
    ([] when ``test_every`` is 0). Neither the first nor (for ``test_every >= 2``) usually the
    last step is held out, so test times lie between training times.

    Raises:
        ValueError: ``test_every`` is 1 or negative (no training steps), or nothing would be
            left for training.
    """
    if test_every == 0:
        return []
    if test_every < 2:
        raise ValueError(f"test_every must be 0 (no test split) or >= 2, got {test_every}")
    steps = list(range(test_every // 2, n_steps, test_every))
    if len(steps) >= n_steps:
        raise ValueError(f"{n_steps} time steps leave none for training with test_every "
                         f"{test_every}")
    return steps


def scene_duration(model) -> float:
    """The scene's declared rollout length (``<custom><numeric name="nerfbot_duration">``,
    seconds), else :data:`DEFAULT_DURATION_S`."""
    declared = custom_numeric(model, "nerfbot_duration")
    return float(declared[0]) if declared else DEFAULT_DURATION_S


def step_poses(rig: SequenceRig, n_steps: int) -> list[list[np.ndarray]]:
    """Per time step, the c2w (4, 4) poses of the rig's cameras (1 for monocular)."""
    if rig.kind == "monocular":
        if rig.camera_path == "random":
            return stratified_views(rig, n_steps, stream=0)
        return [[pose] for pose in spiral_path(rig, n_steps)]
    ring = fixed_ring(rig)
    return [list(ring) for _ in range(n_steps)]


def capture_dynamic(scene: str | Path, rig: SequenceRig, out_dir: Path,
                    frames: int = DEFAULT_FRAMES, duration_s: Optional[float] = None,
                    test_every: int = DEFAULT_TEST_EVERY, fmt: str = "nerfstudio",
                    manifest: bool = True, progress: bool = True,
                    sensor: Optional[DepthSensorModel] = None, overwrite: bool = False,
                    headlight: bool = False) -> Path:
    """Roll the physics of ``scene`` out and render it over time to ``out_dir``.

    Args:
        scene: a dynamic scene: built-in name (``"dynamic"``) or MJCF path.
        rig: the cameras (:func:`sims.sequence.sequence_rig`); monocular or multiview.
        out_dir: dataset folder to create (missing or empty), or with ``overwrite`` to
            replace (a dataset captured there before).
        frames: time steps (>= 2); the dataset has ``frames * rig.views_per_step`` images.
        duration_s: simulated seconds (default: the scene's ``nerfbot_duration``).
        test_every: hold out every ``test_every``-th time step for the test split (0: none).
        fmt, manifest, progress, sensor, overwrite, headlight: as :func:`sims.capture.capture`.

    Returns:
        ``out_dir`` (absolute). Frames are written in time order, the views of one step
        together; each carries ``time`` in [0, 1]. ``states.npz`` holds, per time step ``s``:
        ``time`` (S,) normalised, ``time_s`` (S,) seconds, ``qpos`` (S, nq), ``qvel`` (S, nv),
        ``body_names`` (nbody,), ``body_pos`` (S, nbody, 3) and ``body_quat`` (S, nbody, 4)
        (world, w-x-y-z), ``test_steps``; and per frame ``state_of_frame`` (F,).

    Raises:
        ValueError: not a dynamic scene, bad parameters, or a diverging rollout (before
            anything is written); FileExistsError / RuntimeError as :func:`sims.capture.capture`.
    """
    model, data, name = load_sequence_scene(scene, "dynamic")
    check_output_folder(out_dir, "dataset", overwrite=overwrite)  # before the long part
    lighting = set_lighting(model, headlight)
    duration = scene_duration(model) if duration_s is None else float(duration_s)
    test_steps = held_out_steps(frames, test_every)
    roll = rollout(model, data, duration, frames)

    per_step = step_poses(rig, frames)
    held_out = set(test_steps)
    views, state_of_frame = [], []
    for s in range(frames):
        split = "test" if s in held_out else "train"
        for j, pose in enumerate(per_step[s]):
            views.append(View(split, pose, qpos=roll.qpos[s], time=float(roll.time[s]),
                              where=f"time step {s} view {j}"))
            state_of_frame.append(s)
    check_views(views)

    moving = moving_joints(model, roll.qpos, MOTION_THRESHOLD)
    reset_to_initial_state(model, data)
    meta = scene_manifest(model, data, name, _scene_source(scene), moving_joints=moving,
                          time_varying=True)
    meta["bounds"] = union_bounds(model, data, roll.qpos).tolist()
    meta["lighting"] = lighting
    meta["joint_bodies"] = joint_bodies(model, moving)
    meta["moving_bodies"] = body_geoms(
        model, sorted({b for bodies in meta["joint_bodies"].values() for b in bodies}))
    meta["joint_info"] = joint_info(model, moving)
    meta["capture"] = {
        "kind": "dynamic", "rig": rig.kind, "views_per_frame": rig.views_per_step,
        "camera_path": rig.camera_path if rig.kind == "monocular" else "fixed",
        "frames": frames, "test_every": test_every, "test_steps": test_steps,
        "duration_s": roll.duration_s, "timestep_s": float(model.opt.timestep),
        "state_file": STATE_FILE,
    }
    states = state_arrays(model, data, roll.qpos)
    states.update(time=roll.time, time_s=roll.time_s, qvel=roll.qvel,
                  test_steps=np.asarray(test_steps, dtype=np.int64),
                  state_of_frame=np.asarray(state_of_frame, dtype=np.int64))

    out = write_views(model, data, views, out_dir, rig.width, rig.height, rig.fov_deg, meta,
                      fmt=fmt, manifest=manifest, progress=progress, sensor=sensor,
                      extra_files=lambda root: np.savez(root / STATE_FILE, **states),
                      overwrite=overwrite)
    n_test = sum(1 for v in views if v.split == "test")
    log.info("wrote %d views (%d train, %d test) of '%s' over %d time steps to %s", len(views),
             len(views) - n_test, n_test, name, frames, out)
    return out
