"""tasks.localise's pieces: robot views on the free floor, the summary and its plot, the
command line's errors."""

from __future__ import annotations

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


