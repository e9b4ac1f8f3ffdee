"""Images, depth visualisations and comparison sheets (OpenCV); videos are in
:mod:`nerfbot.query.video`."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Optional

import cv2
import numpy as np


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8 RGB."""
    return (np.clip(np.asarray(rgb, np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_image(path, rgb: np.ndarray) -> Path:
    """Write an RGB image (float in [0, 1] or uint8) as PNG/JPG, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = rgb if rgb.dtype == np.uint8 else to_uint8(rgb)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix or ".png", img)
    if not ok:
        raise ValueError(f"{path}: OpenCV could not encode an image of shape {img.shape}")
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, path)
    return path


def colorize_depth(depth: np.ndarray, valid: Optional[np.ndarray] = None,
                   near: Optional[float] = None, far: Optional[float] = None) -> np.ndarray:
    """(H, W) depth in metres -> (H, W, 3) uint8 RGB (turbo colormap, near = red... far = blue);
    invalid or non-finite pixels are black. ``near``/``far`` default to robust percentiles."""
    d = np.asarray(depth, np.float64)
    ok = np.isfinite(d) if valid is None else (np.asarray(valid, bool) & np.isfinite(d))
    if not ok.any():
        return np.zeros(d.shape + (3,), np.uint8)
    lo = np.percentile(d[ok], 1) if near is None else near
    hi = np.percentile(d[ok], 99) if far is None else far
    x = np.clip((d - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    x = np.where(ok, x, 0.0)
    col = cv2.applyColorMap((255 * (1.0 - x)).astype(np.uint8), cv2.COLORMAP_TURBO)
    col = cv2.cvtColor(col, cv2.COLOR_BGR2RGB)
    col[~ok] = 0
    return col


def label_palette(n: int) -> np.ndarray:
    """(n, 3) uint8 RGB colours of n classes: class 0 (background) black, the others evenly
    spaced in hue at two brightnesses, so neighbouring indices differ."""
    hue = (np.arange(n) * 0.618034) % 1.0
    hsv = np.stack([hue * 179, np.full(n, 200), np.where(np.arange(n) % 2, 255, 170)], -1)
    rgb = cv2.cvtColor(hsv.astype(np.uint8)[None], cv2.COLOR_HSV2RGB)[0]
    rgb[0] = 0
    return rgb


def colorize_labels(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """(H, W) class indices (negative: unlabelled, grey) -> (H, W, 3) uint8 RGB
    (:func:`label_palette`)."""
    labels = np.asarray(labels)
    out = label_palette(n_classes)[np.clip(labels, 0, n_classes - 1)]
    out[labels < 0] = 128
    return out


def error_map(pred: np.ndarray, target: np.ndarray, max_error: float = 0.25) -> np.ndarray:
    """Per-pixel RGB error |pred - target| (mean over channels) as a uint8 heat map."""
    err = np.abs(np.asarray(pred, np.float32) - np.asarray(target, np.float32)).mean(-1)
    x = np.clip(err / max_error, 0.0, 1.0)
    col = cv2.applyColorMap((255 * x).astype(np.uint8), cv2.COLORMAP_INFERNO)
    return cv2.cvtColor(col, cv2.COLOR_BGR2RGB)


def labelled_row(images: Iterable[np.ndarray], labels: Iterable[str], scale: int = 2) -> np.ndarray:
    """Side-by-side uint8 RGB images (same size), each upscaled ``scale``x with a caption strip."""
    tiles = []
    for img, label in zip(images, labels):
        img = img if img.dtype == np.uint8 else to_uint8(img)
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        strip = np.full((22, img.shape[1], 3), 255, np.uint8)
        cv2.putText(strip, label, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(np.vstack([strip, img]))
    return np.hstack(tiles)


def comparison_sheet(rows: list[dict], scale: int = 2) -> np.ndarray:
    """One row per view: ground truth | render | depth | error. Each row dict holds ``gt`` and
    ``rgb`` (H, W, 3) floats and ``depth`` (H, W) metres (and optional ``depth_valid``)."""
    out = []
    for r in rows:
        depth = colorize_depth(r["depth"], r.get("depth_valid"))
        out.append(labelled_row([r["gt"], r["rgb"], depth, error_map(r["rgb"], r["gt"])],
                                ["ground truth", "render", "depth", "|error|"], scale))
    return np.vstack(out)
