"""tasks.localise's pieces: robot views on the free floor, the summary and its plot, the
command line's errors."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from nerfbot.query.localise import WideConfig
from tasks.localise import (estimator_config, main, plot_basin, robot_views,
                            split_estimator_options, summarize)
from tasks.nav_map import true_floor_map
from tasks.navigate import NavTaskConfig, World


def test_robot_views_stand_on_free_floor():
    cfg = NavTaskConfig(capture_size=32)
    world = World("room:0", cfg)
    try:
        gt = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell)
        poses = robot_views(world, cfg, 6, seed=3)
        assert len(poses) == 6
        free = gt.free_for(cfg.robot.radius + cfg.margin)
        for x, y, yaw in poses:
            i, j = gt.to_cell([x, y])
            assert free[i, j] and -np.pi <= yaw <= np.pi
        again = robot_views(world, cfg, 6, seed=3)
        assert all(np.array_equal(a, b) for a, b in zip(poses, again))
        world.reset(*poses[0])
        image = world.observe()
        assert image.shape == (32, 32, 3) and image.std() > 1.0   # the room, not a blank
    finally:
        world.close()


def test_summary_rates_and_plot(tmp_path):
    levels = [(0.02, 1.0), (0.3, 20.0)]
    records = [{"estimator": "inerf", "translation": t, "rotation": r, "error_m": e,
                "error_deg": 0.5, "seconds": 1.0, "success": e < 0.02, "loose": e < 0.05}
               for (t, r), errors in zip(levels, ([0.01, 0.01, 0.05], [0.5, 0.5, 0.01]))
               for e in errors]
    summary = summarize(records, levels, ["inerf"])
    rates = [row["success_rate"] for row in summary["rows"]]
    assert rates == pytest.approx([2 / 3, 1 / 3])
    assert [row["loose_rate"] for row in summary["rows"]] == pytest.approx([2 / 3, 1 / 3])
    plot_basin(summary, tmp_path / "basin.png")
    assert (tmp_path / "basin.png").stat().st_size > 1000


@pytest.mark.parametrize("args, message", [
    (["--estimators", "magic"], "unknown"),
    (["--levels", "0.1"], "levels"),
    (["--views", "0"], "views"),
    (["--estimator-option", "magic=1"], "estimator-option magic: no selected estimator"),
    (["--estimator-option", "wide.rays=1"], "wide has no ['rays']"),
    (["--sensor-depth-weight", "-1"], "--sensor-depth-weight must be at least 0"),
])
def test_command_line_errors(args, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(args + ["--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_estimator_options_reach_their_estimators():
    inerf_cfg = estimator_config("inerf", True, {"across_rays": False, "rays": 256})
    assert inerf_cfg.planar and not inerf_cfg.across_rays and inerf_cfg.rays == 256
    wide = estimator_config("wide", True, {"keep": 2})
    assert wide.planar and wide.keep == 2
    assert wide.rounds == WideConfig().rounds                  # its own defaults kept
    with pytest.raises(ValueError, match="wide has no"):
        estimator_config("wide", True, {"rays": 256})
    options = split_estimator_options([("rays", 256), ("wide.keep", 3)], ["inerf", "wide"])
    assert options == {"inerf": {"rays": 256}, "wide": {"keep": 3}}
    with pytest.raises(ValueError, match="no selected estimator"):
        split_estimator_options([("keep", 3)], ["inerf"])


def test_navigation_capture_mixes_the_rooms_rig_and_the_robots_camera(tmp_path):
    """Half the training views from the robot's camera (its height and pitch, on floor the base
    fits on), half and the test views from the room's rig; the folder says so."""
    from tasks.navigate import ensure_capture, robot_camera_pose, scene_folder

    cfg = NavTaskConfig(capture_size=32, capture_views=8, capture_test_views=2,
                        capture_robot_views=0.5, cache=tmp_path, progress=False)
    assert scene_folder(cfg, 0).name == "32px-8v-robot50"
    assert scene_folder(NavTaskConfig(capture_robot_views=0.0), 0).name == "128px-400v"
    data = ensure_capture(cfg, 0)
    meta = json.loads((data / "transforms.json").read_text())
    pose = {f["file_path"]: np.array(f["transform_matrix"]) for f in meta["frames"]}
    train = [pose[name] for name in meta["train_filenames"]]
    test = [pose[name] for name in meta["test_filenames"]]
    assert len(train) == 8 and len(test) == 2
    robot_height = cfg.robot.camera_height
    at_robot = [p for p in train if abs(p[2, 3] - robot_height) < 1e-6]
    assert len(at_robot) == 4
    world = World("room:0", cfg)
    try:
        gt = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell)
    finally:
        world.close()
    fits = gt.free_for(cfg.robot.radius)
    for c2w in at_robot:
        i, j = gt.to_cell(c2w[:2, 3])
        assert fits[i, j]
        yaw = np.arctan2(-c2w[1, 2], -c2w[0, 2])       # the camera looks along -z
        expected = robot_camera_pose(cfg.robot, (c2w[0, 3], c2w[1, 3], yaw))
        np.testing.assert_allclose(c2w, expected, atol=1e-6)
    rig_heights = [p[2, 3] for p in train if abs(p[2, 3] - robot_height) >= 1e-6]
    assert len(rig_heights) == 4 and all(0.4 <= z <= 1.6 for z in rig_heights)


def test_navigation_fields_train_on_the_depth_sensor_when_asked(tmp_path):
    """--sensor-depth-weight: the field trains with --depth-from sensor_depth, cached in a
    folder of its own beside the images-only field's."""
    from tasks.navigate import ensure_trained

    cfg = NavTaskConfig(capture_size=32, capture_views=4, capture_test_views=1, train_steps=2,
                        cache=tmp_path, progress=False, sensor_depth_weight=0.1)
    run = ensure_trained(cfg, 0)
    assert run.name.endswith("-sensor_depth_weight=0.1")
    train = json.loads((run / "config.json").read_text())["train"]
    assert train["depth_weight"] == 0.1 and train["depth_from"] == "sensor_depth"
    plain = ensure_trained(replace(cfg, sensor_depth_weight=0.0), 0)
    assert plain != run and plain.parent == run.parent
    assert json.loads((plain / "config.json").read_text())["train"]["depth_weight"] == 0.0
