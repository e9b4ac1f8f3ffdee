"""JSON side of the readers: read a transforms file and validate its fields into a `FrameSpec`.

Nothing here touches image pixels; :mod:`nerfbot.data.images` loads what a `FrameSpec` names.
Every error is a :class:`DatasetError` whose message starts with ``<json file>: <field>:``.
"""

from __future__ import annotations

import json
import math
import os
import posixpath
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath
from typing import Any, Optional

import numpy as np

from nerfbot.data.errors import DatasetError
from nerfbot.ops.cameras import check_pose

#: Intrinsics / distortion keys that may appear at the top level or per frame (per frame wins).
CAMERA_KEYS = (
    "fl_x", "fl_y", "cx", "cy", "w", "h",
    "camera_angle_x", "camera_angle_y", "x_fov", "y_fov",
    "camera_model", "is_fisheye", "k1", "k2", "k3", "k4", "p1", "p2",
)
#: A frame carrying any of these has its own intrinsics (so its image size may differ).
PER_FRAME_INTRINSIC_KEYS = CAMERA_KEYS[:10]

#: Extensions tried when a ``file_path`` names no existing file (Blender omits ".png").
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")

#: Largest camera coordinate accepted, metres. Rays are float32, whose spacing at 1e5 is 8 mm:
#: poses further out (e.g. georeferenced UTM or ECEF coordinates) must be recentred first.
MAX_CAMERA_COORDINATE_M = 1e5


@dataclass
class FrameSpec:
    """One frame as described by the JSON, validated but not loaded.

    Attributes:
        where: "<json file>: frames[i]", the prefix of every error about this frame.
        file_path: image path exactly as written in the JSON.
        image_path: resolved image file (inside the dataset root).
        c2w: (4, 4) float64 camera-to-world pose, OpenGL convention, metres.
        camera: intrinsics / distortion key -> (value, "<json file>: <field>"), global values
            overridden by per-frame ones.
        per_frame_intrinsics: the frame carries its own focal length or size.
        group: the JSON file the frame's global intrinsics come from.
        depth_path, mask_path, segmentation_path, sensor_depth_path, sparse_depth_path:
            resolved files or None.
        depth_field: the JSON field that named the depth file (for messages).
        time: float in [0, 1] or None.
        joints: joint name -> position (radians or metres), or None.
        depth_scale: metres per unit of integer depth images.
    """

    where: str
    file_path: str
    image_path: Path
    c2w: np.ndarray
    camera: dict
    per_frame_intrinsics: bool
    group: str
    depth_path: Optional[Path] = None
    depth_field: str = "depth_file_path"
    mask_path: Optional[Path] = None
    segmentation_path: Optional[Path] = None
    sensor_depth_path: Optional[Path] = None
    sparse_depth_path: Optional[Path] = None
    time: Optional[float] = None
    joints: Optional[dict] = None
    depth_scale: float = 1e-3


@dataclass
class ParsedDataset:
    """A dataset's JSON, validated: what to load and how to split it.

    Attributes:
        root: the dataset folder; every file path lies inside it.
        format: "nerfstudio", "blender", "dnerf" or "colmap".
        frames: the frames in output order.
        splits: split name -> frame indices, or None to apply the default rule.
        manifest: the top-level ``scene`` object, or None.
        manifest_where: the JSON file the manifest came from (for messages).
        json_files: the transforms files read.
        extras: top-level values passed through untouched (``applied_transform``, ...).
    """

    root: Path
    format: str
    frames: list
    splits: Optional[dict]
    manifest: Optional[dict]
    manifest_where: str
    json_files: list
    extras: dict


def read_json(path: Path) -> dict:
    """Parse a JSON file whose top level must be an object; errors name line and column."""
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise DatasetError(f"{path}: not UTF-8 text (bad byte at offset {e.start})") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read: {e.strerror or e}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise DatasetError(
            f"{path}: invalid JSON at line {e.lineno}, column {e.colno}: {e.msg}") from None
    except (ValueError, RecursionError) as e:  # e.g. an integer of over 4300 digits, deep nesting
        raise DatasetError(f"{path}: invalid JSON: {e}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: top level must be a JSON object, got {type(data).__name__}")
    return data


def number(value: Any, where: str, *, positive: bool = False) -> float:
    """A finite JSON number (bools rejected), optionally > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise DatasetError(f"{where}: expected a number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:
        v = math.inf
    if not math.isfinite(v):
        raise DatasetError(f"{where}: must be finite, got {value!r}")
    if positive and v <= 0.0:
        raise DatasetError(f"{where}: must be > 0, got {value!r}")
    return v


def positive_int(value: Any, where: str) -> int:
    """A positive integer (an integral float such as 800.0 is accepted)."""
    v = number(value, where, positive=True)
    if v != int(v):
        raise DatasetError(f"{where}: expected an integer, got {value!r}")
    return int(v)


def normalise_rel(value: str) -> str:
    """Canonical form of a relative path for matching: '/' separators, no './', no 'a/..'."""
    return posixpath.normpath(value.replace("\\", "/"))


def resolve_path(root: Path, value: Any, where: str) -> Path:
    """A dataset-relative path as ``root / value``, rejecting absolute paths and ones whose
    ``..`` components climb out of ``root`` (a lexical test; :func:`existing_file` also checks
    where symbolic links lead)."""
    if not isinstance(value, str) or not value.strip():
        raise DatasetError(f"{where}: expected a non-empty relative path string, got {value!r}")
    if "\x00" in value:
        raise DatasetError(f"{where}: path {value!r} contains a NUL character")
    if value.startswith(("/", "\\")) or PureWindowsPath(value).drive or Path(value).is_absolute():
        raise DatasetError(f"{where}: absolute path {value!r} is not allowed; "
                           "paths must be relative to the dataset folder")
    norm = normalise_rel(value)
    if norm in (".", "..") or norm.startswith("../"):
        raise DatasetError(f"{where}: path {value!r} escapes the dataset folder {root}")
    return root / norm


def inside_root(path: Path, root: Path, where: str) -> Path:
    """``path`` with symbolic links followed; DatasetError unless it lies inside ``root`` (also
    resolved), so a link cannot reach files outside the dataset folder."""
    real, real_root = Path(os.path.realpath(path)), Path(os.path.realpath(root))
    if real != real_root and real_root not in real.parents:
        raise DatasetError(f"{where}: {path} resolves to {real}, outside the dataset folder "
                           f"{real_root} (symbolic link)")
    return real


def existing_file(root: Path, value: Any, where: str, what: str,
                  extensions: tuple[str, ...] = ()) -> Path:
    """:func:`resolve_path`, then require a regular file inside ``root`` once symbolic links
    are followed (trying ``extensions`` if missing). Returns the resolved file."""
    p = resolve_path(root, value, where)
    for candidate in (p, *(p.with_name(p.name + ext) for ext in extensions)):
        if candidate.is_file():
            return inside_root(candidate, root, where)
    tried = f" (also tried {', '.join(extensions)})" if extensions else ""
    raise DatasetError(f"{where}: {what} file not found: {p}{tried}")


def pose(value: Any, where: str) -> np.ndarray:
    """A rigid (4, 4) float64 c2w from a JSON 4x4 or 3x4 nested list."""
    if value is None:
        raise DatasetError(f"{where}: missing")
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise DatasetError(f"{where}: expected a 4x4 matrix of numbers, got {value!r}") from None
    try:
        m = check_pose(m, where)
    except ValueError as e:
        raise DatasetError(str(e)) from None
    position = m[:3, 3]
    if np.abs(position).max() > MAX_CAMERA_COORDINATE_M:
        raise DatasetError(f"{where}: camera position {position.tolist()} lies beyond "
                           f"{MAX_CAMERA_COORDINATE_M:g} m of the origin; recentre the poses "
                           "(or check their unit: metres are expected)")
    return m


def time_value(value: Any, where: str) -> float:
    """A frame time, finite and in [0, 1]."""
    t = number(value, where)
    if not 0.0 <= t <= 1.0:
        raise DatasetError(f"{where}: time must be in [0, 1], got {value!r}")
    return t


def joints_value(value: Any, where: str) -> dict:
    """Joint name -> finite position (at least one joint)."""
    if not isinstance(value, dict) or not value:
        raise DatasetError(f"{where}: expected a non-empty object joint name -> position, "
                           f"got {value!r}")
    return {str(k): number(v, f"{where}.{k}") for k, v in value.items()}


#: The frame field of the exact z-depth nerfbot writes beside nerfstudio's ``depth_file_path``:
#: float32 ``.npy`` in metres, ``inf`` where no surface is hit. Read in preference to
#: ``depth_file_path`` (a 16-bit PNG in millimetres, which nerfstudio reads with its default
#: ``depth_unit_scale_factor`` of 1e-3, and which cannot hold ``inf`` or depths past 65.535 m).
EXACT_DEPTH_FIELD = "nerfbot_depth_file_path"


def camera_fields(obj: dict, where: str) -> dict:
    """The intrinsics / distortion keys of ``obj`` as key -> (value, "<where><key>")."""
    return {k: (obj[k], f"{where}{k}") for k in CAMERA_KEYS if k in obj}


def parse_frame(frame: Any, i: int, json_path: Path, root: Path, global_camera: dict,
                depth_scale: float = 1e-3,
                *, image_extensions: tuple[str, ...] = IMAGE_EXTENSIONS) -> FrameSpec:
    """Validate ``frames[i]`` of ``json_path`` (a dict) into a :class:`FrameSpec`.

    Reads the fields shared by all formats: ``file_path``, ``transform_matrix``, per-frame
    intrinsics, ``nerfbot_depth_file_path`` (else ``depth_file_path`` / ``depth_path``),
    ``mask_path``, ``segmentation_path``,
    ``sensor_depth_file_path``, ``sparse_depth_file_path``, ``time`` and ``joints``. Files named
    by the frame must exist inside ``root``.
    """
    where = f"{json_path}: frames[{i}]"
    if not isinstance(frame, dict):
        raise DatasetError(f"{where}: expected an object, got {type(frame).__name__}")
    if "file_path" not in frame:
        raise DatasetError(f"{where}.file_path: missing")
    file_path = frame["file_path"]
    image_path = existing_file(root, file_path, f"{where}.file_path", "image", image_extensions)
    if "transform_matrix" not in frame:
        raise DatasetError(f"{where}.transform_matrix: missing")
    c2w = pose(frame["transform_matrix"], f"{where}.transform_matrix")

    camera = dict(global_camera)
    camera.update(camera_fields(frame, f"{where}."))
    spec = FrameSpec(
        where=where, file_path=file_path, image_path=image_path, c2w=c2w, camera=camera,
        per_frame_intrinsics=any(k in frame for k in PER_FRAME_INTRINSIC_KEYS),
        group=str(json_path), depth_scale=depth_scale,
    )
    for field in (EXACT_DEPTH_FIELD, "depth_file_path", "depth_path"):
        if frame.get(field) is not None:
            spec.depth_path = existing_file(root, frame[field], f"{where}.{field}", "depth")
            spec.depth_field = field
            break
    if frame.get("mask_path") is not None:
        spec.mask_path = existing_file(root, frame["mask_path"], f"{where}.mask_path", "mask")
    if frame.get("segmentation_path") is not None:
        spec.segmentation_path = existing_file(
            root, frame["segmentation_path"], f"{where}.segmentation_path", "segmentation")
    if frame.get("sensor_depth_file_path") is not None:
        spec.sensor_depth_path = existing_file(
            root, frame["sensor_depth_file_path"], f"{where}.sensor_depth_file_path", "depth")
    if frame.get("sparse_depth_file_path") is not None:
        spec.sparse_depth_path = existing_file(
            root, frame["sparse_depth_file_path"], f"{where}.sparse_depth_file_path",
            "sparse depth")
    if "time" in frame:
        spec.time = time_value(frame["time"], f"{where}.time")
    if "joints" in frame:
        spec.joints = joints_value(frame["joints"], f"{where}.joints")
    return spec


def frames_list(meta: dict, json_path: Path) -> list:
    """The non-empty ``frames`` list of a transforms file."""
    frames = meta.get("frames")
    if frames is None:
        raise DatasetError(f"{json_path}: frames: missing")
    if not isinstance(frames, list):
        raise DatasetError(f"{json_path}: frames: expected a list, got {type(frames).__name__}")
    if not frames:
        raise DatasetError(f"{json_path}: frames: empty, the dataset has no frames")
    return frames


def manifest_value(meta: dict, json_path: Path) -> Optional[dict]:
    """The top-level ``scene`` manifest object, or None when absent.

    The keys nerfbot reads are type-checked here (``bounds`` when the bounds are chosen):
    ``objects``, ``transparent_geoms``, ``moving_joints`` (lists of names), ``geoms`` (geom id
    -> name), ``joint_info`` (joint name -> object, see :func:`joint_range`) and
    ``part_bounds`` (list of {"joints": [names], "bounds": [[min], [max]]}) and
    ``moving_bodies`` (body name -> list of geom ids).
    """
    scene = meta.get("scene")
    if scene is None:
        return None
    where = f"{json_path}: scene"
    if not isinstance(scene, dict):
        raise DatasetError(f"{where}: expected an object (the scene manifest), "
                           f"got {type(scene).__name__}")
    for key in ("objects", "transparent_geoms", "moving_joints"):
        if scene.get(key) is not None:
            name_list(scene[key], f"{where}.{key}")
    if scene.get("geoms") is not None:
        _geom_names(scene["geoms"], f"{where}.geoms")
    if scene.get("joint_info") is not None:
        _joint_info(scene["joint_info"], f"{where}.joint_info")
    if scene.get("part_bounds") is not None:
        _part_bounds(scene["part_bounds"], f"{where}.part_bounds")
    if scene.get("moving_bodies") is not None:
        _moving_bodies(scene["moving_bodies"], f"{where}.moving_bodies")
    return scene


def name_list(value: Any, where: str) -> list[str]:
    """A JSON list of strings."""
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise DatasetError(f"{where}: expected a list of names, got {value!r}")
    return value


def _geom_names(value: Any, where: str) -> None:
    """geom id (a decimal string) -> geom name (a string or null)."""
    if not isinstance(value, dict):
        raise DatasetError(f"{where}: expected an object geom id -> name, got {value!r}")
    for key, name in value.items():
        if not key.lstrip("-").isdigit() or not (name is None or isinstance(name, str)):
            raise DatasetError(f"{where}.{key}: expected an integer geom id naming a geom, "
                               f"got {key!r}: {name!r}")


def _moving_bodies(value: Any, where: str) -> None:
    """body name -> list of integer geom ids."""
    if not isinstance(value, dict):
        raise DatasetError(f"{where}: expected an object body name -> geom ids, got {value!r}")
    for name, ids in value.items():
        if not isinstance(ids, list) or not all(
                isinstance(g, int) and not isinstance(g, bool) for g in ids):
            raise DatasetError(f"{where}.{name}: expected a list of integer geom ids, "
                               f"got {ids!r}")


def joint_range(value: Any, where: str) -> Optional[tuple[float, float]]:
    """A joint's limits ``[lo, hi]`` (radians / metres, finite, lo <= hi), or None (unlimited)."""
    if value is None:
        return None
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise DatasetError(f"{where}: expected [lo, hi] (or null for an unlimited joint), "
                           f"got {value!r}")
    lo, hi = number(value[0], f"{where}[0]"), number(value[1], f"{where}[1]")
    if lo > hi:
        raise DatasetError(f"{where}: reversed range [{lo:g}, {hi:g}] (lo must be <= hi)")
    return lo, hi


def _joint_info(value: Any, where: str) -> None:
    if not isinstance(value, dict):
        raise DatasetError(f"{where}: expected an object joint name -> description, got {value!r}")
    for name, info in value.items():
        if not isinstance(info, dict):
            raise DatasetError(f"{where}.{name}: expected an object, got {info!r}")
        joint_range(info.get("range"), f"{where}.{name}.range")


def _part_bounds(value: Any, where: str) -> None:
    if not isinstance(value, list):
        raise DatasetError(f"{where}: expected a list of parts, got {value!r}")
    for k, part in enumerate(value):
        if not isinstance(part, dict):
            raise DatasetError(f"{where}[{k}]: expected an object, got {part!r}")
        name_list(part.get("joints"), f"{where}[{k}].joints")
        try:
            box = np.asarray(part.get("bounds"), dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            box = np.empty(0)
        if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[0] > box[1]):
            raise DatasetError(f"{where}[{k}].bounds: expected [[xmin, ymin, zmin], "
                               f"[xmax, ymax, zmax]] with min <= max, got {part.get('bounds')!r}")


def depth_scale_value(meta: dict, json_path: Path) -> float:
    """Metres per unit of integer depth images: ``depth_unit_scale_factor``, default 1e-3."""
    if "depth_unit_scale_factor" not in meta:
        return 1e-3
    return number(meta["depth_unit_scale_factor"], f"{json_path}: depth_unit_scale_factor",
                  positive=True)
