"""Drawing training rays where the training error is high (Instant-NGP's error map): the tiles,
the draws and their loss weights, the updates, and a training run that uses it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.data.error_map import ErrorMap
from nerfbot.data.pixels import PixelBank

pytestmark = pytest.mark.slow(10)  # rough single-core seconds (tests/conftest.py)


def _map(sizes, tile):
    """An error map over frames of ``sizes`` [(w, h)], pixels numbered frame after frame."""
    w = torch.tensor([s[0] for s in sizes])
    h = torch.tensor([s[1] for s in sizes])
    offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(w * h, 0)])
    return ErrorMap(w, h, offsets, tile), offsets


def test_tiles_cover_every_pixel_once_including_the_ragged_edges():
    sizes = [(10, 7), (4, 4), (9, 12)]
    emap, offsets = _map(sizes, 4)
    assert len(emap) == 3 * 2 + 1 + 3 * 3
    assert float(emap.area.sum()) == sum(w * h for w, h in sizes)
    pixels = torch.arange(int(offsets[-1]))
    slots = torch.searchsorted(offsets[1:], pixels, right=True)
    tiles = emap.tiles_of(pixels, slots)
    counts = torch.bincount(tiles, minlength=len(emap)).double()
    assert torch.equal(counts, emap.area)
    # pixel (row 5, column 9) of frame 0 (3 x 2 tiles) lies in its bottom-right tile, rows
    # 4-6 and columns 8-9
    assert int(emap.tiles_of(torch.tensor([5 * 10 + 9]), torch.tensor([0]))) == 5
    assert emap.area[5] == 3 * 2


def test_draws_follow_the_error_and_stay_inside_their_tile():
    emap, offsets = _map([(8, 8), (8, 8)], 4)                 # 8 tiles of 16 pixels
    slots_all = torch.repeat_interleave(torch.arange(2), 64)
    pixels_all = torch.arange(128)
    # every pixel of tile 1 (frame 0, top right) errs 0.4, of tile 6 (frame 1) 0.1, others 0
    tiles_all = emap.tiles_of(pixels_all, slots_all)
    errors = torch.where(tiles_all == 1, 0.4, torch.where(tiles_all == 6, 0.1, 0.0))
    emap.rate = 1.0
    emap.update(pixels_all, slots_all, errors)
    assert torch.allclose(emap.error, torch.tensor([0, .4, 0, 0, 0, 0, .1, 0], dtype=torch.float64))
    drawn = emap.draw(20000, torch.Generator().manual_seed(0))
    slots = torch.searchsorted(offsets[1:], drawn, right=True)
    tiles = emap.tiles_of(drawn, slots)
    assert set(tiles.tolist()) == {1, 6}                      # an error of 0 is never drawn
    assert abs(float((tiles == 1).double().mean()) - 0.8) < 0.01
    inside = torch.bincount(drawn[tiles == 1], minlength=128)[:64].reshape(8, 8)
    assert inside[:4, 4:].min() > 0 and inside.sum() == inside[:4, 4:].sum()
    # the probability of one draw: e_t / sum(e A), so over all pixels it sums to 1
    q = emap.probability(pixels_all, slots_all)
    assert abs(float(q.sum()) - 1.0) < 1e-12 and float(q[4]) == pytest.approx(0.4 / 8.0)


def test_updates_move_a_tile_towards_its_batch_mean_by_the_rate_per_pixel():
    emap, _ = _map([(4, 4)], 2)
    emap.rate = 0.5
    assert torch.all(emap.error == 1.0)                       # unseen tiles start at 1
    pixels, slots = torch.tensor([0, 1, 5, 15]), torch.zeros(4, dtype=torch.long)
    emap.update(pixels, slots, torch.tensor([0.2, 0.4, 0.0, float("nan")]))
    # tile 0 got 3 pixels (mean 0.2): 1 + (1 - 0.5^3) (0.2 - 1); the NaN is ignored
    assert float(emap.error[0]) == pytest.approx(1 + 0.875 * (0.2 - 1))
    assert torch.all(emap.error[1:] == 1.0)


def test_the_bank_draws_its_error_share_by_the_map_and_weighs_the_loss_back(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    bank = PixelBank(ds, ds.indices("train"))
    bank.enable_error_map(0.5, tile=8, debias=1.0)
    emap = bank.error_map
    with pytest.raises(ValueError, match="use one"):
        bank.set_importance(np.ones(len(bank)), 0.5)
    generator = torch.Generator().manual_seed(0)
    # a sweep: every tile starts at 1, so draws go everywhere, and the loss weights of a
    # map that is uniform per pixel are all 1
    bank.sample(1000, generator)
    assert torch.allclose(bank.last_weights, torch.ones(1000))
    # errors only in frame 3's first tile: half of each batch lands there
    target = int(emap.tile_offsets[3])
    every = torch.arange(len(bank))
    slots = torch.searchsorted(bank.offsets[1:], every, right=True)
    emap.rate = 1.0
    emap.update(every, slots, torch.where(emap.tiles_of(every, slots) == target, 0.3, 0.0))
    bank.sample(2000, generator)
    tiles = emap.tiles_of(bank.last_pixels, bank.last_slots)
    assert bool((tiles[:1000] == target).all())
    assert float((tiles[1000:] == target).double().mean()) < 0.02
    # unbiased weights: (1 / V) / q, q = (1 - f) / V + f e / sum(e A)
    v = len(bank)
    q_hot = 0.5 / v + 0.5 / 64
    w = bank.last_weights[:1000]
    assert torch.allclose(w, torch.full_like(w, (1 / v) / q_hot))
    cold = bank.last_weights[1000:][tiles[1000:] != target]
    assert torch.allclose(cold, torch.full_like(cold, 2.0))
    # the errors the trainer reports go into the tiles drawn
    bank.record_errors(torch.full((2000,), 0.05))
    assert float(emap.error[target]) < 0.3


def test_training_with_error_rays_runs_and_refuses_bad_settings(tiny_capture, tmp_path):
    from nerfbot.train.config import TrainConfig
    from nerfbot.train.trainer import Trainer

    ds = load_dataset(tiny_capture[0])
    for bad in ({"error_rays": 1.5}, {"error_rays_debias": -0.1}, {"error_tile": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TrainConfig(method="ngp", max_steps=1, **bad).validate()
    trainer = Trainer(ds, tmp_path / "run", TrainConfig(
        method="ngp", max_steps=30, progress=False, error_rays=0.5,
        options={"samples_per_batch": 4096}))
    trainer.train()
    emap = trainer.bank.error_map
    seen = emap.error < 1.0
    assert seen.float().mean() > 0.9                          # the sweep reached the tiles
    assert float(emap.error[seen].max()) < 0.5                # and holds squared errors
