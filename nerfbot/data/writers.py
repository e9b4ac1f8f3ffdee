"""Writers of posed-image datasets on disk: nerfstudio ``transforms.json`` and Blender synthetic.

Both writers stream: :meth:`add_frame` writes a frame's image (PNG), z-depth and segmentation
(int32 ``.npy``, MuJoCo geom ids, -1 = none) at once, and :meth:`finish` writes the JSON
file(s) atomically (temporary file + ``os.replace``).
Poses are c2w 4x4 in the OpenGL convention; they are written with full float precision
(``repr`` of float64), so reading them back gives the same numbers.

Layouts::

    nerfstudio/                           blender/
      transforms.json                       transforms_train.json, transforms_test.json
      images/frame_00000.png                train/r_0.png, test/r_0.png
      depth/frame_00000.png                 train/r_0_depth.npy
      depth/frame_00000.npy
      segmentation/frame_00000.npy          train/r_0_seg.npy
      sensor_depth/frame_00000.npy          train/r_0_sensor_depth.npy   (optional)

Depth, nerfstudio: ``depth_file_path`` is a 16-bit PNG in millimetres (0 = no surface or
beyond 65.535 m), which nerfstudio's dataparser reads at its default ``depth_unit_scale_factor``
(1e-3); the exact z-depth (float32 ``.npy``, metres, ``inf`` = no surface) is
``nerfbot_depth_file_path``, which nerfbot reads first. Blender (whose nerfstudio parser reads
no depth): ``depth_file_path`` is the float32 ``.npy``.

nerfstudio: intrinsics are global (``fl_x, fl_y, cx, cy, w, h``, ``camera_model: OPENCV`` with
zero distortion); ``train_filenames`` / ``val_filenames`` / ``test_filenames`` list ``file_path``
values (nerfstudio's own loader requires a ``val`` list once any split list is present, so
``val_filenames`` repeats the test list). Blender: ``camera_angle_x`` (horizontal fov, radians),
``file_path`` without extension; ``depth_file_path`` / ``segmentation_path`` are extensions.
Both: an optional per-frame ``sensor_depth_file_path`` (a simulated depth sensor's z-depth,
float32 ``.npy``, metres, NaN = no return; see :mod:`sims.sensor`), an optional top-level ``scene`` object (the scene manifest of ``sims``), and optional
per-frame ``time`` (in [0, 1]) and ``joints`` (name -> position).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from nerfbot.data.spec import EXACT_DEPTH_FIELD
from nerfbot.ops.cameras import check_pose

FORMATS = ("nerfstudio", "blender")


def json_default(o):
    """JSON encoding of numpy / torch arrays and scalars (``tolist`` / ``item``) and paths."""
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_json_atomic(path: Path, obj, allow_nan: bool = False) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (:func:`write_text_atomic`).

    Arrays, numpy / torch scalars and paths are converted (:func:`json_default`). ``allow_nan``
    permits NaN / Infinity (not strict JSON; Python's json reads them back).
    """
    text = json.dumps(obj, indent=2, allow_nan=allow_nan, default=json_default) + "\n"
    return write_text_atomic(path, text)


def write_text_atomic(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically: a temporary sibling file, then ``os.replace``.

    A reader never sees a partial file; on failure the previous file (if any) is untouched.
    """
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_bytes_atomic(path: Path, content: bytes) -> Path:
    """Write ``content`` to ``path`` atomically, as :func:`write_text_atomic` writes text."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, default_file_mode())  # mkstemp's 0600 would hide datasets from other users
        with os.fdopen(fd, "wb") as f:
            f.write(content)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def default_file_mode() -> int:
    """0o666 minus the process umask: the mode ``open()`` would give a new file."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def encode_png(image: np.ndarray) -> bytes:
    """The PNG file bytes of an (H, W, 3) uint8 RGB or (H, W) uint8 grey image."""
    image = np.ascontiguousarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (
            image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"PNG image must be (H, W, 3) or (H, W) uint8, got {image.shape} "
                         f"{image.dtype}")
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, buffer = cv2.imencode(".png", bgr)
    if not ok:
        raise OSError("OpenCV could not encode the image as PNG")
    return buffer.tobytes()


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Save an (H, W, 3) uint8 RGB image as PNG (via OpenCV, which wants BGR)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write image {path}")


#: The largest depth a 16-bit millimetre PNG holds, metres.
DEPTH_PNG_MAX_M = 65.535


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """(H, W) z-depth in metres -> (H, W) uint16 millimetres, rounded; 0 where the depth is not
    finite, not positive, or beyond :data:`DEPTH_PNG_MAX_M` (nerfstudio's "no depth")."""
    depth = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(depth) & (depth > 0) & (depth <= DEPTH_PNG_MAX_M)
    return np.where(ok, np.rint(np.where(ok, depth, 0.0) * 1000.0), 0).astype(np.uint16)


def write_depth_files(root: Path, stem: str, depth: np.ndarray) -> dict:
    """Write a frame's z-depth (H, W, metres) as ``<root>/<stem>.png`` (16-bit millimetres)
    and ``<root>/<stem>.npy`` (exact float32); returns the frame fields naming them
    (``depth_file_path`` and :data:`~nerfbot.data.spec.EXACT_DEPTH_FIELD`)."""
    png, npy = f"{stem}.png", f"{stem}.npy"
    path = Path(root) / png
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), depth_to_mm(depth)):
        raise OSError(f"could not write depth image {path}")
    _save_npy(Path(root) / npy, np.asarray(depth, dtype=np.float32))
    return {"depth_file_path": png, EXACT_DEPTH_FIELD: npy}


def _check_frame(rgb, depth, segmentation, width: int, height: int, where: str):
    rgb = np.asarray(rgb)
    if rgb.shape != (height, width, 3) or rgb.dtype != np.uint8:
        raise ValueError(f"{where}: rgb must be ({height}, {width}, 3) uint8, "
                         f"got {rgb.shape} {rgb.dtype}")
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (height, width):
            raise ValueError(f"{where}: depth must be ({height}, {width}), got {depth.shape}")
    if segmentation is not None:
        segmentation = np.asarray(segmentation)
        if segmentation.shape != (height, width) or not np.issubdtype(segmentation.dtype,
                                                                       np.integer):
            raise ValueError(f"{where}: segmentation must be ({height}, {width}) integer, "
                             f"got {segmentation.shape} {segmentation.dtype}")
        segmentation = segmentation.astype(np.int32)
    return rgb, depth, segmentation


def _check_sensor_depth(depth, width: int, height: int, where: str) -> np.ndarray:
    depth = np.asarray(depth, dtype=np.float32)
    if depth.shape != (height, width):
        raise ValueError(f"{where}: sensor depth must be ({height}, {width}), got {depth.shape}")
    return depth


def _extensions(entry: dict, time: Optional[float], joints: Optional[dict]) -> dict:
    if time is not None:
        if not 0.0 <= float(time) <= 1.0:
            raise ValueError(f"frame time must be in [0, 1], got {time}")
        entry["time"] = float(time)
    if joints is not None:
        entry["joints"] = {str(k): float(v) for k, v in joints.items()}
    return entry


class NerfstudioWriter:
    """Streams frames into a nerfstudio dataset folder ``root``.

    Args:
        root: dataset folder (created).
        fx, fy, cx, cy: intrinsics in pixels (pixel centres at +0.5), shared by all frames.
        width, height: image size in pixels.
    """

    format = "nerfstudio"

    def __init__(self, root: Path, fx: float, fy: float, cx: float, cy: float, width: int,
                 height: int):
        self.root = Path(root)
        self.width, self.height = int(width), int(height)
        self.intrinsics = dict(fl_x=float(fx), fl_y=float(fy), cx=float(cx), cy=float(cy),
                               w=self.width, h=self.height)
        self.frames: list[dict] = []
        self.splits: dict[str, list[str]] = {}

    def add_frame(self, rgb: np.ndarray, c2w: np.ndarray, split: str = "train",
                  depth: Optional[np.ndarray] = None, segmentation: Optional[np.ndarray] = None,
                  time: Optional[float] = None, joints: Optional[dict] = None,
                  sensor_depth: Optional[np.ndarray] = None) -> dict:
        """Write one frame's files and remember its JSON entry (returned).

        Args:
            rgb: (H, W, 3) uint8. c2w: (4, 4) pose. depth: (H, W) z-depth, metres.
            segmentation: (H, W) geom ids. split: "train", "val" or "test".
            sensor_depth: (H, W) z-depth of a simulated depth sensor, metres (NaN = no return).
        """
        index = len(self.frames)
        stem = f"frame_{index:05d}"
        where = f"{self.root}: frame {index}"
        pose = check_pose(c2w, where)
        rgb, depth, segmentation = _check_frame(rgb, depth, segmentation, self.width,
                                                self.height, where)
        entry = {"file_path": f"images/{stem}.png", "transform_matrix": pose.tolist()}
        write_png(self.root / entry["file_path"], rgb)
        if depth is not None:
            entry.update(write_depth_files(self.root, f"depth/{stem}", depth))
        if segmentation is not None:
            entry["segmentation_path"] = f"segmentation/{stem}.npy"
            _save_npy(self.root / entry["segmentation_path"], segmentation)
        if sensor_depth is not None:
            entry["sensor_depth_file_path"] = f"sensor_depth/{stem}.npy"
            _save_npy(self.root / entry["sensor_depth_file_path"],
                      _check_sensor_depth(sensor_depth, self.width, self.height, where))
        self.frames.append(_extensions(entry, time, joints))
        self.splits.setdefault(split, []).append(entry["file_path"])
        return entry

    def finish(self, manifest: Optional[dict] = None) -> Path:
        """Write ``transforms.json`` (with ``scene`` = ``manifest`` unless None); return its path."""
        if not self.frames:
            raise ValueError(f"{self.root}: no frames to write")
        doc = {"camera_model": "OPENCV", **self.intrinsics,
               "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": self.frames}
        for split in ("train", "val", "test"):
            if split in self.splits:
                doc[f"{split}_filenames"] = list(self.splits[split])
        if "val" not in self.splits and "test" in self.splits:
            doc["val_filenames"] = list(self.splits["test"])
        if manifest is not None:
            doc["scene"] = manifest
        return write_json_atomic(self.root / "transforms.json", doc)


class BlenderWriter:
    """Streams frames into a Blender-synthetic dataset folder ``root`` (one file per split).

    The Blender format describes a centred pinhole with square pixels by its horizontal field
    of view only; other intrinsics raise ``ValueError``.
    """

    format = "blender"

    def __init__(self, root: Path, fx: float, fy: float, cx: float, cy: float, width: int,
                 height: int):
        if (abs(fx - fy) > 1e-9 * fx or abs(cx - width / 2.0) > 1e-9 * width
                or abs(cy - height / 2.0) > 1e-9 * height):
            raise ValueError("the Blender format needs square pixels and a centred principal "
                             f"point, got fx={fx} fy={fy} cx={cx} cy={cy} for {width}x{height}")
        self.root = Path(root)
        self.width, self.height = int(width), int(height)
        self.camera_angle_x = 2.0 * math.atan(0.5 * width / fx)
        self.frames: dict[str, list[dict]] = {}

    def add_frame(self, rgb: np.ndarray, c2w: np.ndarray, split: str = "train",
                  depth: Optional[np.ndarray] = None, segmentation: Optional[np.ndarray] = None,
                  time: Optional[float] = None, joints: Optional[dict] = None,
                  sensor_depth: Optional[np.ndarray] = None) -> dict:
        """Write one frame as ``<split>/r_<i>.png`` (+ ``_depth.npy``, ``_seg.npy``)."""
        frames = self.frames.setdefault(split, [])
        stem = f"{split}/r_{len(frames)}"
        where = f"{self.root}: {split} frame {len(frames)}"
        pose = check_pose(c2w, where)
        rgb, depth, segmentation = _check_frame(rgb, depth, segmentation, self.width,
                                                self.height, where)
        entry = {"file_path": f"./{stem}", "transform_matrix": pose.tolist()}
        write_png(self.root / f"{stem}.png", rgb)
        if depth is not None:
            entry["depth_file_path"] = f"./{stem}_depth.npy"
            _save_npy(self.root / f"{stem}_depth.npy", depth)
        if segmentation is not None:
            entry["segmentation_path"] = f"./{stem}_seg.npy"
            _save_npy(self.root / f"{stem}_seg.npy", segmentation)
        if sensor_depth is not None:
            entry["sensor_depth_file_path"] = f"./{stem}_sensor_depth.npy"
            _save_npy(self.root / f"{stem}_sensor_depth.npy",
                      _check_sensor_depth(sensor_depth, self.width, self.height, where))
        frames.append(_extensions(entry, time, joints))
        return entry

    def finish(self, manifest: Optional[dict] = None) -> Path:
        """Write ``transforms_<split>.json`` for every split; return the train file's path."""
        if not self.frames:
            raise ValueError(f"{self.root}: no frames to write")
        written = []
        for split, frames in self.frames.items():
            doc = {"camera_angle_x": self.camera_angle_x, "frames": frames}
            if manifest is not None:
                doc["scene"] = manifest
            written.append(write_json_atomic(self.root / f"transforms_{split}.json", doc))
        return self.root / "transforms_train.json" if "train" in self.frames else written[0]


def _save_npy(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, array)


def open_writer(fmt: str, root: Path, fx: float, fy: float, cx: float, cy: float, width: int,
                height: int) -> NerfstudioWriter | BlenderWriter:
    """A writer of format ``fmt`` ("nerfstudio" or "blender") into ``root``."""
    if fmt == "nerfstudio":
        return NerfstudioWriter(root, fx, fy, cx, cy, width, height)
    if fmt == "blender":
        return BlenderWriter(root, fx, fy, cx, cy, width, height)
    raise ValueError(f"unknown dataset format '{fmt}' (choose from {FORMATS})")
