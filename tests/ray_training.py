"""Training a model directly on analytic rays, for tests whose scenes are formulas rather
than captures."""

from __future__ import annotations

from typing import Callable

import torch

from nerfbot.ops.cameras import Rays

#: draw(n, generator) -> (rays (n,), their true colours (n, 3))
RayDraw = Callable[[int, torch.Generator], tuple[Rays, torch.Tensor]]


def train_on_rays(model: torch.nn.Module, draw: RayDraw, steps: int) -> torch.nn.Module:
    """``steps`` Adam steps (lr 1e-2) of ``model``'s loss on batches from ``draw``, with the ray
    count adapted to the model's samples per batch as in training; returns it in eval mode."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-2, eps=1e-15)
    gen = torch.Generator().manual_seed(0)
    model.train()
    n_rays, samples = None, None
    for step in range(steps):
        model.before_step(step, gen, step / steps)
        n_rays = model.rays_for_next_batch(samples, n_rays)
        rays, rgb = draw(n_rays, gen)
        loss, out = model.loss(rays, rgb, gen)
        samples = out.num_samples
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model.eval()
