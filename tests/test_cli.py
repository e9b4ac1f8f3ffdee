"""The nerfbot command end to end on a tiny real capture: train, eval --json, render, errors,
and the same capture in Blender format."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from nerfbot.app.cli import main
from nerfbot.data import load_dataset

pytestmark = pytest.mark.slow(75)  # rough single-core seconds (tests/conftest.py)

EVAL_KEYS = {"psnr", "ssim", "depth_mae_m", "render_ms_per_image", "train_seconds", "num_params",
             "method"}


@pytest.fixture(scope="module")
def tiny_run(tiny_capture, tmp_path_factory):
    run = tmp_path_factory.mktemp("cli") / "run"
    code = main(["train", "--data", str(tiny_capture[0]), "--method", "ngp", "--max-steps", "30",
                 "--out", str(run), "--no-progress", "--option", "samples_per_batch=8192"])
    assert code == 0
    return run


def test_train_writes_run_and_metrics(tiny_run, tiny_capture):
    assert (tiny_run / "checkpoint.pt").exists() and (tiny_run / "config.json").exists()
    metrics = json.loads((tiny_run / "metrics.json").read_text())
    assert EVAL_KEYS <= metrics.keys() and metrics["steps"] == 30
    config = json.loads((tiny_run / "config.json").read_text())
    assert config["command"][:4] == ["nerfbot", "train", "--data", str(tiny_capture[0])]
    assert config["versions"]["torch"] == torch.__version__ and config["versions"]["python"]


def test_eval_json(tiny_run, capsys):
    capsys.readouterr()
    assert main(["eval", str(tiny_run), "--split", "test", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert EVAL_KEYS <= out.keys()
    assert out["method"] == "ngp" and out["num_params"] > 1e5
    assert 12.0 < out["psnr"] < 60.0 and 0.0 < out["ssim"] <= 1.0
    assert 0.0 < out["depth_mae_m"] < 1.0 and out["render_ms_per_image"] > 0
    assert out["supersample"] == 2  # ngp's default: 2 x 2 rays per pixel for colour


def test_eval_and_render_supersample_override(tiny_run, tmp_path, capsys):
    """--supersample 1 renders colour through the pixel centres, --supersample-pattern corners
    through the centres and corners, grid through an S x S grid (the default, adaptive, mixes
    the two): other colours, the same depth; a non-positive value or an unknown pattern is
    refused by the parser."""
    capsys.readouterr()
    assert main(["eval", str(tiny_run), "--json", "--supersample", "1"]) == 0
    one = json.loads(capsys.readouterr().out)
    assert main(["eval", str(tiny_run), "--json"]) == 0
    two = json.loads(capsys.readouterr().out)
    assert one["supersample"] == 1 and two["supersample"] == 2
    assert one["psnr"] != two["psnr"] and one["depth_mae_m"] == two["depth_mae_m"]
    folders = {s: tmp_path / f"r{s}" for s in ("1", "2")}
    for s, folder in folders.items():
        assert main(["render", str(tiny_run), "--path", "test", "--out", str(folder),
                     "--supersample", s, "--no-progress"]) == 0
    rgb = {s: cv2.imread(str(f / "rgb_0000.png")) for s, f in folders.items()}
    assert np.abs(rgb["1"].astype(int) - rgb["2"].astype(int)).max() > 0
    np.testing.assert_array_equal(np.load(folders["1"] / "depth_0000.npy"),
                                  np.load(folders["2"] / "depth_0000.npy"))
    with pytest.raises(SystemExit):
        main(["render", str(tiny_run), "--path", "test", "--out", str(tmp_path / "x"),
              "--supersample", "0"])
    # the corner pattern: other colours, the same depth; its name is recorded
    capsys.readouterr()
    assert main(["eval", str(tiny_run), "--json", "--supersample-pattern", "corners"]) == 0
    corners = json.loads(capsys.readouterr().out)
    assert corners["supersample_pattern"] == "corners" and two["supersample_pattern"] == "adaptive"
    assert corners["depth_mae_m"] == two["depth_mae_m"]
    assert main(["eval", str(tiny_run), "--json", "--supersample-pattern", "grid"]) == 0
    grid = json.loads(capsys.readouterr().out)
    assert grid["supersample_pattern"] == "grid" and grid["psnr"] != corners["psnr"]
    assert grid["depth_mae_m"] == two["depth_mae_m"]
    with pytest.raises(SystemExit):
        main(["eval", str(tiny_run), "--supersample-pattern", "diagonal"])


def test_render_orbit_video_and_test_images(tiny_run, tmp_path):
    video = tmp_path / "orbit.mp4"
    assert main(["render", str(tiny_run), "--path", "orbit", "--frames", "5", "--out", str(video),
                 "--no-progress"]) == 0
    cap = cv2.VideoCapture(str(video))
    frames = []
    ok, frame = cap.read()
    while ok:
        frames.append(frame)
        ok, frame = cap.read()
    assert len(frames) == 5 and frames[0].shape == (32, 32, 3)
    assert np.std(frames[0]) > 5  # not a blank frame

    folder = tmp_path / "renders"
    assert main(["render", str(tiny_run), "--path", "test", "--out", str(folder),
                 "--no-progress"]) == 0
    depth = np.load(folder / "depth_0000.npy")
    assert depth.shape == (32, 32) and np.isfinite(depth).all()
    assert sorted(p.name for p in folder.glob("rgb_*.png")) == [f"rgb_{i:04d}.png" for i in range(4)]


def test_render_along_a_pose_file_writes_videos_browsers_play(tiny_run, tmp_path, capsys):
    """--poses: the keyframes of a pose file (capture --poses' format), interpolated to
    --frames views; H.264 .mp4 / VP9 .webm / .gif; the first and last frames are the keyframes'
    views; an unknown suffix and conflicting flags are refused."""
    from nerfbot.query.render import render_image
    from nerfbot.query.video import video_info
    from nerfbot.ops.cameras import Cameras
    from nerfbot.train.runs import load_model

    keys = tmp_path / "path.json"
    keys.write_text(json.dumps({"poses": [
        {"eye": [1.2, -0.8, 1.3], "target": [0.0, 0.0, 0.75]},
        {"eye": [1.0, 0.9, 1.1], "target": [0.0, 0.0, 0.75]},
        {"eye": [-0.9, 1.0, 1.4], "target": [0.0, 0.0, 0.75]}]}))
    for suffix, codec in ((".mp4", "h264"), (".webm", "vp9"), (".gif", "gif")):
        video = tmp_path / f"path{suffix}"
        assert main(["render", str(tiny_run), "--poses", str(keys), "--frames", "7", "--out",
                     str(video), "--no-progress"]) == 0
        info = video_info(video)
        assert info["codec"] == codec and info["frames"] == 7, info
    assert "the path of" in capsys.readouterr().out
    folder = tmp_path / "frames"
    assert main(["render", str(tiny_run), "--poses", str(keys), "--frames", "5", "--out",
                 str(folder), "--no-progress"]) == 0
    model, _ = load_model(tiny_run)
    from sims.rigs import read_pose_file
    first = read_pose_file(keys)[0]
    ds = load_dataset(json.loads((tiny_run / "config.json").read_text())["data"])
    fy = ds.intrinsics[0, 1]
    fov = float(np.degrees(2 * np.arctan(0.5 * ds.sizes[0, 1] / fy)))
    truth = render_image(model, Cameras.pinhole(first[None], fov, 32, 32), 0)
    np.testing.assert_allclose(np.load(folder / "depth_0000.npy"), truth["z_depth"], atol=1e-4)
    assert len(list(folder.glob("rgb_*.png"))) == 5
    capsys.readouterr()
    assert main(["render", str(tiny_run), "--poses", str(keys), "--out",
                 str(tmp_path / "v.mov"), "--no-progress"]) == 2
    assert ".mp4, .webm, .gif" in capsys.readouterr().err
    assert main(["render", str(tiny_run), "--poses", str(keys), "--path", "test", "--out",
                 str(tmp_path / "v.mp4"), "--no-progress"]) == 2
    assert "give one camera path" in capsys.readouterr().err
    assert main(["render", str(tiny_run), "--poses", str(tmp_path / "none.json"), "--out",
                 str(tmp_path / "v.mp4"), "--no-progress"]) == 2
    assert "none.json" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"poses": [[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "x"]}))
    assert main(["render", str(tiny_run), "--poses", str(bad), "--out",
                 str(tmp_path / "v.mp4"), "--no-progress"]) == 2
    assert "bad.json: poses[1]" in capsys.readouterr().err
    assert not (tmp_path / "v.mp4").exists() and not (tmp_path / "v.mov").exists()


def test_render_depth_modes_and_the_auto_runs_default(tiny_run, tmp_path, capsys):
    """--depth-mode picks the depth written (.npy z-depth, NaN where a threshold is never
    reached); a run whose auto.json asks for threshold depth (glass) renders it by default."""
    import shutil

    from nerfbot.query.render import render_image
    from nerfbot.train.runs import load_model

    th = 1.0  # 1/m: the 30-step run is still faint (5 /m, the glass default, is never reached)
    model, _ = load_model(tiny_run)
    ds = load_dataset(json.loads((tiny_run / "config.json").read_text())["data"])
    truth = render_image(model, ds.cameras(ds.indices("test")), 0, thresholds=[th])
    modes = {"expected": truth["z_depth"], "median": truth["median_z_depth"],
             "threshold": truth["threshold_z_depth"][0]}
    assert np.isnan(modes["threshold"]).any() and np.isfinite(modes["threshold"]).any()
    for mode, want in modes.items():
        folder = tmp_path / mode
        extra = ["--threshold", str(th)] if mode == "threshold" else []
        assert main(["render", str(tiny_run), "--path", "test", "--out", str(folder),
                     "--depth-mode", mode, *extra, "--no-progress"]) == 0
        np.testing.assert_allclose(np.load(folder / "depth_0000.npy"), want, rtol=1e-6)
    assert not np.allclose(modes["expected"], modes["median"])
    capsys.readouterr()
    assert main(["render", str(tiny_run), "--path", "test", "--out", str(tmp_path / "x"),
                 "--depth-mode", "threshold"]) == 2
    assert "--threshold" in capsys.readouterr().err
    assert main(["render", str(tiny_run), "--path", "test", "--out", str(tmp_path / "x"),
                 "--depth-mode", "threshold", "--threshold", "-1"]) == 2
    assert "> 0" in capsys.readouterr().err and not (tmp_path / "x").exists()

    glass_run = tmp_path / "glass_run"  # as `nerfbot train --method auto` leaves a glass scene
    shutil.copytree(tiny_run, glass_run)
    (glass_run / "auto.json").write_text(json.dumps(
        {"method": "ngp", "query_defaults": {"depth_mode": "threshold", "threshold": th}}))
    capsys.readouterr()
    assert main(["render", str(glass_run), "--path", "test", "--out", str(tmp_path / "auto"),
                 "--no-progress"]) == 0
    assert "threshold (m = 1 /m), from" in capsys.readouterr().out
    np.testing.assert_allclose(np.load(tmp_path / "auto" / "depth_0000.npy"), modes["threshold"],
                               rtol=1e-6)
    # the flags override the run's defaults
    assert main(["render", str(glass_run), "--path", "test", "--out", str(tmp_path / "exp"),
                 "--depth-mode", "expected", "--no-progress"]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "exp" / "depth_0000.npy"), modes["expected"],
                               rtol=1e-6)


def test_train_refuses_to_overwrite_a_run(tiny_run, tiny_capture, capsys):
    capsys.readouterr()
    assert main(["train", "--data", str(tiny_capture[0]), "--max-steps", "1",
                 "--out", str(tiny_run)]) == 2
    assert "--resume" in capsys.readouterr().err


def test_clear_errors_for_missing_run_and_data(tmp_path, capsys):
    assert main(["eval", str(tmp_path / "nope")]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    assert main(["train", "--data", str(tmp_path / "missing"), "--max-steps", "1",
                 "--out", str(tmp_path / "r")]) == 2
    assert "missing" in capsys.readouterr().err


def test_blender_capture_is_the_same_data(tiny_capture, tiny_run, tmp_path, capsys):
    """--format blender writes the same views (camera_angle_x, extension-less paths), and a run
    evaluates identically on both folders."""
    folder, rig = tiny_capture
    blender = tmp_path / "blender"
    assert main(["capture", "--scene", "tabletop", "--views", "16", "--test-views", "4",
                 "--size", "32", "--format", "blender", "--out", str(blender),
                 "--no-progress"]) == 0
    train_json = json.loads((blender / "transforms_train.json").read_text())
    assert "camera_angle_x" in train_json
    assert all("." not in f["file_path"].rsplit("/", 1)[-1] for f in train_json["frames"])
    a, b = load_dataset(folder), load_dataset(blender)
    assert b.format == "blender"
    np.testing.assert_allclose(a.c2w, b.c2w, atol=1e-6)
    np.testing.assert_allclose(a.intrinsics, b.intrinsics, atol=1e-6)
    for i in range(len(a)):
        np.testing.assert_array_equal(a.images[i], b.images[i])
    capsys.readouterr()
    main(["eval", str(tiny_run), "--json"])
    on_ns = json.loads(capsys.readouterr().out)
    main(["eval", str(tiny_run), "--data", str(blender), "--json"])
    on_blender = json.loads(capsys.readouterr().out)
    assert on_blender["psnr"] == pytest.approx(on_ns["psnr"], abs=1e-6)
