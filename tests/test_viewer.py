"""``nerfbot view``: camera conventions, saved camera paths, and the viewer in a real browser
(headless Chromium from the system packages, driven by playwright)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from nerfbot.app.cli import main
from nerfbot.app.viewer import (CameraPathFile, StartView, c2w_from_viser, load_geometry,
                                look_at_pose, viser_from_c2w)
from nerfbot.data import load_dataset
from nerfbot.ops.cameras import Cameras
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model
from sims.rigs import read_pose_file

pytestmark = pytest.mark.slow(95)  # rough single-core seconds (tests/conftest.py)

#: Screenshots of the browser test are kept here, to be looked at.
ARTIFACTS = Path(os.environ.get("NERFBOT_TEST_ARTIFACTS",
                                Path(__file__).resolve().parents[1] / ".test-artifacts"))
VIEWPORT = (960, 480)  # the browser's canvas, pixels: aspect 2
RESOLUTION = 64  # --resolution of the viewer: still frames are 128 x 64
#: The part of the canvas no control covers: the notification box at the top left, the
#: control panel at the right and the axes at the bottom left (fractions of the viewport).
OPEN_REGION = (slice(0.3, 0.98), slice(0.32, 0.71))  # (rows, columns)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10.0 * np.log10(255.0 ** 2 / max(mse, 1e-12))


def _region(img: np.ndarray) -> np.ndarray:
    h, w = img.shape[:2]
    rows, cols = OPEN_REGION
    return img[int(rows.start * h):int(rows.stop * h), int(cols.start * w):int(cols.stop * w)]


# ----------------------------------------------------------------------------- conventions

def test_viser_poses_are_opencv_cameras_of_the_same_world_pose():
    """A viser camera looks along its +z with +y down; the OpenGL pose looks along -z with +y
    up: the same camera, and the conversion round-trips."""
    c2w = look_at_pose([2.0, -1.0, 1.5], [0.0, 0.2, 0.3], [0.0, 0.0, 1.0])
    wxyz, pos = viser_from_c2w(c2w)
    assert np.allclose(c2w_from_viser(wxyz, pos), c2w, atol=1e-9)
    x, y, z, w = wxyz[1], wxyz[2], wxyz[3], wxyz[0]
    from scipy.spatial.transform import Rotation
    r_cv = Rotation.from_quat([x, y, z, w]).as_matrix()
    ahead = np.array([0.0, 0.2, 0.3]) - np.array([2.0, -1.0, 1.5])
    assert np.allclose(r_cv[:, 2], ahead / np.linalg.norm(ahead))  # +z forward
    assert r_cv[2, 1] < 0  # +y points down: world z along -y
    start = StartView.of_camera(c2w, 40.0, 3.0)
    assert np.allclose(start.pose(), c2w, atol=1e-9)


def test_saved_cameras_are_a_pose_file_render_reads(tmp_path):
    path = tmp_path / "path.json"
    keys = CameraPathFile(path)
    poses = [look_at_pose([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0], [0, 0, 0], [0, 0, 1])
             for a in (0.0, 1.0, 2.0)]
    for i, pose in enumerate(poses[:2]):
        assert keys.append(pose) == i + 1
    again = CameraPathFile(path)  # a second session extends the file
    assert again.append(poses[2]) == 3
    read = read_pose_file(path)
    assert len(read) == 3 and all(np.allclose(a, b) for a, b in zip(read, poses))
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    split = tmp_path / "splits.json"
    split.write_text('{"train": [], "test": []}')
    with pytest.raises(ValueError, match="splits.json: a camera path is one list"):
        CameraPathFile(split)


def test_geometry_files_load_and_empty_ones_are_refused(tmp_path):
    mesh = trimesh.creation.box()
    mesh.export(tmp_path / "box.ply")
    assert len(load_geometry(tmp_path / "box.ply").faces) == 12
    trimesh.PointCloud(np.random.default_rng(0).random((50, 3))).export(tmp_path / "pts.ply")
    assert isinstance(load_geometry(tmp_path / "pts.ply"), trimesh.PointCloud)
    (tmp_path / "bad.ply").write_text("not a ply")
    with pytest.raises(ValueError, match="bad.ply"):
        load_geometry(tmp_path / "bad.ply")


# ----------------------------------------------------------------------------- the browser

@pytest.fixture(scope="module")
def view_run(tiny_capture, tmp_path_factory):
    """A tabletop ngp run trained long enough to show sky, table and objects."""
    out = tmp_path_factory.mktemp("view") / "run"
    assert main(["train", "--data", str(tiny_capture[0]), "--method", "ngp", "--max-steps",
                 "200", "--out", str(out), "--no-progress"]) == 0
    return out, tiny_capture[0]


def _chromium() -> str:
    found = os.environ.get("NERFBOT_CHROMIUM") or shutil.which("chromium") \
        or shutil.which("chromium-browser")
    assert found, "the viewer test needs Chromium (apt-get install chromium; the README's " \
                  "test command installs it)"
    return found


def _expected_view(run: Path, data: Path, width: int, height: int) -> np.ndarray:
    """The run's render of test view 0 at the viewer's still-frame size, uint8."""
    model, _ = load_model(run)
    ds = load_dataset(data)
    i = ds.indices("test")[0]
    fov = float(np.degrees(2 * np.arctan(0.5 * ds.sizes[i][1] / ds.intrinsics[i, 1])))
    img = render_image(model, Cameras.pinhole(ds.c2w[i], fov, width, height), 0)
    return (np.clip(img["rgb"], 0, 1) * 255 + 0.5).astype(np.uint8)


def _frame_number(page, kind: str = "full") -> int:
    text = page.get_by_text(re.compile(r"frame \d+: ")).inner_text()
    found = re.search(rf"frame (\d+): {kind}", text)
    return int(found.group(1)) if found else -1


def _wait_for_full_frame(page, after: int = 0, timeout_s: float = 120.0) -> int:
    page.wait_for_function(
        "n => [...document.querySelectorAll('*')].some(e => e.children.length === 0 && "
        "/frame (\\d+): full/.test(e.textContent) && "
        "+e.textContent.match(/frame (\\d+): full/)[1] > n)", arg=after,
        timeout=timeout_s * 1000)
    return _frame_number(page)


def _screenshot(page, name: str) -> np.ndarray:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / name
    page.screenshot(path=str(path))
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def test_the_viewer_shows_the_field_in_a_browser_and_follows_its_camera(view_run, tmp_path):
    """``nerfbot view`` in a subprocess, opened by headless Chromium: the first still frame is
    the run's render of the start camera (test view 0) over the open part of the canvas, not a
    blank canvas; "save camera" writes that camera to the path file; dragging the mouse moves
    the camera and a new frame shows another view."""
    from playwright.sync_api import sync_playwright

    run, data = view_run
    path_file = tmp_path / "path.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "nerfbot.app.cli", "view", str(run), "--port", "0",
         "--camera", "test:0", "--resolution", str(RESOLUTION), "--path-file", str(path_file)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    try:
        for line in proc.stdout:
            lines.append(line)
            if "http://" in line:
                break
        found = re.search(r"http://[\d.]+:(\d+)", "".join(lines))
        assert found, "".join(lines)
        url = f"http://127.0.0.1:{found.group(1)}"
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=_chromium(),
                                         args=["--enable-unsafe-swiftshader",
                                               "--use-angle=swiftshader"])
            page = browser.new_page(viewport=dict(zip(("width", "height"), VIEWPORT)))
            page.goto(url)
            first = _wait_for_full_frame(page)
            for box in ("training cameras", "scene bounds"):  # the field alone
                page.get_by_text(box, exact=True).click()
            page.wait_for_timeout(500)
            shot = _screenshot(page, "viewer_first_frame.png")
            width, height = round(RESOLUTION * VIEWPORT[0] / VIEWPORT[1]), RESOLUTION
            # compared at half the frame's resolution: the browser's bilinear magnification
            # of the frame and ours differ at sharp edges, not in what they show
            half = (width // 2, height // 2)
            seen = cv2.resize(shot, half, interpolation=cv2.INTER_AREA)
            expected = cv2.resize(_expected_view(run, data, width, height), half,
                                  interpolation=cv2.INTER_AREA)
            blank = np.broadcast_to(seen.reshape(-1, 3).mean(0), seen.shape)
            match, versus_blank = _psnr(_region(seen), _region(expected)), \
                _psnr(_region(blank), _region(expected))
            assert match >= 24.0 and match >= versus_blank + 8.0, (match, versus_blank)

            page.get_by_text("save camera", exact=True).click()
            for _ in range(100):
                if path_file.exists():
                    break
                page.wait_for_timeout(100)
            ds = load_dataset(data)
            saved = read_pose_file(path_file)
            assert len(saved) == 1
            assert np.abs(saved[0] - ds.c2w[ds.indices("test")[0]]).max() < 1e-3

            x0, y0 = int(0.5 * VIEWPORT[0]), int(0.75 * VIEWPORT[1])  # on the canvas
            page.mouse.move(x0, y0)
            page.mouse.down()
            page.mouse.move(x0 - 120, y0 - 30, steps=10)
            page.mouse.up()
            assert _wait_for_full_frame(page, after=first) > first
            moved = cv2.resize(_screenshot(page, "viewer_moved.png"), half,
                               interpolation=cv2.INTER_AREA)
            assert _psnr(_region(moved), _region(seen)) < match - 6.0
            assert _region(moved).std() > 10.0  # still the scene, not a blank canvas
            browser.close()
    finally:
        proc.terminate()
        out = proc.communicate(timeout=60)[0]
    assert proc.returncode == 0, "".join(lines) + out
    assert "nerfbot view: stopped" in out


def test_view_refuses_a_camera_the_dataset_does_not_have(view_run, capsys):
    run, _ = view_run
    assert main(["view", str(run), "--port", "0", "--camera", "test:99"]) == 2
    assert "--camera test:99: expected SPLIT:K" in capsys.readouterr().err
