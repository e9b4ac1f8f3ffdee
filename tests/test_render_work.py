"""Rendering spends density and colour evaluations only where they change the result.

- The occupancy-grid renderer's eval-mode renders march in rounds that grow
  (``first_round_samples``, doubling up to ``inference_round_samples``): the samples kept must
  not depend on the rounds, and small first rounds must spend fewer density evaluations
  behind surfaces; so must training's density-only pass (``train_first_round_samples``).
- With S x S rays through every pixel, the centre ray only gives depth: it is rendered
  without colour, and the image must equal one assembled from full renders.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.fields.background import FixedBackground
from nerfbot.fields.base import Field
from nerfbot.models.occupancy import OccupancyModel, OccupancyModelConfig
from nerfbot.ops.cameras import Cameras, Rays, look_at
from nerfbot.query.render import render_image, render_rays_chunked

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


class Blobs(Field):
    """Opaque balls of random radii and colours in a faint fog: rays saturate at many depths,
    some never. Counts the density evaluations."""

    def __init__(self, n=30, seed=0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.centres = torch.rand(n, 3, generator=g) * 1.4 - 0.7
        self.radii = 0.15 + 0.2 * torch.rand(n, generator=g)
        self.colours = torch.rand(n, 3, generator=g)
        self.calls = 0

    def density(self, x, cond=None):
        self.calls += len(x)
        d = (x[:, None, :] - self.centres[None]).norm(dim=-1) - self.radii[None]
        inside = (d < 0).any(1)
        sigma = torch.where(inside, 400.0, 0.05)
        nearest = d.argmin(1)
        return sigma.to(x.dtype), nearest[:, None].float()

    def color(self, feat, d, cond=None):
        return self.colours[feat[:, 0].long()]


def _rays(n=400, seed=1) -> Rays:
    g = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.0, 0.0, 2.5]) + 0.3 * torch.randn(n, 3, generator=g)
    targets = torch.rand(n, 3, generator=g) * 1.6 - 0.8
    d = targets - origins
    d = d / d.norm(dim=-1, keepdim=True)
    return Rays(origins, d, torch.ones(n), None)


def _model(field, first, most=16) -> OccupancyModel:
    """The renderer over ``field``, its occupancy grid fitted to the field (the fog is pruned,
    so rays skip to the balls as in a trained scene)."""
    cfg = OccupancyModelConfig(first_round_samples=first, inference_round_samples=most)
    model = OccupancyModel(field, FixedBackground((1.0, 1.0, 1.0)), AABB, cfg).eval()
    model.grid.update(lambda x: field.density(x)[0], model.dt_min,
                      torch.Generator().manual_seed(0))
    field.calls = 0
    return model


@pytest.mark.parametrize("first", [1, 2, 4, 16])
def test_kept_samples_do_not_depend_on_the_rounds(first):
    rays = _rays()
    t_near, t_far, _ = _model(Blobs(), 16).ray_range(rays)
    ref = _model(Blobs(), 16)._march_until_opaque(rays, t_near, t_far, None, 1e-4)
    got = _model(Blobs(), first)._march_until_opaque(rays, t_near, t_far, None, 1e-4,
                                                     first_round=first)
    assert ref[0].numel() > 0
    assert torch.equal(ref[0], got[0])  # the same samples of the same rays
    # t resumes from each round's float32 stop, so positions agree to float32 rounding
    for a, b in zip(ref[1:4], got[1:4]):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-6)


def test_small_first_rounds_evaluate_fewer_samples_and_render_the_same():
    rays = _rays()
    fields = {first: Blobs() for first in (16, 4)}
    out = {first: _model(f, first).render_rays(rays) for first, f in fields.items()}
    # rays behind a ball stop within a few samples of it instead of finishing a round of 16
    assert fields[4].calls < 0.8 * fields[16].calls, {k: f.calls for k, f in fields.items()}
    # the last round's samples past saturation weigh under early_stop_transmittance (1e-3)
    saturated = out[16].opacity > 0.99
    assert saturated.sum() > 50 and (~saturated).sum() > 50
    torch.testing.assert_close(out[4].rgb, out[16].rgb, atol=2e-3, rtol=0)
    torch.testing.assert_close(out[4].opacity, out[16].opacity, atol=2e-3, rtol=0)
    torch.testing.assert_close(out[4].depth, out[16].depth, atol=2e-2, rtol=0)


def test_training_density_pass_rounds_keep_the_samples_and_evaluate_fewer():
    """Training's density-only pass (``train_first_round_samples``) finds where each jittered
    training ray saturates: from small first rounds it keeps the same samples, so the trained
    pass and its loss are the same, with fewer density evaluations behind the balls."""
    rays = _rays()
    runs = {}
    for first in (0, 4):
        field = Blobs()
        cfg = OccupancyModelConfig(train_first_round_samples=first)  # a first step: rounds
        model = OccupancyModel(field, FixedBackground((1.0, 1.0, 1.0)), AABB, cfg).train()
        model.grid.update(lambda x: field.density(x)[0], model.dt_min,
                          torch.Generator().manual_seed(0))
        field.calls = 0
        out = model.render_rays(rays, torch.Generator().manual_seed(3))
        runs[first] = (out, field.calls)
    (ref, ref_calls), (got, got_calls) = runs[0], runs[4]
    assert torch.equal(ref.ray_indices, got.ray_indices)
    torch.testing.assert_close(got.t_starts, ref.t_starts, atol=1e-5, rtol=1e-6)
    torch.testing.assert_close(got.rgb, ref.rgb, atol=1e-4, rtol=0)
    assert got_calls < 0.8 * ref_calls, (got_calls, ref_calls)


def test_first_round_must_be_positive():
    with pytest.raises(ValueError, match="first_round_samples"):
        OccupancyModelConfig(first_round_samples=0)
    with pytest.raises(ValueError, match="train_first_round_samples"):
        OccupancyModelConfig(train_first_round_samples=-1)


class CountingBlobs(Blobs):
    """Blobs that also count colour evaluations."""

    def __init__(self):
        super().__init__()
        self.colour_calls = 0

    def color(self, feat, d, cond=None):
        self.colour_calls += len(feat)
        return super().color(feat, d, cond)


def test_supersampled_image_renders_centre_rays_without_colour():
    field = CountingBlobs()
    model = _model(field, 4)
    model.config.supersample = 2
    model.config.supersample_pattern = "grid"   # 2 x 2 rays through every pixel
    c2w = look_at(np.array([0.2, 0.3, 2.5]), np.zeros(3), up=np.array([0, 1.0, 0]))
    cams = Cameras.from_numpy(c2w[None], [[40.0, 40.0, 16.0, 16.0]], [[32, 32]])
    field.colour_calls = 0
    img = render_image(model, cams, 0)
    colours_spent = field.colour_calls

    centre = render_rays_chunked(model, cams.rays(0))
    fine = render_rays_chunked(model, cams.rays(0, 1, 2))
    field.colour_calls = 0
    render_rays_chunked(model, cams.rays(0, 1, 2))
    assert colours_spent == field.colour_calls > 0  # the fine rays' colours and no others
    # colour and opacity: the mean of the 2 x 2 rays of each pixel; depths: the centre ray's
    mean_rgb = fine["rgb"].reshape(32, 2, 32, 2, 3).mean((1, 3)).numpy()
    mean_opacity = fine["opacity"].reshape(32, 2, 32, 2).mean((1, 3)).numpy()
    np.testing.assert_allclose(img["rgb"], mean_rgb.clip(0, 1), atol=1e-6)
    np.testing.assert_allclose(img["opacity"], mean_opacity, atol=1e-6)
    for k in ("depth", "z_depth", "median_depth", "median_z_depth"):
        np.testing.assert_allclose(img[k], centre[k].reshape(32, 32).numpy(), atol=1e-6)
    assert 0.1 < float((img["opacity"] > 0.99).mean()) < 0.9  # balls and background in view
