"""Exports (point cloud, marching-cubes mesh, TSDF mesh) land in world metres: an analytic
sphere far from the origin rendered through the real occupancy-grid renderer; the files round-
trip; ``nerfbot export`` on a tiny trained run; the scores against a true surface."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
import torch
import trimesh

from nerfbot.app.cli import main
from nerfbot.fields.background import FixedBackground
from nerfbot.fields.base import Field
from nerfbot.models.occupancy import OccupancyModel
from nerfbot.ops.cameras import Cameras, look_at
from nerfbot.query.geometry import (DepthQuery, density_mesh, point_cloud, tsdf_mesh,
                                    write_mesh, write_point_cloud)
from nerfbot.query.meshing import compare_cloud, compare_meshes

pytestmark = pytest.mark.slow(40)  # rough single-core seconds (tests/conftest.py)

CENTRE = np.array([10.0, -5.0, 3.0])   # metres: far from the origin, as a scene in a big world
RADIUS = 0.4
RED = (0.9, 0.1, 0.1)


class RedBall(Field):
    """A red ball: density ``peak`` * sigmoid((RADIUS - r) / ``wall``), peak / 2 at the radius."""

    def __init__(self, peak: float, wall: float):
        super().__init__()
        self.peak, self.wall = peak, wall

    def density(self, x, cond=None):
        r = (x - torch.as_tensor(CENTRE, dtype=x.dtype)).norm(dim=-1)
        return self.peak * torch.sigmoid((RADIUS - r) / self.wall), torch.zeros(len(x), 1)

    def color(self, feat, d, cond=None):
        return torch.tensor(RED).expand(len(feat), 3)


def _ball_model(peak, wall):
    aabb = torch.tensor(np.stack([CENTRE - 0.6, CENTRE + 0.6]), dtype=torch.float32)
    return OccupancyModel(RedBall(peak, wall), FixedBackground((1.0, 1.0, 1.0)), aabb).eval()


@pytest.fixture(scope="module")
def ball():
    """Opaque at its surface (half a millimetre wall): rendered depth lands on the radius."""
    return _ball_model(1e4, 5e-4)


@pytest.fixture(scope="module")
def soft_ball():
    """A 1 cm wall (50 /m at the radius): marching cubes interpolates it to well under a cell."""
    return _ball_model(100.0, 0.01)


def _ring_cameras(n=8, size=48, distance=1.5):
    poses = []
    for k in range(n):
        a = 2 * np.pi * k / n
        eye = CENTRE + distance * np.array([np.cos(a), np.sin(a), 0.5 if k % 2 else -0.3])
        poses.append(look_at(eye, CENTRE, up=np.array([0.0, 0.0, 1.0])))
    f = size / (2 * np.tan(np.radians(40) / 2))
    return Cameras.from_numpy(np.stack(poses), [[f, f, size / 2, size / 2]] * n,
                              [[size, size]] * n)


def _truth():
    sphere = trimesh.creation.icosphere(5, radius=RADIUS)
    sphere.apply_translation(CENTRE)
    return sphere


def test_point_cloud_lies_on_the_ball_in_world_metres(ball):
    cloud = point_cloud(ball, _ring_cameras())
    pts = np.asarray(cloud.points)
    assert len(pts) > 2000
    r = np.linalg.norm(pts - CENTRE, axis=1)
    step = float(ball.dt_min)
    assert np.abs(r - RADIUS).max() < step, (np.abs(r - RADIUS).max(), step)
    assert np.median(np.abs(r - RADIUS)) < 0.25 * step
    # normals point out of the ball (towards the cameras that saw each point)
    normals = np.asarray(cloud.normals)
    assert np.mean(np.sum(normals * (pts - CENTRE), axis=1) > 0) > 0.98
    assert np.allclose(np.asarray(cloud.colors), RED, atol=1 / 255 + 1e-6)
    # cropping keeps only the box
    upper = point_cloud(ball, _ring_cameras(), bounds=[CENTRE - 1, CENTRE + [1, 1, 0]])
    assert len(upper.points) < len(pts) and np.asarray(upper.points)[:, 2].max() <= CENTRE[2] + 1e-6


def test_meshes_lie_on_the_ball_in_world_metres(ball, soft_ball):
    truth = _truth()
    mesh = density_mesh(soft_ball, threshold=50.0, resolution=96)   # 12.5 mm cells
    cmp = compare_meshes(mesh, truth, count=20000)
    assert cmp["chamfer_mm"] < 1.0 and cmp["fscore"] > 0.999, cmp
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3] / 255.0
    assert np.allclose(colours, RED, atol=1 / 255 + 1e-6)
    cams = _ring_cameras()
    tsdf = tsdf_mesh(ball, cams, voxel=0.01)
    seen = (cams.c2w.numpy(), torch.stack([cams.fx, cams.fy, cams.cx, cams.cy], 1).numpy(),
            torch.stack([cams.width, cams.height], 1).numpy())
    cmp = compare_meshes(tsdf, truth, count=20000, cameras=seen)
    # what it fuses lies on the ball; 48 px views at grazing angles leave some of it uncovered
    assert cmp["accuracy_mm"] < 5.0 and cmp["precision"] > 0.95 and cmp["recall"] > 0.8, cmp
    assert np.abs(np.linalg.norm(tsdf.vertices - CENTRE, axis=1) - RADIUS).max() < 0.03


def test_threshold_query_needs_a_threshold_and_empty_views_give_empty_exports(ball):
    with pytest.raises(ValueError, match="threshold"):
        DepthQuery("threshold")
    with pytest.raises(ValueError, match="unknown depth mode"):
        DepthQuery("mean")
    # cameras looking away from the ball see only background: nothing to export
    away = look_at(CENTRE + [3.0, 0, 0], CENTRE + [6.0, 0, 0], up=np.array([0.0, 0.0, 1.0]))
    cams = Cameras.from_numpy(away[None], [[20.0, 20.0, 8.0, 8.0]], [[16, 16]])
    assert len(point_cloud(ball, cams).points) == 0
    assert len(tsdf_mesh(ball, cams).faces) == 0
    assert len(density_mesh(ball, threshold=1e5, resolution=16).faces) == 0


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_mesh_files_round_trip(ball, tmp_path, suffix):
    mesh = density_mesh(ball, threshold=5e3, resolution=32)
    path = write_mesh(mesh, tmp_path / f"ball{suffix}")
    back = trimesh.load(path, force="mesh", process=False)
    assert len(back.faces) == len(mesh.faces)
    assert np.allclose(np.sort(back.vertices, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-5)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporaries


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_cloud_files_round_trip(ball, tmp_path, suffix):
    cloud = point_cloud(ball, _ring_cameras(n=2, size=16))
    path = write_point_cloud(cloud, tmp_path / f"ball{suffix}")
    back = o3d.io.read_point_cloud(str(path))
    assert np.allclose(np.asarray(back.points), np.asarray(cloud.points), atol=1e-5)
    assert np.allclose(np.asarray(back.normals), np.asarray(cloud.normals), atol=1e-5)
    with pytest.raises(ValueError, match="point clouds are written as"):
        write_point_cloud(cloud, tmp_path / "ball.stl")


def test_cloud_scores_see_a_shift():
    truth = _truth()
    pts = trimesh.sample.sample_surface(truth, 200000, seed=0)[0]   # 3 mm apart
    exact = compare_cloud(pts, truth, count=20000)
    assert exact["accuracy_mm"] < 1e-3 and exact["fscore"] > 0.999
    shifted = compare_cloud(pts + [0.02, 0, 0], truth, count=20000)
    assert shifted["precision"] < 0.6 and shifted["accuracy_mm"] > 5.0
    assert compare_cloud(np.zeros((0, 3)), truth, count=100)["fscore"] == 0.0


# -- nerfbot export on a tiny trained run ------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_run(tiny_capture, tmp_path_factory):
    data, _ = tiny_capture
    run = tmp_path_factory.mktemp("export") / "run"
    assert main(["train", "--data", str(data), "--method", "ngp", "--max-steps", "60",
                 "--out", str(run), "--no-progress"]) == 0
    return run


def test_export_cli_writes_every_kind_in_the_capture_frame(tiny_run, tmp_path, capsys):
    aabb = json.loads((tiny_run / "config.json").read_text())["spec"]["aabb"]
    lo, hi = np.asarray(aabb, float)
    for kind, name in (("pointcloud", "c.ply"), ("mesh", "m.obj"), ("tsdf", "t.glb")):
        out = tmp_path / name
        # a field trained for 60 steps is faint: the mesh is cut well below the default density
        assert main(["export", str(tiny_run), kind, "--out", str(out), "--no-progress",
                     "--resolution", "48", "--threshold", "5"]) == 0
        assert "world frame, metres" in capsys.readouterr().out
        if kind == "pointcloud":
            pts = np.asarray(o3d.io.read_point_cloud(str(out)).points)
        else:
            pts = trimesh.load(out, force="mesh").vertices
        assert len(pts) > 0
        assert np.all(pts >= lo - 1e-3) and np.all(pts <= hi + 1e-3)


def test_export_cli_refuses_what_it_must_not_write(tiny_run, tmp_path, capsys):
    existing = tmp_path / "mine.ply"
    existing.write_text("the user's file")
    assert main(["export", str(tiny_run), "mesh", "--out", str(existing), "--no-progress"]) == 2
    assert "already exists" in capsys.readouterr().err
    assert existing.read_text() == "the user's file"
    assert main(["export", str(tiny_run), "pointcloud", "--out", str(tmp_path / "c.obj"),
                 "--no-progress"]) == 2
    assert "pointcloud is written as" in capsys.readouterr().err
    assert main(["export", str(tiny_run), "mesh", "--out", str(tmp_path / "m.ply"), "--time",
                 "0.5", "--no-progress"]) == 2
    assert "not conditioned on time" in capsys.readouterr().err
    assert main(["export", str(tiny_run), "mesh", "--out", str(tmp_path / "m.ply"),
                 "--threshold", "1e7", "--no-progress"]) == 2
    assert "no density reaches 1e+07 /m" in capsys.readouterr().err
    assert not (tmp_path / "m.ply").exists()
    assert main(["export", str(tiny_run), "mesh", "--out", str(tmp_path / "m.ply"), "--aabb",
                 "1", "0", "0", "0", "1", "1", "--no-progress"]) == 2
    assert "--aabb" in capsys.readouterr().err
