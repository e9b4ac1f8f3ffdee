"""Evaluate a trained model on a dataset split: image quality, depth accuracy, render speed."""

from __future__ import annotations

import time

import numpy as np
import torch

from nerfbot.data.dataset import Dataset
from nerfbot.metrics import depth_errors, psnr, ssim
from nerfbot.models import Model
from nerfbot.query import render_image


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


def evaluate(model: Model, dataset: Dataset, split: str = "test", max_images: int | None = None,
             with_ssim: bool = True) -> dict:
    """Render every frame of ``split`` and compare with the ground truth.

    Returns psnr / ssim (means over images), depth_mae_m / depth_rmse_m (over all valid depth
    pixels: finite and inside the bounds), render_ms_per_image (median), num_images.
    """
    indices = dataset.indices(split)[:max_images]
    cams = dataset.cameras(indices)
    psnrs, ssims, times = [], [], []
    abs_err, sq_err, n_depth = 0.0, 0.0, 0
    for slot, i in enumerate(indices):
        cond = None if dataset.times is None else [float(dataset.times[i])]
        t0 = time.perf_counter()
        out = render_image(model, cams, slot, cond=cond)
        times.append(time.perf_counter() - t0)
        gt = dataset.image_float(i)
        psnrs.append(psnr(out["rgb"], gt))
        if with_ssim:
            ssims.append(ssim(out["rgb"], gt))
        valid = depth_valid_mask(dataset, i)
        if valid is not None:
            e = depth_errors(out["z_depth"], dataset.depths[i], valid)
            if e["count"]:
                abs_err += e["mae"] * e["count"]
                sq_err += e["rmse"] ** 2 * e["count"]
                n_depth += e["count"]
    result = {
        "psnr": float(np.mean(psnrs)) if psnrs else float("nan"),
        "ssim": float(np.mean(ssims)) if ssims else float("nan"),
        "depth_mae_m": abs_err / n_depth if n_depth else None,
        "depth_rmse_m": float(np.sqrt(sq_err / n_depth)) if n_depth else None,
        "render_ms_per_image": float(np.median(times) * 1e3) if times else None,
        "num_images": len(indices),
    }
    return result
