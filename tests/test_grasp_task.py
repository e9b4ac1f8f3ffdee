"""python -m tasks.grasp pieces: depth sources on a real glassware scene, one physical attempt per
source, object selection and reporting."""

from __future__ import annotations

import json

import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from sims.sensor import DepthSensorModel
from tasks.grasp import (DEPTH_SOURCES, Attempt, DepthContext, GraspTaskConfig, World,
                         attempt_object, format_table, main, plot_success, query_poses,
                         select_objects, summarize)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    import os

    os.environ.setdefault("NERFBOT_CACHE", str(tmp_path_factory.mktemp("cache")))
    w = World("glassware:2", 96, 40.0)
    yield w
    w.close()


def _cfg(tmp_path):
    return GraspTaskConfig(query_size=96, out=tmp_path, progress=False)


def test_query_ring_looks_at_the_object(world):
    center = world.object_position("glass_tumbler") + np.array([0, 0, 0.06])
    poses = query_poses(center, GraspTaskConfig(query_views=6))
    assert len(poses) == 6
    for p in poses:
        eye, forward = p[:3, 3], -p[:3, 2]
        to_center = (center - eye) / np.linalg.norm(center - eye)
        assert forward @ to_center > 1 - 1e-9
        assert abs(np.linalg.norm(center - eye) - 0.5) < 1e-9


def test_ground_truth_depth_grasps_glass_and_the_sensor_cannot_see_it(world, tmp_path):
    ctx = DepthContext(world, sensor=DepthSensorModel(transparent="behind", seed=0))
    cfg = _cfg(tmp_path)
    gt = attempt_object(world, ctx, "gt", "glass_tumbler", 0, 2, cfg, tmp_path / "gt.png")
    assert gt.success, gt.reason
    assert gt.transparent and gt.lift_height >= 0.10
    assert (tmp_path / "gt.png").exists()
    sensor = attempt_object(world, ctx, "sensor", "glass_tumbler", 0, 2, cfg, None)
    assert not sensor.success
    assert sensor.reason == "no grasp found"          # the table behind the glass, nothing else
    opaque = attempt_object(world, ctx, "sensor", "opaque_tumbler", 0, 2, cfg, None)
    assert opaque.success, opaque.reason                # the sensor does see the look-alike
    assert not opaque.transparent


def test_sensor_depth_on_glass_is_the_table_behind_it(world):
    ctx = DepthContext(world, sensor=DepthSensorModel(transparent="behind", seed=0,
                                                      dropout=0.0, edge_jump=0.0))
    center = world.object_position("glass_bottle") + np.array([0, 0, 0.06])
    poses = query_poses(center, GraspTaskConfig(query_views=2, query_size=96))
    gt = DEPTH_SOURCES["gt"][1](ctx, poses)
    sensor = DEPTH_SOURCES["sensor"][1](ctx, poses)
    frame = world.camera.render(poses[0])
    glass = np.isin(frame.segmentation, world.transparent)
    assert glass.sum() > 50
    assert np.nanmedian(sensor[0][glass] - gt[0][glass]) > 0.02     # sees past the glass
    off = ~glass & np.isfinite(gt[0])
    assert np.nanmedian(np.abs(sensor[0][off] - gt[0][off])) < 0.005


def test_select_objects_and_errors(world):
    from sims.manifest import declared_objects

    objects = declared_objects(world.model)
    glass = {o for o in objects if o.startswith("glass_")}
    assert select_objects(world.model, objects, glass, "glass") == sorted(glass, key=objects.index)
    assert all(o.startswith("opaque_") for o in select_objects(world.model, objects, glass, "opaque"))
    assert select_objects(world.model, objects, glass, "all") == objects
    assert select_objects(world.model, objects, glass, "glass_bowl") == ["glass_bowl"]
    with pytest.raises(ValueError, match="unknown objects"):
        select_objects(world.model, objects, glass, "glass_teapot")


def test_summary_rates_table_and_plot(tmp_path):
    attempts = [Attempt(0, 0, "glass_a", True, "gt", True, "lifted", 10),
                Attempt(1, 1, "glass_a", True, "gt", False, "dropped (slipped)", 10),
                Attempt(0, 0, "opaque_a", False, "gt", True, "lifted", 10)]
    s = summarize(attempts, "gt", GraspTaskConfig(trials=2), None)
    assert s["success_rate"] == pytest.approx(2 / 3)
    assert s["transparent_success_rate"] == 0.5 and s["opaque_success_rate"] == 1.0
    assert s["per_object"] == {"glass_a": 0.5, "opaque_a": 1.0}
    assert s["failures"] == {"dropped": 1}
    table = format_table({"gt": s})
    assert "glass_a" in table and "50%" in table and "100%" in table
    png = plot_success({"gt": s, "other": s}, tmp_path / "success.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_rejects_unknown_sources_and_bad_trials(tmp_path, capsys):
    with pytest.raises(SystemExit) as err:
        main(["--depth", "lidar", "--trials", "1", "--out", str(tmp_path), "--no-progress"])
    assert err.value.code == 2
    assert "unknown depth source" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--trials", "0", "--out", str(tmp_path)])


def test_cli_json_reports_success_rate_per_object(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("NERFBOT_CACHE", str(tmp_path / "cache"))
    main(["--depth", "gt", "--trials", "1", "--seed", "2", "--objects", "glass_tumbler",
          "--out", str(tmp_path / "out"), "--json", "--no-progress"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["depth_source"] == "gt" and out["trials"] == 1
    assert out["success_rate"] == 1.0
    assert out["per_object"] == {"glass_tumbler": 1.0}
    log = json.loads((tmp_path / "out" / "log.json").read_text())
    assert log["attempts"][0]["grasp"]["width"] > 0.05
