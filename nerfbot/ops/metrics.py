"""Image and depth quality metrics."""

from __future__ import annotations

import math

import cv2
import numpy as np


#: SSIM's window (Wang et al. 2004; OpenCV's quality module): 11 x 11 Gaussian, sigma 1.5, and
#: its stabilising constants for 8-bit intensities.
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5
SSIM_C1, SSIM_C2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2


def psnr(pred: np.ndarray, target: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio (dB) of images in [0, 1]; +inf for identical images.

    ``valid``: optional (H, W) bool; the mean squared error is then taken over those pixels only
    (ValueError if there are none).
    """
    err = (np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2
    if valid is not None:
        valid = np.asarray(valid, bool)
        if not valid.any():
            raise ValueError("psnr: no valid pixel")
        err = err[valid]
    mse = float(np.mean(err))
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def ssim(pred: np.ndarray, target: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Structural similarity (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5) of (H, W, 3)
    images in [0, 1], averaged over channels (OpenCV's quality module).

    ``valid``: optional (H, W) bool. Each window's means, variances and covariance are then
    Gaussian-weighted over its valid pixels only (normalised convolution), and the SSIM map is
    averaged over the valid pixels, so invalid pixels' values have no influence at all. With
    every pixel valid this equals the unmasked SSIM (to float32 rounding).
    """
    p = np.clip(np.asarray(pred, np.float64), 0, 1) * 255.0
    t = np.clip(np.asarray(target, np.float64), 0, 1) * 255.0
    if valid is not None:
        return _masked_ssim(p, t, np.asarray(valid, bool))
    score = cv2.quality.QualitySSIM_compute(t, p)[0]
    return float(np.mean(score[: p.shape[-1] if p.ndim == 3 else 1]))


def _masked_ssim(p: np.ndarray, t: np.ndarray, valid: np.ndarray) -> float:
    """SSIM of (H, W[, C]) images in [0, 255] over the ``valid`` (H, W) pixels (:func:`ssim`)."""
    if not valid.any():
        raise ValueError("ssim: no valid pixel")

    def blur(x):
        return cv2.GaussianBlur(x, (SSIM_WINDOW, SSIM_WINDOW), SSIM_SIGMA)

    m = valid.astype(np.float64)
    weight = np.maximum(blur(m), 1e-12)
    scores = []
    for c in range(p.shape[2] if p.ndim == 3 else 1):
        x = np.where(valid, p[..., c] if p.ndim == 3 else p, 0.0)
        y = np.where(valid, t[..., c] if t.ndim == 3 else t, 0.0)
        mx, my = blur(x) / weight, blur(y) / weight
        vx = blur(x * x) / weight - mx * mx
        vy = blur(y * y) / weight - my * my
        cxy = blur(x * y) / weight - mx * my
        score = ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)
                 / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2)))
        scores.append(float(score[valid].mean()))
    return float(np.mean(scores))


def depth_errors(pred: np.ndarray, target: np.ndarray, valid: np.ndarray) -> dict:
    """Depth errors on ``valid`` pixels whose target is positive: mae and rmse (metres), bias
    (the mean of pred - target, metres: negative when the surfaces come out too near), abs_rel
    (the mean of |pred - target| / target, the error as a fraction of the distance) and the
    pixel count."""
    target = np.asarray(target, np.float64)
    v = np.asarray(valid, bool) & np.isfinite(target) & np.isfinite(pred)
    v[v] = target[v] > 0
    if not v.any():
        return {"mae": float("nan"), "rmse": float("nan"), "bias": float("nan"),
                "abs_rel": float("nan"), "count": 0}
    err = np.asarray(pred, np.float64)[v] - target[v]
    return {"mae": float(np.abs(err).mean()), "rmse": float(np.sqrt((err ** 2).mean())),
            "bias": float(err.mean()), "abs_rel": float((np.abs(err) / target[v]).mean()),
            "count": int(v.sum())}
