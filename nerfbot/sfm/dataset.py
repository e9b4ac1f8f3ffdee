"""From images to a posed dataset: gather the input, run structure from motion, put the cameras
in a useful frame, write a nerfstudio dataset.

Inputs: a folder of images (intrinsics unknown: one shared camera is estimated, or given by
``focal_px``), or an existing dataset (its intrinsics are used and kept fixed; its poses are
only used to measure and align the recovered ones).

The frame of the written poses:

- a dataset with poses (e.g. a ``sims`` capture): the recovered cameras are mapped onto the
  dataset's by the least-squares similarity of their centres (Umeyama), so the result is in
  metres and in the scene's frame, and the pose errors are reported;
- plain images: the mean camera "up" becomes +z and the median sparse point the origin. The
  scale is COLMAP's (arbitrary) unless a ``baseline`` gives the distance in metres between two
  cameras (e.g. from a robot's odometry).

Output layout::

    OUT/transforms.json        nerfstudio: shared intrinsics, registered frames, split lists
    OUT/images/...             the registered images (copies, or downscaled PNGs)
    OUT/sparse_depth/...       per image: the sparse points it sees as (u, v, z-depth, sigma)
                               rows, float32 .npy, for DS-NeRF (frames[].sparse_depth_file_path)
    OUT/sparse_pc.ply          COLMAP's sparse points in the frame of transforms.json
    OUT/colmap/database.db     features and matches (without the repeated features dropped
                               by SfmOptions.drop_repeated)
    OUT/colmap/database_every_feature.db   every feature, and the verified pairs' matches
                               of the second stage (SfmOptions.refine_all_features), whose
                               keypoints the refined model observes
    OUT/colmap/every_feature/  the second stage's triangulation, before its refinement
    OUT/colmap/mapper/RUN/     each mapping run's models as found (COLMAP's frame, before
                               refinement)
    OUT/colmap/sparse/0/       the refined model: the input's image names and pixels, the frame
                               of transforms.json
    OUT/sfm_report.json        registration, timings, reprojection error, pose errors
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import pycolmap

from nerfbot.data.colmap import image_c2w
from nerfbot.data.errors import DatasetError
from nerfbot.data.intrinsics import resolve_intrinsics
from nerfbot.data.readers import default_splits, parse_dataset
from nerfbot.data.spec import EXACT_DEPTH_FIELD, IMAGE_EXTENSIONS, normalise_rel
from nerfbot.data.writers import write_depth_files, write_json_atomic
from nerfbot.ops.alignment import PoseErrors, Similarity, pose_errors
from nerfbot.sfm.keypoints import image_keypoints
from nerfbot.sfm.pipeline import (CameraPrior, SfmOptions, SfmResult, run_sfm,
                                  triangulate_known_poses)

log = logging.getLogger(__name__)

#: Per-frame files carried from an input dataset (resized with the images).
_COMPANIONS = (("depth_path", "depth_file_path"), ("mask_path", "mask_path"),
               ("segmentation_path", "segmentation_path"),
               ("sensor_depth_path", "sensor_depth_file_path"))


@dataclass
class SfmInput:
    """The images to pose and what is known about them.

    Attributes:
        root: folder the image names are relative to.
        names: image paths relative to ``root``, in capture order.
        camera: known shared intrinsics, or None to estimate them.
        true_c2w: name -> (4, 4) known pose (OpenGL, metres), or None.
        splits: name -> "train" / "test", or None (the reader's default rule applies).
        frames: name -> the input frame's extra fields to carry (paths relative to ``root``,
            time, joints).
        manifest: the input's scene manifest, or None.
        depth_unit_scale_factor: the input's integer-depth unit, or None.
    """

    root: Path
    names: list[str]
    camera: Optional[CameraPrior] = None
    true_c2w: Optional[dict] = None
    splits: Optional[dict] = None
    frames: Optional[dict] = None
    manifest: Optional[dict] = None
    depth_unit_scale_factor: Optional[float] = None


def images_input(folder: Path, focal_px: Optional[float] = None) -> SfmInput:
    """Every image (.png, .jpg, .jpeg) under ``folder``, sorted by path; with ``focal_px`` the
    camera is a pinhole of that focal length (pixels) centred on the image, kept fixed."""
    folder = Path(folder)
    names = sorted(str(p.relative_to(folder).as_posix()) for p in folder.rglob("*")
                   if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if len(names) < 2:
        raise DatasetError(f"{folder}: found {len(names)} images (.png, .jpg, .jpeg); structure "
                           "from motion needs at least 2")
    camera = None
    if focal_px is not None:
        if not focal_px > 0:
            raise ValueError(f"focal_px: must be > 0, got {focal_px}")
        height, width = _image_size(folder / names[0])
        camera = CameraPrior("PINHOLE", (focal_px, focal_px, width / 2.0, height / 2.0))
    return SfmInput(root=folder, names=names, camera=camera)


def _image_size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: cannot read the image")
    return image.shape[:2]


def dataset_input(path: Path) -> SfmInput:
    """The images of an existing dataset, with its (shared) intrinsics, poses and splits."""
    parsed = parse_dataset(path)
    root = Path(parsed.root).resolve()
    names, true_c2w, frames = [], {}, {}
    intrinsics = None
    for spec in parsed.frames:
        name = spec.image_path.relative_to(root).as_posix()
        height, width = _image_size(spec.image_path)
        intr = resolve_intrinsics(spec.camera, width, height, spec.where)
        key = (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height, intr.model,
               intr.coeffs)
        if intrinsics is None:
            intrinsics = (key, spec.where)
        elif key != intrinsics[0]:
            raise DatasetError(f"{spec.where}: intrinsics differ from {intrinsics[1]}'s; "
                               "structure from motion here shares one camera across images")
        names.append(name)
        true_c2w[name] = spec.c2w
        extra = {(spec.depth_field if attr == "depth_path" else field):
                 spec_path(spec, attr, root) for attr, field in _COMPANIONS
                 if getattr(spec, attr) is not None}
        if spec.time is not None:
            extra["time"] = spec.time
        if spec.joints is not None:
            extra["joints"] = spec.joints
        frames[name] = extra
    (fx, fy, cx, cy, _, _, model, coeffs), _ = intrinsics
    if model == "PINHOLE" or not any(coeffs):
        camera = CameraPrior("PINHOLE", (fx, fy, cx, cy))
    elif model == "OPENCV" and coeffs[4] == 0.0:
        camera = CameraPrior("OPENCV", (fx, fy, cx, cy, *coeffs[:4]))
    else:
        raise DatasetError(f"{parsed.frames[0].where}: {model} distortion {coeffs} is not "
                           "supported for structure from motion (OPENCV without k3 is)")
    split_index = parsed.splits if parsed.splits is not None else default_splits(len(names))
    splits = {}
    for split in ("train", "test"):
        for i in split_index.get(split, []):
            splits[names[i]] = split
    return SfmInput(root=root, names=names, camera=camera, true_c2w=true_c2w, splits=splits,
                    frames=frames, manifest=parsed.manifest,
                    depth_unit_scale_factor=parsed.frames[0].depth_scale)


def spec_path(spec, attr: str, root: Path) -> str:
    """The frame's ``attr`` file as a path relative to ``root``."""
    return Path(getattr(spec, attr)).relative_to(root).as_posix()


def _up_and_centre(rec: "pycolmap.Reconstruction", c2w: np.ndarray) -> Similarity:
    """Rigid transform putting the mean camera up axis on +z and the median point at 0."""
    up = c2w[:, :3, 1].mean(0)
    up /= max(np.linalg.norm(up), 1e-12)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = np.linalg.norm(axis), float(up @ z)
    if s < 1e-9:
        rotation = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = axis / s
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rotation = np.eye(3) + s * kx + (1 - c) * kx @ kx
    points = np.array([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() else \
        c2w[:, :3, 3]
    centre = np.median(points, axis=0)
    return Similarity(1.0, rotation, -rotation @ centre)


def choose_frame(rec: "pycolmap.Reconstruction", sfm_input: SfmInput,
                 baseline: Optional[tuple[str, str, float]] = None
                 ) -> tuple[Similarity, str, Optional[PoseErrors]]:
    """(transform COLMAP frame -> output frame, description, pose errors or None)."""
    images = {im.name: im for im in rec.images.values() if im.has_pose}
    names = sorted(images)
    c2w = np.stack([image_c2w(images[n]) for n in names])
    if sfm_input.true_c2w is not None:
        if len(names) < 3:
            raise ValueError(f"only {len(names)} images registered; aligning to the dataset's "
                             "poses needs 3")
        true = np.stack([sfm_input.true_c2w[n] for n in names])
        errors = pose_errors(c2w, true)
        return (errors.alignment, "aligned to the input dataset's poses (Umeyama similarity of "
                "the camera centres): metres, the scene's frame", errors)
    frame = _up_and_centre(rec, c2w)
    if baseline is None:
        return frame, ("mean camera up = +z, median sparse point at the origin; scale: "
                       "COLMAP's arbitrary unit (give a baseline for metres)"), None
    a, b, metres = baseline
    missing = [n for n in (a, b) if n not in images]
    if missing:
        raise ValueError(f"baseline: image(s) {missing} not registered (or not in the input)")
    distance = float(np.linalg.norm(c2w[names.index(a), :3, 3] - c2w[names.index(b), :3, 3]))
    if not metres > 0 or distance <= 0:
        raise ValueError(f"baseline: need a positive distance, got {metres} m for cameras "
                         f"{distance:.3g} units apart")
    scale = Similarity(metres / distance, np.eye(3), np.zeros(3))
    return frame.then(scale), (f"mean camera up = +z, median sparse point at the origin; metres "
                               f"from the baseline {a} - {b} = {metres} m"), None


def _transform(rec: "pycolmap.Reconstruction", sim: Similarity) -> None:
    rec.transform(pycolmap.Sim3d(sim.scale, pycolmap.Rotation3d(sim.rotation),
                                 sim.translation))


def _camera_json(camera: "pycolmap.Camera", scale_x: float, scale_y: float) -> dict:
    """nerfstudio intrinsics of a pycolmap camera resized by (scale_x, scale_y)."""
    model = camera.model.name
    p = [float(v) for v in camera.params]
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        k = p[3:] + [0.0] * (2 - len(p[3:]))
        dist = {"k1": k[0], "k2": k[1], "p1": 0.0, "p2": 0.0}
    elif model in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy = p[:4]
        rest = p[4:] + [0.0] * (4 - len(p[4:]))
        dist = dict(zip(("k1", "k2", "p1", "p2"), rest))
    else:
        raise RuntimeError(f"unexpected camera model {model} from structure from motion")
    width, height = round(camera.width * scale_x), round(camera.height * scale_y)
    return {"camera_model": "OPENCV", "fl_x": fx * scale_x, "fl_y": fy * scale_y,
            "cx": cx * scale_x, "cy": cy * scale_y, "w": width, "h": height, **dist}


def _write_image(src: Path, dst: Path, downscale: int) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if downscale == 1:
        shutil.copyfile(src, dst)
        return
    image = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{src}: cannot read the image")
    height, width = image.shape[:2]
    small = cv2.resize(image, (round(width / downscale), round(height / downscale)),
                       interpolation=cv2.INTER_AREA)
    if not cv2.imwrite(str(dst), small):
        raise OSError(f"could not write image {dst}")


def _resize_nearest(array: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, ...) -> (height, width, ...) by the nearest source pixel of each output centre
    (no blending across surfaces, any dtype)."""
    h, w = array.shape[:2]
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return array[rows[:, None], cols[None, :]]


def _resize_nearest_file(src: Path, downscale: int) -> np.ndarray:
    """A depth / mask / segmentation file's array (.npy or image), resized by the nearest pixel
    at ``downscale``."""
    if src.suffix.lower() == ".npy":
        array = np.load(src, allow_pickle=False)
    else:
        array = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        if array is None:
            raise DatasetError(f"{src}: cannot read the image")
    if downscale == 1:
        return array
    h, w = array.shape[:2]
    return _resize_nearest(array, round(w / downscale), round(h / downscale))


def _copy_companion(src: Path, dst: Path, downscale: int) -> None:
    """Copy a depth / mask / segmentation file, resized by the nearest pixel at ``downscale``."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if downscale == 1:
        shutil.copyfile(src, dst)
        return
    small = _resize_nearest_file(src, downscale)
    if src.suffix.lower() == ".npy":
        np.save(dst, small)
    elif not cv2.imwrite(str(dst), small):
        raise OSError(f"could not write {dst}")


def _output_name(sfm_input: SfmInput, name: str, downscale: int) -> str:
    rel = name if sfm_input.true_c2w is not None else f"images/{name}"
    rel = normalise_rel(rel)
    if not rel.startswith("images/"):
        rel = f"images/{rel}"
    return str(Path(rel).with_suffix(".png")) if downscale > 1 else rel


def check_new_folder(out: Path) -> None:
    """Refuse an output folder that exists and is not empty (nothing a user made is touched)."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out}: exists and is not an empty folder; choose a new --out")


def poses_from_images(sfm_input: SfmInput, out: Path, options: Optional[SfmOptions] = None,
                      downscale: int = 1, baseline: Optional[tuple[str, str, float]] = None,
                      known_poses: bool = False, progress: bool = True) -> dict:
    """Run structure from motion on ``sfm_input`` and write the posed dataset ``out``.

    Args:
        sfm_input: from :func:`images_input` or :func:`dataset_input`.
        out: a new (or empty) folder.
        options: structure-from-motion choices (:class:`SfmOptions`).
        downscale: write the images (and intrinsics) this many times smaller (integer >= 1);
            structure from motion always runs on the full images. Depth, masks and
            segmentations are carried, resized by the nearest pixel.
        baseline: (image name, image name, metres) fixing the scale of plain images.
        known_poses: keep the input dataset's poses and only triangulate sparse points with
            them (:func:`~nerfbot.sfm.pipeline.triangulate_known_poses`), e.g. for sparse depth
            supervision of a capture whose poses a robot's kinematics give.
        progress: show progress bars.

    Returns:
        The report written to ``out/sfm_report.json``.
    """
    if int(downscale) != downscale or downscale < 1:
        raise ValueError(f"downscale: expected an integer >= 1, got {downscale}")
    downscale = int(downscale)
    out = Path(out)
    check_new_folder(out)
    if known_poses and (sfm_input.true_c2w is None or sfm_input.camera is None):
        raise ValueError("known poses: the input must be a dataset with poses and intrinsics")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _pose_and_write(sfm_input, out, options, downscale, baseline, known_poses,
                               progress)
    except BaseException:  # leave no half-written dataset behind (the folder was new or empty)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        else:
            for child in out.iterdir():
                if child.is_dir():
                    shutil.rmtree(child)
                else:
                    child.unlink()
        raise


def _pose_and_write(sfm_input: SfmInput, out: Path, options: Optional[SfmOptions],
                    downscale: int, baseline, known_poses: bool, progress: bool) -> dict:
    """The work of :func:`poses_from_images` in its (new, empty) output folder."""
    if known_poses:
        result: SfmResult = triangulate_known_poses(
            sfm_input.root, sfm_input.names, out / "colmap", sfm_input.camera,
            sfm_input.true_c2w, options=options, progress=progress)
        frame, frame_text, errors = (Similarity.identity(), "the input dataset's poses, kept; "
                                     "sparse points triangulated with them", None)
    else:
        result = run_sfm(sfm_input.root, sfm_input.names, out / "colmap",
                         camera=sfm_input.camera, options=options, progress=progress)
        frame, frame_text, errors = choose_frame(result.reconstruction, sfm_input, baseline)
    rec = result.reconstruction
    _transform(rec, frame)
    model_dir = out / "colmap" / "sparse" / "0"
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(model_dir))
    rec.export_PLY(str(out / "sparse_pc.ply"))

    cameras = {im.camera_id for im in rec.images.values() if im.has_pose}
    camera = rec.cameras[min(cameras)]
    sample = sfm_input.root / result.registered[0]
    height, width = _image_size(sample)
    scale_x = round(width / downscale) / width
    scale_y = round(height / downscale) / height
    meta = _camera_json(camera, scale_x, scale_y)
    images = {im.name: im for im in rec.images.values() if im.has_pose}
    keypoints = image_keypoints(rec, scale_x, scale_y)
    entries, lists = [], {"train": [], "test": []}
    for name in result.registered:
        rel = _output_name(sfm_input, name, downscale)
        _write_image(sfm_input.root / name, out / rel, downscale)
        entry = {"file_path": rel, "transform_matrix": image_c2w(images[name]).tolist()}
        if len(keypoints.get(name, ())):
            sparse = str(Path("sparse_depth", *Path(rel).parts[1:]).with_suffix(".npy"))
            (out / sparse).parent.mkdir(parents=True, exist_ok=True)
            np.save(out / sparse, keypoints[name])
            entry["sparse_depth_file_path"] = sparse
        for key, value in ((sfm_input.frames or {}).get(name) or {}).items():
            if key == EXACT_DEPTH_FIELD:  # the exact depth, and nerfstudio's PNG beside it
                depth = _resize_nearest_file(sfm_input.root / value, downscale)
                entry.update(write_depth_files(out, str(Path(value).with_suffix("")), depth))
                continue
            if key.endswith("_path"):
                _copy_companion(sfm_input.root / value, out / value, downscale)
            entry[key] = value
        entries.append(entry)
        if sfm_input.splits is not None:
            lists[sfm_input.splits.get(name, "train")].append(rel)
    meta["frames"] = entries
    if sfm_input.splits is not None:
        meta["train_filenames"] = lists["train"]
        meta["val_filenames"] = list(lists["test"])
        meta["test_filenames"] = lists["test"]
    meta["ply_file_path"] = "sparse_pc.ply"
    if sfm_input.depth_unit_scale_factor is not None:
        meta["depth_unit_scale_factor"] = sfm_input.depth_unit_scale_factor
    if sfm_input.manifest is not None and (errors is not None or known_poses):
        meta["scene"] = sfm_input.manifest
    write_json_atomic(out / "transforms.json", meta)

    report = {"input": str(sfm_input.root), **result.summary(), "frame": frame_text,
              "colmap_to_output": {"scale": frame.scale, "rotation": frame.rotation.tolist(),
                                   "translation": frame.translation.tolist()},
              "downscale": downscale, "pycolmap": pycolmap.__version__,
              "options": vars(options or SfmOptions())}
    if errors is not None:
        report["pose_errors"] = errors.summary()
        report["pose_errors_per_image"] = {
            n: {"rotation_deg": float(r), "translation_percent": float(t)}
            for n, r, t in zip(sorted(images), errors.rotation_deg, errors.translation_percent)}
    write_json_atomic(out / "sfm_report.json", report)
    return report


