"""Estimate an unknown joint configuration from one image by inverse rendering.

With a trained joint-conditioned model (``articulated``, or ``tnerf`` on joints) and a posed
image, the joint values q are found by gradient descent on the photometric error of rendered
rays, the field frozen:

1. coarse search: every configuration of a small grid over the joint limits is rendered on a
   fixed subset of pixels, and the best few become starting points (the photometric error of a
   door angle has local minima: a half-open door can match a closed one in part of the image);
2. from each start, Adam on the normalised joint values (clamped to the limits), each step on a
   fresh random set of pixels; gradients flow through the forward kinematics into the fields;
3. the start whose final error on the fixed pixels is lowest wins.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm.auto import tqdm

from nerfbot.data.conditioning import Conditioning
from nerfbot.models.base import Model
from nerfbot.ops.cameras import Cameras


@dataclass
class JointEstimateConfig:
    grid_per_joint: int = 7
    """Coarse-search values per joint across its limits (grid_per_joint ** C renders of the
    probe pixels, so keep it small for many joints)."""
    starts: int = 3
    """Best coarse configurations refined by gradient descent."""
    steps: int = 60
    """Adam steps per start."""
    rays_per_step: int = 2048
    """Random pixels rendered per step."""
    probe_rays: int = 4096
    """Fixed pixels used to rank configurations."""
    lr: float = 0.02
    """Adam learning rate on joint values normalised to [0, 1] over their limits."""
    seed: int = 0


def _set_requires_grad(model: Model, flag: bool) -> list[bool]:
    before = [p.requires_grad for p in model.parameters()]
    for p in model.parameters():
        p.requires_grad_(flag)
    return before


@torch.no_grad()
def _probe_loss(model: Model, rays, target, q: torch.Tensor, chunk: int = 8192) -> float:
    err = 0.0
    for i in range(0, len(rays), chunk):
        sub = rays[i:i + chunk]
        cond = q.reshape(1, -1).expand(len(sub), -1)
        out = model.render_rays(sub, None, cond)
        err += float(((out.rgb - target[i:i + chunk]) ** 2).sum())
    return err / (3 * len(rays))


def estimate_joints(model: Model, conditioning: Conditioning, cameras: Cameras, index: int,
                    image: np.ndarray, config: Optional[JointEstimateConfig] = None) -> dict:
    """Joint values that best explain ``image`` (H, W, 3) float in [0, 1] seen by camera ``index``.

    Returns {"joints": {name: value (rad / m)}, "loss": photometric MSE on the probe pixels,
    "starts": [(start values, final values, loss), ...]}.
    """
    if conditioning.kind != "joints":
        raise ValueError("joint estimation needs a joint-conditioned run (e.g. method "
                         "'articulated' trained on an articulated capture)")
    cfg = config or JointEstimateConfig()
    gen = torch.Generator().manual_seed(cfg.seed)
    device = model.aabb.device
    all_rays = cameras.rays(index).to(device)
    target_all = torch.as_tensor(np.asarray(image, np.float32).reshape(-1, 3), device=device)
    probe = torch.randperm(len(all_rays), generator=gen)[:cfg.probe_rays].to(device)
    probe_rays, probe_rgb = all_rays[probe], target_all[probe]
    lo = torch.tensor([r[0] for r in conditioning.ranges], dtype=torch.float32, device=device)
    span = torch.tensor([r[1] - r[0] for r in conditioning.ranges], dtype=torch.float32,
                        device=device)

    was_training = model.training
    grads_before = _set_requires_grad(model, False)
    try:
        model.eval()
        grid = np.linspace(0.0, 1.0, cfg.grid_per_joint)
        scored = []
        for u in itertools.product(grid, repeat=conditioning.dim):
            u_t = torch.tensor(u, dtype=torch.float32, device=device)
            scored.append((_probe_loss(model, probe_rays, probe_rgb, lo + u_t * span), u_t))
        scored.sort(key=lambda s: s[0])
        results = []
        for _, u0 in scored[:cfg.starts]:
            u = u0.clone().requires_grad_(True)
            opt = torch.optim.Adam([u], lr=cfg.lr)
            model.train()  # differentiable marching (jittered samples)
            for _ in range(cfg.steps):
                pick = torch.randint(len(all_rays), (cfg.rays_per_step,), generator=gen).to(device)
                rays = all_rays[pick]
                q = lo + u * span
                out = model.render_rays(rays, gen, q.reshape(1, -1).expand(len(rays), -1))
                loss = F.mse_loss(out.rgb, target_all[pick])
                opt.zero_grad()
                loss.backward()
                opt.step()
                with torch.no_grad():
                    u.clamp_(0.0, 1.0)
            model.eval()
            q = (lo + u.detach() * span)
            results.append((lo + u0 * span, q, _probe_loss(model, probe_rays, probe_rgb, q)))
        best = min(results, key=lambda r: r[2])
    finally:
        for p, flag in zip(model.parameters(), grads_before):
            p.requires_grad_(flag)
        model.train(was_training)
    return {"joints": {n: float(v) for n, v in zip(conditioning.names, best[1].tolist())},
            "loss": best[2],
            "starts": [(s.tolist(), q.tolist(), loss) for s, q, loss in results]}


def joint_errors(estimate: dict, truth: dict, conditioning: Conditioning) -> dict:
    """Absolute error per joint in degrees (hinge) or millimetres (slide)."""
    out = {}
    for n in conditioning.names:
        kind = (conditioning.joint_info.get(n) or {}).get("type", "hinge")
        err = abs(float(estimate[n]) - float(truth[n]))
        out[n] = math.degrees(err) if kind == "hinge" else 1000.0 * err
    return out


def evaluate_joint_estimation(model: Model, dataset, conditioning: Conditioning,
                              indices: Sequence[int], config: Optional[JointEstimateConfig] = None,
                              progress: bool = False) -> dict:
    """Estimate the joints of each frame of ``indices`` independently; errors against the truth.

    Returns {"per_image": [...], "median_error": {joint: deg or mm}, "mean_error": {...},
    "units": {joint: "deg" | "mm"}}."""
    idx = list(indices)
    cams = dataset.cameras(idx)
    rows = []
    for slot in tqdm(range(len(idx)), desc="estimate joints", disable=not progress):
        i = idx[slot]
        est = estimate_joints(model, conditioning, cams, slot, dataset.image_float(i), config)
        rows.append({"frame": dataset.file_paths[i], "truth": dataset.joints[i],
                     "estimate": est["joints"], "loss": est["loss"],
                     "error": joint_errors(est["joints"], dataset.joints[i], conditioning)})
    units = {n: ("deg" if (conditioning.joint_info.get(n) or {}).get("type", "hinge") == "hinge"
                 else "mm") for n in conditioning.names}
    med = {n: float(np.median([r["error"][n] for r in rows])) for n in conditioning.names} if rows else {}
    mean = {n: float(np.mean([r["error"][n] for r in rows])) for n in conditioning.names} if rows else {}
    return {"per_image": rows, "median_error": med, "mean_error": mean, "units": units}
