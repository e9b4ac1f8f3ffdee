"""Evaluate a trained model on a dataset split: image quality, depth accuracy, render speed."""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from nerfbot.conditioning import dataset_conditioning, frame_conditions
from nerfbot.data.dataset import Dataset
from nerfbot.metrics import depth_errors, psnr, ssim
from nerfbot.models import Model
from nerfbot.query import render_image


#: Pixels added around the objects' mask for ``psnr_objects``, so a render that misplaces an
#: object's silhouette by a pixel or two is still scored there.
OBJECT_MASK_DILATION_PX = 2


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    import cv2

    if px <= 0 or not mask.any():
        return mask
    kernel = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)


def depth_valid_mask(dataset: Dataset, i: int) -> np.ndarray | None:
    """Pixels of frame ``i`` whose ground-truth depth is finite and whose 3D point lies inside
    the scene bounds; None when the frame has no depth."""
    depth = dataset.depths[i]
    if depth is None:
        return None
    cams = dataset.cameras([i])
    rays = cams.rays(0)
    z = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)).reshape(-1)
    finite = torch.isfinite(z)
    t = torch.where(finite, z, torch.zeros_like(z)) / rays.z_per_t
    pts = rays.origins + rays.directions * t[:, None]
    lo, hi = torch.as_tensor(dataset.aabb, dtype=torch.float32)
    inside = ((pts >= lo) & (pts <= hi)).all(-1) & finite
    return inside.reshape(depth.shape).numpy()


def object_geom_ids(dataset: Dataset) -> np.ndarray | None:
    """Geom ids of the objects the scene manifest declares (``objects``), or None."""
    manifest = dataset.manifest or {}
    names = set(manifest.get("objects") or ())
    if not names:
        return None
    return np.array([int(g) for g, n in manifest.get("geoms", {}).items() if n in names], np.int32)


class _DepthErrorSum:
    """Running absolute / squared depth error over many images."""

    def __init__(self):
        self.abs, self.sq, self.n = 0.0, 0.0, 0

    def add(self, pred, target, valid):
        e = depth_errors(pred, target, valid)
        if e["count"]:
            self.abs += e["mae"] * e["count"]
            self.sq += e["rmse"] ** 2 * e["count"]
            self.n += e["count"]

    def mae(self):
        return self.abs / self.n if self.n else None

    def rmse(self):
        return float(np.sqrt(self.sq / self.n)) if self.n else None


def evaluate(model: Model, dataset: Dataset, split: str = "test", max_images: int | None = None,
             with_ssim: bool = True) -> dict:
    """Render every frame of ``split`` and compare with the ground truth.

    Returns psnr / ssim (means over images); depth_mae_m / depth_rmse_m of the expected z-depth
    over all valid depth pixels (finite and inside the bounds); depth_mae_objects_m /
    depth_rmse_objects_m over the valid pixels of the objects the manifest declares (None without
    segmentation or objects); median_depth_mae_m / median_depth_mae_objects_m, the same for
    the median depth (robust at object edges, where the expected depth blends two surfaces);
    psnr_objects: PSNR pooled over the pixels of those objects, their mask dilated by
    :data:`OBJECT_MASK_DILATION_PX` (in dynamic and articulated scenes the objects are what
    moves, a small part of each image; None without segmentation or objects);
    render_ms_per_image (median over images); num_images.
    """
    indices = dataset.indices(split)[:max_images]
    cams = dataset.cameras(indices)
    psnrs, ssims, times = [], [], []
    all_px, obj_px = _DepthErrorSum(), _DepthErrorSum()
    all_med, obj_med = _DepthErrorSum(), _DepthErrorSum()
    objects = object_geom_ids(dataset)
    obj_sq, obj_n = 0.0, 0
    conds = frame_conditions(dataset, dataset_conditioning(dataset))
    for slot, i in enumerate(indices):
        cond = None if conds is None else conds[i]
        t0 = time.perf_counter()
        out = render_image(model, cams, slot, cond=cond)
        times.append(time.perf_counter() - t0)
        gt = dataset.image_float(i)
        psnrs.append(psnr(out["rgb"], gt))
        if with_ssim:
            ssims.append(ssim(out["rgb"], gt))
        seg = dataset.segmentations[i]
        if objects is not None and seg is not None:
            mask = _dilate(np.isin(seg, objects), OBJECT_MASK_DILATION_PX)
            obj_sq += float(((out["rgb"][mask] - gt[mask]).astype(np.float64) ** 2).sum())
            obj_n += 3 * int(mask.sum())
        valid = depth_valid_mask(dataset, i)
        if valid is not None:
            all_px.add(out["z_depth"], dataset.depths[i], valid)
            all_med.add(out["median_z_depth"], dataset.depths[i], valid)
            if objects is not None and seg is not None:
                on_objects = valid & np.isin(seg, objects)
                obj_px.add(out["z_depth"], dataset.depths[i], on_objects)
                obj_med.add(out["median_z_depth"], dataset.depths[i], on_objects)
    result = {
        "psnr": float(np.mean(psnrs)) if psnrs else float("nan"),
        "ssim": float(np.mean(ssims)) if ssims else float("nan"),
        "psnr_objects": (None if not obj_n else float("inf") if obj_sq == 0
                         else -10.0 * math.log10(obj_sq / obj_n)),
        "depth_mae_m": all_px.mae(),
        "depth_rmse_m": all_px.rmse(),
        "depth_mae_objects_m": obj_px.mae(),
        "depth_rmse_objects_m": obj_px.rmse(),
        "median_depth_mae_m": all_med.mae(),
        "median_depth_mae_objects_m": obj_med.mae(),
        "render_ms_per_image": float(np.median(times) * 1e3) if times else None,
        "num_images": len(indices),
    }
    return result
