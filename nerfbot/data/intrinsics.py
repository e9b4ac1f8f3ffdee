"""Resolve a frame's intrinsics and lens distortion from nerfstudio / instant-ngp / Blender keys.

Focal length, in priority order per axis: ``fl_x`` (pixels), ``x_fov`` (degrees, instant-ngp),
``camera_angle_x`` (radians, Blender / instant-ngp); likewise ``fl_y``, ``y_fov``,
``camera_angle_y``. A missing axis takes the other's focal (square pixels). ``cx``, ``cy``
default to the image centre ``w / 2``, ``h / 2`` (pixel centres at +0.5, as in nerfstudio and
:mod:`nerfbot.ops.cameras`).

Distortion models: ``OPENCV`` (also ``SIMPLE_RADIAL``, ``RADIAL``) with k1, k2, p1, p2 and
optional k3; ``OPENCV_FISHEYE`` (or instant-ngp ``is_fisheye``) with k1..k4; ``PINHOLE`` /
``SIMPLE_PINHOLE`` without distortion. With no ``camera_model``, non-zero k1, k2, k3, p1, p2
mean OPENCV.

Plausibility (so that float32 rays stay finite): ``fx / max(w, h)`` and ``fy / max(w, h)`` in
[1e-4, 1e4] (fields of view from about 0.006 to 179.99 degrees), and the principal point within
``1e4 * max(w, h)`` pixels of the image centre (crops of large sensors keep theirs far out).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from nerfbot.data.errors import DatasetError
from nerfbot.data.spec import number
from nerfbot.ops.cameras import focal_from_fov

log = logging.getLogger(__name__)

#: Range of focal length / longer image side, and the largest principal point offset from the
#: image centre in units of the longer side (see the module docstring).
FOCAL_RATIO_RANGE = (1e-4, 1e4)
MAX_PRINCIPAL_OFFSET = 1e4

_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_OPENCV_MODELS = ("OPENCV", "SIMPLE_RADIAL", "RADIAL")
_FISHEYE_MODELS = ("OPENCV_FISHEYE",)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one image plus the distortion to remove.

    Attributes:
        fx, fy, cx, cy: pixels, principal point with pixel centres at +0.5.
        width, height: image size in pixels.
        model: "PINHOLE", "OPENCV" or "OPENCV_FISHEYE" (the source model, canonicalised).
        coeffs: OPENCV (k1, k2, p1, p2, k3); OPENCV_FISHEYE (k1, k2, k3, k4); PINHOLE ().
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    model: str = "PINHOLE"
    coeffs: tuple = ()

    @property
    def distorted(self) -> bool:
        """True when the image needs undistortion (some coefficient is non-zero)."""
        return any(c != 0.0 for c in self.coeffs)


def _focal(camera: dict, axis: str, size: int) -> float | None:
    """Focal length (pixels) along ``axis`` ("x" or "y") from the first key present."""
    fl_key, fov_key, angle_key = f"fl_{axis}", f"{axis}_fov", f"camera_angle_{axis}"
    if fl_key in camera:
        value, where = camera[fl_key]
        return number(value, where, positive=True)
    for key, to_degrees in ((fov_key, False), (angle_key, True)):
        if key in camera:
            value, where = camera[key]
            fov = number(value, where, positive=True)
            try:
                return focal_from_fov(math.degrees(fov) if to_degrees else fov, size)
            except ValueError as e:
                unit = "radians" if to_degrees else "degrees"
                raise DatasetError(f"{where}: {e} (this field is in {unit})") from None
    return None


def _coeff(camera: dict, key: str) -> float:
    if key not in camera:
        return 0.0
    value, where = camera[key]
    return number(value, where)


def _distortion(camera: dict, where: str) -> tuple[str, tuple]:
    """(canonical model, coefficients) from ``camera_model`` / ``is_fisheye`` and k*, p*."""
    k = {name: _coeff(camera, name) for name in ("k1", "k2", "k3", "k4", "p1", "p2")}
    if "camera_model" in camera:
        raw, model_where = camera["camera_model"]
        if not isinstance(raw, str):
            raise DatasetError(f"{model_where}: expected a string, got {raw!r}")
        model = raw.upper()
    elif "is_fisheye" in camera and camera["is_fisheye"][0] is True:
        model, model_where = "OPENCV_FISHEYE", camera["is_fisheye"][1]
    else:
        if k["k4"] != 0.0:
            raise DatasetError(f"{camera['k4'][1]}: k4 without a camera_model is ambiguous; "
                               "set camera_model to OPENCV_FISHEYE")
        model = "OPENCV" if any(k.values()) else "PINHOLE"
        model_where = f"{where}.camera_model"

    if model in _PINHOLE_MODELS:
        if any(k.values()):
            log.warning("%s: camera_model %s declares no distortion; ignoring k/p coefficients",
                        model_where, model)
        return "PINHOLE", ()
    if model in _OPENCV_MODELS:
        if k["k4"] != 0.0:
            raise DatasetError(f"{camera['k4'][1]}: k4 is not a coefficient of {model} "
                               "(k1, k2, p1, p2, k3); use OPENCV_FISHEYE")
        return "OPENCV", (k["k1"], k["k2"], k["p1"], k["p2"], k["k3"])
    if model in _FISHEYE_MODELS:
        for name in ("p1", "p2"):
            if k[name] != 0.0:
                raise DatasetError(f"{camera[name][1]}: {name} is not a coefficient of "
                                   "OPENCV_FISHEYE (k1..k4)")
        return "OPENCV_FISHEYE", (k["k1"], k["k2"], k["k3"], k["k4"])
    raise DatasetError(f"{model_where}: unsupported camera_model {model!r} (supported: "
                       f"{', '.join(_PINHOLE_MODELS + _OPENCV_MODELS + _FISHEYE_MODELS)})")


def _field(camera: dict, keys: tuple, where: str) -> str:
    """The "<json file>: <field>" of the first of ``keys`` present, else ``where``."""
    return next((camera[k][1] for k in keys if k in camera), where)


def _check_plausible(camera: dict, fx: float, fy: float, cx: float, cy: float, width: int,
                     height: int, where: str) -> None:
    """DatasetError naming the field when a focal length or the principal point is absurd for a
    ``width`` x ``height`` image (thresholds in the module docstring)."""
    side = max(width, height)
    lo, hi = FOCAL_RATIO_RANGE
    for axis, f in (("x", fx), ("y", fy)):
        if not lo <= f / side <= hi:
            field = _field(camera, (f"fl_{axis}", f"{axis}_fov", f"camera_angle_{axis}",
                                    "fl_x", "fl_y", "x_fov", "y_fov", "camera_angle_x",
                                    "camera_angle_y"), where)
            raise DatasetError(f"{field}: focal length {f:.6g} px is implausible for a "
                               f"{width}x{height} image (must be {lo:g} to {hi:g} times the "
                               "longer side)")
    for key, c, size in (("cx", cx, width), ("cy", cy, height)):
        if abs(c - size / 2.0) > MAX_PRINCIPAL_OFFSET * side:
            raise DatasetError(f"{_field(camera, (key,), where)}: principal point {c:.6g} px is "
                               f"implausibly far from the centre of a {width}x{height} image")


def resolve_intrinsics(camera: dict, width: int, height: int, where: str) -> Intrinsics:
    """Intrinsics of a ``width`` x ``height`` image from merged camera fields.

    Args:
        camera: key -> (value, "<json file>: <field>") as built by
            :func:`nerfbot.data.spec.camera_fields` (per-frame values already override global).
        width, height: the image size in pixels (already checked against declared w, h).
        where: "<json file>: frames[i]", for errors about missing fields.
    """
    fx = _focal(camera, "x", width)
    fy = _focal(camera, "y", height)
    if fx is None and fy is None:
        raise DatasetError(f"{where}: no intrinsics: need fl_x (or fl_y, x_fov, camera_angle_x) "
                           "at the top level or in the frame")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    cx = number(camera["cx"][0], camera["cx"][1]) if "cx" in camera else width / 2.0
    cy = number(camera["cy"][0], camera["cy"][1]) if "cy" in camera else height / 2.0
    _check_plausible(camera, fx, fy, cx, cy, width, height, where)
    model, coeffs = _distortion(camera, where)
    return Intrinsics(fx, fy, cx, cy, int(width), int(height), model, coeffs)
