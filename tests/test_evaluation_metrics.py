"""Scores beside whole-image PSNR: the pixels that show the scene (non-sky) and the objects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nerfbot.data import load_dataset
from nerfbot.data.pixels import depth_valid_mask
from nerfbot.eval.evaluation import _PooledPSNR, evaluate
from nerfbot.methods import build_model
from nerfbot.ops.metrics import depth_errors
from nerfbot.query.render import render_image


def test_pooled_psnr_arithmetic():
    pooled = _PooledPSNR()
    assert pooled.value() is None  # nothing pooled
    a = np.zeros((2, 2, 3))
    b = np.full((2, 2, 3), 0.1)
    pooled.add(a, b, np.array([[True, False], [False, False]]))
    assert pooled.value() == pytest.approx(20.0)  # MSE 0.01
    pooled.add(a, a, np.ones((2, 2), bool))  # four exact pixels dilute the error five-fold
    assert pooled.value() == pytest.approx(20.0 + 10 * math.log10(5))
    exact = _PooledPSNR()
    exact.add(a, a, np.ones((2, 2), bool))
    assert exact.value() == math.inf


def test_non_sky_psnr_scores_only_the_pixels_that_show_a_geom(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    model = build_model("ngp", ds.aabb, "learned", {"log2_hashmap_size": 12}, 0).eval()
    metrics = evaluate(model, ds, "test", max_images=2, with_ssim=False)
    sq, n = 0.0, 0
    for slot, i in enumerate(ds.indices("test")[:2]):
        rgb = render_image(model, ds.cameras(ds.indices("test")), slot)["rgb"]
        content = ds.segmentations[i] >= 0
        assert 0 < content.mean() < 1  # the tabletop shows sky and scene
        sq += float(((rgb[content] - ds.image_float(i)[content]) ** 2).sum())
        n += 3 * int(content.sum())
    assert metrics["psnr_non_sky"] == pytest.approx(-10 * math.log10(sq / n), abs=1e-6)
    assert metrics["psnr_non_sky"] != pytest.approx(metrics["psnr"], abs=1e-3)


def test_depth_spread_is_the_median_spread_over_pixels_with_a_true_depth(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    model = build_model("ngp", ds.aabb, "learned", {"log2_hashmap_size": 12}, 0).eval()
    metrics = evaluate(model, ds, "test", max_images=2, with_ssim=False)
    test = ds.indices("test")[:2]
    spreads = []
    for slot, i in enumerate(test):
        img = render_image(model, ds.cameras(ds.indices("test")), slot)
        valid = depth_valid_mask(ds, i)
        assert valid.any() and np.isfinite(img["depth_spread"]).all()
        spreads.append(img["depth_spread"][valid])
    assert metrics["depth_spread_m"] == pytest.approx(float(np.median(np.concatenate(spreads))))
    # an untrained field is fog: its rays end anywhere over centimetres of their length
    assert metrics["depth_spread_m"] > 0.01


def test_depth_errors_relative_to_the_distance():
    target = np.array([[1.0, 2.0], [4.0, np.nan]])
    pred = np.array([[1.1, 1.8], [4.0, 3.0]])
    e = depth_errors(pred, target, np.ones((2, 2), bool))
    assert e["count"] == 3  # the unknown target is left out
    assert e["mae"] == pytest.approx((0.1 + 0.2 + 0.0) / 3)
    assert e["abs_rel"] == pytest.approx((0.1 / 1 + 0.2 / 2 + 0.0) / 3)
    assert e["bias"] == pytest.approx((0.1 - 0.2 + 0.0) / 3)
    # a zero distance has no relative error: left out, not a division by zero
    e = depth_errors(np.array([0.5, 1.5]), np.array([0.0, 1.0]), np.ones(2, bool))
    assert e["count"] == 1 and e["abs_rel"] == pytest.approx(0.5)


def test_wall_depth_is_scored_on_the_pixels_of_the_walls_the_manifest_names(tiny_capture):
    ds = load_dataset(tiny_capture[0])
    model = build_model("ngp", ds.aabb, "learned", {"log2_hashmap_size": 12}, 0).eval()
    assert evaluate(model, ds, "test", max_images=2, with_ssim=False)["depth_abs_rel_walls"] \
        is None  # the tabletop has no walls
    # call the table's geoms walls, as a room's manifest names its walls
    geoms = ds.manifest["geoms"]
    tables = [g for g, n in geoms.items() if n.startswith("table")]
    assert tables
    ds.manifest = {**ds.manifest, "geoms": {g: ("wall_" + n if g in tables else n)
                                            for g, n in geoms.items()}}
    metrics = evaluate(model, ds, "test", max_images=2, with_ssim=False)
    rel, signed, n = 0.0, 0.0, 0
    for slot, i in enumerate(ds.indices("test")[:2]):
        z = render_image(model, ds.cameras(ds.indices("test")), slot)["z_depth"]
        on = depth_valid_mask(ds, i) & np.isin(ds.segmentations[i], [int(g) for g in tables])
        rel += float((np.abs(z[on] - ds.depths[i][on]) / ds.depths[i][on]).sum())
        signed += float((z[on] - ds.depths[i][on]).sum())
        n += int(on.sum())
    assert n > 0
    assert metrics["depth_abs_rel_walls"] == pytest.approx(rel / n, rel=1e-5)
    assert metrics["depth_bias_walls_m"] == pytest.approx(signed / n, rel=1e-5, abs=1e-7)
    assert metrics["depth_abs_rel_walls"] != pytest.approx(metrics["depth_abs_rel"], rel=1e-3)
