"""Masks (``mask_path``, and the pixels undistortion leaves without a source) are honoured:
never drawn for training, never scored in evaluation, ignored by depth supervision."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from nerfbot.data import DatasetError, load_dataset
from nerfbot.data.pixels import PixelBank, ValidPixels
from nerfbot.eval.evaluation import evaluate
from nerfbot.ops.metrics import psnr, ssim
from nerfbot.train.runs import build_from_spec, model_spec
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(20)  # rough single-core seconds (tests/conftest.py)

#: The masked block of every frame (rows, columns) and an unmasked block, on 32x32 images.
MASKED = (slice(6, 18), slice(4, 20))
UNMASKED = (slice(22, 30), slice(22, 30))
MAGENTA = (255, 0, 255)
TINY_NGP = {"samples_per_batch": 4096, "grid_update_every": 4}
METRICS = ("psnr", "ssim", "psnr_objects", "depth_mae_m", "depth_rmse_m", "depth_mae_objects_m",
           "median_depth_mae_m")


def _masked_copy(tiny_capture, dest: Path) -> Path:
    """A copy of the tiny capture whose every frame masks out :data:`MASKED` (PNG masks for
    even frames, .npy for odd ones)."""
    shutil.copytree(tiny_capture[0], dest)
    meta = json.loads((dest / "transforms.json").read_text())
    (dest / "masks").mkdir()
    for k, frame in enumerate(meta["frames"]):
        mask = np.full((32, 32), 255, np.uint8)
        mask[MASKED] = 0
        if k % 2:
            np.save(dest / "masks" / f"{k}.npy", mask > 0)
            frame["mask_path"] = f"masks/{k}.npy"
        else:
            cv2.imwrite(str(dest / "masks" / f"{k}.png"), mask)
            frame["mask_path"] = f"masks/{k}.png"
    (dest / "transforms.json").write_text(json.dumps(meta))
    return dest


def _paint(root: Path, region, colour=MAGENTA, depth_m: float | None = None) -> None:
    """Paint ``region`` of every image of ``root`` in ``colour`` (and set its depth)."""
    meta = json.loads((root / "transforms.json").read_text())
    for frame in meta["frames"]:
        path = root / frame["file_path"]
        img = cv2.imread(str(path))
        img[region] = colour[::-1]
        cv2.imwrite(str(path), img)
        if depth_m is not None:
            depth = np.load(root / frame["nerfbot_depth_file_path"])
            depth[region] = depth_m
            np.save(root / frame["nerfbot_depth_file_path"], depth)


def _drawn_pixels(bank: PixelBank, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(n,) frame slots and (n,) pixel indices within their frame of ``n`` draws."""
    _, _, slot = bank.sample(n, torch.Generator().manual_seed(seed))
    return slot, bank.last_pixels - bank.offsets[slot]


@pytest.fixture(scope="module")
def masked(tiny_capture, tmp_path_factory) -> Path:
    return _masked_copy(tiny_capture, tmp_path_factory.mktemp("masked") / "tabletop")


# ----------------------------------------------------------------------------- training


def test_valid_pixels_maps_ranks_and_membership_in_both_layouts():
    """Empty, sparse, dense and full masks (stored as valid list or as skip list) give the same
    rank mapping and membership."""
    rng = np.random.default_rng(0)
    for density in (0.0, 0.05, 0.5, 0.97, 1.0):
        valid = rng.random(5000) < density
        vp = ValidPixels(valid)
        assert (vp.valid is None) == (valid.sum() >= (~valid).sum())
        ranks = torch.arange(len(vp))
        np.testing.assert_array_equal(vp.pixel(ranks).numpy(), np.flatnonzero(valid))
        for _ in range(2):  # the second call uses the cached index
            np.testing.assert_array_equal(vp.contains(torch.arange(5000)).numpy(), valid)


def test_pixel_bank_never_draws_a_masked_pixel(masked):
    ds = load_dataset(masked)
    train = ds.indices("train")
    assert all(ds.masks[i] is not None and not ds.masks[i][MASKED].any() for i in train)
    bank = PixelBank(ds, train)
    slot, local = _drawn_pixels(bank, 300_000, seed=1)
    frames = torch.as_tensor(train)[slot]
    valid = np.stack([ds.masks[i].reshape(-1) for i in range(len(ds))])
    assert valid[frames.numpy(), local.numpy()].all()
    # uniform over the valid pixels: every one of them is drawn (about 22 times each)
    drawn = np.zeros_like(valid)
    drawn[frames.numpy(), local.numpy()] = True
    assert (drawn[train] == valid[train]).all()
    # the mean colour the model starts from is that of the valid pixels
    mean = np.concatenate([ds.images[i][ds.masks[i]] for i in train]).mean(0) / 255.0
    np.testing.assert_allclose(bank.mean_color().numpy(), mean, atol=1e-6)


def test_unmasked_pixel_bank_draws_exactly_as_an_unmasked_bank(tiny_capture):
    """Without masks the bank keeps one ``torch.randint`` over all pixels, so seeds, exact resume
    and stored runs reproduce bit for bit."""
    ds = load_dataset(tiny_capture[0])
    assert ds.masks == [None] * len(ds)
    bank = PixelBank(ds, ds.indices("train"))
    assert bank.valid is None
    for s in (1, 2):
        gen = torch.Generator().manual_seed(7)
        bank.sample(500, gen, s)
        expected = torch.randint(len(bank), (500,), generator=torch.Generator().manual_seed(7))
        assert torch.equal(bank.last_pixels, expected)


def test_all_masked_or_empty_training_set_is_refused(masked):
    ds = load_dataset(masked)
    ds.masks = [np.zeros((32, 32), bool) for _ in range(len(ds))]
    with pytest.raises(DatasetError, match=r"every pixel of the 16 training frame\(s\) is masked"):
        PixelBank(ds, ds.indices("train"))
    ds.splits["train"] = []
    with pytest.raises(DatasetError, match=r"the training split is empty"):
        Trainer(ds, masked.parent / "run", TrainConfig(method="ngp", max_steps=1))


def test_depth_supervision_ignores_masked_pixels(masked):
    ds = load_dataset(masked)
    train = ds.indices("train")
    bank = PixelBank(ds, train)
    bank.load_depths()
    depths = bank.depths.reshape(len(train), 32, 32)
    assert torch.isnan(depths[(slice(None), *MASKED)]).all()
    assert torch.isfinite(depths).any()


# ----------------------------------------------------------------------------- masked content


def _train(ds, out: Path, steps: int = 6):
    trainer = Trainer(ds, out, TrainConfig(method="ngp", max_steps=steps, seed=0, progress=False,
                                           options=TINY_NGP, depth_weight=0.1))
    trainer.train()
    trainer.model.eval()
    return trainer


def test_masked_content_changes_neither_training_nor_metrics(masked, tmp_path):
    """Painting the masked block magenta (and moving its depth) leaves the drawn training
    colours, a few trained steps (colour and depth supervision) and every metric of the trained
    model bit-identical; painting an unmasked block changes PSNR."""
    painted = tmp_path / "painted"
    shutil.copytree(masked, painted)
    _paint(painted, MASKED, depth_m=0.7)
    a, b = load_dataset(masked), load_dataset(painted)
    assert not np.array_equal(a.images[0], b.images[0])

    banks = [PixelBank(ds, ds.indices("train")) for ds in (a, b)]
    colours = [bank.sample(4096, torch.Generator().manual_seed(5))[1] for bank in banks]
    assert torch.equal(colours[0], colours[1])

    ta, tb = _train(a, tmp_path / "a"), _train(b, tmp_path / "b")
    for k, v in ta.model.state_dict().items():
        assert torch.equal(v, tb.model.state_dict()[k]), k

    for downscale in (2, 1):
        ma = evaluate(ta.model, a, "test", downscale=downscale)
        mb = evaluate(ta.model, b, "test", downscale=downscale)
        assert {k: ma[k] for k in METRICS} == {k: mb[k] for k in METRICS}
    assert all(ma[k] is not None for k in METRICS), {k: ma[k] for k in METRICS}

    unmasked = tmp_path / "unmasked"
    shutil.copytree(masked, unmasked)
    _paint(unmasked, UNMASKED)
    mc = evaluate(ta.model, load_dataset(unmasked), "test")
    assert mc["psnr"] < ma["psnr"] - 0.5 and mc["ssim"] != ma["ssim"]


def test_undistortion_invalid_pixels_are_neither_drawn_nor_scored(tiny_capture, tmp_path):
    """Strong pincushion distortion leaves the corners of the undistorted images without a
    source pixel: they are masked, never drawn, and repainting them changes no metric."""
    root = tmp_path / "distorted"
    shutil.copytree(tiny_capture[0], root)
    meta = json.loads((root / "transforms.json").read_text())
    meta.update(k1=0.4, k2=0.1)
    (root / "transforms.json").write_text(json.dumps(meta))
    ds = load_dataset(root)
    invalid = [~m for m in ds.masks]
    assert all(m.any() and not m.all() for m in invalid) and all(m[0, 0] for m in invalid)

    bank = PixelBank(ds, ds.indices("train"))
    slot, local = _drawn_pixels(bank, 100_000, seed=2)
    frames = torch.as_tensor(ds.indices("train"))[slot].numpy()
    assert not np.stack([m.reshape(-1) for m in invalid])[frames, local.numpy()].any()

    spec = model_spec(TrainConfig(method="ngp", max_steps=1, options=TINY_NGP), ds)
    model = build_from_spec(spec).eval()
    before = evaluate(model, ds, "test")
    for i, m in enumerate(invalid):
        ds.images[i] = ds.images[i].copy()
        ds.images[i][m] = MAGENTA
    after = evaluate(model, ds, "test")
    assert {k: before[k] for k in METRICS} == {k: after[k] for k in METRICS}


# ----------------------------------------------------------------------------- evaluation rules


def test_masked_metrics_ignore_invalid_pixels_and_match_unmasked_when_all_valid():
    rng = np.random.default_rng(0)
    pred = rng.random((24, 28, 3))
    target = np.clip(pred + 0.1 * rng.standard_normal(pred.shape), 0, 1)
    everywhere = np.ones((24, 28), bool)
    assert ssim(pred, target, everywhere) == pytest.approx(ssim(pred, target), abs=1e-6)
    assert psnr(pred, target, everywhere) == pytest.approx(psnr(pred, target), abs=1e-12)
    valid = everywhere.copy()
    valid[4:12, 3:15] = False
    other = target.copy()
    other[~valid] = (1.0, 0.0, 1.0)
    assert ssim(pred, other, valid) == ssim(pred, target, valid)
    assert psnr(pred, other, valid) == psnr(pred, target, valid)
    assert ssim(pred, other) != ssim(pred, target)
    with pytest.raises(ValueError, match="no valid pixel"):
        psnr(pred, target, np.zeros((24, 28), bool))


def test_evaluating_an_empty_missing_or_fully_masked_split_is_an_error(masked):
    ds = load_dataset(masked)
    model = build_from_spec(model_spec(TrainConfig(method="ngp", max_steps=1), ds)).eval()
    with pytest.raises(DatasetError, match=r"no 'holdout' split \(available: test, train, val\)"):
        evaluate(model, ds, "holdout")
    with pytest.raises(DatasetError, match=r"gives no frame with max_images=0"):
        evaluate(model, ds, "test", max_images=0)
    ds.masks = [np.zeros((32, 32), bool) for _ in range(len(ds))]
    with pytest.raises(DatasetError, match=r"every pixel of the 4 'test' frame\(s\) is masked"):
        evaluate(model, ds, "test")
    ds.splits["test"] = []
    with pytest.raises(DatasetError, match=rf"{ds.root}: the 'test' split is empty"):
        evaluate(model, ds, "test")
