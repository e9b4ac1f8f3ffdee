"""The baked background: the learned sky tabulated on an octahedral map of directions."""

import numpy as np
import torch

from nerfbot.fields.background import BakedBackground, FixedBackground, LearnedBackground
from nerfbot.ops.octahedral import direction_grid


def _directions(n=20000, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    # the map's seams: the equator (the diamond's edges), the poles, the mirrored border
    extra = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0],
                          [0.6, 0.8, 0.0], [-0.6, 0.8, -1e-7], [0.6, -0.8, 1e-7]])
    return torch.cat([d, torch.nn.functional.normalize(extra, dim=-1)])


def test_table_matches_the_learned_background_within_its_stated_error():
    """At the default 256^2 vertices, a learned sky (SH degree 4) read from the table is within
    2e-3 of the network everywhere, 1e-4 on average: below an 8-bit pixel's step (3.9e-3)."""
    torch.manual_seed(0)
    sky = LearnedBackground()
    with torch.no_grad():  # as varied over the sphere as the tabletop's trained skies (std 0.05)
        for p in sky.parameters():
            p.mul_(2.0)
    d = _directions()
    ref = sky(d).detach().numpy()
    err = np.abs(BakedBackground(sky)(d) - ref)
    assert err.max() < 2e-3 and err.mean() < 1e-4, (err.max(), err.mean())
    # a coarser table is coarser: the error is the interpolation's, not an offset
    assert np.abs(BakedBackground(sky, 32)(d) - ref).mean() > 4 * err.mean()


def test_table_is_exact_at_its_vertices_and_for_a_fixed_colour():
    torch.manual_seed(1)
    sky = LearnedBackground()
    baked = BakedBackground(sky, 16)
    vertices = direction_grid(16).reshape(-1, 3)
    np.testing.assert_allclose(baked(vertices), sky(vertices).detach().numpy(), atol=1e-6)
    fixed = BakedBackground(FixedBackground((0.2, 0.4, 0.9)))
    np.testing.assert_allclose(fixed(_directions(100)), np.tile([0.2, 0.4, 0.9], (107, 1)),
                               atol=1e-6)


def test_table_follows_the_module_when_it_changes():
    """Fine-tuning changes the background in place: the table is rebuilt, never stale."""
    sky = LearnedBackground()
    baked = BakedBackground(sky, 64)
    d = _directions(500)
    before = baked(d).copy()
    with torch.no_grad():
        sky.net[-1].bias.add_(1.0)
    after = baked(d)
    assert np.abs(after - before).min() > 1e-3
    np.testing.assert_allclose(after, sky(d).detach().numpy(), atol=5e-3)
