"""Depth accuracy per depth mode on pixel classes: transparent objects, opaque objects, the scene.

This is how Dex-NeRF's threshold depth is measured against the expected and median depth of a
radiance field, and against a simulated depth sensor: each mode's z-depth is compared with the
ground truth (in which glass is opaque) on the pixels of each class. A mode may give no depth
for a pixel (a threshold never reached, a sensor without return); errors are then taken over the
pixels that have one, and ``valid_fraction`` says how many did.

Pixel classes (from the segmentation and the scene manifest):

- ``transparent``: pixels whose first surface is a transparent geom;
- ``opaque_objects``: pixels of the declared objects that are not transparent;
- ``scene``: every pixel with finite ground-truth depth inside the scene bounds.

Pixels the dataset's masks mark invalid belong to no class
(:func:`~nerfbot.data.pixels.depth_valid_mask`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from matplotlib.figure import Figure
from tqdm import tqdm

from nerfbot.data.dataset import Dataset
from nerfbot.data.pixels import depth_valid_mask
from nerfbot.models.base import Model
from nerfbot.query.render import render_image

log = logging.getLogger(__name__)

#: Density thresholds (1/m) swept by default: log-spaced over the range where a field's
#: faint (glass) and solid surfaces lie.
DEFAULT_THRESHOLDS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0)
CLASSES = ("transparent", "opaque_objects", "scene")
#: A threshold must give depth on at least this fraction of a class's pixels to be "best".
MIN_VALID_FRACTION = 0.8


def _ids(dataset: Dataset, names) -> np.ndarray:
    names = set(names or ())
    geoms = (dataset.manifest or {}).get("geoms", {})
    return np.array([int(g) for g, n in geoms.items() if n in names], dtype=np.int64)


def pixel_classes(dataset: Dataset, i: int) -> Optional[dict[str, np.ndarray]]:
    """(H, W) bool masks of the classes for frame ``i``; None without depth or segmentation."""
    valid = depth_valid_mask(dataset, i)
    seg = dataset.segmentations[i]
    if valid is None or seg is None:
        return None
    manifest = dataset.manifest or {}
    transparent = _ids(dataset, manifest.get("transparent_geoms"))
    objects = _ids(dataset, manifest.get("objects"))
    is_glass = np.isin(seg, transparent)
    return {"transparent": valid & is_glass,
            "opaque_objects": valid & np.isin(seg, objects) & ~is_glass,
            "scene": valid}


@dataclass
class _Errors:
    """Accumulated errors of one (mode, class): sums over pixels with a prediction."""

    abs_sum: float = 0.0
    sq_sum: float = 0.0
    predicted: int = 0
    pixels: int = 0

    def add(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> None:
        have = mask & np.isfinite(pred)
        err = pred[have].astype(np.float64) - gt[have].astype(np.float64)
        self.abs_sum += float(np.abs(err).sum())
        self.sq_sum += float((err ** 2).sum())
        self.predicted += int(have.sum())
        self.pixels += int(mask.sum())

    def summary(self) -> dict:
        n = self.predicted
        return {"mae_m": self.abs_sum / n if n else None,
                "rmse_m": float(np.sqrt(self.sq_sum / n)) if n else None,
                "valid_fraction": n / self.pixels if self.pixels else None,
                "pixels": self.pixels}


@dataclass
class DepthSweep:
    """Result of :func:`depth_mode_sweep`.

    Attributes:
        thresholds: the K density thresholds (1/m).
        modes: class -> mode ("expected", "median", "sensor") -> error summary.
        threshold: class -> list of K error summaries, one per threshold.
        best_threshold: class -> the threshold with the lowest MAE among those giving depth on
            at least :data:`MIN_VALID_FRACTION` of the pixels (None if none does).
        num_images: frames evaluated.
    """

    thresholds: list[float]
    modes: dict = field(default_factory=dict)
    threshold: dict = field(default_factory=dict)
    best_threshold: dict = field(default_factory=dict)
    num_images: int = 0

    def to_dict(self) -> dict:
        return {"thresholds": self.thresholds, "modes": self.modes, "threshold": self.threshold,
                "best_threshold": self.best_threshold, "num_images": self.num_images}


def depth_mode_sweep(model: Model, dataset: Dataset, split: str = "test",
                     thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
                     max_images: Optional[int] = None, progress: bool = True) -> DepthSweep:
    """Compare expected, median and threshold depth (every threshold, one pass per image) and
    the dataset's simulated sensor depth (when present) with the ground truth, per pixel class.

    Raises:
        ValueError: the split has no frame with both depth and segmentation.
    """
    thresholds = [float(m) for m in thresholds]
    indices = dataset.indices(split)[:max_images]
    cams = dataset.cameras(indices)
    modes = {c: {m: _Errors() for m in ("expected", "median", "sensor")} for c in CLASSES}
    per_threshold = {c: [_Errors() for _ in thresholds] for c in CLASSES}
    used = 0
    for slot, i in enumerate(tqdm(indices, desc="depth sweep", unit="view", disable=not progress)):
        classes = pixel_classes(dataset, i)
        if classes is None:
            continue
        used += 1
        gt = dataset.depths[i]
        out = render_image(model, cams, slot, thresholds=thresholds, supersample=1)
        sensor = dataset.sensor_depths[i] if dataset.sensor_depths else None
        for c, mask in classes.items():
            modes[c]["expected"].add(out["z_depth"], gt, mask)
            modes[c]["median"].add(out["median_z_depth"], gt, mask)
            if sensor is not None:
                modes[c]["sensor"].add(sensor, gt, mask)
            for k in range(len(thresholds)):
                per_threshold[c][k].add(out["threshold_z_depth"][k], gt, mask)
    if not used:
        raise ValueError(f"{dataset.root}: no '{split}' frame has both depth and segmentation")
    has_sensor = any(s is not None for s in dataset.sensor_depths)
    result = DepthSweep(thresholds, num_images=used)
    for c in CLASSES:
        result.modes[c] = {m: e.summary() for m, e in modes[c].items()
                           if m != "sensor" or has_sensor}
        result.threshold[c] = [dict(threshold=m, **e.summary())
                               for m, e in zip(thresholds, per_threshold[c])]
        result.best_threshold[c] = best_threshold(result.threshold[c])
    return result


def _merge(summaries: list[dict]) -> dict:
    """Pool error summaries of several datasets (weights: pixels with a prediction)."""
    pixels = sum(s["pixels"] for s in summaries)
    have = [(s, s["valid_fraction"] * s["pixels"]) for s in summaries
            if s["pixels"] and s["mae_m"] is not None]
    n = sum(w for _, w in have)
    return {"mae_m": sum(s["mae_m"] * w for s, w in have) / n if n else None,
            "rmse_m": float(np.sqrt(sum(s["rmse_m"] ** 2 * w for s, w in have) / n)) if n else None,
            "valid_fraction": n / pixels if pixels else None,
            "pixels": pixels}


def pool_sweeps(sweeps: list[DepthSweep]) -> DepthSweep:
    """One sweep from several (e.g. one per scene) over the same thresholds: errors pooled over
    all their pixels, the best threshold chosen again on the pooled errors."""
    if not sweeps:
        raise ValueError("no sweeps to pool")
    thresholds = sweeps[0].thresholds
    if any(s.thresholds != thresholds for s in sweeps):
        raise ValueError("sweeps to pool must share their thresholds")
    pooled = DepthSweep(list(thresholds), num_images=sum(s.num_images for s in sweeps))
    for c in CLASSES:
        modes = sorted({m for s in sweeps for m in s.modes.get(c, {})})
        pooled.modes[c] = {m: _merge([s.modes[c][m] for s in sweeps if m in s.modes.get(c, {})])
                           for m in modes}
        pooled.threshold[c] = [dict(threshold=m, **_merge([s.threshold[c][k] for s in sweeps]))
                               for k, m in enumerate(thresholds)]
        pooled.best_threshold[c] = best_threshold(pooled.threshold[c])
    return pooled


def sweep_from_dict(d: dict) -> DepthSweep:
    """Inverse of :meth:`DepthSweep.to_dict`."""
    return DepthSweep(list(d["thresholds"]), dict(d["modes"]), dict(d["threshold"]),
                      dict(d["best_threshold"]), int(d["num_images"]))


def best_threshold(rows: list[dict], min_valid: float = MIN_VALID_FRACTION) -> Optional[float]:
    """The threshold of ``rows`` (dicts with threshold, mae_m, valid_fraction) with the lowest
    MAE among those valid on at least ``min_valid`` of the pixels; None if none qualifies."""
    ok = [r for r in rows if r["mae_m"] is not None and (r["valid_fraction"] or 0) >= min_valid]
    return min(ok, key=lambda r: r["mae_m"])["threshold"] if ok else None


def plot_threshold_sweep(sweep: DepthSweep, path: Path, title: str = "") -> Path:
    """PNG of MAE (and valid fraction) against the density threshold per class, with the
    expected / median / sensor depth as horizontal reference lines."""
    fig = Figure(figsize=(11, 4.2))
    ax, axv = fig.subplots(1, 2)
    colours = {"transparent": "tab:blue", "opaque_objects": "tab:orange", "scene": "tab:gray"}
    styles = {"expected": "--", "median": ":", "sensor": "-."}
    for c in CLASSES:
        rows = sweep.threshold.get(c) or []
        if not rows or not rows[0]["pixels"]:
            continue
        ms = [r["threshold"] for r in rows]
        mae = [np.nan if r["mae_m"] is None else 100 * r["mae_m"] for r in rows]
        ax.plot(ms, mae, "o-", color=colours[c], label=f"{c}: threshold")
        axv.plot(ms, [r["valid_fraction"] or 0 for r in rows], "o-", color=colours[c], label=c)
        for mode, s in sweep.modes.get(c, {}).items():
            if s["mae_m"] is not None:
                ax.axhline(100 * s["mae_m"], color=colours[c], ls=styles[mode], lw=1,
                           label=f"{c}: {mode}")
        best = sweep.best_threshold.get(c)
        if best is not None:
            ax.axvline(best, color=colours[c], lw=0.6, alpha=0.5)
    ax.set(xscale="log", yscale="log", xlabel="density threshold m (1/m)",
           ylabel="depth MAE (cm)", title=title or "threshold depth vs ground truth")
    axv.set(xscale="log", xlabel="density threshold m (1/m)", ylabel="fraction of pixels with depth",
            ylim=(0, 1.02), title="completeness")
    ax.legend(fontsize=7)
    axv.legend(fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
