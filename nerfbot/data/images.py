"""Pixel side of the readers: images, depth, masks, segmentation, alpha compositing, undistortion.

All functions are vectorised (OpenCV / numpy); errors are :class:`DatasetError` prefixed by
the JSON field that named the file.
"""

from __future__ import annotations

import threading
from functools import lru_cache
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from nerfbot.data.errors import DatasetError
from nerfbot.data.intrinsics import Intrinsics

#: Millimetres to metres, the default unit of 16-bit depth PNGs.
DEFAULT_DEPTH_SCALE = 1e-3

# np.load parses a .npy header with ast.literal_eval, and CPython 3.11's AST constructor keeps
# its recursion depth per interpreter, not per thread (gh-106905): two frames parsed at once on
# the readers' threads raise "SystemError: AST constructor recursion depth mismatch".
_NPY_LOCK = threading.Lock()


def _imread(path: Path, where: str, what: str) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{where}: cannot read {what} file {path} (missing, unreadable or "
                           "not an image format OpenCV decodes)")
    return img


def _to_uint8(img: np.ndarray, where: str, path: Path) -> np.ndarray:
    """uint8 as is; uint16 rescaled to [0, 255] with rounding."""
    if img.dtype == np.uint8:
        return img
    if img.dtype == np.uint16:
        return ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    raise DatasetError(f"{where}: image {path} has pixel type {img.dtype}; "
                       "expected 8- or 16-bit unsigned")


def read_image(path: Path, where: str) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Read an image as RGB.

    Returns:
        rgb: (H, W, 3) uint8; grey images are replicated to three channels.
        alpha: (H, W) uint8 if the file has an alpha channel, else None.
    """
    img = _to_uint8(_imread(path, where, "image"), where, path)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB), None
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB), None
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB), np.ascontiguousarray(img[:, :, 3])
    raise DatasetError(f"{where}: image {path} has shape {img.shape}; expected 1, 3 or 4 channels")


def composite(rgb: np.ndarray, alpha: np.ndarray, background: tuple) -> np.ndarray:
    """Blend (H, W, 3) uint8 ``rgb`` (straight alpha) over a constant colour in [0, 1].

    Returns (H, W, 3) uint8 ``rgb * a + background * (1 - a)`` with ``a = alpha / 255``.
    """
    a = alpha.astype(np.float32)[:, :, None] * np.float32(1.0 / 255.0)
    bg = np.asarray(background, dtype=np.float32) * np.float32(255.0)
    out = rgb.astype(np.float32) * a + bg * (np.float32(1.0) - a)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _check_shape(arr: np.ndarray, shape: tuple, where: str, what: str, path: Path) -> None:
    if arr.shape != shape:
        raise DatasetError(f"{where}: {what} {path} has shape {arr.shape} but the image is "
                           f"(H, W) = {shape}")


def _load_npy(path: Path, where: str, what: str) -> np.ndarray:
    try:
        with _NPY_LOCK:
            return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise DatasetError(f"{where}: cannot read {what} file {path}: {e}") from None


def _squeeze(arr: np.ndarray) -> np.ndarray:
    return arr[:, :, 0] if arr.ndim == 3 and arr.shape[2] == 1 else arr


def read_depth(path: Path, where: str, shape: tuple, unit_scale: float) -> np.ndarray:
    """Read a z-depth map as (H, W) float32 metres.

    ``.npy``: float metres; ``inf`` = no surface, NaN = unknown. Images (PNG, TIFF, ...):
    16-bit integers times ``unit_scale`` (default 1e-3, millimetres), 0 = unknown (NaN); float
    images are metres. Negative depth is an error.
    """
    if path.suffix.lower() == ".npy":
        raw = _squeeze(_load_npy(path, where, "depth"))
        if raw.dtype.kind != "f":
            raise DatasetError(f"{where}: depth {path} has dtype {raw.dtype}; .npy depth must be "
                               "float metres")
        depth = raw.astype(np.float32, copy=False)
    else:
        raw = _squeeze(_imread(path, where, "depth"))
        if raw.dtype == np.uint16:
            depth = raw.astype(np.float32) * np.float32(unit_scale)
            depth[raw == 0] = np.nan
        elif raw.dtype.kind == "f":
            depth = raw.astype(np.float32, copy=False)
        else:
            raise DatasetError(f"{where}: depth image {path} has pixel type {raw.dtype}; expected "
                               "16-bit (millimetres) or float (metres)")
    if depth.ndim != 2:
        raise DatasetError(f"{where}: depth {path} has shape {depth.shape}; expected (H, W)")
    _check_shape(depth, shape, where, "depth map", path)
    negative = depth < 0
    if negative.any():
        raise DatasetError(f"{where}: depth {path} has {int(negative.sum())} negative value(s) "
                           f"(min {float(np.nanmin(depth)):.4g}); depth must be >= 0")
    return np.ascontiguousarray(depth)


def read_mask(path: Path, where: str, shape: tuple) -> np.ndarray:
    """Read a validity mask as (H, W) bool: nonzero (in any channel) = valid."""
    raw = (_load_npy(path, where, "mask") if path.suffix.lower() == ".npy"
           else _imread(path, where, "mask"))
    mask = raw != 0
    if mask.ndim == 3:
        mask = mask.any(axis=2)
    _check_shape(mask, shape, where, "mask", path)
    return mask


def read_segmentation(path: Path, where: str, shape: tuple) -> np.ndarray:
    """Read a segmentation as (H, W) int32 ids (.npy of integers, or a 1-channel 8/16-bit image)."""
    raw = _squeeze(_load_npy(path, where, "segmentation") if path.suffix.lower() == ".npy"
                   else _imread(path, where, "segmentation"))
    if raw.dtype.kind not in "iu":
        raise DatasetError(f"{where}: segmentation {path} has dtype {raw.dtype}; expected integers")
    info = np.iinfo(np.int32)
    if raw.size and (raw.min() < info.min or raw.max() > info.max):
        raise DatasetError(f"{where}: segmentation {path} has ids outside the int32 range")
    seg = raw.astype(np.int32, copy=False)
    if seg.ndim != 2:
        raise DatasetError(f"{where}: segmentation {path} has shape {seg.shape}; expected (H, W)")
    _check_shape(seg, shape, where, "segmentation", path)
    return np.ascontiguousarray(seg)


def read_keypoints(path: Path, where: str, shape: tuple) -> np.ndarray:
    """Read sparse depth as (K, 4) float32: u, v (pixels, centres at +0.5), z-depth and its
    standard deviation (metres). Keypoints outside the (H, W) image ``shape`` or with a
    non-positive depth or deviation are refused."""
    raw = _load_npy(path, where, "sparse depth")
    if raw.ndim != 2 or raw.shape[1] != 4 or not np.issubdtype(raw.dtype, np.floating):
        raise DatasetError(f"{where}: sparse depth {path} has shape {raw.shape} {raw.dtype}; "
                           "expected (K, 4) floats: u, v, z-depth, sigma")
    keys = raw.astype(np.float32)
    h, w = shape
    bad = ~np.isfinite(keys).all(1) | (keys[:, 0] < 0) | (keys[:, 0] > w) | (keys[:, 1] < 0) \
        | (keys[:, 1] > h) | (keys[:, 2] <= 0) | (keys[:, 3] <= 0)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DatasetError(f"{where}: sparse depth {path}: row {k} {keys[k].tolist()} is not a "
                           f"keypoint inside the {w}x{h} image with positive depth and sigma")
    return keys


class Undistorter:
    """Remap tables that undistort images of one camera while keeping the same K.

    OpenCV's pixel centres are at integer coordinates, nerfbot's at +0.5, so the principal point
    handed to OpenCV is ``(cx - 0.5, cy - 0.5)``.

    Attributes:
        map_x, map_y: (H, W) float32 source pixel coordinates (OpenCV convention) of each
            undistorted pixel.
        valid: (H, W) bool, the source point lies inside the distorted image (bilinear
            interpolation uses real pixels only).
    """

    def __init__(self, intr: Intrinsics):
        k = np.array([[intr.fx, 0.0, intr.cx - 0.5],
                      [0.0, intr.fy, intr.cy - 0.5],
                      [0.0, 0.0, 1.0]])
        size = (intr.width, intr.height)
        coeffs = np.asarray(intr.coeffs, dtype=np.float64)
        self.k, self.coeffs, self.model = k, coeffs, intr.model
        if intr.model == "OPENCV_FISHEYE":
            self.map_x, self.map_y = cv2.fisheye.initUndistortRectifyMap(
                k, coeffs, np.eye(3), k, size, cv2.CV_32FC1)
        elif intr.model == "OPENCV":
            self.map_x, self.map_y = cv2.initUndistortRectifyMap(
                k, coeffs, None, k, size, cv2.CV_32FC1)
        else:
            raise ValueError(f"no undistortion for camera model {intr.model}")
        w, h = intr.width, intr.height
        mx, my = self.map_x, self.map_y
        self.valid = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        # non-finite or huge source coordinates (absurd coefficients) become "outside"
        xi = np.rint(np.clip(np.nan_to_num(mx, nan=-1.0), -1, w)).astype(np.int64)
        yi = np.rint(np.clip(np.nan_to_num(my, nan=-1.0), -1, h)).astype(np.int64)
        self._near_ok = ((xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)).reshape(-1)
        self._near_idx = (np.clip(yi, 0, h - 1) * w + np.clip(xi, 0, w - 1)).reshape(-1).astype(
            np.int32 if w * h < 2**31 else np.int64)

    def linear(self, img: np.ndarray, border=0) -> np.ndarray:
        """Bilinear remap of an (H, W) or (H, W, C) uint8 / float image; ``border`` outside."""
        if img.ndim == 3 and not isinstance(border, (int, float)):
            border = tuple(float(b) for b in border) + (0.0,) * (4 - img.shape[2])
        return cv2.remap(img, self.map_x, self.map_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=border)

    def points(self, uv: np.ndarray) -> np.ndarray:
        """(K, 2) pixel coordinates (centres at +0.5) in the distorted image -> the same points
        in the undistorted image (same K)."""
        if not len(uv):
            return np.asarray(uv, dtype=np.float32).reshape(0, 2)
        src = (np.asarray(uv, dtype=np.float64) - 0.5).reshape(-1, 1, 2)
        if self.model == "OPENCV_FISHEYE":
            out = cv2.fisheye.undistortPoints(src, self.k, self.coeffs, P=self.k)
        else:
            out = cv2.undistortPoints(src, self.k, self.coeffs, P=self.k)
        return (out.reshape(-1, 2) + 0.5).astype(np.float32)

    def nearest(self, arr: np.ndarray, fill) -> np.ndarray:
        """Nearest-neighbour remap of an (H, W) array of any dtype; ``fill`` outside.

        No value is invented: every output is a source value or ``fill``.
        """
        out = arr.reshape(-1)[self._near_idx]
        out[~self._near_ok] = fill
        return out.reshape(arr.shape)


@lru_cache(maxsize=4)
def undistorter(intr: Intrinsics) -> Undistorter:
    """The (cached) :class:`Undistorter` of a camera; frames sharing a camera share tables.

    About 9 bytes per pixel per entry; ``undistorter.cache_clear()`` releases them.
    """
    return Undistorter(intr)
