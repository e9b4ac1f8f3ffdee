"""The carving prior (``carving_weight``): a uniformly coloured plate seen from two arcs of
cameras at its own height is learnt as its visual hull, a lens around the plate, unless the
prior carves the density that no image needs."""

from __future__ import annotations

import math

import pytest
import torch

from nerfbot.methods import build_model
from nerfbot.ops.cameras import Rays
from nerfbot.query.density import default_obstacle_threshold, density_at
from nerfbot.query.render import render_rays_chunked
from ray_training import train_on_rays

pytestmark = pytest.mark.slow(75)  # rough single-core seconds (tests/conftest.py)

PLATE_HALF = torch.tensor([0.5, 0.01, 0.4])     # a 1 m x 2 cm x 0.8 m plate at the origin, metres
PLATE_RGB = torch.tensor([0.1, 0.5, 0.5])


def plate_rays(n: int, gen: torch.Generator) -> tuple[Rays, torch.Tensor]:
    """n rays from cameras 2 m from the plate in its mid-plane, on two 120-degree arcs facing
    its two sides (no camera looks along it), through random points near it; the colour
    each sees: the plate's, or the white background."""
    arc = torch.rand(n, generator=gen) * (2 * math.pi / 3) + math.pi / 6
    phi = torch.where(torch.arange(n) % 2 == 0, arc, arc + math.pi)
    origins = torch.stack([2.0 * torch.cos(phi), 2.0 * torch.sin(phi), torch.zeros(n)], 1)
    targets = (torch.rand(n, 3, generator=gen) * 2 - 1) * torch.tensor([0.8, 0.3, 0.7])
    d = targets - origins
    d = d / d.norm(dim=1, keepdim=True)
    t0, t1 = (-PLATE_HALF - origins) / d, (PLATE_HALF - origins) / d
    hit = torch.minimum(t0, t1).amax(1) < torch.maximum(t0, t1).amin(1)
    return Rays(origins, d, torch.ones(n)), torch.where(hit[:, None], PLATE_RGB, torch.ones(3))


def train_plate(carving_weight: float, steps: int = 300) -> torch.nn.Module:
    """ngp trained on :func:`plate_rays` from the start that leaves 0.2 of the light along the
    cube's diagonal, from which the plain field grows the full hull the prior is tested on."""
    torch.manual_seed(0)
    model = build_model("ngp", [[-1, -1, -1], [1, 1, 1]], background="white", options={
        "log2_hashmap_size": 15, "carving_weight": carving_weight, "samples_per_batch": 1 << 14,
        "supersample": 1, "density_noise": 0.0, "initial_transmittance": 0.2,
        "initial_transmittance_path": "diagonal"})
    return train_on_rays(model, plate_rays, steps)


def plate_thickness(model) -> float:
    """Mean length (metres) of the obstacle-dense stretch of nine lines across the plate."""
    ys = torch.linspace(-0.4, 0.4, 161)
    threshold = default_obstacle_threshold(model)
    lengths = []
    for x in (-0.3, 0.0, 0.3):
        for z in (-0.2, 0.0, 0.2):
            p = torch.stack([torch.full_like(ys, x), ys, torch.full_like(ys, z)], 1)
            with torch.no_grad():
                lengths.append(float((density_at(model, p) >= threshold).sum()) * 0.005)
    return sum(lengths) / len(lengths)


def plate_psnr(model) -> float:
    rays, rgb = plate_rays(4096, torch.Generator().manual_seed(9))
    with torch.no_grad():
        out = render_rays_chunked(model, rays)
    return -10.0 * math.log10(float(((out["rgb"] - rgb) ** 2).mean()))


def test_carving_thins_the_visual_hull_of_a_plain_plate():
    plain, carved = train_plate(0.0), train_plate(1e-3)
    thick, thin = plate_thickness(plain), plate_thickness(carved)
    # observed: 10.2 cm without the prior, 1.1 cm with it (the plate is 2 cm); 30.2 and 29.9 dB
    assert thick > 0.04, thick                   # the hull: twice the plate's thickness
    assert thin < 0.4 * thick, (thin, thick)
    assert plate_psnr(carved) > 25.0 and plate_psnr(carved) > plate_psnr(plain) - 1.0
