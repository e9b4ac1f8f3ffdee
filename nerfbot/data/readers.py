"""`load_dataset`: detect the format of a posed-image dataset, load and validate it.

Formats:

- **nerfstudio / instant-ngp**: a folder with ``transforms.json`` (or any other ``.json`` file
  given directly). See :mod:`nerfbot.data.nerfstudio`.
- **Blender synthetic / D-NeRF**: a folder with ``transforms_train.json`` (and
  ``transforms_val.json``, ``transforms_test.json`` when present; a folder with only some of
  them is read too), or one of those files given directly. See :mod:`nerfbot.data.blender`.
- **COLMAP**: a project folder (``images/`` and ``sparse/0/``) or a model folder (``cameras``,
  ``images``, ``points3D`` as ``.bin`` or ``.txt``). See :mod:`nerfbot.data.colmap`.

A folder holding both ``transforms.json`` and Blender split files is read as nerfstudio.

Default splits (nerfstudio without ``*_filenames`` lists): frames 0, 8, 16, ... (every 8th,
starting with the first) are "test", the others "train"; a single-frame dataset is all "train".

Checks across frames: every frame names the same joints; with a scene manifest's bounds, every
camera lies within ``max(100 diagonals, 100 m)`` of their centre (a rig sees its scene from a
few diagonals away; a pose in millimetres or in another frame lands far beyond). Frames sharing
an image file, and training images that are also test or val images, are logged as warnings.
"""

from __future__ import annotations

import logging
import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np
from tqdm.auto import tqdm

from nerfbot.data.blender import parse_blender
from nerfbot.data.bounds import as_aabb, choose_space, estimate_bounds_with_rule, pad_bounds
from nerfbot.data.colmap import find_colmap_model, parse_colmap
from nerfbot.data.dataset import Dataset
from nerfbot.data.errors import DatasetError
from nerfbot.data.images import (composite, read_depth, read_image, read_keypoints, read_mask,
                                 read_segmentation, undistorter)
from nerfbot.data.intrinsics import Intrinsics, resolve_intrinsics
from nerfbot.data.nerfstudio import parse_nerfstudio
from nerfbot.data.spec import FrameSpec, ParsedDataset, positive_int

log = logging.getLogger(__name__)

WHITE = (1.0, 1.0, 1.0)
BLACK = (0.0, 0.0, 0.0)
#: Every TEST_EVERY-th frame (from frame 0) is a test frame when the dataset names no splits.
TEST_EVERY = 8
_BLENDER_JSON = re.compile(r"transforms_(train|val|test)\.json")
#: Undistortion must leave at least this fraction of an image with a source pixel; less means
#: absurd coefficients (k1 = 1e6 leaves none), not a real lens.
MIN_UNDISTORTED_FRACTION = 0.1
#: With manifest bounds, cameras farther than max(MAX_SCENE_DIAGONALS * diagonal, MIN_REACH_M)
#: from the centre of the bounds are refused.
MAX_SCENE_DIAGONALS = 100.0
MIN_REACH_M = 100.0


@dataclass
class _Frame:
    """One loaded frame: arrays (H, W, ...) of the undistorted image and its companions."""

    rgb: np.ndarray
    alpha: Optional[np.ndarray]
    intr: Intrinsics
    depth: Optional[np.ndarray]
    mask: Optional[np.ndarray]
    seg: Optional[np.ndarray]
    sensor_depth: Optional[np.ndarray] = None
    keypoints: Optional[np.ndarray] = None
    opaque_alpha: bool = False
    """The file had an alpha channel that is 255 everywhere (read as an opaque image)."""


def parse_background(value) -> Optional[tuple]:
    """None, "white", "black" or an (r, g, b) triple in [0, 1] -> None or a float triple."""
    if value is None:
        return None
    if isinstance(value, str):
        named = {"white": WHITE, "black": BLACK}.get(value.lower())
        if named is None:
            raise ValueError(f"background: expected None, 'white', 'black' or (r, g, b) in "
                             f"[0, 1], got {value!r}")
        return named
    try:
        rgb = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        rgb = np.empty(0)
    if rgb.shape != (3,) or not np.all(np.isfinite(rgb)) or rgb.min() < 0 or rgb.max() > 1:
        raise ValueError(f"background: expected None, 'white', 'black' or (r, g, b) in [0, 1], "
                         f"got {value!r}")
    return tuple(float(c) for c in rgb)


def default_splits(n: int) -> dict[str, list[int]]:
    """Frames ``0, 8, 16, ...`` are "test", the rest "train" (all "train" when ``n < 2``)."""
    if n < 2:
        return {"train": list(range(n)), "test": []}
    test = list(range(0, n, TEST_EVERY))
    return {"train": [i for i in range(n) if i % TEST_EVERY], "test": test}


def is_dataset_folder(path: Union[str, os.PathLike]) -> bool:
    """Whether ``path`` is a folder holding a dataset description (nerfstudio, Blender / D-NeRF
    or COLMAP), as :func:`parse_dataset` looks for one."""
    path = Path(path)
    if not path.is_dir():
        return False
    names = ("transforms.json",) + tuple(f"transforms_{s}.json" for s in ("train", "val", "test"))
    if any((path / name).is_file() for name in names):
        return True
    try:
        return find_colmap_model(path) is not None
    except DatasetError:   # a model whose images are missing is still a dataset (a broken one)
        return True


def parse_dataset(path: Union[str, os.PathLike]) -> ParsedDataset:
    """Detect a dataset's format and validate its description (no image is read)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: dataset not found (no such folder or JSON file)")
    if path.is_dir():
        if (path / "transforms.json").is_file():
            return parse_nerfstudio(path / "transforms.json")
        if any((path / f"transforms_{s}.json").is_file() for s in ("train", "val", "test")):
            return parse_blender(path)
        found = find_colmap_model(path)
        if found is not None:
            return parse_colmap(*found)
        raise DatasetError(f"{path}: not a dataset folder: no transforms.json (nerfstudio), "
                           "transforms_{train,val,test}.json (Blender / D-NeRF) or COLMAP model "
                           "(sparse/0/cameras.bin with images/) in it")
    if path.suffix.lower() != ".json":
        raise DatasetError(f"{path}: expected a dataset folder or a transforms .json file")
    if _BLENDER_JSON.fullmatch(path.name):
        return parse_blender(path.parent)
    return parse_nerfstudio(path)


def _check_declared_size(spec: FrameSpec, width: int, height: int) -> None:
    for key, actual in (("w", width), ("h", height)):
        if key in spec.camera:
            value, where = spec.camera[key]
            declared = positive_int(value, where)
            if declared != actual:
                raise DatasetError(
                    f"{spec.where}.file_path: image {spec.image_path} is {width}x{height} "
                    f"(w x h) but {key} is declared as {declared} ({where})")


def _coefficient_field(spec: FrameSpec) -> str:
    """"<json file>: <field>" of the frame's largest distortion coefficient (for messages)."""
    present = [k for k in ("k1", "k2", "k3", "k4", "p1", "p2") if k in spec.camera]
    if not present:
        return f"{spec.where}.camera_model"
    return spec.camera[max(present, key=lambda k: abs(float(spec.camera[k][0])))][1]


def _undistorter(spec: FrameSpec, intr: Intrinsics):
    """The frame's :class:`~nerfbot.data.images.Undistorter`; DatasetError naming the largest
    coefficient when the distortion leaves under MIN_UNDISTORTED_FRACTION of the image."""
    try:
        u = undistorter(intr)
    except cv2.error as e:
        raise DatasetError(f"{_coefficient_field(spec)}: cannot undistort with {intr.model} "
                           f"{intr.coeffs}: {str(e).strip().splitlines()[-1]}") from None
    fraction = float(u.valid.mean())
    if fraction < MIN_UNDISTORTED_FRACTION:
        raise DatasetError(f"{_coefficient_field(spec)}: {intr.model} distortion {intr.coeffs} "
                           f"leaves {fraction:.1%} of the {intr.width}x{intr.height} image with "
                           f"source pixels (at least {MIN_UNDISTORTED_FRACTION:.0%} needed); "
                           "check the coefficients")
    return u


def _load_frame(spec: FrameSpec, background: tuple) -> _Frame:
    """Read, check, composite and undistort one frame."""
    rgb, alpha = read_image(spec.image_path, f"{spec.where}.file_path")
    opaque_alpha = alpha is not None and bool((alpha == 255).all())
    if opaque_alpha:  # an RGBA export of an opaque photo: no background to composite
        alpha = None
    height, width = rgb.shape[:2]
    _check_declared_size(spec, width, height)
    intr = resolve_intrinsics(spec.camera, width, height, spec.where)
    shape = (height, width)
    depth = mask = seg = sensor = None
    if spec.depth_path is not None:
        depth = read_depth(spec.depth_path, f"{spec.where}.{spec.depth_field}", shape,
                           spec.depth_scale)
    if spec.sensor_depth_path is not None:
        sensor = read_depth(spec.sensor_depth_path, f"{spec.where}.sensor_depth_file_path", shape,
                            spec.depth_scale)
    keypoints = None
    if spec.sparse_depth_path is not None:
        keypoints = read_keypoints(spec.sparse_depth_path, f"{spec.where}.sparse_depth_file_path",
                                   shape)
    if spec.mask_path is not None:
        mask = read_mask(spec.mask_path, f"{spec.where}.mask_path", shape)
    if spec.segmentation_path is not None:
        seg = read_segmentation(spec.segmentation_path, f"{spec.where}.segmentation_path", shape)
    if alpha is not None:
        rgb = composite(rgb, alpha, background)
    if intr.distorted:
        u = _undistorter(spec, intr)
        if alpha is not None:
            rgb = u.linear(rgb, tuple(255.0 * c for c in background))
            alpha = u.linear(alpha, 0)
        else:
            rgb = u.linear(rgb, 0)
        if depth is not None:
            depth = u.nearest(depth, np.nan)
        if sensor is not None:
            sensor = u.nearest(sensor, np.nan)
        if keypoints is not None:
            keypoints = keypoints.copy()
            keypoints[:, :2] = u.points(keypoints[:, :2])
            inside = ((keypoints[:, :2] >= 0) & (keypoints[:, :2] <= [width, height])).all(1)
            keypoints = keypoints[inside]
        if seg is not None:
            seg = u.nearest(seg, -1)
        if mask is not None:
            mask = u.nearest(mask, False) & u.valid
        elif not u.valid.all():
            mask = u.valid.copy()
    return _Frame(rgb, alpha, intr, depth, mask, seg, sensor, keypoints, opaque_alpha)


def _load_frames(parsed: ParsedDataset, background: tuple) -> list[_Frame]:
    """Load all frames in order, on a few threads (OpenCV decoding releases the GIL)."""
    specs = parsed.frames
    n = len(specs)
    bar = dict(total=n, desc=f"loading {parsed.root.name or parsed.root}", unit="frame",
               disable=True if n < 50 else None)
    workers = min(4, os.cpu_count() or 1, n)
    if workers <= 1:
        return [_load_frame(s, background) for s in tqdm(specs, **bar)]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(_load_frame, s, background) for s in specs]
        try:
            return [f.result() for f in tqdm(futures, **bar)]
        except BaseException:
            for f in futures:
                f.cancel()
            raise


def _check_mixed_sizes(specs: list[FrameSpec], frames: list[_Frame]) -> None:
    """Frames sharing global intrinsics (same JSON, none of their own) must share a size."""
    first: dict[str, tuple[FrameSpec, tuple]] = {}
    for spec, frame in zip(specs, frames):
        if spec.per_frame_intrinsics:
            continue
        size = (frame.intr.width, frame.intr.height)
        ref = first.setdefault(spec.group, (spec, size))
        if ref[1] != size:
            raise DatasetError(
                f"{spec.where}.file_path: image {spec.image_path} is {size[0]}x{size[1]} but "
                f"{ref[0].where} is {ref[1][0]}x{ref[1][1]}; images of different sizes need "
                "per-frame intrinsics (w, h, fl_x, ... in each frame)")


def _all_or_none(specs: list[FrameSpec], field: str) -> Optional[list]:
    """Per-frame ``field`` values, None if no frame has one; an error if only some do."""
    values = [getattr(s, field) for s in specs]
    present = [i for i, v in enumerate(values) if v is not None]
    if not present:
        return None
    if len(present) != len(values):
        missing = next(i for i, v in enumerate(values) if v is None)
        raise DatasetError(f"{specs[missing].where}.{field}: missing, but other frames carry "
                           f"one (e.g. {specs[present[0]].where})")
    return values


def _check_joint_names(specs: list[FrameSpec]) -> None:
    """Every frame must name the same joints as the first."""
    first = set(specs[0].joints)
    for spec in specs[1:]:
        names = set(spec.joints)
        if names != first:
            raise DatasetError(f"{spec.where}.joints: joint names {sorted(names)} differ from "
                               f"{specs[0].where}'s {sorted(first)}")


def _warn_duplicate_files(specs: list[FrameSpec]) -> None:
    """Log a warning for every image file that more than one frame names."""
    users: dict[Path, list[str]] = {}
    for spec in specs:
        users.setdefault(spec.image_path, []).append(spec.where)
    for path, wheres in users.items():
        if len(wheres) > 1:
            log.warning("%d frames use the same image file %s: %s", len(wheres), path,
                        "; ".join(wheres))


def _warn_split_overlap(specs: list[FrameSpec], splits: dict[str, list[int]]) -> None:
    """Log a warning when a test or val frame is, or shares its image with, a training frame
    (its metrics would then measure memorisation)."""
    train_files = {specs[i].image_path for i in splits.get("train", [])}
    for name in ("val", "test"):
        shared = [specs[i].where for i in splits.get(name, [])
                  if specs[i].image_path in train_files]
        if shared:
            log.warning("%d of %d '%s' frames are also training images, so %s metrics overstate "
                        "quality: %s", len(shared), len(splits[name]), name, name,
                        "; ".join(shared[:5]) + (" ..." if len(shared) > 5 else ""))


def _check_cameras_near_scene(specs: list[FrameSpec], c2w: np.ndarray, box: np.ndarray) -> None:
    """DatasetError naming the first camera farther from the centre of the manifest's bounds
    ``box`` (2, 3) than max(MAX_SCENE_DIAGONALS diagonals, MIN_REACH_M metres)."""
    centre = 0.5 * (box[0] + box[1])
    reach = max(MAX_SCENE_DIAGONALS * float(np.linalg.norm(box[1] - box[0])), MIN_REACH_M)
    distance = np.linalg.norm(c2w[:, :3, 3] - centre, axis=1)
    far = np.flatnonzero(distance > reach)
    if far.size:
        i = int(far[0])
        raise DatasetError(f"{specs[i].where}.transform_matrix: camera is {distance[i]:.4g} m from "
                           f"the centre of the scene bounds (scene.bounds), beyond {reach:.4g} m; "
                           "are the poses in metres and in the scene's frame?")


def _bounds(aabb, parsed: ParsedDataset, c2w, intrinsics, sizes,
            images) -> tuple[np.ndarray, str, str]:
    """(aabb (2, 3), aabb_source, rule): user > manifest scene.bounds (padded) > cameras (and
    ``images``, the training views' RGB, None for the others)."""
    manifest_box = None
    if parsed.manifest is not None and "bounds" in parsed.manifest:
        try:
            manifest_box = as_aabb(parsed.manifest["bounds"],
                                   f"{parsed.manifest_where}: scene.bounds", strict=False)
        except ValueError as e:
            raise DatasetError(str(e)) from None
    if aabb is not None:
        return as_aabb(aabb, "aabb argument", strict=True), "user", "user"
    if manifest_box is not None:
        return pad_bounds(manifest_box), "manifest", "manifest_padded"
    box, rule = estimate_bounds_with_rule(c2w, intrinsics, sizes, images)
    return box, "cameras", rule


def load_dataset(path: Union[str, os.PathLike], *, aabb=None, background=None) -> Dataset:
    """Load a nerfstudio, instant-ngp, Blender or D-NeRF dataset into a :class:`Dataset`.

    Args:
        path: a dataset folder, or a transforms JSON file inside one.
        aabb: optional (2, 3) [[xmin, ymin, zmin], [xmax, ymax, zmax]] in metres; overrides
            the manifest's bounds and the camera-based estimate.
        background: colour RGBA images are composited on: None (white), "white", "black" or
            an (r, g, b) triple in [0, 1]. For RGB-only datasets, None leaves
            ``Dataset.background = "learned"`` and a colour is recorded as given.

    Returns:
        The validated dataset: undistorted uint8 RGB images (and alpha), float64 poses and
        intrinsics, optional depth (float32 metres), masks, segmentations, times and joints,
        splits, bounds. Distorted (OPENCV / OPENCV_FISHEYE) images are undistorted keeping the
        same K; pixels whose source falls outside the distorted image are marked invalid in
        ``masks`` (a mask is created for that frame if it had none).

    Raises:
        DatasetError: malformed or missing input; the message names the file and the field.
        ValueError: an invalid ``aabb`` or ``background`` argument.
    """
    bg = parse_background(background)
    parsed = parse_dataset(path)
    try:
        frames = _load_frames(parsed, bg if bg is not None else WHITE)
    finally:
        undistorter.cache_clear()
    specs = parsed.frames
    _check_mixed_sizes(specs, frames)
    times = _all_or_none(specs, "time")
    joints = _all_or_none(specs, "joints")
    if joints is not None:
        _check_joint_names(specs)
    splits = parsed.splits if parsed.splits is not None else default_splits(len(frames))
    _warn_duplicate_files(specs)
    _warn_split_overlap(specs, splits)

    c2w = np.stack([s.c2w for s in specs])
    intrinsics = np.array([[f.intr.fx, f.intr.fy, f.intr.cx, f.intr.cy] for f in frames],
                          dtype=np.float64)
    sizes = np.array([[f.intr.width, f.intr.height] for f in frames], dtype=np.int64)
    train = set(splits.get("train", range(len(frames))))
    box, source, rule = _bounds(aabb, parsed, c2w, intrinsics, sizes,
                                [f.rgb if i in train else None for i, f in enumerate(frames)])
    if source == "manifest":
        _check_cameras_near_scene(specs, c2w, box)
    space = choose_space(box, source, c2w)
    if not np.array_equal(space.aabb, box):
        box = space.aabb
        log.info("%s", space.reason)

    any_alpha = any(f.alpha is not None for f in frames)
    opaque = sum(f.opaque_alpha for f in frames)
    if opaque:
        log.info("%d of %d images have an alpha channel that is 255 everywhere: read as opaque "
                 "images%s", opaque, len(frames),
                 "" if any_alpha else " (the background is learned, as for RGB images)")
    dataset_bg = bg if bg is not None else (WHITE if any_alpha else "learned")
    extras = dict(parsed.extras)
    extras.update(
        json_files=parsed.json_files,
        source_camera_models=[f.intr.model for f in frames],
        undistorted=[f.intr.distorted for f in frames],
        bounds_rule=rule,
        space=space.reason,
    )
    log.info("loaded %d frames (%s) from %s; bounds from %s", len(frames), parsed.format,
             parsed.root, source)
    return Dataset(
        root=parsed.root,
        format=parsed.format,
        file_paths=[s.file_path for s in specs],
        images=[f.rgb for f in frames],
        alphas=[f.alpha for f in frames],
        c2w=c2w,
        intrinsics=intrinsics,
        sizes=sizes,
        depths=[f.depth for f in frames],
        masks=[f.mask for f in frames],
        segmentations=[f.seg for f in frames],
        sensor_depths=[f.sensor_depth for f in frames],
        keypoints=[f.keypoints for f in frames],
        times=None if times is None else np.asarray(times, dtype=np.float32),
        joints=joints,
        splits=splits,
        aabb=box,
        aabb_source=source,
        manifest=parsed.manifest,
        unbounded=space.contraction,
        background=dataset_bg,
        extras=extras,
    )
