"""What robots and tasks ask of a trained model: images, depth maps, opacity, from any camera.

Depth comes in three modes (:data:`DEPTH_MODES`):

- ``expected``: the weight-averaged sample distance (NeRF's depth; a glass surface of low
  density barely moves it towards the glass, as most weight lies behind).
- ``median``: where the accumulated weight reaches one half.
- ``threshold``: Dex-NeRF's depth, the first point along the ray where the density reaches
  ``threshold`` (1/m), interpolated between samples; rays that never reach it are invalid (NaN),
  never the near plane. Several thresholds are answered from one rendering pass.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
from scipy import ndimage

from nerfbot.models.base import Model
from nerfbot.models.labels import render_labels
from nerfbot.ops.cameras import Cameras, Rays
from nerfbot.ops.rendering import RenderOutput, depth_spread, threshold_depth

DEPTH_MODES = ("expected", "median", "threshold")
_IMAGE_KEYS = ("rgb", "opacity", "depth", "z_depth", "median_depth", "median_z_depth",
               "depth_spread")

#: How a supersampled render spreads its rays over a pixel (:func:`render_image`).
SUPERSAMPLE_PATTERNS = ("grid", "corners", "adaptive")


def as_thresholds(threshold) -> list[float]:
    """Density threshold(s) in 1/m (a number, a sequence or None) as a list, each checked finite
    and > 0 (ValueError otherwise)."""
    if threshold is None:
        return []
    values = [float(threshold)] if np.isscalar(threshold) else [float(m) for m in threshold]
    for m in values:
        if not (np.isfinite(m) and m > 0):
            raise ValueError(f"density thresholds must be finite and > 0 (1/m), got {m}")
    return values


@torch.no_grad()
def render_rays_chunked(model: Model, rays: Rays, chunk: int = 1 << 14, cond=None,
                        thresholds: Sequence[float] = (), labels: bool = False,
                        geometry_only: bool = False) -> dict:
    """Render any number of rays in chunks (eval mode, no gradients).

    Args:
        thresholds: K density thresholds (1/m) for threshold depth, answered in the same pass.
        labels: also render class probabilities, ``labels`` (R, C), from the model's label
            head (:func:`~nerfbot.models.labels.render_labels`; ValueError without one).
        geometry_only: only opacity and depths are wanted (:meth:`Model.render_geometry`:
            ``rgb`` may come back black); not with ``labels``.

    Returns:
        A dict of float32 tensors: rgb (R, 3), opacity, depth (expected ray distance), z_depth,
        median_depth (ray distance), median_z_depth and depth_spread (R,), metres (the spread:
        :func:`~nerfbot.ops.rendering.depth_spread`, how thick the surface is along the ray);
        with thresholds also threshold_depth (K, R) ray distance and threshold_z_depth (K, R),
        NaN where the ray never reaches the threshold.
    """
    thresholds = as_thresholds(list(thresholds))
    if labels and model.label_head is None:
        raise ValueError("this run has no label head (train it with --labels)")
    if labels and geometry_only:
        raise ValueError("labels come from a full render, not a geometry-only one")
    was_training = model.training
    if was_training:  # train() walks every submodule: skip it when already in eval mode
        model.eval()
    parts: dict[str, list] = {k: [] for k in _IMAGE_KEYS}
    if thresholds:
        parts["threshold_depth"], parts["threshold_z_depth"] = [], []
    if labels:
        parts["labels"] = []
    try:
        for i in range(0, len(rays), chunk):
            sub = rays[i:i + chunk]
            c = None if cond is None else cond[i:i + chunk]
            out: RenderOutput = model.render_geometry(sub, c) if geometry_only \
                else model.render_rays(sub, None, c)
            for k in ("rgb", "opacity", "depth", "z_depth", "median_depth"):
                parts[k].append(getattr(out, k).float())
            parts["median_z_depth"].append((out.median_depth * sub.z_per_t).float())
            parts["depth_spread"].append(depth_spread(
                out.weights, 0.5 * (out.t_starts + out.t_ends), out.ray_indices, len(sub),
                out.opacity, out.depth).float())
            if thresholds:
                t = torch.stack([threshold_depth(out.sigmas, out.t_starts, out.t_ends,
                                                 out.ray_indices, len(sub), m)[0].float()
                                 for m in thresholds])
                parts["threshold_depth"].append(t)
                parts["threshold_z_depth"].append(t * sub.z_per_t[None])
            if labels:
                parts["labels"].append(render_labels(model.label_head, out))
    finally:
        if was_training:
            model.train()
    out = {}
    for k, v in parts.items():
        dim = 1 if k.startswith("threshold") else 0
        out[k] = v[0] if len(v) == 1 else torch.cat(v, dim) if v else torch.zeros(0)
    return out


#: Weight of the centre ray in a ``corners`` supersampled pixel; each of its four corner rays
#: weighs a quarter of the rest. 2/3 and 1/12 reproduce the mean over the pixel square of any
#: quadratic in x or in y (Simpson's rule along each axis).
CORNER_CENTRE_WEIGHT = 2.0 / 3.0


def render_image(model: Model, cameras: Cameras, index: int, downscale: int = 1,
                 chunk: int = 1 << 14, cond=None, thresholds: Sequence[float] = (),
                 supersample: Optional[int] = None,
                 supersample_tolerance: Optional[float] = None, labels: bool = False,
                 supersample_pattern: Optional[str] = None,
                 adaptive_tolerance: Optional[float] = None) -> dict:
    """Render camera ``index`` as numpy images: rgb (H, W, 3) in [0, 1], and (H, W) opacity,
    depth (ray distance, m), z_depth (m), median_depth (ray distance, m), median_z_depth (m),
    depth_spread (m, the standard deviation of where the ray ends);
    with ``thresholds`` (K values, 1/m) also threshold_depth / threshold_z_depth (K, H, W),
    NaN where invalid; with ``labels`` also labels (H, W, C) class probabilities of the
    model's label head, from the pixel centres.

    ``supersample`` S (None: the model's :attr:`~nerfbot.models.base.Model.supersample`): rgb and
    opacity are the means of S x S rays through each pixel (:meth:`Cameras.rays`), as the
    model was trained to match anti-aliased pixels; the depths always come from the ray
    through the pixel centre, as a depth camera (and the captures' ground truth) measures
    them. S > 1 renders up to S^2 + 1 rays per pixel (the centre ray without colour when the
    S x S rays go through every pixel); pass 1 when only depth is needed.
    ``supersample_tolerance`` (None: the model's): the S x S rays go only through pixels
    whose 3 x 3 neighbourhood of centre colours spans more than it (:func:`edge_pixels`); 0
    sends them through every pixel.

    ``supersample_pattern`` (None: the model's) "corners" replaces the S x S rays by the
    pixel's four corner rays (:meth:`Cameras.corner_rays`, each shared by the pixels that meet
    there): rgb and opacity are :data:`CORNER_CENTRE_WEIGHT` x the centre ray's plus the rest
    spread evenly over the corners, (H+1)(W+1) + HW rays in all, about 2 per pixel; the
    tolerance does not apply. "adaptive" renders the corners, then sends the S x S rays
    through the pixels whose centre and four corner colours span more than
    ``adaptive_tolerance`` (None: the model's) in some channel, and their mean replaces the
    corner rule there: the rule where the pixel is smooth, the training's estimator where it
    is not."""
    s = model.supersample if supersample is None else supersample
    tol = getattr(model, "supersample_tolerance", 0.0) if supersample_tolerance is None \
        else float(supersample_tolerance)
    pattern = getattr(model, "supersample_pattern", "grid") if supersample_pattern is None \
        else supersample_pattern
    if pattern not in SUPERSAMPLE_PATTERNS:
        raise ValueError(f"supersample_pattern must be one of {SUPERSAMPLE_PATTERNS}, got "
                         f"{pattern!r}")
    h = int(cameras.height[index]) // downscale
    w = int(cameras.width[index]) // downscale
    if s > 1 and pattern in ("corners", "adaptive"):
        out = _render_camera_rays(model, cameras.rays(index, downscale), chunk, cond,
                                  thresholds, labels)
        corner = _render_camera_rays(model, cameras.corner_rays(index, downscale), chunk, cond,
                                     ())
        centre_rgb = out["rgb"].reshape(h, w, 3)
        for key, shape in (("rgb", (h + 1, w + 1, 3)), ("opacity", (h + 1, w + 1))):
            c = corner[key].reshape(shape)
            around = 0.25 * (c[:-1, :-1] + c[:-1, 1:] + c[1:, :-1] + c[1:, 1:])
            out[key] = CORNER_CENTRE_WEIGHT * out[key] \
                + (1.0 - CORNER_CENTRE_WEIGHT) * around.reshape(out[key].shape)
        if pattern == "adaptive":
            tol = model.adaptive_tolerance if adaptive_tolerance is None \
                else float(adaptive_tolerance)
            c = corner["rgb"].reshape(h + 1, w + 1, 3)
            five = torch.stack([centre_rgb, c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])
            spread = (five.amax(0) - five.amin(0)).amax(-1)
            _grid_pixels(model, cameras, index, downscale, s, h, w, chunk, cond, out,
                         torch.nonzero(spread.reshape(-1) > tol)[:, 0].cpu())
        return _image_result(out, h, w, labels)
    # with S x S rays through every pixel, the centre rays give only the depths
    geometry_only = s > 1 and tol <= 0 and not labels
    out = _render_camera_rays(model, cameras.rays(index, downscale), chunk, cond, thresholds,
                              labels, geometry_only)
    if s > 1:
        if tol > 0:
            pick = torch.as_tensor(edge_pixels(out["rgb"].reshape(h, w, 3).cpu().numpy(), tol))
        else:
            pick = torch.arange(h * w)
        _grid_pixels(model, cameras, index, downscale, s, h, w, chunk, cond, out, pick)
    return _image_result(out, h, w, labels)


def _grid_pixels(model: Model, cameras: Cameras, index: int, downscale: int, s: int, h: int,
                 w: int, chunk: int, cond, out: dict, pick: torch.Tensor) -> None:
    """Replace ``out``'s rgb (H*W, 3) and opacity (H*W,) at the row-major pixel indices
    ``pick`` (P,) by the means of S x S rays through each of those pixels."""
    if not len(pick):
        return
    fine_rays = cameras.rays(index, downscale, s)
    # the S x S fine-grid rays of each picked pixel, pixel after pixel
    py, px = pick // w, pick % w
    dy, dx = torch.meshgrid(torch.arange(s), torch.arange(s), indexing="ij")
    fine = (py[:, None] * s + dy.reshape(1, -1)) * (w * s) + px[:, None] * s + dx.reshape(1, -1)
    sub = _render_camera_rays(model, fine_rays[fine.reshape(-1).to(fine_rays.origins.device)],
                              chunk, cond, ())
    pick = pick.to(out["rgb"].device)
    out["rgb"][pick] = sub["rgb"].reshape(len(pick), s * s, 3).mean(1)
    out["opacity"][pick] = sub["opacity"].reshape(len(pick), s * s).mean(1)


def _image_result(out: dict, h: int, w: int, labels: bool) -> dict:
    """:func:`render_image`'s numpy images from the per-ray tensors of one camera."""
    img = {k: v.cpu().numpy() for k, v in out.items()}
    result = {"rgb": img["rgb"].reshape(h, w, 3).clip(0, 1),
              **{k: img[k].reshape(h, w) for k in _IMAGE_KEYS[1:]}}
    for k in ("threshold_depth", "threshold_z_depth"):
        if k in img:
            result[k] = img[k].reshape(-1, h, w)
    if labels:
        result["labels"] = img["labels"].reshape(h, w, -1)
    return result


def depth_of(img: dict, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) z-depth in metres, (H, W) bool valid) of a :func:`render_image` result for depth
    ``mode``: threshold depth (its first threshold) where it is reached, else the expected or
    median z-depth where the opacity exceeds one half."""
    if mode == "threshold":
        z = img["threshold_z_depth"][0]
        return z, np.isfinite(z)
    z = img["median_z_depth"] if mode == "median" else img["z_depth"]
    return z, img["opacity"] > 0.5


def edge_pixels(rgb: np.ndarray, tolerance: float) -> np.ndarray:
    """(P,) row-major indices of the pixels of ``rgb`` (H, W, 3) whose 3 x 3 neighbourhood
    spans more than ``tolerance`` (max - min) in some channel: where one ray per pixel may not
    stand for the pixel's mean. The span bounds every neighbour's difference from the centre,
    so no pixel with a neighbour more than ``tolerance`` away is missed. Pixels on the image's
    border always count: what lies beyond them is unknown."""
    spread = ndimage.maximum_filter(rgb, size=(3, 3, 1), mode="nearest") \
        - ndimage.minimum_filter(rgb, size=(3, 3, 1), mode="nearest")
    edge = spread.max(axis=-1) > tolerance
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    return np.flatnonzero(edge)


def _render_camera_rays(model: Model, rays: Rays, chunk: int, cond, thresholds,
                        labels: bool = False, geometry_only: bool = False) -> dict:
    """:func:`render_rays_chunked` of one camera's rays; ``cond`` (D,) is that camera's."""
    if cond is not None:
        cond = torch.as_tensor(cond, dtype=torch.float32).reshape(1, -1).expand(len(rays), -1)
    return render_rays_chunked(model, rays.to(model.aabb.device), chunk, cond, thresholds,
                               labels, geometry_only)


def sweep_conditions(conditioning, what: str, n: int, base: Optional[Sequence[float]] = None
                     ) -> list[list[float]]:
    """``n`` condition vectors sweeping ``what`` ("time", or a joint name) over its whole range
    (evenly, both ends included), the other values held at ``base`` (default: the middle of
    their ranges). ValueError naming the choices for an unknown ``what``."""
    names = list(conditioning.names)
    if what not in names:
        raise ValueError(f"cannot sweep {what!r}: this run is conditioned on {names or 'nothing'}")
    base = list(base) if base is not None else conditioning.vector(0.0, {}) \
        if conditioning.kind == "time" else conditioning.vector(None, {})
    k = names.index(what)
    lo, hi = conditioning.ranges[k]
    out = []
    for v in np.linspace(lo, hi, max(int(n), 2)):
        c = list(base)
        c[k] = float(v)
        out.append(c)
    return out


def depth(model: Model, cameras: Cameras, index: int, mode: str = "expected",
          threshold: Optional[float | Sequence[float]] = None, z: bool = True,
          downscale: int = 1, cond=None) -> np.ndarray:
    """Depth map of camera ``index``.

    Args:
        mode: "expected", "median" or "threshold" (see the module docstring).
        threshold: density threshold(s) in 1/m, required for mode "threshold"; a sequence gives
            one map per threshold from a single rendering pass.
        z: z-depth (distance along the optical axis, the project's default) or, if False, ray
            distance.
        downscale: render 1/downscale of the resolution (same field of view).

    Returns:
        (H, W) float32 metres, or (K, H, W) for K thresholds; NaN where the mode gives no depth
        (threshold never reached).

    Raises:
        ValueError: unknown mode, or a threshold missing / not positive.
    """
    if mode not in DEPTH_MODES:
        raise ValueError(f"unknown depth mode {mode!r} (choose from {DEPTH_MODES})")
    if mode == "threshold":
        if threshold is None:
            raise ValueError("depth mode 'threshold' needs threshold=m (density, 1/m)")
        ms = as_thresholds(threshold)
        img = render_image(model, cameras, index, downscale, cond=cond, thresholds=ms,
                           supersample=1)
        maps = img["threshold_z_depth" if z else "threshold_depth"]
        return maps[0] if np.isscalar(threshold) else maps
    img = render_image(model, cameras, index, downscale, cond=cond, supersample=1)
    key = {("expected", True): "z_depth", ("expected", False): "depth",
           ("median", True): "median_z_depth", ("median", False): "median_depth"}[(mode, z)]
    return img[key]
