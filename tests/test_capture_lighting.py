"""Captures are lit statically by default: MuJoCo's headlight (on in every MJCF) follows the
camera, so with it a surface point changes colour with the viewpoint; without its diffuse and
specular terms, two views of a matte point agree."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from nerfbot.ops.cameras import look_at, spherical_eye
from sims.camera import CaptureCamera
from sims.capture import (DEFAULT_HEADLIGHT_DIFFUSE, DEFAULT_HEADLIGHT_SPECULAR,
                          set_lighting)
from sims.scene import load_capture_model

#: A matte grey box lit from above by a fixed light; no <visual>, so MuJoCo's default headlight
#: (ambient 0.1, diffuse 0.4, specular 0.5) is on.
SCENE = """<mujoco>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true" diffuse="0.5 0.5 0.5" specular="0 0 0"/>
    <geom type="box" size="0.3 0.3 0.1" rgba="0.6 0.6 0.6 1" material="matte"/>
  </worldbody>
  <asset><material name="matte" specular="0" shininess="0" reflectance="0"/></asset>
</mujoco>
"""
TOP = np.array([0.05, -0.04, 0.1])  # a point on the box's top face, metres
VIEWS = ((20.0, 35.0), (200.0, 75.0))  # (azimuth, elevation) degrees: a grazing and a steep view
SIZE = 48


def _pixel(c2w: np.ndarray, point: np.ndarray, f: float) -> tuple[int, int]:
    """(row, column) of the pixel that sees ``point`` from OpenGL pose ``c2w``."""
    p = c2w[:3, :3].T @ (point - c2w[:3, 3])
    u = SIZE / 2 + f * p[0] / -p[2]
    v = SIZE / 2 - f * p[1] / -p[2]
    return int(v), int(u)


def _colours_of_the_point(path, headlight: bool) -> tuple[str, list[np.ndarray]]:
    model, data = load_capture_model(path)
    lighting = set_lighting(model, headlight)
    colours = []
    with CaptureCamera(model, data, SIZE, SIZE, 40.0) as cam:
        for azimuth, elevation in VIEWS:
            pose = look_at(spherical_eye(TOP, 1.5, azimuth, elevation), TOP)
            frame = cam.render(pose)
            row, col = _pixel(frame.c2w, TOP, cam.intrinsics.fx)
            assert frame.segmentation[row, col] >= 0  # the box, not the sky
            colours.append(frame.rgb[row - 1:row + 2, col - 1:col + 2].reshape(-1, 3).mean(0))
    return lighting, colours


def test_static_lighting_removes_view_dependence(tmp_path):
    path = tmp_path / "box.xml"
    path.write_text(SCENE)
    lighting, (a, b) = _colours_of_the_point(path, headlight=False)
    assert lighting == "static"
    assert np.abs(a - b).max() <= 2.0, (a, b)  # the same colour from both views
    lighting, (a, b) = _colours_of_the_point(path, headlight=True)
    assert lighting == "headlight"
    assert np.abs(a - b).max() >= 15.0, (a, b)  # the headlight shades each view differently


def test_capture_records_its_lighting(tmp_path):
    from nerfbot.app.cli import main

    path = tmp_path / "box.xml"
    path.write_text(SCENE)
    for flags, expected in (([], "static"), (["--headlight"], "headlight")):
        out = tmp_path / f"data_{expected}"
        assert main(["capture", "--scene", str(path), "--views", "3", "--test-views", "1",
                     "--size", "16", "--out", str(out), "--no-progress", *flags]) == 0
        manifest = json.loads((out / "transforms.json").read_text())["scene"]
        assert manifest["lighting"] == expected


@pytest.mark.parametrize("scene", ["tabletop", "dynamic", "articulated", "workspace:0"])
def test_scenes_without_a_moving_headlight_get_one_when_asked(scene):
    model, _ = load_capture_model(scene)
    before = (model.vis.headlight.diffuse.copy(), model.vis.headlight.specular.copy())
    assert not before[0].any() and not before[1].any()  # static as built
    assert set_lighting(model, headlight=False) == "static"
    np.testing.assert_array_equal(model.vis.headlight.diffuse, before[0])
    np.testing.assert_array_equal(model.vis.headlight.specular, before[1])
    assert set_lighting(model, headlight=True) == "headlight"
    assert model.vis.headlight.active
    np.testing.assert_allclose(model.vis.headlight.diffuse, DEFAULT_HEADLIGHT_DIFFUSE)
    np.testing.assert_allclose(model.vis.headlight.specular, DEFAULT_HEADLIGHT_SPECULAR)


def test_headlight_shades_a_zoo_scene_differently_from_static(tmp_path):
    from nerfbot.app.cli import main

    images = {}
    for flags, name in (([], "static"), (["--headlight"], "headlight")):
        out = tmp_path / name
        assert main(["capture", "--scene", "workspace:0", "--views", "2", "--test-views", "1",
                     "--size", "24", "--out", str(out), "--no-progress", *flags]) == 0
        manifest = json.loads((out / "transforms.json").read_text())["scene"]
        assert manifest["lighting"] == name
        images[name] = np.stack([cv2.imread(str(p)) for p in sorted(out.glob("images/*.png"))])
    assert images["static"].shape == images["headlight"].shape
    assert np.abs(images["headlight"].astype(int) - images["static"]).mean() >= 5.0
