"""COLMAP models (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``) read as datasets,
through pycolmap's ``Reconstruction``.

Accepted layouts (the first that matches)::

    project/                      project/                 model/   (given directly)
      images/...                    images/...               cameras.bin, images.bin, ...
      sparse/0/cameras.bin, ...     sparse/cameras.bin, ...

A model folder given directly finds its images in ``images/`` beside it, one level up or two
levels up (``project/sparse/0`` -> ``project/images``). Registered images become frames, sorted
by name; the dataset root is the folder holding ``images/``. COLMAP's poses are world-to-camera
in the OpenCV convention: :func:`c2w_from_cam_from_world` turns them into nerfbot's OpenGL c2w.
COLMAP's pixel convention (centre of the top-left pixel at (0.5, 0.5)) is nerfbot's, so
principal points pass through unchanged.

The supported pycolmap release is :data:`PYCOLMAP_SERIES` (its API changed across releases:
option names, ``cam_from_world`` as a property or a method); :func:`require_pycolmap` says so
clearly on any other.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import pycolmap

from nerfbot.data.errors import DatasetError
from nerfbot.data.spec import FrameSpec, ParsedDataset, inside_root
from nerfbot.ops.cameras import check_pose, opencv_to_opengl, opengl_to_opencv

#: The pycolmap release series nerfbot is written against (pyproject pins it).
PYCOLMAP_SERIES = "4.2"

#: COLMAP camera model -> the nerfstudio keys its parameters fill, in COLMAP's order.
_CAMERA_PARAMS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fl_x", "fl_y", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2"),
    "OPENCV_FISHEYE": ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4"),
}
_MODEL_FILES = ("cameras", "images", "points3D")


def require_pycolmap() -> None:
    """Raise RuntimeError unless the installed pycolmap belongs to :data:`PYCOLMAP_SERIES`."""
    version = getattr(pycolmap, "__version__", "unknown")
    if not version.startswith(PYCOLMAP_SERIES + "."):
        raise RuntimeError(
            f"nerfbot's COLMAP support is written for pycolmap {PYCOLMAP_SERIES}.x, found "
            f"{version} (option names and pose accessors differ between releases); install it "
            f"with: pip install 'pycolmap~={PYCOLMAP_SERIES}.1'")


def c2w_from_cam_from_world(cam_from_world: np.ndarray) -> np.ndarray:
    """(4, 4) OpenGL c2w from a COLMAP world-to-camera (3, 4) or (4, 4) OpenCV matrix."""
    m = np.eye(4)
    m[:3] = np.asarray(cam_from_world, dtype=np.float64)[:3]
    return opencv_to_opengl(np.linalg.inv(m))


def cam_from_world_from_c2w(c2w: np.ndarray) -> np.ndarray:
    """(3, 4) COLMAP world-to-camera (OpenCV) matrix of an OpenGL c2w (4, 4)."""
    return np.linalg.inv(opengl_to_opencv(c2w))[:3]


def image_c2w(image: "pycolmap.Image") -> np.ndarray:
    """The (4, 4) OpenGL c2w of a registered pycolmap image."""
    return c2w_from_cam_from_world(image.cam_from_world().matrix())


def camera_fields_of(camera: "pycolmap.Camera", where: str) -> dict:
    """nerfstudio intrinsics keys of a pycolmap camera as key -> (value, where), the form
    :func:`nerfbot.data.intrinsics.resolve_intrinsics` reads."""
    model = camera.model.name
    if model not in _CAMERA_PARAMS:
        raise DatasetError(f"{where}: camera model {model} is not supported (supported: "
                           f"{', '.join(_CAMERA_PARAMS)})")
    fields = {"camera_model": model, "w": int(camera.width), "h": int(camera.height)}
    for key, value in zip(_CAMERA_PARAMS[model], np.asarray(camera.params, dtype=np.float64)):
        if key == "f":
            fields["fl_x"] = fields["fl_y"] = float(value)
        else:
            fields[key] = float(value)
    return {k: (v, f"{where}.{k}") for k, v in fields.items()}


def _has_model(folder: Path) -> bool:
    return all(any((folder / f"{name}{ext}").is_file() for ext in (".bin", ".txt"))
               for name in _MODEL_FILES)


def find_colmap_model(path: Path) -> Optional[tuple[Path, Path]]:
    """(model folder, images folder) of a COLMAP project or model folder, or None when
    ``path`` holds no model. DatasetError when the model is there but its images are not."""
    path = Path(path)
    for model in (path / "sparse" / "0", path / "sparse", path):
        if model.is_dir() and _has_model(model):
            break
    else:
        return None
    for images in (path / "images", model.parent / "images", model.parent.parent / "images"):
        if images.is_dir():
            return model, images
    raise DatasetError(f"{model}: COLMAP model found but no images/ folder beside it, one or two "
                       "levels up (expected project/images with project/sparse/0)")


def read_reconstruction(model: Path) -> "pycolmap.Reconstruction":
    """pycolmap's Reconstruction of a model folder; DatasetError naming it if unreadable."""
    require_pycolmap()
    try:
        return pycolmap.Reconstruction(str(model))
    except Exception as e:  # pycolmap raises plain RuntimeError / ValueError for bad files
        raise DatasetError(f"{model}: cannot read the COLMAP model: "
                           f"{str(e).strip().splitlines()[-1] if str(e).strip() else e}") from None


def parse_colmap(model: Path, images: Path) -> ParsedDataset:
    """Frames of a COLMAP model's registered images (sorted by name), poses in OpenGL c2w."""
    rec = read_reconstruction(model)
    root = images.parent
    registered = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not registered:
        raise DatasetError(f"{model}: images: no registered image in the COLMAP model")
    frames = []
    for im in registered:
        where = f"{model}: images[{im.name}]"
        image_path = images / im.name
        if not image_path.is_file():
            raise DatasetError(f"{where}: image file not found: {image_path}")
        image_path = inside_root(image_path, root, where)
        try:
            c2w = check_pose(image_c2w(im), f"{where}.cam_from_world")
        except ValueError as e:
            raise DatasetError(str(e)) from None
        camera = camera_fields_of(rec.cameras[im.camera_id], f"{model}: cameras[{im.camera_id}]")
        frames.append(FrameSpec(
            where=where, file_path=f"{images.name}/{im.name}", image_path=image_path,
            c2w=c2w, camera=camera, per_frame_intrinsics=True,
            group=f"{model}: cameras[{im.camera_id}]"))
    return ParsedDataset(
        root=root, format="colmap", frames=frames, splits=None, manifest=None,
        manifest_where=str(model), json_files=[],
        extras={"colmap_model": str(model), "colmap_points": int(rec.num_points3D())},
    )
