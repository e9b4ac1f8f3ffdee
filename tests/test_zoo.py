"""The scene zoo (sims/zoo): workspace, room, bins and yard, generated, compiled and captured with
real MuJoCo rendering at tiny sizes, and the ``inside`` rig of the room."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os

import mujoco
import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco renders)
from nerfbot.data import load_dataset
from sims.capture import capture
from sims.cli import add_capture_arguments, rigs_from_args
from sims.manifest import custom_numeric, declared_objects, declared_obstacles, scene_manifest
from sims.rigs import RigConfig, default_rig, make_test_rig, rig_poses
from sims.scene import builtin_scenes, generated_scene, load_model, resolve_scene, scene_cache_dir
from sims.sensor import DepthSensorModel
from sims.zoo import bins, room, workspace, yard
from sims.zoo.bins import bins_scene
from sims.zoo.room import room_glass_scene, room_scene
from sims.zoo.workspace import workspace_scene
from sims.zoo.yard import yard_scene

pytestmark = pytest.mark.slow(15)

FAMILIES = {"workspace": workspace_scene, "room": room_scene, "room_glass": room_glass_scene,
            "bins": bins_scene, "yard": yard_scene}
SEEDS = (0, 1, 7)
SIZE = 32
#: Capture format per family: both readers are exercised.
FORMATS = {"workspace": "nerfstudio", "room": "nerfstudio", "room_glass": "nerfstudio",
           "bins": "blender", "yard": "blender"}


@pytest.fixture(scope="module", autouse=True)
def scene_cache(tmp_path_factory):
    """Generated scenes go to a fresh cache folder for this module."""
    old = os.environ.get("NERFBOT_CACHE")
    os.environ["NERFBOT_CACHE"] = str(tmp_path_factory.mktemp("cache"))
    yield scene_cache_dir()
    if old is None:
        os.environ.pop("NERFBOT_CACHE", None)
    else:
        os.environ["NERFBOT_CACHE"] = old


def _forward(scene: str) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = load_model(scene)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def _largest(model: mujoco.MjModel, name: str) -> float:
    """Largest dimension of geom ``name`` in its own frame, metres."""
    return float(2.0 * model.geom_aabb[model.geom(name).id, 3:].max())


# -- generation ---------------------------------------------------------------------------------

def test_families_are_built_in_scene_names():
    assert set(FAMILIES) <= set(builtin_scenes())
    assert resolve_scene("room") == resolve_scene("room:0")
    assert resolve_scene("room:3").parent.name == "room-3"
    with pytest.raises(ValueError, match="integer"):
        resolve_scene("yard:x")


@pytest.mark.parametrize("family", FAMILIES)
def test_each_family_compiles_for_several_seeds_and_the_seed_changes_the_layout(family):
    layouts = []
    for seed in SEEDS:
        model, data = _forward(f"{family}:{seed}")
        objects = declared_objects(model)
        assert objects, (family, seed)
        layouts.append(np.concatenate([data.geom_xpos[model.geom(n).id] for n in objects]))
        assert scene_manifest(model, data, f"{family}-{seed}", "test")["objects"] == objects
    for a in range(len(SEEDS)):
        for b in range(a + 1, len(SEEDS)):
            assert layouts[a].shape != layouts[b].shape or not np.allclose(layouts[a], layouts[b])


@pytest.mark.parametrize("family", FAMILIES)
def test_same_seed_same_bytes_and_files_rewritten_only_on_change(family):
    first, again = FAMILIES[family](5), FAMILIES[family](5)
    assert first.xml == again.xml and first.assets.keys() == again.assets.keys()
    for name, content in first.assets.items():
        assert np.array_equal(content, again.assets[name]), name
        assert name in first.xml                     # every asset is referenced
    assert FAMILIES[family](6).xml != first.xml
    path = generated_scene(family, 5)
    files = sorted(path.parent.iterdir())
    assert {f.name for f in files} == set(first.assets) | {path.name}
    stamps = {f: f.stat().st_mtime_ns for f in files}
    contents = {f: f.read_bytes() for f in files}
    os.utime(path, ns=(1, 1))                        # an old stamp: a rewrite would renew it
    stamps[path] = path.stat().st_mtime_ns
    assert generated_scene(family, 5) == path
    assert {f: f.stat().st_mtime_ns for f in files} == stamps
    assert {f: f.read_bytes() for f in files} == contents
    path.write_text(path.read_text() + "<!-- edited -->")
    generated_scene(family, 5)
    assert path.read_bytes() == contents[path]       # an edited file is put back


def test_generation_finds_room_for_everything_over_many_seeds():
    for seed in range(12):
        for family in ("workspace", "bins"):
            text = FAMILIES[family](100 + seed).xml
            count = len(text.split('name="nerfbot_objects" data="')[1].split('"')[0].split())
            low, high = (workspace.PROP_COUNT if family == "workspace" else bins.PROP_COUNT)
            assert low <= count <= high, (family, seed, count)


# -- sizes and layout per family ------------------------------------------------------------------

@pytest.mark.parametrize("seed", SEEDS)
def test_workspace_and_bins_objects_have_their_stated_sizes(seed):
    for family, module in (("workspace", workspace), ("bins", bins)):
        model, data = _forward(f"{family}:{seed}")
        objects = declared_objects(model)
        assert module.PROP_COUNT[0] <= len(objects) <= module.PROP_COUNT[1]
        lo, hi = module.PROP_SIZE
        for name in objects:
            assert lo - 1e-6 <= _largest(model, name) <= hi + 1e-6, (family, name)
    model, data = _forward(f"bins:{seed}")
    floor = model.geom("bin_floor").id
    half = model.geom_size[floor, :2] - bins.BIN_WALL
    for name in declared_objects(model):             # every part lies in the tray
        assert (np.abs(data.geom_xpos[model.geom(name).id][:2]) < half).all(), name


@pytest.mark.parametrize("seed", SEEDS)
def test_yard_has_near_objects_and_far_content(seed):
    model, data = _forward(f"yard:{seed}")
    objects = declared_objects(model)
    assert yard.NEAR_COUNT[0] <= len(objects) <= yard.NEAR_COUNT[1]
    for name in objects:
        assert yard.NEAR_SIZE[0] - 1e-6 <= _largest(model, name) <= yard.NEAR_SIZE[1] + 1e-6
        assert np.hypot(*data.geom_xpos[model.geom(name).id][:2]) < 3.0
    far = [model.geom(g).name for g in range(model.ngeom)
           if model.geom(g).name.startswith(("building", "hill", "tree"))]
    assert any(n.startswith("building") for n in far) and any(n.startswith("hill") for n in far)
    for name in far:
        distance = np.hypot(*data.geom_xpos[model.geom(name).id][:2])
        assert 20.0 <= distance <= 100.0, name
    bounds = np.asarray(scene_manifest(model, data, "yard", "test")["bounds"])
    assert (bounds[1] - bounds[0])[:2].min() > 200.0   # unbounded: the ground and hills


@pytest.mark.parametrize("seed", SEEDS)
def test_room_is_closed_has_a_narrow_passage_and_declares_its_obstacles(seed):
    model, data = _forward(f"room:{seed}")
    width, depth, height = custom_numeric(model, "nerfbot_room_size")
    assert 4.0 <= width <= 8.0 and 4.0 <= depth <= 8.0 and 2.4 <= height <= 3.0
    manifest = scene_manifest(model, data, "room", "test")
    expected = [[-width / 2, -depth / 2, 0.0], [width / 2, depth / 2, height]]
    assert np.allclose(manifest["bounds"], expected, atol=0.03)    # the bounds are the room
    x0, y0, x1, y1 = custom_numeric(model, "nerfbot_passage")
    assert 0.5 <= math.hypot(x1 - x0, y1 - y0) <= 0.7
    obstacles = manifest["obstacles"]
    pieces = {n.split("_")[0] for n in obstacles}
    assert "partition" in pieces and len(pieces) >= 3          # and furniture of two kinds
    for name, (lo, hi) in obstacles.items():
        # the room size is stored in float32 custom numerics: compare to 1 mm
        assert lo[0] >= -width / 2 - 1e-3 and hi[0] <= width / 2 + 1e-3, name
        assert lo[1] >= -depth / 2 - 1e-3 and hi[1] <= depth / 2 + 1e-3, name
    # the doorway is free: its midpoint is outside every obstacle footprint
    mx, my = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    assert all(not (lo[0] < mx < hi[0] and lo[1] < my < hi[1]) for lo, hi in obstacles.values())


# -- the inside rig -----------------------------------------------------------------------------

def _pitch_and_roll(pose: np.ndarray) -> tuple[float, float]:
    forward = -pose[:3, 2]
    return math.degrees(math.asin(forward[2])), float(pose[2, 0])   # right vector's z: roll


def test_inside_rig_poses_stay_in_the_free_region_seeded_and_test_differs():
    box = (0.0, 0.0, 1.0, 1.0)
    cfg = RigConfig(kind="inside", count=60, region=(-2.0, -1.0, 3.0, 2.0),
                    height_range=(0.4, 1.6), pitch_range=(-20.0, 10.0), clearance=0.3,
                    keep_out=(box,), seed=3)
    poses = rig_poses(cfg)
    assert len(poses) == 60
    for pose in poses:
        x, y, z = pose[:3, 3]
        assert -1.7 <= x <= 2.7 and -0.7 <= y <= 1.7 and 0.4 <= z <= 1.6
        dx, dy = max(box[0] - x, 0, x - box[2]), max(box[1] - y, 0, y - box[3])
        assert math.hypot(dx, dy) >= 0.3
        pitch, roll = _pitch_and_roll(pose)
        assert -20.0 - 1e-6 <= pitch <= 10.0 + 1e-6 and abs(roll) < 1e-9
    yaws = [math.atan2(-p[1, 2], -p[0, 2]) for p in poses]
    assert np.ptp(yaws) > 4.0                       # all around
    again = rig_poses(cfg)
    assert all(np.array_equal(a, b) for a, b in zip(poses, again))
    test = rig_poses(make_test_rig(cfg, 10))
    other_seed = rig_poses(dataclasses.replace(cfg, seed=4))
    train_xy = np.array([p[:2, 3] for p in poses])
    for pose in test:
        assert np.linalg.norm(train_xy - pose[:2, 3], axis=1).min() > 1e-6
    assert not np.allclose(poses[0], other_seed[0])
    with pytest.raises(ValueError, match="region"):
        RigConfig(kind="inside", count=3)
    with pytest.raises(ValueError, match="free floor"):
        rig_poses(RigConfig(kind="inside", count=3, region=(0, 0, 1, 1),
                            keep_out=((-1, -1, 2, 2),)))


@pytest.mark.parametrize("seed", SEEDS)
def test_room_default_rig_is_inside_and_its_cameras_stand_on_free_floor(seed):
    scene = f"room:{seed}"
    rig = default_rig(scene, count=60, width=SIZE, height=SIZE)
    assert rig.kind == "inside" and rig.fov_deg == room.CAMERA_FOVY
    model, data = _forward(scene)
    width, depth, _ = custom_numeric(model, "nerfbot_room_size")
    obstacles = declared_obstacles(model, data)
    assert len(rig.keep_out) == len(obstacles) > 0
    clearance = room.CAMERA_CLEARANCE
    for split_rig in (rig, make_test_rig(rig, 10)):
        for pose in rig_poses(split_rig):
            x, y, z = pose[:3, 3]
            assert abs(x) <= width / 2 - clearance + 1e-9 and abs(y) <= depth / 2 - clearance + 1e-9
            assert room.CAMERA_HEIGHTS[0] <= z <= room.CAMERA_HEIGHTS[1]
            for name, (lo, hi) in obstacles.items():
                dx, dy = max(lo[0] - x, 0, x - hi[0]), max(lo[1] - y, 0, y - hi[1])
                assert math.hypot(dx, dy) >= clearance - 1e-9, name


def test_capture_command_line_takes_the_scenes_default_rig(tmp_path):
    parser = add_capture_arguments(argparse.ArgumentParser())
    args = parser.parse_args(["--scene", "room:3", "--out", str(tmp_path / "x"),
                              "--views", "6", "--test-views", "2", "--size", "24"])
    train, test = rigs_from_args(args)
    assert train.kind == test.kind == "inside" and test.count == 2 and train.width == 24
    args = parser.parse_args(["--scene", "room:3", "--out", str(tmp_path / "x"),
                              "--rig", "hemisphere"])
    assert rigs_from_args(args)[0].kind == "hemisphere"
    args = parser.parse_args(["--scene", "workspace:2", "--out", str(tmp_path / "x")])
    train, _ = rigs_from_args(args)
    assert train.kind == "hemisphere" and train.elevation_range == workspace.RIG_ELEVATION
    assert train.radius == workspace.RIG_RADIUS


# -- captures -----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """family -> loaded dataset of a 32x32 capture of seed 1: 4 train + 1 test views of the
    scene's default rig."""
    out = {}
    for family, fmt in FORMATS.items():
        scene = f"{family}:1"
        rig = default_rig(scene, count=4, width=SIZE, height=SIZE, seed=2)
        folder = tmp_path_factory.mktemp(family) / "data"
        capture(scene, rig, make_test_rig(rig, 1), folder, fmt=fmt, progress=False)
        out[family] = load_dataset(folder)
    return out


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_captures_a_dataset_that_loads(captures, family):
    ds = captures[family]
    assert ds.format == FORMATS[family] and len(ds) == 5
    assert len(ds.indices("train")) == 4 and len(ds.indices("test")) == 1
    assert ds.aabb_source == "manifest" and ds.manifest["name"] == f"{family}-1"
    ids = {int(g) for g, n in ds.manifest["geoms"].items() if n in ds.manifest["objects"]}
    seen = set()
    for seg, depth in zip(ds.segmentations, ds.depths):
        seen |= set(np.unique(seg).tolist()) & ids
        assert np.isfinite(depth[seg >= 0]).all() and np.isinf(depth[seg < 0]).all()
    assert seen, "no declared object in any view"


def test_workspace_fills_every_frame(captures):
    for depth in captures["workspace"].depths:
        assert np.isfinite(depth).mean() > 0.8


def test_bins_cameras_are_close_and_see_the_tray(captures):
    ds = captures["bins"]
    target = np.asarray(custom_numeric(load_model("bins:1"), "nerfbot_rig_target"))
    distance = np.linalg.norm(ds.c2w[:, :3, 3] - target, axis=1)
    assert (distance >= 0.3).all() and (distance <= 0.6).all()
    for depth in ds.depths:
        assert np.isfinite(depth).mean() > 0.8


def test_room_frames_show_no_sky_and_cameras_stand_in_the_room(captures):
    ds = captures["room"]
    for depth in ds.depths:
        assert np.isfinite(depth).all()
    lo, hi = np.asarray(ds.manifest["bounds"])
    positions = ds.c2w[:, :3, 3]
    assert ((positions > lo) & (positions < hi)).all()
    for x, y, _ in positions:
        for name, (olo, ohi) in ds.manifest["obstacles"].items():
            assert not (olo[0] <= x <= ohi[0] and olo[1] <= y <= ohi[1]), name


def test_yard_frames_see_far_content_and_sky(captures):
    depths = np.stack(captures["yard"].depths)
    assert (depths[np.isfinite(depths)] > 20.0).any()
    assert np.isinf(depths).any()
    assert (depths < 10.0).any()                     # and the near objects


@pytest.mark.parametrize("family", FAMILIES)
def test_only_the_yard_loads_as_unbounded(captures, family):
    """The reader models the yard's space around its cameras (content 20-100 m away); the
    room from inside and the table scenes keep their manifest's box."""
    ds = captures[family]
    assert ds.unbounded == (family == "yard"), ds.extras["space"]
    if family == "yard":
        positions = ds.c2w[:, :3, 3]
        assert ((positions > ds.aabb[0]) & (positions < ds.aabb[1])).all()
        assert (ds.aabb[1] - ds.aabb[0]).max() < 20.0
    else:
        assert ds.extras["space"] == "bounds from the manifest: a box"


# -- room_glass -----------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", (0, 3))
def test_room_glass_is_the_room_with_a_glass_partition(seed):
    """room_glass:K keeps room:K's layout; its partition panels are transparent (manifest) and
    an opaque post stands at each jamb without narrowing the doorway."""
    plain, plain_data = _forward(f"room:{seed}")
    glass, glass_data = _forward(f"room_glass:{seed}")
    plain_obstacles = scene_manifest(plain, plain_data, "room", "test")["obstacles"]
    manifest = scene_manifest(glass, glass_data, "room_glass", "test")
    for name, box in plain_obstacles.items():                  # the same layout
        np.testing.assert_allclose(manifest["obstacles"][name], box, atol=1e-6)
    panels = sorted(n for n in plain_obstacles if n.startswith("partition"))
    assert sorted(manifest["transparent_geoms"]) == panels
    assert {"post_a", "post_b"} <= set(manifest["obstacles"])
    x0, y0, x1, y1 = custom_numeric(glass, "nerfbot_passage")
    assert np.allclose([x0, y0, x1, y1], custom_numeric(plain, "nerfbot_passage"))
    along = 1 if abs(y1 - y0) > abs(x1 - x0) else 0
    (a_lo, a_hi), (b_lo, b_hi) = (manifest["obstacles"][f"post_{s}"] for s in "ab")
    jamb_a, jamb_b = sorted([(x0, y0)[along], (x1, y1)[along]])
    assert a_hi[along] == pytest.approx(jamb_a, abs=1e-4)       # posts end at the jambs
    assert b_lo[along] == pytest.approx(jamb_b, abs=1e-4)


def test_room_glass_depth_sensor_sees_through_the_partition(tmp_path):
    """A camera facing a glass panel from 1.5 m: the true depth stops at the glass, the
    simulated depth sensor reads what lies behind it."""
    model, data = _forward("room_glass:0")
    x0, y0, x1, y1 = custom_numeric(model, "nerfbot_passage")
    jambs = np.array([[x0, y0], [x1, y1]])
    along = (jambs[1] - jambs[0]) / np.linalg.norm(jambs[1] - jambs[0])
    across = np.array([-along[1], along[0]])
    lo, hi = np.asarray(scene_manifest(model, data, "room_glass", "test")["obstacles"]
                        ["partition_a_0"])
    panel = 0.5 * (lo[:2] + hi[:2])                              # a panel's centre
    height = 0.5 * hi[2]
    # look at the panel from whichever side has room for the camera
    room_w, room_d, _ = custom_numeric(model, "nerfbot_room_size")
    eye = panel + 1.5 * across
    if abs(eye[0]) > room_w / 2 - 0.2 or abs(eye[1]) > room_d / 2 - 0.2:
        eye = panel - 1.5 * across
    poses = tmp_path / "poses.json"
    poses.write_text(json.dumps([{"eye": [*eye, height], "target": [*panel, height]}]))
    rig = RigConfig(kind="explicit", count=0, width=SIZE, height=SIZE, fov_deg=30.0,
                    poses_file=poses)
    folder = capture("room_glass:0", rig, None, tmp_path / "data", progress=False,
                     sensor=DepthSensorModel(dropout=0.0, edge_jump=0.0))
    ds = load_dataset(folder)
    centre = (slice(SIZE // 2 - 4, SIZE // 2 + 4),) * 2
    depth, sensed = ds.depths[0][centre], ds.sensor_depths[0][centre]
    assert np.allclose(depth, 1.5 - room.PARTITION_THICKNESS / 2, atol=0.02)
    assert (sensed > depth + 0.5).all()                         # the wall beyond the glass
