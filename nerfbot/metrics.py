"""Image and depth quality metrics."""

from __future__ import annotations

import math

import cv2
import numpy as np


def psnr(pred: np.ndarray, target: np.ndarray) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1]; +inf for identical images."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def ssim(pred: np.ndarray, target: np.ndarray) -> float:
    """Structural similarity (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5) of (H, W, 3)
    images in [0, 1], averaged over channels (OpenCV's quality module)."""
    p = np.clip(np.asarray(pred, np.float64), 0, 1) * 255.0
    t = np.clip(np.asarray(target, np.float64), 0, 1) * 255.0
    score = cv2.quality.QualitySSIM_compute(t, p)[0]
    return float(np.mean(score[: p.shape[-1] if p.ndim == 3 else 1]))


def depth_errors(pred: np.ndarray, target: np.ndarray, valid: np.ndarray) -> dict:
    """Absolute depth errors (metres) on ``valid`` pixels: mae, rmse and the pixel count."""
    v = np.asarray(valid, bool) & np.isfinite(target) & np.isfinite(pred)
    if not v.any():
        return {"mae": float("nan"), "rmse": float("nan"), "count": 0}
    err = np.asarray(pred, np.float64)[v] - np.asarray(target, np.float64)[v]
    return {"mae": float(np.abs(err).mean()), "rmse": float(np.sqrt((err ** 2).mean())),
            "count": int(v.sum())}
