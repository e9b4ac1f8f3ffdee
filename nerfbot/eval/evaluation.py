"""Evaluate a trained model on a dataset split: image quality, depth accuracy, render speed."""

from __future__ import annotations

import math
import time

import cv2
import numpy as np

from nerfbot.data.conditioning import dataset_conditioning, frame_conditions
from nerfbot.data.dataset import Dataset
from nerfbot.data.errors import DatasetError
from nerfbot.data.labels import label_map, mean_iou
from nerfbot.data.pixels import depth_valid_mask
from nerfbot.models.base import Model
from nerfbot.ops.cameras import Cameras
from nerfbot.ops.metrics import depth_errors, psnr, ssim
from nerfbot.query.localise import InerfConfig, inerf, pose_error
from nerfbot.query.render import render_image


#: Pixels added around the objects' mask for ``psnr_objects``, so a render that misplaces an
#: object's silhouette by a pixel or two is still scored there.
OBJECT_MASK_DILATION_PX = 2


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0 or not mask.any():
        return mask
    kernel = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def object_geom_ids(dataset: Dataset) -> np.ndarray | None:
    """Geom ids of the objects the scene manifest declares (``objects``), or None."""
    manifest = dataset.manifest or {}
    names = set(manifest.get("objects") or ())
    if not names:
        return None
    return np.array([int(g) for g, n in manifest.get("geoms", {}).items() if n in names], np.int32)


def wall_geom_ids(dataset: Dataset) -> np.ndarray | None:
    """Geom ids of the walls the scene manifest names (names starting with ``wall``, as the
    ``room`` and ``room_glass`` scenes name theirs), or None when it names none."""
    geoms = (dataset.manifest or {}).get("geoms", {})
    ids = [int(g) for g, n in geoms.items() if str(n).startswith("wall")]
    return np.array(ids, np.int32) if ids else None


def downscale_area(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` (H, W) or (H, W, C) resized to (height, width) by area averaging
    (cv2.INTER_AREA, the multiscale protocol's ground truth), as float32."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.shape[:2] == (height, width):
        return image
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def downscale_depth(depth: np.ndarray, valid: np.ndarray, width: int, height: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth depth (H, W) at a lower resolution: each low-resolution pixel is the
    area-weighted mean of the full-resolution depths it covers, and it is valid only when all
    of them are valid (a block that is partly invalid, e.g. straddling the scene bounds, is
    dropped rather than averaged over its valid part). Returns (depth, valid), (height, width)."""
    v = valid.astype(np.float32)
    d = np.where(valid, np.nan_to_num(np.asarray(depth, np.float32)), 0.0)
    cover = downscale_area(v, width, height)
    total = downscale_area(d * v, width, height)
    ok = cover >= 1.0 - 1e-4
    return np.where(ok, total / np.maximum(cover, 1e-12), np.nan).astype(np.float32), ok


def pixel_mask(dataset: Dataset, i: int, width: int, height: int) -> np.ndarray | None:
    """(height, width) bool, the pixels of frame ``i`` to score at that resolution: its mask
    (:meth:`Dataset.valid_mask`), and below full resolution the low-resolution pixels whose
    whole block is valid (so no masked colour leaks into a score); None when all are valid."""
    mask = dataset.valid_mask(i)
    if mask is None:
        return None
    if mask.shape != (height, width):
        mask = downscale_area(mask.astype(np.float32), width, height) >= 1.0 - 1e-4
    return mask


def eval_indices(dataset: Dataset, split: str, max_images: int | None = None) -> list[int]:
    """The first ``max_images`` frames of ``split``; :class:`DatasetError` naming the dataset
    and the split when there is none to evaluate (a missing or empty split)."""
    indices = dataset.indices(split)[:max_images]
    if not indices:
        why = ("is empty" if not dataset.indices(split)
               else f"gives no frame with max_images={max_images}")
        raise DatasetError(f"{dataset.root}: the '{split}' split {why}; nothing to evaluate "
                           f"(splits: {dataset.split_sizes()})")
    return indices


class _DepthErrorSum:
    """Running absolute / squared / relative depth error over many images."""

    def __init__(self):
        self.abs, self.sq, self.rel, self.signed, self.n = 0.0, 0.0, 0.0, 0.0, 0

    def add(self, pred, target, valid):
        e = depth_errors(pred, target, valid)
        if e["count"]:
            self.abs += e["mae"] * e["count"]
            self.sq += e["rmse"] ** 2 * e["count"]
            self.rel += e["abs_rel"] * e["count"]
            self.signed += e["bias"] * e["count"]
            self.n += e["count"]

    def mae(self):
        return self.abs / self.n if self.n else None

    def abs_rel(self):
        return self.rel / self.n if self.n else None

    def bias(self):
        return self.signed / self.n if self.n else None

    def rmse(self):
        return float(np.sqrt(self.sq / self.n)) if self.n else None


class _PooledPSNR:
    """PSNR pooled over the selected pixels of many images (one squared-error sum)."""

    def __init__(self):
        self.sq, self.n = 0.0, 0

    def add(self, pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> None:
        """``pred``, ``target`` (H, W, 3) in [0, 1]; ``mask`` (H, W) bool, the pixels to pool."""
        self.sq += float(((pred[mask] - target[mask]).astype(np.float64) ** 2).sum())
        self.n += 3 * int(mask.sum())

    def value(self) -> float | None:
        """dB; None when no pixel was pooled, inf for a perfect match."""
        if not self.n:
            return None
        return float("inf") if self.sq == 0 else -10.0 * math.log10(self.sq / self.n)


def evaluate(model: Model, dataset: Dataset, split: str = "test", max_images: int | None = None,
             with_ssim: bool = True, downscale: int = 1, supersample: int | None = None,
             refine_poses: InerfConfig | None = None,
             supersample_pattern: str | None = None) -> dict:
    """Render every frame of ``split`` and compare with the ground truth.

    Returns psnr / ssim (means over images); depth_mae_m / depth_rmse_m of the expected z-depth
    over all valid depth pixels (finite and inside the bounds); depth_mae_objects_m /
    depth_rmse_objects_m over the valid pixels of the objects the manifest declares (None without
    segmentation or objects); depth_abs_rel: over all valid depth pixels, the mean of the
    expected z-depth's error as a fraction of the true depth; depth_abs_rel_walls,
    depth_mae_walls_m and depth_bias_walls_m: the same, the MAE and the mean signed error
    (negative: walls too near) over the pixels of the walls the manifest names
    (:func:`wall_geom_ids`; None without segmentation or walls); median_depth_mae_m /
    median_depth_mae_objects_m: the MAEs of the median depth (robust at object edges, where the
    expected depth blends two surfaces); depth_spread_m: the median over the valid depth pixels
    of how far along its ray the centre ray's weight spreads
    (:func:`~nerfbot.ops.rendering.depth_spread`): about a marching step on a sharp surface,
    more where the field is fog;
    psnr_objects: PSNR pooled over the pixels of those objects, their mask dilated by
    :data:`OBJECT_MASK_DILATION_PX` (in dynamic and articulated scenes the objects are what
    moves, a small part of each image; None without segmentation or objects); psnr_non_sky:
    PSNR pooled over the pixels that show a geom (segmentation >= 0; at 1/K resolution, pixels
    whose whole block does), so a scene that is mostly sky is not scored mostly on its sky
    (None without segmentation); for a model with a label head and test frames with
    segmentation, label_miou (mean IoU over the classes present, pooled over the frames'
    pixels: :func:`~nerfbot.data.labels.mean_iou`) and label_iou {class: IoU};
    render_ms_per_image (median over images); num_images; downscale; supersample;
    supersample_pattern.

    Pixels the dataset's masks mark invalid (``mask_path``, or outside an undistorted image)
    are left out of every score: psnr takes the mean squared error over the valid pixels, ssim
    weights each window's statistics over its valid pixels and averages the SSIM map over the
    valid pixels (:func:`~nerfbot.ops.metrics.ssim`); frames without a valid pixel count in
    num_images and render time only.

    Colour is rendered with ``supersample`` x ``supersample`` rays per pixel (None: the
    model's own :attr:`~nerfbot.models.base.Model.supersample`) spread over each pixel as
    ``supersample_pattern`` says (None: the model's), depth from the pixel centres
    (:func:`~nerfbot.query.render.render_image`).

    ``downscale`` K > 1 evaluates at 1/K resolution (the multiscale protocol): the cameras are
    :meth:`~nerfbot.ops.cameras.Cameras.scaled` by 1/K, the ground-truth images area-averaged
    (:func:`downscale_area`), depth compared on low-resolution pixels whose K x K block is
    entirely valid, against the block's mean depth (:func:`downscale_depth`); object masks
    (a low-resolution pixel belongs to the objects if any of its block does, then dilated) for
    psnr_objects, and blocks entirely on objects for the object depth errors; a low-resolution
    pixel is valid only when its whole block is (:func:`pixel_mask`).

    ``refine_poses`` (an iNeRF setting, :func:`~nerfbot.query.localise.inerf`): each frame's
    pose is first refined against the model from the dataset's, and the frame is scored there
    (for views posed by structure from motion: their pose errors are then not counted as the
    field's; BARF's protocol). ``pose_refinement`` reports how far the poses moved (medians,
    metres and degrees).

    Raises:
        DatasetError: the split is missing or empty, or every pixel of its frames is masked out.
    """
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise ValueError(f"downscale must be a positive integer, got {downscale!r}")
    downscale = int(downscale)
    indices = eval_indices(dataset, split, max_images)
    conds = frame_conditions(dataset, dataset_conditioning(dataset, tracks=False))
    c2w = dataset.c2w[indices]
    moved = None
    if refine_poses is not None:
        if conds is not None:
            raise ValueError("pose refinement is for static scenes (this dataset has time or "
                             "joints)")
        c2w = np.stack([inerf(model, dataset.images[i], dataset.intrinsics[i], dataset.c2w[i],
                              refine_poses, seed=int(i)).c2w for i in indices])
        moved = [pose_error(new, old) for new, old in zip(c2w, dataset.c2w[indices])]
    cams = Cameras.from_numpy(c2w, dataset.intrinsics[indices], dataset.sizes[indices])
    if downscale > 1:
        cams = cams.scaled(1.0 / downscale)
    head = model.label_head
    label_pred, label_true = [], []
    psnrs, ssims, times = [], [], []
    all_px, obj_px = _DepthErrorSum(), _DepthErrorSum()
    all_med, obj_med = _DepthErrorSum(), _DepthErrorSum()
    spreads = []
    objects = object_geom_ids(dataset)
    walls = wall_geom_ids(dataset)
    wall_px = _DepthErrorSum()
    on_objects_psnr, non_sky_psnr = _PooledPSNR(), _PooledPSNR()
    for slot, i in enumerate(indices):
        cond = None if conds is None else conds[i]
        t0 = time.perf_counter()
        out = render_image(model, cams, slot, cond=cond, supersample=supersample,
                           labels=head is not None, supersample_pattern=supersample_pattern)
        times.append(time.perf_counter() - t0)
        h, w = out["rgb"].shape[:2]
        gt = downscale_area(dataset.image_float(i), w, h)
        scored = pixel_mask(dataset, i, w, h)
        if scored is None or scored.any():
            psnrs.append(psnr(out["rgb"], gt, scored))
            if with_ssim:
                ssims.append(ssim(out["rgb"], gt, scored))
        seg = dataset.segmentations[i]
        if head is not None and seg is not None:
            # a low-resolution pixel is scored against the class at its block's centre
            k = downscale
            truth = label_map(seg, head.classes, dataset.valid_mask(i))[k // 2::k, k // 2::k]
            label_true.append(truth[:h, :w].reshape(-1))
            label_pred.append(out["labels"].argmax(-1).reshape(-1))
        if seg is not None:
            content = downscale_area((seg >= 0).astype(np.float32), w, h) >= 1.0 - 1e-4
            non_sky_psnr.add(out["rgb"], gt, content if scored is None else content & scored)
        on_obj = None
        if objects is not None and seg is not None:
            cover = downscale_area(np.isin(seg, objects).astype(np.float32), w, h)
            on_obj = cover >= 1.0 - 1e-4  # pixels entirely on objects (all of them when K = 1)
            mask = _dilate(cover > 0, OBJECT_MASK_DILATION_PX)
            if scored is not None:
                mask &= scored
            on_objects_psnr.add(out["rgb"], gt, mask)
        valid = depth_valid_mask(dataset, i)
        if valid is not None:
            depth = dataset.depths[i]
            if downscale > 1:
                depth, valid = downscale_depth(depth, valid, w, h)
            all_px.add(out["z_depth"], depth, valid)
            spreads.append(out["depth_spread"][valid])
            all_med.add(out["median_z_depth"], depth, valid)
            if on_obj is not None:
                on_objects = valid & on_obj
                obj_px.add(out["z_depth"], depth, on_objects)
                obj_med.add(out["median_z_depth"], depth, on_objects)
            if walls is not None and seg is not None:
                on_walls = downscale_area(np.isin(seg, walls).astype(np.float32), w, h)
                wall_px.add(out["z_depth"], depth, valid & (on_walls >= 1.0 - 1e-4))
    if not psnrs:
        raise DatasetError(f"{dataset.root}: every pixel of the {len(indices)} '{split}' frame(s) "
                           "is masked out; nothing to evaluate")
    result = {
        "psnr": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)) if ssims else float("nan"),
        "psnr_objects": on_objects_psnr.value(),
        "psnr_non_sky": non_sky_psnr.value(),
        "depth_mae_m": all_px.mae(),
        "depth_rmse_m": all_px.rmse(),
        "depth_mae_objects_m": obj_px.mae(),
        "depth_rmse_objects_m": obj_px.rmse(),
        "depth_abs_rel": all_px.abs_rel(),
        "depth_abs_rel_walls": wall_px.abs_rel(),
        "depth_mae_walls_m": wall_px.mae(),
        "depth_bias_walls_m": wall_px.bias(),
        "median_depth_mae_m": all_med.mae(),
        "median_depth_mae_objects_m": obj_med.mae(),
        "depth_spread_m": float(np.median(np.concatenate(spreads)))
        if sum(map(len, spreads)) else None,
        "render_ms_per_image": float(np.median(times) * 1e3) if times else None,
        "num_images": len(indices),
        "downscale": downscale,
        "supersample": model.supersample if supersample is None else supersample,
        "supersample_pattern": model.supersample_pattern if supersample_pattern is None
        else supersample_pattern,
    }
    if label_true:
        miou, iou = mean_iou(np.concatenate(label_pred), np.concatenate(label_true),
                             head.n_classes)
        result["label_miou"] = miou
        result["label_iou"] = {name: (None if np.isnan(v) else float(v))
                               for name, v in zip(head.classes.names, iou)}
    if moved is not None:
        result["pose_refinement"] = {
            "translation_m_median": float(np.median([m[0] for m in moved])),
            "rotation_deg_median": float(np.median([m[1] for m in moved]))}
    return result
