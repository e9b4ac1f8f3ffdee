"""tasks.planner: antipodal top-down grasps on point clouds made from trimesh primitives.

Clouds: object surfaces sampled with a fixed seed (normals from the face normals; bottom faces
left out, as no camera sees them) plus a table patch of random points on z = 0.75 with upward
normals. Real open3d / trimesh / scipy, no mocks; every planning call takes well under a second.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from sims.gripper import GRIPPER
from tasks.grasp_pose import Grasp
from tasks.gripper_collision import collision_free, grasp_collision_free
from tasks.planner import PlannerConfig, antipodal_candidates, plan_grasps
from tasks.scene_cloud import (TablePlane, fit_table, orient_normals_outward, prepare_cloud,
                               segment_objects, select_clusters)

TABLE_Z = 0.75
DENSITY = 120_000  # surface samples per square metre (about one per 3 mm voxel)
BOX_XY = (0.1, -0.05)
BOX_SIZE = (0.06, 0.04, 0.10)
G = GRIPPER


def surface_points(mesh: trimesh.Trimesh, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and face normals sampled on ``mesh`` (no downward-facing faces)."""
    pts, face = trimesh.sample.sample_surface(mesh, int(mesh.area * DENSITY), seed=seed)
    nrm = mesh.face_normals[face]
    keep = nrm[:, 2] > -0.9
    return pts[keep], nrm[keep]


def box_cloud(size=BOX_SIZE, xy=BOX_XY, seed=0):
    mesh = trimesh.creation.box(extents=size)
    mesh.apply_translation([xy[0], xy[1], TABLE_Z + size[2] / 2])
    return surface_points(mesh, seed)


def cylinder_cloud(radius, height, xy=BOX_XY, seed=0):
    mesh = trimesh.creation.cylinder(radius=radius, height=height, sections=64)
    mesh.apply_translation([xy[0], xy[1], TABLE_Z + height / 2])
    return surface_points(mesh, seed)


def table_cloud(half=0.18, center=BOX_XY, seed=0):
    rng = np.random.default_rng(seed)
    n = int((2 * half) ** 2 * DENSITY)
    pts = np.column_stack([rng.uniform(-half, half, (n, 2)) + center, np.full(n, TABLE_Z)])
    return pts, np.tile([0.0, 0.0, 1.0], (n, 1))


def merge(*parts):
    return np.concatenate([p for p, _ in parts]), np.concatenate([n for _, n in parts])


def in_gripper(grasp: Grasp, points: np.ndarray, open_width: float, sweep: float = 0.0):
    """(N,) bool, written independently of the planner: points inside the finger boxes or the
    palm box at the grasp pose, the boxes extended ``sweep`` upwards."""
    local = (points - grasp.center) @ grasp.rotation()
    x, y, z = np.abs(local[:, 0]), np.abs(local[:, 1]), local[:, 2]
    tip = -G.tcp_height
    finger = ((x >= open_width / 2) & (x <= open_width / 2 + G.finger_thickness)
              & (y <= G.finger_width / 2) & (z >= tip) & (z <= tip + G.finger_length + sweep))
    palm_lo = tip + G.finger_length
    palm = ((x <= G.max_opening / 2 + G.finger_thickness) & (y <= G.palm_width / 2)
            & (z >= palm_lo) & (z <= palm_lo + G.palm_height + sweep))
    return finger | palm


def fingertip_z(grasp: Grasp) -> float:
    return float(grasp.center[2] - G.tcp_height)


def axis_distance(grasp: Grasp, xy) -> float:
    """Horizontal distance from the point ``xy`` to the grasp's closing line."""
    d = np.asarray(xy) - grasp.center[:2]
    a = grasp.axis[:2] / np.linalg.norm(grasp.axis[:2])
    return float(abs(d[0] * a[1] - d[1] * a[0]))


def check_box_grasp(grasp: Grasp, tol=0.005):
    assert abs(grasp.axis[1]) > 0.95, grasp.axis  # narrow side (4 cm along y)
    assert abs(grasp.width - BOX_SIZE[1]) < tol, grasp.width
    assert np.linalg.norm(grasp.center[:2] - BOX_XY) < tol, grasp.center
    assert fingertip_z(grasp) >= TABLE_Z + PlannerConfig().table_clearance - 1e-9
    # contact within the box, palm (finger_length above the fingertips) above the box top
    top = TABLE_Z + BOX_SIZE[2]
    assert TABLE_Z + 0.02 < grasp.center[2] < top - 0.005, grasp.center
    assert fingertip_z(grasp) + G.finger_length > top, grasp.center


@pytest.fixture(scope="module")
def box_scene():
    return merge(box_cloud(), table_cloud())


@pytest.fixture(scope="module")
def neighbour_scene():
    # a 6 x 3 x 10 cm box 2 cm beside the target box along +y
    gap, depth = 0.02, 0.03
    y = BOX_XY[1] + BOX_SIZE[1] / 2 + gap + depth / 2
    neighbour = box_cloud(size=(0.06, depth, 0.10), xy=(BOX_XY[0], y), seed=1)
    return merge(box_cloud(), neighbour, table_cloud()), neighbour[0]


# ----------------------------------------------------------------------------- pieces


def test_prepare_cloud_keeps_given_normals(box_scene):
    pts, nrm = box_scene
    flipped = -nrm  # deliberately "wrong": the planner must not re-orient given normals
    out_p, out_n = prepare_cloud(pts, flipped)
    assert len(out_p) == len(out_n) and 0 < len(out_p) < len(pts)  # downsampled
    table = np.abs(out_p[:, 2] - TABLE_Z) < 1e-6
    assert np.all(out_n[table, 2] < -0.99)
    # and with all normals inward there is no antipodal grasp on the box at all
    assert plan_grasps(pts, flipped) == []


def test_estimated_normals_point_outward(box_scene):
    pts, _ = box_scene
    cfg = PlannerConfig()
    p, n = prepare_cloud(pts, None, config=cfg)
    table = fit_table(p, config=cfg)
    labels = segment_objects(p, table, config=cfg)
    n = orient_normals_outward(p, n, labels, table)
    obj = labels == 0
    outward = np.einsum("ij,ij->i", n[obj], p[obj] - p[obj].mean(axis=0))
    assert np.mean(outward > 0) > 0.99
    assert np.all(n[~obj][:, 2] >= 0)


def test_fit_table_skips_walls():
    rng = np.random.default_rng(0)
    table = table_cloud(half=0.1)[0]
    wall = np.column_stack([np.full(8000, 0.3), rng.uniform(-0.3, 0.3, 8000),
                            rng.uniform(0.5, 1.2, 8000)])  # vertical, larger than the table
    plane = fit_table(np.vstack([wall, table]))
    assert plane is not None
    assert abs(plane.z - TABLE_Z) < 1e-3 and plane.normal[2] > 0.999
    assert plane.noise < 1e-3
    assert fit_table(wall) is None
    given = fit_table(table, table_z=TABLE_Z)
    assert given.z == pytest.approx(TABLE_Z) and np.array_equal(given.normal, [0, 0, 1])
    assert len(given.inliers) == len(table)


def test_segment_and_select_clusters(neighbour_scene):
    (pts, _), neighbour = neighbour_scene
    cfg = PlannerConfig()
    table = fit_table(pts, config=cfg)
    labels = segment_objects(pts, table, config=cfg)
    assert set(np.unique(labels)) == {-1, 0, 1}
    assert np.all(labels[np.abs(pts[:, 2] - TABLE_Z) < 1e-6] == -1)
    near_box = select_clusters(pts, labels, BOX_XY, radius=0.02)
    assert len(near_box) == 1
    box_label = near_box[0]
    assert np.all(np.abs(pts[labels == box_label, 1] - BOX_XY[1]) <= BOX_SIZE[1] / 2 + 1e-6)
    assert select_clusters(pts, labels, (0.5, 0.5), radius=0.05) == []
    assert select_clusters(pts, labels) == [0, 1]


def test_antipodal_pairs_respect_friction_cone_and_tilt(box_scene):
    pts, nrm = box_scene
    sel = pts[:, 2] > TABLE_Z + 0.01
    cfg = PlannerConfig(friction=0.3, max_axis_tilt_deg=10.0)
    pairs = antipodal_candidates(pts[sel], nrm[sel], config=cfg)
    assert len(pairs) > 50
    cone = np.degrees(np.arctan(0.3))
    assert np.all(np.degrees(pairs.angle_p) <= cone + 1e-6)
    assert np.all(np.degrees(pairs.angle_q) <= cone + 1e-6)
    assert np.all(np.degrees(pairs.tilt) <= 10.0 + 1e-6)
    assert np.all(np.abs(pairs.axis[:, 2]) < 1e-12)
    assert np.allclose(np.linalg.norm(pairs.axis, axis=1), 1.0)
    assert np.all((pairs.width >= cfg.min_width)
                  & (pairs.width <= G.max_opening - cfg.width_margin))
    # the box has only two antipodal widths: 4 cm (y) and 6 cm (x)
    assert np.all((np.abs(pairs.width - 0.04) < 0.006) | (np.abs(pairs.width - 0.06) < 0.006))


def test_collision_free_finger_boxes_and_table(box_scene):
    pts, _ = box_scene
    table = TablePlane(normal=np.array([0.0, 0.0, 1.0]), offset=-TABLE_Z, z=TABLE_Z)
    obstacles = pts[pts[:, 2] > TABLE_Z + 0.005]
    c = np.array([BOX_XY[0], BOX_XY[1], TABLE_Z + 0.05])
    y_axis, x_axis = [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]
    centers = [c, c, c, c + [0, 0, -0.03]]
    axes = [y_axis, x_axis, y_axis, y_axis]
    widths = [0.06, 0.05, 0.035, 0.06]
    free = collision_free(centers, axes, widths, obstacles, table=table)
    # ok; fingers inside the 6 cm side; fingers inside the 4 cm side; fingertips below the table
    assert free.tolist() == [True, False, False, False]
    assert collision_free(centers[:1], axes[:1], widths[:1], np.zeros((0, 3)), table=table)[0]
    # the approach sweep: single points above the grasp (closing along y, fingers at
    # |y| in [0.03, 0.042]; palm |y| <= 0.082, |x| <= 0.025 from the centre)
    above_finger = c + [0.0, 0.036, 0.15]
    above_palm = c + [0.02, 0.07, 0.20]
    beyond_sweep = c + [0.0, 0.036, 0.30]
    beside = c + [0.03, 0.036, 0.10]
    for point, expected in ((above_finger, False), (above_palm, False), (beyond_sweep, True),
                            (beside, True)):
        got = collision_free([c], [y_axis], [0.06], np.vstack([obstacles, point]), table=table)
        assert got[0] == expected, point - c


# ----------------------------------------------------------------------------- planning


@pytest.mark.parametrize("given_normals", [True, False], ids=["face_normals", "estimated"])
def test_box_grasp_on_narrow_side(box_scene, given_normals):
    pts, nrm = box_scene
    grasps = plan_grasps(pts, nrm if given_normals else None)
    assert grasps
    assert all(isinstance(g, Grasp) for g in grasps)
    scores = [g.score for g in grasps]
    assert scores == sorted(scores, reverse=True)
    best = grasps[0]
    check_box_grasp(best)
    info = best.info
    assert {"friction", "center", "height", "width_term", "open_width"} <= set(info)
    assert info["open_width"] == pytest.approx(best.width + PlannerConfig().width_margin)
    assert info["table_z"] == pytest.approx(TABLE_Z, abs=1e-3)
    assert np.allclose(best.approach, [0, 0, -1])
    assert abs(best.axis @ best.approach) < 1e-9
    for g in grasps:
        assert fingertip_z(g) >= TABLE_Z + PlannerConfig().table_clearance - 1e-9
        assert not in_gripper(g, pts, g.info["open_width"], sweep=0.15).any()


@pytest.mark.parametrize("given_normals", [True, False], ids=["face_normals", "estimated"])
def test_cylinder_grasp_through_axis(given_normals):
    radius, height = 0.035, 0.12
    pts, nrm = merge(cylinder_cloud(radius, height), table_cloud())
    grasps = plan_grasps(pts, nrm if given_normals else None)
    assert grasps
    best = grasps[0]
    assert abs(best.width - 2 * radius) < 0.005, best.width
    assert axis_distance(best, BOX_XY) < 0.005
    assert np.linalg.norm(best.center[:2] - BOX_XY) < 0.005
    assert TABLE_Z + 0.02 < best.center[2] < TABLE_Z + height


def test_box_too_wide_gives_no_grasp():
    pts, nrm = merge(box_cloud(size=(0.2, 0.2, 0.1)), table_cloud(half=0.25))
    assert plan_grasps(pts, nrm) == []
    assert plan_grasps(pts, None) == []


def test_neighbour_blocks_grasps_on_its_side(neighbour_scene):
    (pts, nrm), neighbour = neighbour_scene
    grasps = plan_grasps(pts, nrm, target=BOX_XY, target_radius=0.02)
    assert grasps
    best = grasps[0]
    # the 4 cm (y) grasp would put a finger into the neighbour: the planner closes along x
    assert abs(best.axis[0]) > 0.95, best.axis
    assert abs(best.width - BOX_SIZE[0]) < 0.005
    assert np.linalg.norm(best.center[:2] - BOX_XY) < 0.005
    for g in grasps:
        assert abs(g.axis[1]) < 0.9  # no grasp closing towards the neighbour
        assert np.all(np.abs(g.center[:2] - BOX_XY) < np.array(BOX_SIZE[:2]) / 2)
        assert grasp_collision_free(g, pts[pts[:, 2] > TABLE_Z + 0.005])
        assert not in_gripper(g, neighbour, g.info["open_width"], sweep=0.15).any()
        assert not in_gripper(g, pts, g.info["open_width"]).any()
    # the same y grasp is free without the neighbour, blocked with it
    box_only = box_cloud()[0]
    y_grasp = Grasp(center=np.array([*BOX_XY, TABLE_Z + 0.05]), axis=np.array([0.0, 1.0, 0.0]),
                    width=0.04)
    assert grasp_collision_free(y_grasp, box_only)
    assert not grasp_collision_free(y_grasp, neighbour)
    assert in_gripper(y_grasp, neighbour, 0.06).any()


def test_target_selects_object(neighbour_scene):
    (pts, nrm), neighbour = neighbour_scene
    n_xy = neighbour[:, :2].mean(axis=0)
    on_neighbour = plan_grasps(pts, nrm, target=n_xy, target_radius=0.01)
    assert on_neighbour
    for g in on_neighbour:
        assert abs(g.center[1] - n_xy[1]) < 0.015 + 1e-6  # inside the 3 cm deep neighbour
    # the neighbour's narrow side is 3 cm along y, and a y grasp would hit the box: along x
    assert abs(on_neighbour[0].axis[0]) > 0.95
    assert plan_grasps(pts, nrm, target=(BOX_XY[0] + 0.12, BOX_XY[1]), target_radius=0.03) == []


def test_noise_and_outliers():
    rng = np.random.default_rng(7)
    pts, nrm = merge(box_cloud(), table_cloud())
    pts = pts + rng.normal(0.0, 0.0015, pts.shape)
    n_out = int(0.02 * len(pts))
    lo, hi = np.array([-0.08, -0.23, TABLE_Z]), np.array([0.28, 0.13, TABLE_Z + 0.25])
    outliers = rng.uniform(lo, hi, (n_out, 3))
    out_n = rng.normal(size=(n_out, 3))
    cloud = np.vstack([pts, outliers])
    for normals in (np.vstack([nrm, out_n / np.linalg.norm(out_n, axis=1, keepdims=True)]), None):
        grasps = plan_grasps(cloud, normals)
        assert grasps
        check_box_grasp(grasps[0])


def test_known_table_z(box_scene):
    pts, nrm = box_scene
    grasps = plan_grasps(pts, nrm, table_z=TABLE_Z)
    check_box_grasp(grasps[0])
    assert grasps[0].info["table_z"] == pytest.approx(TABLE_Z)


def test_deterministic(box_scene):
    pts, nrm = box_scene
    a, b = plan_grasps(pts, nrm), plan_grasps(pts, nrm)
    assert [g.score for g in a] == [g.score for g in b]
    assert np.array_equal(a[0].center, b[0].center)


# ----------------------------------------------------------------------------- bad input


def test_bad_input(box_scene, caplog):
    pts, nrm = box_scene
    with pytest.raises(ValueError, match="shape"):
        plan_grasps(pts[:, :2])
    with pytest.raises(ValueError, match="shape"):
        plan_grasps(pts[0])
    with pytest.raises(ValueError, match="normals"):
        plan_grasps(pts, nrm[:-1])
    with pytest.raises(ValueError, match="target"):
        plan_grasps(pts, nrm, target=(0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="target_radius"):
        plan_grasps(pts, nrm, target=(0.1, 0.2), target_radius=0.0)
    with pytest.raises(ValueError, match="friction"):
        PlannerConfig(friction=0.0)
    assert plan_grasps(np.zeros((0, 3))) == []
    assert plan_grasps(np.full((10, 3), np.nan)) == []
    assert plan_grasps(table_cloud()[0]) == []  # a table and nothing on it
    bad = pts.copy()
    bad[::50] = np.nan
    with caplog.at_level(logging.WARNING, logger="tasks.planner"):
        grasps = plan_grasps(bad, nrm)
    assert f"dropped {len(bad[::50])} non-finite point(s)" in caplog.text
    check_box_grasp(grasps[0])
