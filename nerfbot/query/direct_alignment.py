"""Direct image alignment of an observed image to a rendered RGB-D reference.

The field is rendered once at a reference pose (colour, z depth and opacity); the observed
camera's pose is then found by Gauss-Newton (Levenberg-Marquardt) on the photometric error of
the reference pixels warped into the observed image through their rendered depth, as direct
visual odometry aligns a frame to a keyframe. No field query is made while aligning, so every
pixel of the image takes part, and a coarse-to-fine pyramid of blurred images gives the wide
basin; the pose is as good as the reference's colours and depth near the truth, which is why
:func:`nerfbot.query.localise.localise_wide` renders a new reference at the estimate and aligns
again.

Shapes: images (H, W, 3) floats in [0, 1]; poses (4, 4) camera-to-world, OpenGL convention
(the camera looks along -z, y up), world metres; intrinsics (fx, fy, cx, cy) in pixels of the
full-resolution image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from nerfbot.ops.cameras import pixel_rays

#: A pose update: (start (4, 4), parameters (P,)) -> pose (4, 4), in the dtype of its inputs.
PoseUpdate = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class AlignConfig:
    """Settings of one pyramid level's Levenberg-Marquardt run.

    Attributes:
        iterations: at most this many accepted or rejected steps.
        sigma: Gaussian blur of both images, pixels of the level.
        huber: colour residual (per pixel, Euclidean over RGB) beyond which a pixel's weight
            falls as 1 / residual: occlusions and the reference's errors.
        min_opacity: reference pixels less opaque than this carry no depth and are left out.
        max_shift: a step that moves the median point by more than this fraction of the
            level's width is damped further: on a coarse, blurred level a long leap can lower
            the cost by sliding the image onto a smooth region.
        damping: initial Levenberg-Marquardt damping, relative to the diagonal.
    """

    iterations: int = 15
    sigma: float = 1.0
    huber: float = 0.1
    min_opacity: float = 0.9
    max_shift: float = 0.15
    damping: float = 1e-3


@dataclass
class Reference:
    """A render of the field at ``c2w``: rgb (h, w, 3), z depth (h, w) metres along the view
    axis, opacity (h, w), at ``scale`` times the observed image's resolution."""

    c2w: torch.Tensor
    rgb: torch.Tensor
    z: torch.Tensor
    opacity: torch.Tensor
    scale: float


def level_size(w: int, h: int, scale: float) -> tuple[int, int]:
    """(w, h) of an image of w x h pixels resized by ``scale`` (at least 1 x 1)."""
    return max(1, round(w * scale)), max(1, round(h * scale))


def level_pixels(w: int, h: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(w * h,) x and y pixel centres of a w x h image, row-major."""
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=device),
                          torch.arange(w, dtype=torch.float32, device=device), indexing="ij")
    return u.reshape(-1) + 0.5, v.reshape(-1) + 0.5


@torch.no_grad()
def render_reference(model, c2w: torch.Tensor, intrinsics, size: tuple[int, int],
                     scale: float, chunk: int = 1 << 13) -> Reference:
    """The field rendered at pose ``c2w`` (4, 4) with ``intrinsics`` of the full-resolution
    image scaled by ``scale``, one ray per pixel of ``size`` = (w, h), by the model's
    :meth:`~nerfbot.models.base.Model.render_rays_differentiable` (the rendering the pose
    estimators descend through)."""
    fx, fy, cx, cy = (float(v) * scale for v in intrinsics)
    w, h = size
    px, py = level_pixels(w, h, c2w.device)
    rays = pixel_rays(c2w, fx, fy, cx, cy, px, py, 1 / scale, 1 / scale)
    parts = [model.render_rays_differentiable(rays[i:i + chunk])
             for i in range(0, len(rays), chunk)]
    rgb, z, opacity = (torch.cat([getattr(p, k) for p in parts])
                       for k in ("rgb", "z_depth", "opacity"))
    return Reference(c2w, rgb.reshape(h, w, 3), z.reshape(h, w), opacity.reshape(h, w), scale)


def blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """(..., H, W) images (channels and batches in the leading dimensions) blurred by a
    separable Gaussian of ``sigma`` pixels, edges replicated; unchanged for sigma <= 0."""
    if sigma <= 0:
        return img
    r = max(1, int(np.ceil(2.5 * sigma)))
    x = torch.arange(-r, r + 1, dtype=img.dtype, device=img.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    h, w = img.shape[-2:]
    flat = img.reshape(1, -1, h, w)
    c = flat.shape[1]
    out = F.pad(flat, (r, r, r, r), mode="replicate")
    out = F.conv2d(out, k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    return F.conv2d(out, k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c).reshape(img.shape)


def resize(img: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(H, W, C) or (H, W) float image area-resized to ``size`` = (w, h) (opencv)."""
    if (img.shape[1], img.shape[0]) == tuple(size):
        return img
    out = cv2.resize(img.cpu().numpy(), size, interpolation=cv2.INTER_AREA)
    return torch.as_tensor(out, device=img.device).reshape(size[1], size[0], *img.shape[2:])


def _gradients(img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central-difference x and y gradients (C, H, W) of a (C, H, W) image, per pixel."""
    pad = F.pad(img[None], (1, 1, 1, 1), mode="replicate")[0]
    return (pad[:, 1:-1, 2:] - pad[:, 1:-1, :-2]) / 2, (pad[:, 2:, 1:-1] - pad[:, :-2, 1:-1]) / 2


def _sample(img: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """(N, C) bilinear samples of a (C, H, W) image at pixel coordinates (N,) (centres at
    +0.5; edges replicated)."""
    c, h, w = img.shape
    grid = torch.stack([2 * px / w - 1, 2 * py / h - 1], -1).view(1, 1, -1, 2)
    out = F.grid_sample(img[None], grid, mode="bilinear", padding_mode="border",
                        align_corners=False)
    return out.view(c, -1).T


class _Level:
    """The warp of one pyramid level: the reference's opaque pixels lifted to world points
    (N, 3) by their depth, and the blurred observed image with its gradients."""

    def __init__(self, reference: Reference, observed: torch.Tensor, intrinsics, scale: float,
                 config: AlignConfig):
        h_obs, w_obs = observed.shape[:2]
        size = level_size(w_obs, h_obs, scale)
        self.fx, self.fy, self.cx, self.cy = (float(v) * scale for v in intrinsics)
        self.w, self.h = size
        self.image = blur(resize(observed, size).permute(2, 0, 1), config.sigma)
        self.gx, self.gy = _gradients(self.image)
        ref_rgb = blur(resize(reference.rgb, size).permute(2, 0, 1), config.sigma)
        z = resize(reference.z, size).reshape(-1)
        opacity = resize(reference.opacity, size).reshape(-1)
        px, py = level_pixels(*size, observed.device)
        keep = (opacity >= config.min_opacity) & (z > 1e-3)
        px, py, z = px[keep], py[keep], z[keep]
        cam = torch.stack([(px - self.cx) / self.fx * z, -(py - self.cy) / self.fy * z, -z], -1)
        c2w = reference.c2w
        self.points = cam @ c2w[:3, :3].T + c2w[:3, 3]
        self.target = ref_rgb.reshape(3, -1).T[keep]
        self.config = config

    def project(self, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(px, py) (N,) of the points in the camera at ``c2w`` (4, 4), and (N,) in front."""
        cam = (self.points - c2w[:3, 3]) @ c2w[:3, :3]
        depth = (-cam[:, 2]).clamp_min(1e-6)
        return (self.cx + self.fx * cam[:, 0] / depth, self.cy - self.fy * cam[:, 1] / depth,
                cam[:, 2] < -1e-3)

    def pixel_jacobian(self, c2w: torch.Tensor, dc2w: torch.Tensor) -> torch.Tensor:
        """(N, 2, P) derivatives of the points' pixels w.r.t. the P pose parameters, from the
        pose ``c2w`` (4, 4) and its derivatives ``dc2w`` (P, 4, 4)."""
        rel = self.points - c2w[:3, 3]
        cam = rel @ c2w[:3, :3]                                           # (N, 3)
        dcam = rel @ dc2w[:, :3, :3] - (dc2w[:, None, :3, 3] @ c2w[:3, :3])  # (P, N, 3)
        x, y, depth = cam[:, 0], cam[:, 1], (-cam[:, 2]).clamp_min(1e-6)
        dx, dy, dz = dcam.unbind(-1)
        dpx = self.fx * (dx / depth + x * dz / depth ** 2)
        dpy = -self.fy * (dy / depth + y * dz / depth ** 2)
        return torch.stack([dpx, dpy], -1).permute(1, 2, 0)

    def residuals(self, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                     torch.Tensor]:
        """Colour residuals (N, 3), validity (N,) and the projected pixels (N,) x 2."""
        px, py, front = self.project(c2w)
        inside = front & (px >= 0.5) & (px <= self.w - 0.5) & (py >= 0.5) & (py <= self.h - 0.5)
        return _sample(self.image, px, py) - self.target, inside, px, py

    def cost(self, c2w: torch.Tensor, points: torch.Tensor) -> float:
        """The mean Huber cost at pose ``c2w`` of the points selected by ``points`` (N,) bool,
        sampled with the image's edges replicated where they leave it."""
        px, py, _ = self.project(c2w)
        r = _sample(self.image, px[points], py[points]) - self.target[points]
        return float(_huber(r.norm(dim=-1), self.config.huber).mean()) if len(r) else 0.0


def _huber(norm: torch.Tensor, delta: float) -> torch.Tensor:
    return torch.where(norm <= delta, 0.5 * norm ** 2, delta * (norm - 0.5 * delta))


def align(reference: Reference, observed: torch.Tensor, intrinsics, start: torch.Tensor,
          update: PoseUpdate, parameters: int, scales: tuple[float, ...],
          config: AlignConfig = AlignConfig()) -> tuple[torch.Tensor, float]:
    """The pose of the camera that took ``observed`` (H, W, 3) by Levenberg-Marquardt over the
    ``parameters`` of ``update(start, q)``, coarse to fine over the pyramid ``scales`` (each a
    fraction of the observed resolution, at most the reference's): (pose (4, 4), the finest
    level's mean Huber cost)."""
    q = torch.zeros(parameters, dtype=torch.float32, device=start.device)
    cost = float("inf")
    for scale in scales:
        level = _Level(reference, observed, intrinsics, min(scale, reference.scale), config)
        if len(level.points) < parameters:
            break
        q, cost = _levenberg_marquardt(level, start, update, q, config)
    with torch.no_grad():
        return update(start, q), cost


def _pose_derivatives(update: PoseUpdate, start: torch.Tensor, q: torch.Tensor,
                      eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """The pose ``update(start, q)`` (4, 4) and its derivatives (P, 4, 4) w.r.t. q, by central
    differences in float64 (a pose is a handful of operations; exact to ~1e-9)."""
    s64, q64 = start.double(), q.double()
    steps = torch.eye(len(q), dtype=torch.float64, device=q.device) * eps
    d = torch.stack([(update(s64, q64 + e) - update(s64, q64 - e)) / (2 * eps) for e in steps])
    return update(s64, q64).to(start.dtype), d.to(start.dtype)


def _levenberg_marquardt(level: _Level, start, update: PoseUpdate, q: torch.Tensor,
                         config: AlignConfig) -> tuple[torch.Tensor, float]:
    lam, cost = config.damping, float("inf")
    # the points judged: those in view at the level's start, for the whole level, so that
    # no pose is rewarded for pushing the worst of them out of view (a point that leaves is
    # judged by the image's edge colour, and gives no Jacobian)
    judged = None
    for _ in range(config.iterations):
        c2w, dc2w = _pose_derivatives(update, start, q)
        r, inside, px, py = level.residuals(c2w)
        judged = inside if judged is None else judged
        valid = judged & inside
        if int(valid.sum()) < len(q):
            break
        cost = level.cost(c2w, judged)
        jp = level.pixel_jacobian(c2w, dc2w)[valid]                     # (N, 2, P)
        gx = _sample(level.gx, px[valid], py[valid])                   # (N, 3)
        gy = _sample(level.gy, px[valid], py[valid])
        jac = gx[..., None] * jp[:, None, 0, :] + gy[..., None] * jp[:, None, 1, :]  # (N, 3, P)
        r = r[valid]
        norm = r.norm(dim=-1)
        weight = torch.where(norm <= config.huber, torch.ones_like(norm),
                             config.huber / norm.clamp_min(1e-12))
        jac = jac.reshape(-1, len(q))
        wr = (weight[:, None] * r).reshape(-1)
        wj = (weight[:, None, None] * jac.view(-1, 3, len(q))).reshape(-1, len(q))
        hess = (wj.T @ jac).double()
        grad = (jac.T @ wr).double()
        improved = False
        while lam < 1e8:
            system = hess + lam * torch.diag(torch.diagonal(hess).clamp_min(1e-12))
            step = -torch.linalg.solve(system, grad).float()
            trial = q + step
            trial_pose = update(start, trial)
            tx, ty, _ = level.project(trial_pose)
            shift = torch.hypot(tx[valid] - px[valid], ty[valid] - py[valid]).median()
            if float(shift) > config.max_shift * max(level.w, level.h):
                lam *= 4                       # a leap the linearisation cannot vouch for
                continue
            new_cost = level.cost(trial_pose, judged)
            if new_cost < cost:
                q, cost, lam, improved = trial, new_cost, max(lam / 3, 1e-7), True
                break
            lam *= 4
        if not improved or float(step.abs().max()) < 1e-6:
            break
    return q, cost
