"""Where is the camera? Pose estimation from one observed image through a frozen field.

- :func:`inerf` (iNeRF, Yen-Chen et al. 2021): gradient descent on the photometric error of a
  batch of pixels, over a pose update in se(3) applied in the camera frame through the
  exponential map, ``c2w = c2w_0 @ exp(xi)``. Pixels are drawn from an interest region
  (opencv keypoints, dilated), where the image gradient tells the pose apart. Its basin is
  narrow (the iNeRF paper's finding).
- :func:`localise_multistart`: meant to widen the basin. Many perturbed starts descend
  together (one batched render per iteration) for a short coarse phase; the start with the
  lowest error on a fixed pixel set is refined by :func:`inerf`. Its cost is ``starts`` times a
  coarse iteration plus one iNeRF run. Not yet validated: on a tiny test capture it drifted
  along the view axis (BENCHMARKS.md, open points).

Both need a model that renders with gradients w.r.t. its rays
(:meth:`~nerfbot.models.base.Model.render_rays_differentiable`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from nerfbot.ops.alignment import rotation_angle_deg
from nerfbot.ops.cameras import pixel_rays
from nerfbot.ops.lie import se3_exp


def pose_error(c2w: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(translation error in metres, rotation error in degrees) between two (4, 4) poses."""
    c2w, reference = np.asarray(c2w, float), np.asarray(reference, float)
    dt = float(np.linalg.norm(c2w[:3, 3] - reference[:3, 3]))
    return dt, float(rotation_angle_deg(c2w[:3, :3], reference[:3, :3]))


def interest_pixels(image: np.ndarray, dilate: int = 3, max_keypoints: int = 500) -> np.ndarray:
    """(K, 2) integer pixel coordinates (x, y) of the interest region: ORB keypoints of the
    image, each grown to a (2 * dilate + 1)^2 square. Empty when the image has no keypoints."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
    gray = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    orb = cv2.ORB_create(nfeatures=max_keypoints, edgeThreshold=7, patchSize=7, fastThreshold=5)
    keypoints = orb.detect(gray, None)
    mask = np.zeros(gray.shape, np.uint8)
    for kp in keypoints:
        x, y = (int(round(v)) for v in kp.pt)
        mask[max(y - dilate, 0):y + dilate + 1, max(x - dilate, 0):x + dilate + 1] = 1
    ys, xs = np.nonzero(mask)
    return np.stack([xs, ys], -1)


@dataclass(frozen=True)
class InerfConfig:
    """iNeRF's settings.

    Attributes:
        iterations: gradient steps.
        rays: pixels per step.
        lr: Adam learning rate of the twist (radians and metres), decayed to a tenth.
        interest: draw pixels from the interest region (else uniformly).
        interest_fraction: share of the pixels drawn from the interest region (the rest
            uniformly, so flat regions still anchor the pose).
        dilate: interest-region growth around each keypoint, pixels.
    """

    iterations: int = 80
    rays: int = 512
    lr: float = 0.02
    interest: bool = True
    interest_fraction: float = 0.75
    dilate: int = 3


@dataclass
class PoseEstimate:
    """The estimated camera-to-world pose (4, 4), the final photometric MSE on a fixed set of
    pixels, the seconds it took and the mean batch MSE at every iteration."""

    c2w: np.ndarray
    loss: float
    seconds: float
    losses: list[float]


class _Observation:
    """An observed image, its intrinsics and its pixel samplers."""

    def __init__(self, image: np.ndarray, intrinsics, config: InerfConfig, generator, device):
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[-1] < 3:
            raise ValueError(f"the observed image must be (H, W, 3), got {img.shape}")
        if img.dtype == np.uint8:
            img = img.astype(np.float32) / 255.0
        self.h, self.w = img.shape[:2]
        self.rgb = torch.as_tensor(img[..., :3], dtype=torch.float32, device=device)
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in intrinsics)
        self.generator = generator
        self.device = device
        self.config = config
        self.interest = interest_pixels(img, config.dilate) if config.interest else \
            np.zeros((0, 2), int)

    def draw(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(n,) x and y pixel indices: a share from the interest region, the rest uniform."""
        n_int = int(round(n * self.config.interest_fraction)) if len(self.interest) else 0
        k = torch.randint(len(self.interest) or 1, (n_int,), generator=self.generator)
        pts = torch.as_tensor(self.interest, dtype=torch.long)[k] if n_int else \
            torch.zeros((0, 2), dtype=torch.long)
        rest = n - n_int
        ux = torch.randint(self.w, (rest,), generator=self.generator)
        uy = torch.randint(self.h, (rest,), generator=self.generator)
        return torch.cat([pts[:, 0], ux]), torch.cat([pts[:, 1], uy])

    def rays(self, c2w: torch.Tensor, px: torch.Tensor, py: torch.Tensor):
        return pixel_rays(c2w, self.fx, self.fy, self.cx, self.cy,
                          px.to(self.device).float() + 0.5, py.to(self.device).float() + 0.5)

    def target(self, px, py) -> torch.Tensor:
        return self.rgb[py.to(self.device), px.to(self.device)]


def _photometric(model, obs: _Observation, c2w: torch.Tensor, px, py) -> torch.Tensor:
    """(K,) mean squared colour error of each of K poses c2w (K, 4, 4) at pixels (px, py)."""
    k = c2w.shape[0]
    n = len(px)
    rays = obs.rays(c2w.repeat_interleave(n, 0), px.repeat(k), py.repeat(k))
    rgb = model.render_rays_differentiable(rays).rgb
    return ((rgb - obs.target(px, py).repeat(k, 1)) ** 2).mean(-1).reshape(k, n).mean(-1)


def _descend(model, obs: _Observation, c2w0: torch.Tensor, iterations: int, rays: int,
             lr: float) -> tuple[torch.Tensor, list[float]]:
    """Adam on one twist per start: c2w0 (K, 4, 4) -> refined (K, 4, 4), mean losses per
    iteration."""
    xi = torch.zeros(c2w0.shape[0], 6, device=c2w0.device, requires_grad=True)
    opt = torch.optim.Adam([xi], lr=lr)
    losses = []
    for it in range(iterations):
        for group in opt.param_groups:
            group["lr"] = lr * 0.1 ** (it / max(iterations - 1, 1))
        px, py = obs.draw(rays)
        loss = _photometric(model, obs, c2w0 @ se3_exp(xi), px, py)
        opt.zero_grad()
        loss.sum().backward()
        opt.step()
        losses.append(float(loss.detach().mean()))
    with torch.no_grad():
        return c2w0 @ se3_exp(xi), losses


class _Frozen:
    """Eval mode and no parameter gradients for the duration (the pose is what is optimised;
    the backward pass then skips the field's weights and tables)."""

    def __init__(self, model):
        self.model = model

    def __enter__(self):
        self.training = self.model.training
        self.grads = [(p, p.requires_grad) for p in self.model.parameters()]
        self.model.eval()
        for p, _ in self.grads:
            p.requires_grad_(False)
        return self.model

    def __exit__(self, *exc):
        for p, flag in self.grads:
            p.requires_grad_(flag)
        self.model.train(self.training)


def _evaluation_pixels(obs: _Observation, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randint(obs.w, (n,), generator=g), torch.randint(obs.h, (n,), generator=g)


def inerf(model, image: np.ndarray, intrinsics, c2w_init: np.ndarray,
          config: InerfConfig = InerfConfig(), seed: int = 0) -> PoseEstimate:
    """iNeRF: the pose of the camera that took ``image`` (H, W, 3; uint8 or floats in [0, 1]),
    with ``intrinsics`` (fx, fy, cx, cy) in pixels, from the initial guess ``c2w_init`` (4, 4,
    OpenGL camera convention, world metres)."""
    t0 = time.perf_counter()
    device = model.aabb.device
    obs = _Observation(image, intrinsics, config, torch.Generator().manual_seed(seed), device)
    c2w0 = torch.as_tensor(np.asarray(c2w_init, np.float32), device=device)[None]
    with _Frozen(model):
        c2w, losses = _descend(model, obs, c2w0, config.iterations, config.rays, config.lr)
        with torch.no_grad():
            loss = float(_photometric(model, obs, c2w, *_evaluation_pixels(obs, 1024, seed))[0])
    return PoseEstimate(c2w[0].cpu().numpy().astype(float), loss, time.perf_counter() - t0,
                        losses)


@dataclass(frozen=True)
class MultiStartConfig:
    """The wider estimator's settings.

    Attributes:
        starts: perturbed starts (the initial guess is one of them).
        translation: largest start offset per axis, metres.
        rotation: largest start rotation about each axis, degrees.
        coarse_iterations: steps every start takes before the best is chosen.
        coarse_rays: pixels per start per coarse step.
        refine: the iNeRF run from the best start.
    """

    starts: int = 8
    translation: float = 0.25
    rotation: float = 15.0
    coarse_iterations: int = 20
    coarse_rays: int = 128
    refine: InerfConfig = InerfConfig(iterations=60)


def localise_multistart(model, image: np.ndarray, intrinsics, c2w_init: np.ndarray,
                        config: MultiStartConfig = MultiStartConfig(),
                        seed: int = 0) -> PoseEstimate:
    """The wider estimator (see the module docstring); same arguments as :func:`inerf`."""
    t0 = time.perf_counter()
    device = model.aabb.device
    gen = torch.Generator().manual_seed(seed)
    obs = _Observation(image, intrinsics, config.refine, gen, device)
    c2w_init = torch.as_tensor(np.asarray(c2w_init, np.float32), device=device)
    offsets = torch.zeros(config.starts, 6)
    if config.starts > 1:
        u = torch.rand(config.starts - 1, 6, generator=gen) * 2 - 1
        offsets[1:, :3] = u[:, :3] * math.radians(config.rotation)
        offsets[1:, 3:] = u[:, 3:] * config.translation
    starts = c2w_init[None] @ se3_exp(offsets.to(device))
    with _Frozen(model):
        coarse, _ = _descend(model, obs, starts, config.coarse_iterations, config.coarse_rays,
                             config.refine.lr)
        with torch.no_grad():
            scores = _photometric(model, obs, coarse, *_evaluation_pixels(obs, 512, seed))
        best = coarse[int(torch.argmin(scores))]
    refined = inerf(model, image, intrinsics, best.cpu().numpy(), config.refine, seed)
    return PoseEstimate(refined.c2w, refined.loss, time.perf_counter() - t0, refined.losses)


def perturb(c2w: np.ndarray, translation: float, rotation_deg: float,
            rng: np.random.Generator) -> np.ndarray:
    """``c2w`` moved by exactly ``translation`` metres in a random direction and rotated by
    exactly ``rotation_deg`` degrees about a random axis through the camera centre."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    rot = cv2.Rodrigues(axis * math.radians(rotation_deg))[0]
    out = np.array(c2w, float)
    out[:3, :3] = rot @ out[:3, :3]
    out[:3, 3] += translation * direction
    return out
