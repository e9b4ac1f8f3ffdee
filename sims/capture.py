"""Capture a posed-image dataset (RGB, z-depth, segmentation, manifest) of a MuJoCo scene.

The dataset appears atomically: everything is written into a hidden sibling folder which is
renamed into place only once complete, so ``out_dir`` is either absent/unchanged (failure) or a
whole dataset (success). ``out_dir`` follows :mod:`nerfbot.data.outputs`: it must be missing or
empty, or a dataset nerfbot captured there before, replaced only with ``overwrite``
(``--overwrite``) and only if it holds nothing else; a user's folder or dataset is never touched.

:func:`write_views` renders and writes any list of :class:`View` (pose, split, optional scene
state, ``time`` and ``joints``) this way; :func:`capture` (static scenes), :mod:`sims.dynamic`
(over time) and :mod:`sims.articulated` (over joint configurations) build their views and call it.

Run as ``nerfbot capture --scene tabletop --views 60 --test-views 10 --out DIR`` (or
``python -m sims.cli`` with the same options).
"""

from __future__ import annotations

import logging
import os
import shutil
import uuid
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional, Sequence

import mujoco
import numpy as np
from tqdm import tqdm

from nerfbot.data.outputs import check_output_folder, write_marker
from nerfbot.data.spec import MAX_CAMERA_COORDINATE_M
from nerfbot.data.writers import FORMATS, open_writer
from sims.camera import CaptureCamera, nearest_rigid
from sims.manifest import scene_manifest
from sims.rigs import RigConfig, parse_size, rig_poses
from sims.scene import builtin_scenes, load_capture_model, parse_generated, resolve_scene
from sims.sensor import DepthSensorModel

log = logging.getLogger(__name__)

#: MuJoCo's default headlight diffuse and specular intensities (``<visual><headlight>``), given
#: to a scene without a moving headlight when a capture asks for one.
DEFAULT_HEADLIGHT_DIFFUSE = 0.4
DEFAULT_HEADLIGHT_SPECULAR = 0.5


def _check_destination(out_dir: Path, overwrite: bool) -> None:
    """FileExistsError unless ``out_dir`` may receive a dataset (:mod:`nerfbot.data.outputs`)."""
    check_output_folder(out_dir, "dataset", overwrite=overwrite)


def _move_into_place(tmp: Path, out_dir: Path) -> None:
    """Rename the finished ``tmp`` folder to ``out_dir``, replacing an empty folder or an old
    dataset there (checked by :func:`_check_destination`)."""
    if not out_dir.exists():
        os.rename(tmp, out_dir)
        return
    old = out_dir.with_name(f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}")
    os.rename(out_dir, old)
    try:
        os.rename(tmp, out_dir)
    except BaseException:
        os.rename(old, out_dir)
        raise
    shutil.rmtree(old, ignore_errors=True)


def set_lighting(model: mujoco.MjModel, headlight: bool = False) -> str:
    """Light the capture statically unless ``headlight``; returns the manifest's ``lighting``.

    MuJoCo's headlight (on in every MJCF unless it says otherwise) is attached to the viewing
    camera, so its diffuse and specular terms shade the scene differently from every viewpoint.
    By default they are turned off, its ambient term kept: "static". With ``headlight`` they
    stay, as a light mounted on a robot's camera would shade: "headlight"; a scene whose
    headlight has no diffuse or specular light (the built-in scenes and the zoo's) gets
    MuJoCo's default ones (:data:`DEFAULT_HEADLIGHT_DIFFUSE`, :data:`DEFAULT_HEADLIGHT_SPECULAR`).
    """
    head = model.vis.headlight
    moving = bool(head.active) and (np.any(np.asarray(head.diffuse) > 0)
                                    or np.any(np.asarray(head.specular) > 0))
    if headlight:
        if not moving:
            head.active = 1
            head.diffuse[:] = DEFAULT_HEADLIGHT_DIFFUSE
            head.specular[:] = DEFAULT_HEADLIGHT_SPECULAR
            log.warning("the scene's headlight has no diffuse or specular light: --headlight "
                        "gives it MuJoCo's default (diffuse %.1f, specular %.1f), which moves "
                        "with the camera", DEFAULT_HEADLIGHT_DIFFUSE, DEFAULT_HEADLIGHT_SPECULAR)
        else:
            log.warning("keeping the scene's headlight: its diffuse and specular light move "
                        "with the camera, so shading changes with the viewpoint")
        return "headlight"
    if not moving:
        return "static"
    head.diffuse[:] = 0.0
    head.specular[:] = 0.0
    log.info("static lighting: the headlight keeps only its ambient light, so shading does not "
             "follow the camera (--headlight keeps its diffuse and specular light)")
    return "static"


def _scene_source(scene) -> str:
    text = str(scene)
    if isinstance(scene, str) and "/" not in text and (
            text in builtin_scenes() or parse_generated(text) is not None):
        return f"builtin:{text}"
    return str(resolve_scene(scene))


@dataclass
class View:
    """One image to render: where the camera is, in which state the scene is, and its labels.

    Attributes:
        split: "train", "val" or "test".
        pose: (4, 4) c2w, OpenGL convention, metres.
        qpos: (nq,) joint positions to set (then ``mj_forward``) before rendering; None keeps
            the current state.
        time: the frame's ``time`` in [0, 1], or None.
        joints: the frame's ``joints`` (name -> position), or None.
        where: how error messages name the view.
    """

    split: str
    pose: np.ndarray
    qpos: Optional[np.ndarray] = None
    time: Optional[float] = None
    joints: Optional[dict] = None
    where: str = "view"


def check_views(views: Sequence[View]) -> None:
    """Validate every view's pose (``ValueError`` naming the view), before anything is written:
    a rigid transform, and a camera within the coordinates a dataset may hold
    (:data:`~nerfbot.data.spec.MAX_CAMERA_COORDINATE_M`; a scene framed from farther away is
    not in metres, or too large)."""
    for view in views:
        pose = nearest_rigid(view.pose, view.where)
        far = float(np.abs(pose[:3, 3]).max())
        if not far <= MAX_CAMERA_COORDINATE_M:
            raise ValueError(f"{view.where}: the camera would stand {far:.3g} m from the origin, "
                             f"beyond the {MAX_CAMERA_COORDINATE_M:g} m a dataset may hold (is "
                             "the scene in metres?)")


def write_views(model: mujoco.MjModel, data: mujoco.MjData, views: Sequence[View],
                out_dir: Path, width: int, height: int, fov_deg: float, meta: dict,
                fmt: str = "nerfstudio", manifest: bool = True, progress: bool = True,
                sensor: Optional[DepthSensorModel] = None,
                extra_files: Optional[Callable[[Path], None]] = None,
                overwrite: bool = False) -> Path:
    """Render ``views`` of the compiled capture model and write them atomically to ``out_dir``.

    Args:
        model, data: from :func:`sims.scene.load_capture_model`; views that carry ``qpos``
            change ``data`` (it is left in the last view's state).
        views: the frames, in the order they are written.
        width, height, fov_deg: image size (pixels) and vertical field of view (degrees).
        meta: the scene manifest (written as ``scene`` unless ``manifest`` is False; its
            ``transparent_geoms`` decide what the depth sensor sees through). The share of the
            training pixels that show its ``shiny_geoms`` is added as ``shiny_pixel_fraction``.
        fmt, progress, sensor: as :func:`capture`.
        extra_files: called with the (temporary) dataset folder before it is moved into place,
            to add files of its own.
        overwrite: replace a dataset captured at ``out_dir`` before (never anything else).

    Returns:
        ``out_dir`` as an absolute Path.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown dataset format '{fmt}' (choose from {FORMATS})")
    if not views:
        raise ValueError("nothing to capture: no views")
    transparent_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
                       for name in meta["transparent_geoms"]]
    shiny_ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
                 for name in meta.get("shiny_geoms", ())]
    shiny_px = train_px = 0
    if sensor is not None:
        meta["depth_sensor"] = sensor.to_dict()

    out_dir = Path(out_dir).expanduser().absolute()
    _check_destination(out_dir, overwrite)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.with_name(f".{out_dir.name}.partial-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()
    try:
        with CaptureCamera(model, data, width, height, fov_deg) as cam:
            k = cam.intrinsics
            writer = open_writer(fmt, tmp, k.fx, k.fy, k.cx, k.cy, k.width, k.height)
            bar = tqdm(views, desc=f"capture {meta['name']}", unit="view", disable=not progress)
            for view_index, view in enumerate(bar):
                if view.qpos is not None:
                    data.qpos[:] = view.qpos
                    mujoco.mj_forward(model, data)
                frame = cam.render(view.pose, where=view.where)
                sensor_depth = None
                if sensor is not None:
                    behind = cam.depth_without(transparent_ids) if transparent_ids else frame.depth
                    glass = np.isin(frame.segmentation, transparent_ids)
                    sensor_depth = sensor.read(behind, glass, view_index=view_index)
                writer.add_frame(frame.rgb, frame.c2w, view.split, depth=frame.depth,
                                 segmentation=frame.segmentation, time=view.time,
                                 joints=view.joints, sensor_depth=sensor_depth)
                if view.split == "train":
                    train_px += frame.segmentation.size
                    shiny_px += int(np.isin(frame.segmentation, shiny_ids).sum())
        if train_px:
            meta["shiny_pixel_fraction"] = shiny_px / train_px
        writer.finish(meta if manifest else None)
        if extra_files is not None:
            extra_files(tmp)
        write_marker(tmp, "dataset")
        _check_destination(out_dir, overwrite)  # again: the folder may have changed meanwhile
        _move_into_place(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def capture(scene: str | Path, rig: RigConfig, test_rig: Optional[RigConfig], out_dir: Path,
            size: Optional[int | Sequence[int]] = None, fmt: str = "nerfstudio",
            manifest: bool = True, progress: bool = True,
            sensor: Optional[DepthSensorModel] = None, overwrite: bool = False,
            headlight: bool = False) -> Path:
    """Render ``rig`` (train split) and ``test_rig`` (test split) views of ``scene`` to ``out_dir``.

    Args:
        scene: built-in scene name (e.g. "tabletop") or path to an MJCF file.
        rig, test_rig: camera rigs (see :mod:`sims.rigs`); ``test_rig`` may be None. Both must
            share image size and field of view (the formats store one camera).
        out_dir: dataset folder to create (missing or empty), or with ``overwrite`` to replace
            (a dataset captured there before).
        size: image size N or (W, H) overriding both rigs' sizes; None keeps the rigs' sizes.
        fmt: "nerfstudio" (``transforms.json``) or "blender" (``transforms_{split}.json``).
        manifest: write the scene manifest as the top-level ``scene`` object.
        progress: show a progress bar.
        sensor: also write each view's simulated depth-sensor reading (``sensor_depth``, see
            :mod:`sims.sensor`); the manifest records the model under ``depth_sensor``.
        overwrite: replace a dataset captured at ``out_dir`` before.
        headlight: keep the headlight's diffuse and specular light, which follow the camera
            (default: static lighting, :func:`set_lighting`); the manifest's ``lighting`` says
            which.

    Returns:
        ``out_dir`` as a Path. Files: RGB PNG (uint8), z-depth ``.npy`` (float32 metres, ``inf``
        on sky), segmentation ``.npy`` (int32 geom ids, -1 on sky), per the format's layout
        (see :mod:`nerfbot.data.writers`).

    Raises:
        FileNotFoundError / ValueError: bad scene, rig, pose or size (before anything is written);
        FileExistsError: ``out_dir`` holds something else (or, without ``overwrite``, a
        dataset); RuntimeError: no OpenGL backend.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown dataset format '{fmt}' (choose from {FORMATS})")
    if size is not None:
        width, height = parse_size(size)
        rig = replace(rig, width=width, height=height)
        test_rig = replace(test_rig, width=width, height=height) if test_rig else None
    if test_rig is not None and (test_rig.size != rig.size or test_rig.fov_deg != rig.fov_deg):
        raise ValueError(f"train and test rigs must share image size and fov, got "
                         f"{rig.size} @ {rig.fov_deg} deg vs {test_rig.size} @ {test_rig.fov_deg} deg")

    model, data = load_capture_model(scene)
    lighting = set_lighting(model, headlight)
    views = [View("train", p, where=f"train view {i}") for i, p in enumerate(rig_poses(rig))]
    if test_rig is not None and (test_rig.count > 0 or test_rig.kind == "explicit"):
        views += [View("test", p, where=f"test view {i}")
                  for i, p in enumerate(rig_poses(test_rig))]
    try:
        check_views(views)  # fail before writing anything
    except ValueError as err:
        raise ValueError(f"{_scene_source(scene).removeprefix('builtin:')}: {err}") from None
    meta = scene_manifest(model, data, resolve_scene(scene).stem, _scene_source(scene))
    meta["lighting"] = lighting
    out_dir = write_views(model, data, views, out_dir, rig.width, rig.height, rig.fov_deg, meta,
                          fmt=fmt, manifest=manifest, progress=progress, sensor=sensor,
                          overwrite=overwrite)
    n_test = sum(1 for v in views if v.split == "test")
    log.info("wrote %d views (%d train, %d test) of '%s' to %s", len(views), len(views) - n_test,
             n_test, meta["name"], out_dir)
    return out_dir
