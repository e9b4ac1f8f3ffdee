"""--method auto: what the manifest decides, and the budget chosen from bench rows."""

from __future__ import annotations

import json

import pytest

from nerfbot.bench.auto_sweep import auto_train_config
from nerfbot.data import load_dataset
from nerfbot.train.auto import (TRANSPARENT_DEPTH_THRESHOLD, TRANSPARENT_GRID_THRESHOLD, bench_rows,
                                choose_budget, choose_from_manifest)


def _manifest(**kw):
    base = {"name": "s", "bounds": [[0, 0, 0], [1, 1, 1]], "transparent_geoms": [],
            "moving_joints": [], "time_varying": False, "specular": True}
    base.update(kw)
    return base


def test_static_specular_scene_keeps_view_dependence_and_no_conditioning():
    c = choose_from_manifest(_manifest())
    assert c.method == "ngp" and c.conditioning == "static"
    assert "sh_degree" not in c.options and not c.query_defaults


def test_matte_scene_gets_view_independent_colour():
    c = choose_from_manifest(_manifest(specular=False))
    assert c.options["sh_degree"] == 0
    assert any("SH degree 0" in r for r in c.reasons)


def test_few_shiny_pixels_without_glass_get_view_independent_colour():
    few = choose_from_manifest(_manifest(shiny_pixel_fraction=0.02))
    assert few.options["sh_degree"] == 0
    assert any("2.0 % of the training pixels" in r for r in few.reasons)
    many = choose_from_manifest(_manifest(shiny_pixel_fraction=0.05))
    assert "sh_degree" not in many.options
    assert any("SH degree 4" in r and "5.0 %" in r for r in many.reasons)
    # glass keeps view dependence however little of the image it covers; so does a manifest
    # that does not say how much is shiny (not written by a capture)
    glass = choose_from_manifest(_manifest(shiny_pixel_fraction=0.01, transparent_geoms=["g"]))
    assert "sh_degree" not in glass.options
    assert "sh_degree" not in choose_from_manifest(_manifest()).options


def test_glass_keeps_faint_density_and_defaults_to_threshold_depth():
    c = choose_from_manifest(_manifest(transparent_geoms=["glass_a"]))
    assert c.options["grid_threshold"] == TRANSPARENT_GRID_THRESHOLD < 0.01
    assert c.options["distortion_weight"] > 0
    assert c.options["density_noise"] == 0.0  # glass is a real veil: no noise against veils
    assert "density_noise" not in choose_from_manifest(_manifest()).options
    assert c.query_defaults == {"depth_mode": "threshold", "threshold": TRANSPARENT_DEPTH_THRESHOLD}


def test_changing_scenes_get_a_conditioned_method():
    c = choose_from_manifest(_manifest(time_varying=True, moving_joints=["ball_free"]))
    assert (c.method, c.conditioning) == ("kplanes", "time")
    c = choose_from_manifest(_manifest(moving_joints=["door"]))
    assert (c.method, c.conditioning) == ("articulated", "joints")
    assert "sh_degree" not in c.options


def test_no_manifest_is_the_plain_default():
    c = choose_from_manifest(None)
    assert c.method == "ngp" and c.options == {}


ROWS = [dict(scene="s", method="ngp", budget=30.0, psnr=26.0, train_seconds=30.2),
        dict(scene="s", method="ngp", budget=60.0, psnr=28.4, train_seconds=60.1),
        dict(scene="s", method="ngp", budget=120.0, psnr=29.1, train_seconds=120.3)]


def test_choose_budget_cheapest_reaching_target_or_best_within_time():
    assert choose_budget(ROWS, target_psnr=28.0)["budget"] == 60.0
    assert choose_budget(ROWS, target_psnr=25.0)["budget"] == 30.0
    assert choose_budget(ROWS, target_psnr=40.0)["budget"] == 120.0   # unreachable: the best
    assert choose_budget(ROWS, time_budget=90)["budget"] == 60.0
    with pytest.raises(ValueError, match="within 10"):
        choose_budget(ROWS, time_budget=10)
    with pytest.raises(ValueError, match="exactly one"):
        choose_budget(ROWS, target_psnr=28.0, time_budget=60)


def test_auto_config_reads_a_bench_table(tmp_path):
    rows = [dict(r, budget_kind="seconds", option_sh_degree=0) for r in ROWS]
    rows.append(dict(ROWS[0], budget=15.0, psnr=30.0, train_seconds=15.0, method="nerf",
                     budget_kind="seconds", option_sh_degree=0))
    rows.append(dict(ROWS[0], budget=15.0, psnr=30.0, train_seconds=15.0, budget_kind="seconds",
                     option_sh_degree=4))   # another option value: not this configuration
    (tmp_path / "bench.json").write_text(json.dumps({"summary": rows}))
    data = tmp_path / "s"
    data.mkdir()
    assert len(bench_rows(tmp_path, scene="s", method="ngp", options={"sh_degree": 0})) == 3
    choice = auto_train_config(choose_from_manifest(_manifest(specular=False)), data,
                               tmp_path / "run", {},
                               target_psnr=28.0, bench_table=tmp_path)
    assert choice.budget_seconds == 60.0 and choice.options == {"sh_degree": 0}
    with pytest.raises(FileNotFoundError):
        bench_rows(tmp_path / "missing")


def test_train_auto_on_a_capture_writes_its_reasons(tiny_capture, tmp_path, capsys):
    from nerfbot.app.cli import main

    run = tmp_path / "run"
    assert main(["train", "--data", str(tiny_capture[0]), "--method", "auto", "--max-steps", "3",
                 "--out", str(run), "--no-progress"]) == 0
    auto = json.loads((run / "auto.json").read_text())
    assert auto["method"] == "ngp" and auto["conditioning"] == "static"
    # the tabletop is specular, but its shiny surfaces (metal legs, chrome sphere, glazed can,
    # gem) are a small share of the image
    manifest = load_dataset(tiny_capture[0]).manifest
    assert manifest["specular"] and 0.0 < manifest["shiny_pixel_fraction"] < 0.03
    assert auto["options"] == {"sh_degree": 0}
    assert any("shiny surfaces cover" in r for r in auto["reasons"])
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["spec"]["method"] == "ngp"
    again = tmp_path / "again"  # re-created from its config: the same choice and query defaults
    assert main(["train", "--config", str(run / "config.json"), "--out", str(again),
                 "--no-progress"]) == 0
    assert json.loads((again / "auto.json").read_text()) == auto
    capsys.readouterr()
    assert main(["train", "--data", str(tiny_capture[0]), "--target-psnr", "20",
                 "--out", str(tmp_path / "x")]) == 2
    assert "need --method auto" in capsys.readouterr().err
