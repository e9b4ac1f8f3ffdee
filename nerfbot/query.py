"""What robots and tasks ask of a trained model: images, depth maps, opacity, from any camera."""

from __future__ import annotations

import numpy as np
import torch

from nerfbot.cameras import Cameras, Rays
from nerfbot.models import Model
from nerfbot.rendering import RenderOutput


@torch.no_grad()
def render_rays_chunked(model: Model, rays: Rays, chunk: int = 1 << 14, cond=None) -> dict:
    """Render any number of rays in chunks (eval mode, no gradients).

    Returns a dict of (R, ...) float32 tensors: rgb (R, 3), opacity, depth (expected ray
    distance), z_depth, median_depth (ray distance) and median_z_depth (R,), metres.
    """
    was_training = model.training
    model.eval()
    parts: dict[str, list] = {k: [] for k in ("rgb", "opacity", "depth", "z_depth", "median_depth",
                                              "median_z_depth")}
    try:
        for i in range(0, len(rays), chunk):
            sub = rays[i:i + chunk]
            c = None if cond is None else cond[i:i + chunk]
            out: RenderOutput = model.render_rays(sub, None, c)
            for k in ("rgb", "opacity", "depth", "z_depth", "median_depth"):
                parts[k].append(getattr(out, k).float())
            parts["median_z_depth"].append((out.median_depth * sub.z_per_t).float())
    finally:
        model.train(was_training)
    return {k: torch.cat(v) if v else torch.zeros(0) for k, v in parts.items()}


def render_image(model: Model, cameras: Cameras, index: int, downscale: int = 1,
                 chunk: int = 1 << 14, cond=None) -> dict:
    """Render camera ``index`` as numpy images: rgb (H, W, 3) in [0, 1], and (H, W) opacity,
    depth (ray distance, m), z_depth (m), median_depth (ray distance, m), median_z_depth (m)."""
    rays = cameras.rays(index, downscale)
    h = int(cameras.height[index]) // downscale
    w = int(cameras.width[index]) // downscale
    if cond is not None:
        cond = torch.as_tensor(cond, dtype=torch.float32).reshape(1, -1).expand(len(rays), -1)
    out = render_rays_chunked(model, rays.to(model.aabb.device), chunk, cond)
    img = {k: v.cpu().numpy() for k, v in out.items()}
    return {"rgb": img["rgb"].reshape(h, w, 3).clip(0, 1),
            **{k: img[k].reshape(h, w) for k in ("opacity", "depth", "z_depth", "median_depth",
                                                 "median_z_depth")}}
