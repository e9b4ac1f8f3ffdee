"""Where is the camera? Pose estimation from one observed image through a frozen field.

- :func:`inerf` (iNeRF, Yen-Chen et al. 2021): gradient descent on the photometric error of a
  batch of pixels, over a pose update applied through the exponential map,
  ``c2w = c2w_0 @ exp(xi)``. Pixels are drawn from an interest region (opencv keypoints,
  dilated), where the image gradient tells the pose apart. Its basin is narrow: a pixel's
  colour says nothing about a pose that moves it by more than a few pixels. The ray origins'
  gradients are kept only across their rays (:func:`across_rays`): along a ray they are
  quadrature noise, which Adam's per-coordinate scaling would turn into steps along the view
  axis. With ``coarse_levels`` it first descends on whole blurred images at 16 x 16, 32 x 32,
  ... pixels, coarse to fine, whose error changes smoothly over shifts of several of their
  pixels: a wider basin for the same descent.
- :func:`localise_wide`: widens the basin by comparing whole images, blurred, and by direct
  image alignment (:mod:`nerfbot.query.direct_alignment`): a grid of hypotheses around the
  guess is scored by 16 x 16 renders; from the guess and the best few, the observed image is
  aligned to a 32 x 32 render by Gauss-Newton through the render's depth; the candidate whose
  colours fit best at full resolution is refined by rounds of rendering a reference at the
  estimate (64 x 64, then full resolution) and aligning to it again. No round descends
  through the field, so every pixel takes part at each step; its cost is the renders (about
  one 16 x 16 render per hypothesis, a 32 x 32 one per start, and one per round).

The pose update is one of two models (``planar`` in the configs):

- ``planar=False``: a twist in se(3) in the camera frame, all six degrees of freedom;
- ``planar=True``: (dx, dy, dyaw) in the world, the camera turning about the vertical through
  its centre, as a ground robot's camera moves: its height, roll and pitch are known from its
  body, and a 6-DoF search would spend its pixels on them.

All need a model that renders with gradients w.r.t. its rays
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
from nerfbot.ops.cameras import Rays, pixel_rays
from nerfbot.ops.lie import se3_exp
from nerfbot.query.direct_alignment import (AlignConfig, align, blur, level_pixels,
                                            level_size, render_reference)


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
        planar: update (dx, dy, dyaw) in the world instead of a 6-DoF twist (module docstring).
        across_rays: pass the ray origins' gradients only across their rays
            (:func:`across_rays`); False: the raw gradients of the samples' positions.
        coarse_levels: whole-image levels descended before the sparse pixels, coarse to fine:
            the observed image area-averaged to ``coarse_resolution`` pixels square, then
            twice that, ... (each level twice the last), and both it and the render at that
            resolution blurred by ``coarse_sigma`` of its pixels. A blurred image's error
            changes smoothly over shifts of a few of its pixels, which full-resolution pixels
            do not: the basin widens. 0: iNeRF as published.
        coarse_iterations: Adam steps on each coarse level (the rate decayed to a tenth on
            each).
        coarse_sigma: the coarse levels' Gaussian blur, in their pixels.
        coarse_resolution: pixels per side of the first coarse level.
        coarse_supersample: s: each coarse pixel rendered as the mean of s x s rays through
            it (the observed image's pixels there are area averages); 1: one ray, at its
            centre.
    """

    iterations: int = 80
    rays: int = 512
    lr: float = 0.02
    interest: bool = True
    interest_fraction: float = 0.75
    dilate: int = 3
    planar: bool = False
    across_rays: bool = True
    coarse_levels: int = 0
    coarse_iterations: int = 20
    coarse_sigma: float = 1.0
    coarse_resolution: int = 16
    coarse_supersample: int = 1

    def __post_init__(self):
        if (self.coarse_levels < 0 or self.coarse_iterations < 1 or not self.coarse_sigma >= 0
                or self.coarse_resolution < 2 or self.coarse_supersample < 1):
            raise ValueError(f"InerfConfig: coarse_levels must be >= 0, coarse_iterations >= 1, "
                             f"coarse_sigma >= 0, coarse_resolution >= 2 and "
                             f"coarse_supersample >= 1, got {self.coarse_levels}, "
                             f"{self.coarse_iterations}, {self.coarse_sigma}, "
                             f"{self.coarse_resolution}, {self.coarse_supersample}")


@dataclass
class PoseEstimate:
    """The estimated camera-to-world pose (4, 4), the final photometric MSE on a fixed set of
    pixels, the seconds it took, and ``losses``: iNeRF's mean batch MSE at every iteration,
    or the wide estimator's last alignment cost of each finalist."""

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


class _AcrossRays(torch.autograd.Function):
    """The identity on ray origins (R, 3) whose backward drops each gradient's component along
    its ray's unit direction (R, 3). Moving an origin along its ray leaves the ray's line, and
    so its colour, unchanged; but the quadrature's samples sit at fixed distances from the
    origin, so that component of the gradient is the hash grid's variation along the ray,
    noise that walks the pose along the view axis."""

    @staticmethod
    def forward(ctx, origins, directions):
        ctx.save_for_backward(directions)
        return origins.view_as(origins)

    @staticmethod
    def backward(ctx, grad):
        (d,) = ctx.saved_tensors
        return grad - (grad * d).sum(-1, keepdim=True) * d, None


def across_rays(rays: Rays) -> Rays:
    """``rays`` whose origins pass gradients only across the rays (:class:`_AcrossRays`)."""
    return Rays(_AcrossRays.apply(rays.origins, rays.directions.detach()), rays.directions,
                rays.z_per_t, rays.radii)


def _photometric(model, obs: _Observation, c2w: torch.Tensor, px, py) -> torch.Tensor:
    """(K,) mean squared colour error of each of K poses c2w (K, 4, 4) at pixels (px, py)."""
    k = c2w.shape[0]
    n = len(px)
    rays = obs.rays(c2w.repeat_interleave(n, 0), px.repeat(k), py.repeat(k))
    if obs.config.across_rays:
        rays = across_rays(rays)
    rgb = model.render_rays_differentiable(rays).rgb
    return ((rgb - obs.target(px, py).repeat(k, 1)) ** 2).mean(-1).reshape(k, n).mean(-1)


def planar_update(c2w: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """(K, 4, 4) poses ``c2w`` (K, 4, 4) turned by q[:, 2] radians about the world's vertical
    through each camera centre, then moved by (q[:, 0], q[:, 1], 0) metres; differentiable."""
    c, s = torch.cos(q[:, 2]), torch.sin(q[:, 2])
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    rz = torch.stack([torch.stack([c, -s, zero], -1), torch.stack([s, c, zero], -1),
                      torch.stack([zero, zero, one], -1)], -2)
    centre = c2w[:, :3, 3] + torch.stack([q[:, 0], q[:, 1], zero], -1)
    bottom = c2w[:, 3:, :].expand(len(q), 1, 4)
    return torch.cat([torch.cat([rz @ c2w[:, :3, :3], centre[..., None]], -1), bottom], 1)


def _update(c2w0: torch.Tensor, xi: torch.Tensor, planar: bool) -> torch.Tensor:
    return planar_update(c2w0, xi) if planar else c2w0 @ se3_exp(xi)


def _adam(c2w0: torch.Tensor, planar: bool, iterations: int, lr: float, loss_of
          ) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    """Adam on one pose update per start, the rate decayed to a tenth: c2w0 (K, 4, 4) ->
    (refined (K, 4, 4), last losses (K,), mean loss per iteration). ``loss_of(poses)`` gives
    the (K,) losses of poses (K, 4, 4)."""
    xi = torch.zeros(c2w0.shape[0], 3 if planar else 6, device=c2w0.device, requires_grad=True)
    opt = torch.optim.Adam([xi], lr=lr)
    losses, loss = [], torch.zeros(c2w0.shape[0])
    for it in range(iterations):
        for group in opt.param_groups:
            group["lr"] = lr * 0.1 ** (it / max(iterations - 1, 1))
        loss = loss_of(_update(c2w0, xi, planar))
        opt.zero_grad()
        loss.sum().backward()
        opt.step()
        losses.append(float(loss.detach().mean()))
    with torch.no_grad():
        return _update(c2w0, xi, planar), loss.detach(), losses


def _descend(model, obs: _Observation, c2w0: torch.Tensor, iterations: int, rays: int,
             lr: float, planar: bool = False) -> tuple[torch.Tensor, list[float]]:
    """iNeRF's descent from each start c2w0 (K, 4, 4) on ``rays`` pixels per iteration:
    (refined (K, 4, 4), mean loss per iteration)."""
    refined, _, losses = _adam(c2w0, planar, iterations, lr,
                               lambda poses: _photometric(model, obs, poses, *obs.draw(rays)))
    return refined, losses


class _LowRes:
    """The observed image area-averaged to ``res`` x ``res`` pixels and blurred by ``sigma``
    of them, and the whole-image photometric error of poses rendered at that resolution
    (the origins' gradients only across their rays with ``across``, :func:`across_rays`)."""

    def __init__(self, model, obs: _Observation, res: int, sigma: float, across: bool = False,
                 supersample: int = 1):
        self.model, self.res, self.sigma, self.across = model, res, sigma, across
        self.supersample = supersample
        small = cv2.resize(obs.rgb.cpu().numpy(), (res, res), interpolation=cv2.INTER_AREA)
        self.target = blur(
            torch.as_tensor(small, device=obs.device).permute(2, 0, 1)[None], sigma)
        self.sx, self.sy = res / obs.w, res / obs.h
        px, py = level_pixels(res, res, obs.device)
        if supersample > 1:  # s x s rays per pixel, at the centres of an s x s grid over it
            grid = (torch.arange(supersample, dtype=torch.float32, device=obs.device) + 0.5) \
                / supersample - 0.5
            gy, gx = torch.meshgrid(grid, grid, indexing="ij")
            px = (px[:, None] + gx.reshape(1, -1)).reshape(-1)
            py = (py[:, None] + gy.reshape(1, -1)).reshape(-1)
        self.px, self.py = px, py
        self.obs = obs

    def __call__(self, c2w: torch.Tensor) -> torch.Tensor:
        """(K,) mean squared error of the blurred renders of poses c2w (K, 4, 4)."""
        k, n, o = c2w.shape[0], len(self.px), self.obs
        ss = self.supersample
        rays = pixel_rays(c2w.repeat_interleave(n, 0), o.fx * self.sx, o.fy * self.sy,
                          o.cx * self.sx, o.cy * self.sy, self.px.repeat(k), self.py.repeat(k),
                          1 / (self.sx * ss), 1 / (self.sy * ss))
        if self.across:
            rays = across_rays(rays)
        rgb = self.model.render_rays_differentiable(rays).rgb
        rgb = rgb.reshape(k, self.res * self.res, ss * ss, 3).mean(2)
        rgb = rgb.reshape(k, self.res, self.res, 3).permute(0, 3, 1, 2)
        return ((blur(rgb, self.sigma) - self.target) ** 2).mean((1, 2, 3))


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
        c2w, losses = c2w0, []
        for level in range(config.coarse_levels):
            res = min(config.coarse_resolution << level, obs.w, obs.h)
            coarse = _LowRes(model, obs, res, config.coarse_sigma, config.across_rays,
                             config.coarse_supersample)
            c2w, _, coarse_losses = _adam(c2w, config.planar, config.coarse_iterations,
                                          config.lr, coarse)
            losses += coarse_losses
        c2w, fine_losses = _descend(model, obs, c2w, config.iterations, config.rays, config.lr,
                                    config.planar)
        losses += fine_losses
        with torch.no_grad():
            loss = float(_photometric(model, obs, c2w, *_evaluation_pixels(obs, 1024, seed))[0])
    return PoseEstimate(c2w[0].cpu().numpy().astype(float), loss, time.perf_counter() - t0,
                        losses)


@dataclass(frozen=True)
class WideConfig:
    """The wide estimator's settings.

    Attributes:
        translation: the hypothesis grid spans +-this around the guess along each moved axis,
            metres (3 steps per axis: -, 0, +).
        rotation: and +-this about each turned axis, degrees (5 steps: -, -/2, 0, +/2, +).
        score_resolution, score_sigma: the hypotheses are scored by renders of this many
            pixels a side, blurred by this many of them.
        keep: starts aligned to their own reference render (the guess and the best scored).
        finalists: of the aligned starts and the guess, this many (the lowest colour errors
            at full resolution) go through the refinement rounds; the best at the end wins.
        start_scale: the starts' reference renders, a fraction of the image's resolution.
        start_levels: the pyramid the starts align over (fractions of the image's resolution).
        rounds: (reference scale, pyramid levels) of each refinement round, coarse to fine:
            a reference rendered at the estimate, the image aligned to it.
        align: the Gauss-Newton settings of every level.
        planar: the ground-robot pose model (module docstring).
    """

    translation: float = 0.2
    rotation: float = 16.0
    score_resolution: int = 16
    score_sigma: float = 1.0
    keep: int = 4
    finalists: int = 1
    start_scale: float = 0.25
    start_levels: tuple = (0.125, 0.25)
    rounds: tuple = ((0.5, (0.25, 0.5)), (1.0, (0.5, 1.0)))
    align: AlignConfig = AlignConfig()
    planar: bool = False


def _hypotheses(config: WideConfig) -> torch.Tensor:
    """(N, 3 or 6) pose updates of the hypothesis grid (the zero update first). Planar: every
    (dx, dy, dyaw) of the grid. 6-DoF: the grid's turns about the camera's vertical and
    horizontal axes (the directions the image moves most) with its moves along its three axes,
    one axis at a time."""
    t = config.translation
    r = math.radians(config.rotation)
    moves = (-t, 0.0, t)
    turns = (-r, -r / 2, 0.0, r / 2, r)
    if config.planar:
        grid = [(dx, dy, a) for a in turns for dx in moves for dy in moves]
    else:
        grid = [(rx, ry, 0.0, 0.0, 0.0, 0.0) for rx in turns for ry in turns]
        grid += [tuple(v if i == axis else 0.0 for i in range(6))
                 for axis in (3, 4, 5) for v in (-t, t)]
    grid.sort(key=lambda g: sum(abs(v) for v in g))     # the zero update first
    return torch.tensor(grid, dtype=torch.float32)


def localise_wide(model, image: np.ndarray, intrinsics, c2w_init: np.ndarray,
                  config: WideConfig = WideConfig(), seed: int = 0) -> PoseEstimate:
    """The wide estimator (see the module docstring); same arguments as :func:`inerf`.
    ``losses`` holds each finalist's last alignment cost."""
    t0 = time.perf_counter()
    device = model.aabb.device
    obs = _Observation(image, intrinsics, InerfConfig(interest=False),
                       torch.Generator().manual_seed(seed), device)
    guess = torch.as_tensor(np.asarray(c2w_init, np.float32), device=device)[None]
    parameters = 3 if config.planar else 6

    def update(start: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        return _update(start[None], q[None], config.planar)[0]

    def aligned(start: torch.Tensor, scale: float, levels) -> tuple[torch.Tensor, float]:
        reference = render_reference(model, start, intrinsics, level_size(obs.w, obs.h, scale),
                                     scale)
        return align(reference, obs.rgb, intrinsics, start, update, parameters, levels,
                     config.align)

    with _Frozen(model), torch.no_grad():
        coarse = _LowRes(model, obs, config.score_resolution, config.score_sigma)
        hypotheses = _hypotheses(config).to(device)
        candidates = _update(guess.expand(len(hypotheses), 4, 4), hypotheses, config.planar)
        scores = torch.cat([coarse(chunk) for chunk in torch.split(candidates, 16)])
        # the guess itself always starts: blurred low-resolution scores can prefer a wrong
        # hypothesis in a view with little texture
        order = [0] + [int(i) for i in torch.argsort(scores) if int(i) != 0]
        starts = [aligned(candidates[i], config.start_scale, config.start_levels)[0]
                  for i in order[:config.keep]]
        # the aligned starts and the guess itself (a low-resolution alignment can pull a good
        # guess a few degrees off) are judged by the field's colours at full resolution
        c2w = torch.cat([guess, torch.stack(starts)])
        pixels = _evaluation_pixels(obs, 1024, seed)
        order = torch.argsort(_photometric(model, obs, c2w, *pixels))[:config.finalists]
        finals, costs = [], []
        for pose in c2w[order]:
            for scale, levels in config.rounds:
                pose, cost = aligned(pose, scale, levels)
            finals.append(pose)
            costs.append(cost)
        finals = torch.stack(finals)
        errors = _photometric(model, obs, finals, *pixels)
        best = int(torch.argmin(errors))
        pose, final = finals[best], float(errors[best])
    return PoseEstimate(pose.cpu().numpy().astype(float), final, time.perf_counter() - t0,
                        costs)


def perturb(c2w: np.ndarray, translation: float, rotation_deg: float,
            rng: np.random.Generator, planar: bool = False) -> np.ndarray:
    """``c2w`` moved by exactly ``translation`` metres in a random direction and rotated by
    exactly ``rotation_deg`` degrees about a random axis through the camera centre; with
    ``planar``, the direction horizontal and the axis vertical (a ground robot's error)."""
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    if planar:
        axis = np.array([0.0, 0.0, rng.choice([-1.0, 1.0])])
        direction[2] = 0.0
    axis /= np.linalg.norm(axis)
    direction /= np.linalg.norm(direction)
    rot = cv2.Rodrigues(axis * math.radians(rotation_deg))[0]
    out = np.array(c2w, float)
    out[:3, :3] = rot @ out[:3, :3]
    out[:3, 3] += translation * direction
    return out
