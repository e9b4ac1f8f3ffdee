"""Importance sampling of training rays where a capture changes over time (DyNeRF): the
weights, and the pixel bank's draws by them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.data.importance import temporal_weights
from nerfbot.data.pixels import PixelBank, ValidPixels

pytestmark = pytest.mark.slow(5)  # rough single-core seconds (tests/conftest.py)


def _draws(bank: PixelBank, batches: int, pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """(batches, pixels) arrays of the pixels ``bank.sample`` draws (seed 0) and their loss
    weights."""
    generator = torch.Generator().manual_seed(0)
    drawn, loss_weights = [], []
    for _ in range(batches):
        bank.sample(pixels, generator)
        drawn.append(bank.last_pixels.numpy())
        loss_weights.append(bank.last_weights.numpy())
    return np.stack(drawn), np.stack(loss_weights)


def test_a_pixel_that_never_changes_weighs_zero_and_a_changing_one_its_temporal_variance():
    rng = np.random.default_rng(0)
    frames = np.repeat(rng.integers(0, 256, (1, 6, 5, 3), dtype=np.uint8), 7, axis=0)
    frames[:, 2, 3] = rng.integers(0, 256, (7, 3))         # changes over time
    frames[:, 4, 1, 0] = np.arange(7) * 10                   # one channel ramps
    w = temporal_weights(list(frames))
    assert w.shape == (7, 30) and w.dtype == np.float32
    changing = {2 * 5 + 3, 4 * 5 + 1}
    still = [p for p in range(30) if p not in changing]
    assert np.all(w[:, still] == 0.0)
    x = frames.reshape(7, 30, 3).astype(np.float64) / 255.0
    variance = x.var(axis=0).mean(-1)                         # per pixel, over time
    np.testing.assert_allclose(w.mean(0), variance, rtol=1e-5, atol=1e-9)
    # within a pixel, the frames that differ most from its mean weigh most
    ramp = w[:, 4 * 5 + 1]
    assert ramp[0] == ramp[-1] == ramp.max() and ramp[3] == 0.0
    # twice the change, four times the weight
    np.testing.assert_allclose(temporal_weights(list(2 * (x.reshape(7, 6, 5, 3) - 0.5) + 0.5)),
                               4 * temporal_weights(list(x.reshape(7, 6, 5, 3))), rtol=1e-5,
                               atol=1e-9)
    assert not temporal_weights([frames[0]]).any()           # one frame: nothing changes


def test_the_bank_draws_the_important_share_in_proportion_to_the_weights(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    bank = PixelBank(ds, ds.indices("train"))
    weights = np.zeros(len(bank), np.float32)
    chosen = np.array([5, 900, 4000, 7001])
    weights[chosen] = [1.0, 2.0, 3.0, 4.0]
    bank.set_importance(weights, 0.25)
    drawn, loss_weights = _draws(bank, 50, 4000)
    important = drawn[:, :1000].reshape(-1)                   # the first quarter of each batch
    assert set(np.unique(important)) == set(chosen)           # weight 0 is never drawn
    share = np.array([(important == p).mean() for p in chosen])
    np.testing.assert_allclose(share, [0.1, 0.2, 0.3, 0.4], atol=0.01)
    rest = drawn[:, 1000:].reshape(-1)                        # uniform over every pixel
    assert np.isin(rest, chosen).mean() < 0.01 and len(np.unique(rest)) > 0.9 * len(bank)
    # loss weights (1 / P) / q undo the bias: a pixel of weight 0 counts 1 / (1 - f), the
    # chosen ones far less, and their mean over the draws is 1 (a uniform batch's)
    q = 0.75 / len(bank) + 0.25 * weights / weights.sum()
    np.testing.assert_allclose(loss_weights.reshape(-1), (1 / len(bank)) / q[drawn.reshape(-1)],
                               rtol=1e-5)
    assert np.all(loss_weights[np.isin(drawn, chosen, invert=True)] == np.float32(1 / 0.75))
    assert abs(loss_weights.mean() - 1.0) < 0.01


def test_a_time_limit_draws_only_the_frames_up_to_it_and_keeps_the_weights_proportions(
        tiny_capture):
    """``set_time_limit``: uniform and importance draws stay within the frames up to the limit
    (the first ones of a bank in order of time), the importance draws in the proportions of
    the weights there, and the loss weights undo the bias within them."""
    ds = load_dataset(tiny_capture[0])
    train = ds.indices("train")
    times = np.zeros((len(ds.images), 1), np.float32)
    times[train, 0] = np.linspace(0.0, 1.0, len(train))
    bank = PixelBank(ds, train, conditions=times)
    per_frame = int(bank.offsets[1])
    weights = np.zeros(len(bank), np.float32)
    weights[[7, per_frame + 3, 10 * per_frame]] = [1.0, 3.0, 50.0]  # frames 0, 1 and 10
    bank.set_importance(weights, 0.25)
    bank.set_time_limit(float(times[train[3], 0]))  # frames 0-3
    drawn, loss_weights = _draws(bank, 40, 2000)
    assert drawn.max() < 4 * per_frame and len(np.unique(drawn[:, 500:])) > 0.9 * 4 * per_frame
    important = drawn[:, :500].reshape(-1)
    assert set(np.unique(important)) == {7, per_frame + 3}
    assert abs((important == 7).mean() - 0.25) < 0.02
    q = 0.75 / (4 * per_frame) + 0.25 * weights / 4.0
    np.testing.assert_allclose(loss_weights.reshape(-1),
                               (1 / (4 * per_frame)) / q[drawn.reshape(-1)], rtol=1e-5)
    assert abs(loss_weights.mean() - 1.0) < 0.02
    bank.set_time_limit(None)  # every frame again, frame 10's pixel the most drawn
    drawn, _ = _draws(bank, 1, 2000)
    assert (drawn[0, :500] == 10 * per_frame).mean() > 0.8
    with pytest.raises(ValueError, match="keeps no frame"):
        bank.set_time_limit(-0.1)
    with pytest.raises(ValueError, match="in order of time"):
        PixelBank(ds, train[::-1], conditions=times).set_time_limit(0.5)
    with pytest.raises(ValueError, match="time-conditioned"):
        PixelBank(ds, train).set_time_limit(0.5)
    errors = PixelBank(ds, train, conditions=times)
    errors.enable_error_map(0.5)
    with pytest.raises(ValueError, match="error-rays"):
        errors.set_time_limit(0.5)


def test_valid_pixels_count_those_below_an_index_in_both_of_their_forms():
    rng = np.random.default_rng(0)
    for share in (0.9, 0.1):  # mostly valid: the invalid ones listed; mostly invalid: the valid
        valid = rng.random(5000) < share
        pixels = ValidPixels(valid)
        for p in (0, 1, 17, 2500, 4999, 5000):
            assert pixels.count_below(p) == int(valid[:p].sum())


def test_importance_weights_refuse_bad_input(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    bank = PixelBank(ds, ds.indices("train"))
    with pytest.raises(ValueError, match="expected"):
        bank.set_importance(np.ones(3), 0.5)
    with pytest.raises(ValueError, match="finite and >= 0"):
        bank.set_importance(-np.ones(len(bank)), 0.5)
    with pytest.raises(ValueError, match="zero on every"):
        bank.set_importance(np.zeros(len(bank)), 0.5)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        bank.set_importance(np.ones(len(bank)), 1.5)


def test_the_photometric_loss_weighs_each_pixel():
    from nerfbot.models.base import photometric_loss

    generator = torch.Generator().manual_seed(0)
    rgb, target = torch.rand(8, 3, generator=generator), torch.rand(2, 3, generator=generator)
    plain = photometric_loss(rgb, target, rays_per_pixel=4)
    means = rgb.reshape(2, 4, 3).mean(1)
    torch.testing.assert_close(plain, torch.nn.functional.mse_loss(means, target))
    torch.testing.assert_close(photometric_loss(rgb, target, 4, torch.ones(2)), plain)
    weighted = photometric_loss(rgb, target, 4, torch.tensor([3.0, 0.0]))
    torch.testing.assert_close(weighted, 1.5 * (means[0] - target[0]).square().mean())
