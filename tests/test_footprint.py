"""Anti-aliasing by the sample's footprint (``ngp``'s ``footprint_scale``, Zip-NeRF's feature
down-weighting): a striped wall seen through fine pixels, which resolve the stripes, and
through coarse ones, which average them to grey. A field that gives a point one colour
whatever the pixel that sees it must split the difference; one that knows the footprint fits
both."""

from __future__ import annotations

import math

import pytest
import torch

from nerfbot.fields.base import BoxNormalizer, ContractedNormalizer
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.methods import build_model
from nerfbot.ops.cameras import Rays
from nerfbot.query.render import render_rays_chunked
from ray_training import train_on_rays

WALL_HALF = torch.tensor([0.8, 0.01, 0.6])    # a 1.6 x 1.2 m wall, 2 cm thick, at y = 0, metres
PERIOD = 0.06                                 # the stripes' period along x, metres
DISTANCE = 1.0                                # the cameras' distance from the wall, metres
#: cone radius per metre of distance of the fine cameras' pixels and of the coarse ones' (a
#: camera of 24x fewer pixels across); at 1 m the coarse pixels average the stripes to grey
RADIUS_FINE, RADIUS_COARSE = 0.0025, 0.06


def test_level_weights_are_one_for_points_and_fall_with_the_footprint_fine_levels_first():
    aabb = [[-1, -1, -1], [1, 1, 1]]
    field = NGPField(aabb, NGPFieldConfig(footprint_scale=1.0, log2_hashmap_size=12))
    x = torch.zeros(4, 3)
    w = field.level_weights(x, torch.tensor([0.0, 1e-3, 1e-2, 1e-1]))
    assert torch.equal(w[0], torch.ones(field.encoding.n_levels))
    assert bool((w[1:].diff(dim=1) <= 0).all()), "finer levels must weigh less"
    assert bool((w[1:].diff(dim=0) <= 0).all()), "larger footprints must weigh less"
    assert bool((w[1:, -1].diff() < 0).all()) and float(w[3, -1]) < 0.05
    # the formula: erf(1 / sqrt(8 (r n)^2)), r in the unit cube (2 m edge here)
    r, n = 1e-2 / 2.0, float(field.encoding.res[-1])
    assert float(w[2, -1]) == pytest.approx(math.erf(1.0 / math.sqrt(8.0 * (r * n) ** 2)),
                                            rel=1e-5)
    # without a footprint the field is the point-sampled one
    pts = torch.rand(64, 3) * 2 - 1
    with torch.no_grad():
        a = field.density(pts)
        b = field.density_at_scale(pts, None)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


@pytest.mark.parametrize("normalizer", [BoxNormalizer, ContractedNormalizer])
def test_unit_scale_is_the_normalisers_isotropic_jacobian(normalizer):
    """unit_scale = |det J|^(1/3) of the map from metres to the grid's unit cube, inside the
    bounds and (contracted) far outside them."""
    norm = normalizer(torch.tensor([[-1.0, -2.0, -0.5], [1.0, 2.0, 0.5]]))
    points = torch.tensor([[0.3, -0.2, 0.1], [3.0, 0.5, -0.4], [-6.0, 9.0, 2.0]])
    if normalizer is BoxNormalizer:
        points = points[:1]
    for p in points:
        jac = torch.autograd.functional.jacobian(lambda q: norm(q[None])[0], p)
        assert float(norm.unit_scale(p[None])[0]) == pytest.approx(
            float(torch.det(jac).abs() ** (1.0 / 3.0)), rel=1e-5)


def wall_rays(n: int, gen: torch.Generator) -> tuple[Rays, torch.Tensor, torch.Tensor]:
    """n rays from cameras DISTANCE in front of the wall through random points of it, half
    with the fine cameras' cones and half with the coarse ones'; the colour each pixel sees:
    the stripes 0.5 + 0.4 sin(2 pi x / PERIOD) filtered by its footprint (a Gaussian of half
    the cone's radius scales a sinusoid by exp(-2 pi^2 sigma^2 / PERIOD^2)), so fine pixels
    see the stripes and coarse ones grey. Both kinds march the same samples, so only the
    footprint tells them apart. Returns rays, colours (n, 3) and (n,) bool: coarse."""
    coarse = torch.arange(n) % 2 == 1
    hit = (torch.rand(n, 3, generator=gen) * 2 - 1) * torch.tensor([0.6, 0.0, 0.45])
    hit[:, 1] = WALL_HALF[1]
    origins = hit + torch.stack([(torch.rand(n, generator=gen) * 2 - 1) * 0.3,
                                 torch.full((n,), DISTANCE),
                                 (torch.rand(n, generator=gen) * 2 - 1) * 0.3], 1)
    d = hit - origins
    t = d.norm(dim=1)
    d = d / t[:, None]
    radii = torch.where(coarse, torch.tensor(RADIUS_COARSE), torch.tensor(RADIUS_FINE))
    sigma = 0.5 * radii * t
    amplitude = 0.4 * torch.exp(-2.0 * math.pi ** 2 * sigma ** 2 / PERIOD ** 2)
    grey = 0.5 + amplitude * torch.sin(2.0 * math.pi * hit[:, 0] / PERIOD)
    rays = Rays(origins, d, torch.ones(n), radii)
    return rays, grey[:, None].expand(n, 3).contiguous(), coarse


def train_wall(footprint_scale: float, steps: int = 400) -> torch.nn.Module:
    torch.manual_seed(0)
    model = build_model("ngp", [[-1, -1, -1], [1, 1, 1]], background="white", options={
        "log2_hashmap_size": 16, "samples_per_batch": 1 << 14, "supersample": 1,
        "density_noise": 0.0, "carving_weight": 0.0, "sh_degree": 0,
        "footprint_scale": footprint_scale})
    return train_on_rays(model, lambda n, gen: wall_rays(n, gen)[:2], steps)


def psnr_fine_and_coarse(model) -> tuple[float, float]:
    rays, rgb, coarse = wall_rays(4096, torch.Generator().manual_seed(9))
    with torch.no_grad():
        out = render_rays_chunked(model, rays)
    err = ((out["rgb"] - rgb) ** 2).mean(1)
    return tuple(-10.0 * math.log10(float(err[m].mean())) for m in (~coarse, coarse))


@pytest.mark.slow(70)  # rough single-core seconds (tests/conftest.py)
def test_the_footprint_lets_one_field_fit_fine_stripes_and_their_coarse_average():
    """400 steps each (seen: point samples 15.5 dB on the fine pixels and 17.5 dB on the
    coarse ones; with the footprint 24.9 and 33.5 dB)."""
    point_fine, point_coarse = psnr_fine_and_coarse(train_wall(0.0))
    cone_fine, cone_coarse = psnr_fine_and_coarse(train_wall(1.0))
    print(f"point samples: fine {point_fine:.1f} dB, coarse {point_coarse:.1f} dB; "
          f"footprint: fine {cone_fine:.1f} dB, coarse {cone_coarse:.1f} dB")
    assert cone_fine > point_fine + 5.0
    assert cone_coarse > point_coarse + 10.0
