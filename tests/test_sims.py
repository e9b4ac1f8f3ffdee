"""sims: scenes, rigs, capture camera, manifest, dataset writers, on real MuJoCo renders.

Renders are tiny (32x32, a handful of views); one capture is shared by most tests.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
from dataclasses import replace

import cv2
import mujoco
import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from nerfbot.data import load_dataset
from nerfbot.ops.cameras import check_pose, look_at
from sims import capture as capture_mod
from sims.camera import CaptureCamera, Frame
from sims.capture import capture
from sims.cli import add_capture_arguments, run_capture
from sims.manifest import scene_manifest
from sims.rigs import (RigConfig, make_test_rig, orbit_poses, read_pose_file, rig_poses,
                       scene_rig_defaults)
from sims.scene import load_capture_model, load_model

SIZE = 32
TABLE_TOP_Z = 0.75
OBJECTS = ("red_crate", "chrome_sphere", "blue_can", "green_capsule", "yellow_ellipsoid",
           "purple_gem", "teal_book")


def small_rig(**kw) -> RigConfig:
    base = dict(count=6, width=SIZE, height=SIZE, seed=3)
    base.update(kw)
    return RigConfig(**base)


@pytest.fixture(scope="module")
def tabletop():
    """(model, data) of the tabletop with the capture camera, after mj_forward."""
    return load_capture_model("tabletop")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A 32x32 nerfstudio capture of the tabletop: 6 train + 2 test views."""
    rig = small_rig()
    out = capture("tabletop", rig, make_test_rig(rig, 2),
                  tmp_path_factory.mktemp("cap") / "tabletop", progress=False)
    meta = json.loads((out / "transforms.json").read_text())
    return out, meta, rig


def geom_id(model, name: str) -> int:
    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
    assert gid >= 0, name
    return gid


def project(meta: dict, c2w: np.ndarray, point) -> tuple[float, float, float]:
    """(u, v, z-depth) of a world point through a written pose and the global intrinsics."""
    w2c = np.linalg.inv(np.asarray(c2w))
    x, y, z = w2c[:3, :3] @ np.asarray(point, dtype=np.float64) + w2c[:3, 3]
    return meta["cx"] + meta["fl_x"] * x / -z, meta["cy"] - meta["fl_y"] * y / -z, -z


# ----------------------------------------------------------------------------- scene

def test_tabletop_has_objects_lights_sky_and_no_floor():
    model = load_model("tabletop")
    names = {model.geom(i).name for i in range(model.ngeom)}
    assert set(OBJECTS) <= names and "table_top" in names
    assert len([n for n in names if not n.startswith("table")]) >= 6
    assert len({int(model.geom_type[geom_id(model, n)]) for n in OBJECTS}) >= 6  # shapes
    assert model.nlight >= 2 and model.light_castshadow.any()
    assert not (model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE).any()
    assert (model.tex_type == mujoco.mjtTexture.mjTEXTURE_SKYBOX).any()
    top = model.geom_size[geom_id(model, "table_top")]
    assert np.allclose(2 * top[:2], [1.2, 0.8])
    assert (model.mat_specular > 0.5).any() and (model.mat_reflectance > 0).any()


def test_missing_and_malformed_mjcf_raise_naming_the_file(tmp_path):
    missing = tmp_path / "nope.xml"
    with pytest.raises(FileNotFoundError, match="nope.xml"):
        load_model(missing)
    with pytest.raises(FileNotFoundError, match="built-in"):
        load_model("no_such_scene")
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><geom type='box' size='1 1'/></worldbody>")
    with pytest.raises(ValueError, match="broken.xml") as err:
        load_model(bad)
    assert "XML" in str(err.value)  # MuJoCo's own message is kept
    invalid = tmp_path / "invalid.xml"
    invalid.write_text("<mujoco><worldbody><geom type='box' size='-1 1 1'/></worldbody></mujoco>")
    with pytest.raises(ValueError, match="invalid.xml"):
        capture(invalid, small_rig(count=1), None, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- rigs

def test_hemisphere_rig_is_seeded_in_range_and_looks_at_target():
    rig = RigConfig(count=40, elevation_range=(15, 70), seed=7)
    poses = rig_poses(rig)
    assert len(poses) == 40
    assert all(np.allclose(a, b) for a, b in zip(poses, rig_poses(rig)))
    test = rig_poses(make_test_rig(rig, 10))
    assert not any(np.allclose(t, p) for t in test for p in poses)
    target = np.array(rig.target)
    for c2w in poses + test:
        check_pose(c2w, "rig")
        offset = c2w[:3, 3] - target
        assert np.linalg.norm(offset) == pytest.approx(rig.radius)
        elevation = math.degrees(math.asin(offset[2] / rig.radius))
        assert 15 - 1e-9 <= elevation <= 70 + 1e-9
        assert np.allclose(-c2w[:3, 2], -offset / rig.radius)  # looks along -z at the target
        assert abs(c2w[2, 0]) < 1e-12  # no roll: camera x stays horizontal


def test_orbit_test_views_sit_between_training_views():
    rig = RigConfig(kind="orbit", count=8, elevation=30.0)
    az = [math.degrees(math.atan2(p[1, 3], p[0, 3])) % 360 for p in orbit_poses(rig)]
    az_test = [math.degrees(math.atan2(p[1, 3], p[0, 3])) % 360
               for p in orbit_poses(make_test_rig(rig, 4))]
    assert np.allclose(az, np.arange(8) * 45.0)
    assert np.allclose(az_test, 22.5 + np.arange(4) * 90.0)


def test_explicit_pose_file_layouts(tmp_path):
    eye_target = [{"eye": [3, 0, 2], "target": [0, 0, 0.75]}, {"eye": [0, 3, 2], "target": [0, 0, 0.75]}]
    flat = tmp_path / "flat.json"
    flat.write_text(json.dumps(eye_target + [look_at([-3, 0, 2], [0, 0, 0.75]).tolist()]))
    rig = RigConfig(kind="explicit", count=2, poses_file=flat)
    train, test = rig_poses(rig), rig_poses(make_test_rig(rig, 0))
    assert len(train) == 2 and len(test) == 1
    assert np.allclose(train[0], look_at([3, 0, 2], [0, 0, 0.75]))
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": eye_target, "test": eye_target[:1]}))
    assert len(read_pose_file(split)["test"]) == 1
    with pytest.raises(ValueError, match="only 2 available"):
        rig_poses(RigConfig(kind="explicit", count=5, poses_file=split))


def test_tabletop_rig_defaults_come_from_the_scene():
    d = scene_rig_defaults(load_model("tabletop"))
    assert d["radius"] == pytest.approx(4.0)
    assert d["target"] == pytest.approx((0.0, 0.0, TABLE_TOP_Z))
    assert 25.0 <= d["fov_deg"] <= 30.0


# ----------------------------------------------------------------------------- camera

def test_rendered_camera_pose_equals_requested_pose(tabletop):
    model, data = tabletop
    rot, _ = cv2.Rodrigues(np.array([0.3, -1.1, 2.0]))  # an arbitrary pose with roll
    rolled = np.eye(4)
    rolled[:3, :3], rolled[:3, 3] = rot, [0.4, -2.5, 1.9]
    poses = rig_poses(small_rig(count=4)) + [rolled, look_at([0, 0, 5], [0, 0, 0.75])]
    with CaptureCamera(model, data, SIZE, SIZE, 30.0) as cam:
        for c2w in poses:
            got = cam.place(c2w)
            assert np.abs(got - c2w).max() < 1e-6
            assert np.abs(data.cam_xpos[cam.cam_id] - c2w[:3, 3]).max() < 1e-6
            assert np.abs(data.cam_xmat[cam.cam_id].reshape(3, 3) - c2w[:3, :3]).max() < 1e-6
            assert model.cam_fovy[cam.cam_id] == 30.0
        with pytest.raises(ValueError, match="not rigid"):
            cam.place(np.diag([2.0, 1.0, 1.0, 1.0]), "scaled pose")


# ----------------------------------------------------------------------------- capture

def test_capture_writes_nerfstudio_transforms_and_files(dataset):
    out, meta, rig = dataset
    assert meta["camera_model"] == "OPENCV" and (meta["w"], meta["h"]) == (SIZE, SIZE)
    f = 0.5 * SIZE / math.tan(math.radians(rig.fov_deg) / 2)
    assert meta["fl_x"] == pytest.approx(f) and meta["fl_y"] == pytest.approx(f)
    assert (meta["cx"], meta["cy"]) == (SIZE / 2, SIZE / 2)
    frames = meta["frames"]
    assert len(frames) == 8 and [fr["file_path"] for fr in frames][:1] == ["images/frame_00000.png"]
    assert meta["train_filenames"] == [fr["file_path"] for fr in frames[:6]]
    assert meta["test_filenames"] == [fr["file_path"] for fr in frames[6:]]
    requested = rig_poses(rig) + rig_poses(make_test_rig(rig, 2))
    for fr, c2w in zip(frames, requested):
        assert np.abs(np.array(fr["transform_matrix"]) - c2w).max() < 1e-6
        img = cv2.imread(str(out / fr["file_path"]), cv2.IMREAD_UNCHANGED)
        assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
        depth = np.load(out / fr["nerfbot_depth_file_path"])
        seg = np.load(out / fr["segmentation_path"])
        assert depth.shape == seg.shape == (SIZE, SIZE)
        assert depth.dtype == np.float32 and seg.dtype == np.int32
    assert not list(out.parent.glob(".*"))  # no temporary folders left behind


def test_depth_is_finite_on_the_table_and_inf_on_sky(dataset, tabletop):
    out, meta, rig = dataset
    top = geom_id(tabletop[0], "table_top")
    sky_pixels = 0
    for fr in meta["frames"]:
        depth = np.load(out / fr["nerfbot_depth_file_path"])
        seg = np.load(out / fr["segmentation_path"])
        assert (seg == top).sum() > 20
        table = depth[seg == top]
        assert np.isfinite(table).all()
        assert (table > rig.radius - 1.0).all() and (table < rig.radius + 1.0).all()
        assert np.isinf(depth[seg == -1]).all() and (depth[seg >= 0] > 0).all()
        assert np.isfinite(depth[seg >= 0]).all()
        sky_pixels += int((seg == -1).sum())
    assert sky_pixels > 0


def test_nerfstudio_reads_the_depth_in_metres(dataset):
    """nerfstudio's own reading rules applied to the written files: ``transforms.json`` has
    the intrinsics and every frame a ``depth_file_path`` (nerfstudio takes depth for all frames
    or none), which it reads as ``cv2.imread(path, IMREAD_ANYDEPTH) * depth_unit_scale_factor``
    (1e-3 by default; no such key is written, so its default applies). That gives the z-depth in
    metres to half a millimetre, and 0 (nerfstudio's "no depth") where a ray hits nothing. The
    exact float depth stays beside it for nerfbot."""
    out, meta, _ = dataset
    assert "depth_unit_scale_factor" not in meta
    assert all(k in meta for k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_model"))
    assert all("depth_file_path" in fr for fr in meta["frames"])
    names = {fr["file_path"] for fr in meta["frames"]}
    for split in ("train", "val", "test"):
        assert set(meta[f"{split}_filenames"]) <= names
    for fr in meta["frames"]:
        raw = cv2.imread(str(out / fr["depth_file_path"]), cv2.IMREAD_ANYDEPTH)
        assert raw is not None and raw.dtype == np.uint16
        read = raw.astype(np.float64) * 1e-3
        exact = np.load(out / fr["nerfbot_depth_file_path"]).astype(np.float64)
        hit = np.isfinite(exact)
        assert hit.any() and (~hit).any()
        assert np.abs(read[hit] - exact[hit]).max() <= 0.5e-3 + 1e-9
        assert (read[~hit] == 0).all()


def test_nerfbot_reads_the_exact_depth_and_a_millimetre_png_alone(dataset, tmp_path):
    """nerfbot loads the exact depth (``inf`` kept where nothing is hit); a copy whose frames name
    only the 16-bit PNG reads it in millimetres (unknown where 0)."""
    out, meta, _ = dataset
    exact = load_dataset(out)
    assert np.isinf(exact.depths[0]).any()
    alone = tmp_path / "png_only"
    shutil.copytree(out, alone)
    doc = json.loads((alone / "transforms.json").read_text())
    for fr in doc["frames"]:
        fr.pop("nerfbot_depth_file_path")
    (alone / "transforms.json").write_text(json.dumps(doc))
    png = load_dataset(alone)
    hit = np.isfinite(exact.depths[0])
    assert np.abs(png.depths[0][hit] - exact.depths[0][hit]).max() <= 0.5e-3 + 1e-6
    assert np.isnan(png.depths[0][~hit]).all()


@pytest.fixture(scope="module")
def closeups(tmp_path_factory, tabletop):
    """A 32x32 capture through an explicit rig: one close view (1.2 m) of each object."""
    model, data = tabletop
    views = []
    for i, name in enumerate(OBJECTS):
        centre = data.geom_xpos[geom_id(model, name)]
        a, e = math.radians(10 + i * 360 / len(OBJECTS)), math.radians(50)
        eye = centre + 1.2 * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a),
                                       math.sin(e)])
        views.append({"eye": eye.tolist(), "target": (centre + [0.003, 0.002, 0]).tolist()})
    root = tmp_path_factory.mktemp("closeups")
    (root / "poses.json").write_text(json.dumps(views))
    rig = small_rig(kind="explicit", count=0, poses_file=root / "poses.json")
    out = capture("tabletop", rig, None, root / "ds", progress=False)
    return out, json.loads((out / "transforms.json").read_text())


def test_projected_geom_centres_land_on_their_geom(closeups, tabletop):
    out, meta = closeups
    model, data = tabletop
    hits = total = 0
    for k, fr in enumerate(meta["frames"]):
        depth = np.load(out / fr["nerfbot_depth_file_path"])
        seg = np.load(out / fr["segmentation_path"])
        for name in OBJECTS:
            gid = geom_id(model, name)
            u, v, z = project(meta, fr["transform_matrix"], data.geom_xpos[gid])
            if not (0 <= u < SIZE and 0 <= v < SIZE):
                continue
            total += 1
            row, col = int(v), int(u)
            if name == OBJECTS[k]:  # the object this view looks at
                assert abs(u - SIZE / 2) < 1 and abs(v - SIZE / 2) < 1
                assert seg[row, col] == gid, name
            if seg[row, col] == gid:
                hits += 1
            else:  # only an occluder in front may hide the centre
                assert depth[row, col] < z, (fr["file_path"], name)
    assert total >= len(OBJECTS) and hits >= 0.75 * total


def test_depth_back_projects_onto_the_sphere_surface(closeups, tabletop):
    out, meta = closeups
    model, data = tabletop
    gid = geom_id(model, "chrome_sphere")
    centre, radius = data.geom_xpos[gid], model.geom_size[gid, 0]
    checked = 0
    for fr in meta["frames"]:
        depth = np.load(out / fr["nerfbot_depth_file_path"])
        seg = np.load(out / fr["segmentation_path"])
        inner = cv2.erode((seg == gid).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        rows, cols = np.nonzero(inner)
        c2w = np.asarray(fr["transform_matrix"])
        for r, c in zip(rows, cols):
            z = float(depth[r, c])
            x_cam = np.array([(c + 0.5 - meta["cx"]) / meta["fl_x"] * z,
                              -(r + 0.5 - meta["cy"]) / meta["fl_y"] * z, -z])
            world = c2w[:3, :3] @ x_cam + c2w[:3, 3]
            assert abs(np.linalg.norm(world - centre) - radius) < 0.005
            checked += 1
    assert checked >= 5


def test_manifest_bounds_contain_geoms_and_table(dataset, tabletop):
    _, meta, _ = dataset
    model, data = tabletop
    scene = meta["scene"]
    lo, hi = np.array(scene["bounds"])
    for gid in range(model.ngeom):
        assert (lo - 1e-9 <= data.geom_xpos[gid]).all() and (data.geom_xpos[gid] <= hi + 1e-9).all()
    assert np.allclose(lo[:2], [-0.6, -0.4]) and np.allclose(hi[:2], [0.6, 0.4])
    assert lo[2] == pytest.approx(0.0) and TABLE_TOP_Z < hi[2] < 1.0
    assert scene["name"] == "tabletop" and scene["source"] == "builtin:tabletop"
    assert scene["transparent_geoms"] == [] and scene["moving_joints"] == []
    assert scene["time_varying"] is False and scene["specular"] is True
    assert scene["geoms"][str(geom_id(model, "chrome_sphere"))] == "chrome_sphere"
    # strongly view-dependent: the metal legs, chrome, glazed can and gem; not the table top,
    # whose wood has a faint reflectance (0.06) and a low specular (0.25)
    assert sorted(scene["shiny_geoms"]) == sorted(
        ["table_leg_fl", "table_leg_fr", "table_leg_bl", "table_leg_br", "chrome_sphere",
         "blue_can", "purple_gem"])
    from nerfbot.data import load_dataset

    ds = load_dataset(dataset[0])
    shiny = [geom_id(model, n) for n in scene["shiny_geoms"]]
    segs = [ds.segmentations[i] for i in ds.indices("train")]
    share = sum(int(np.isin(s, shiny).sum()) for s in segs) / sum(s.size for s in segs)
    assert share > 0 and scene["shiny_pixel_fraction"] == pytest.approx(share, abs=1e-12)


def test_manifest_transparency_groups_and_planes(tmp_path):
    xml = """<mujoco><asset><material name="glass" rgba="0.8 0.9 1 0.3" specular="0.1"/>
      <material name="matte" specular="0.1"/></asset>
      <worldbody><light pos="0 0 3"/>
        <geom name="floor" type="plane" size="0 0 1" material="matte"/>
        <geom name="cup" type="cylinder" size="0.05 0.1" pos="0.5 0 0.1" material="glass"/>
        <geom name="tint" type="sphere" size="0.1" pos="-1 0 0.1" rgba="1 0 0 0.5" material="matte"/>
        <geom name="block" type="box" size="0.1 0.2 0.3" pos="0 0 0.3" euler="0 0 0.5" material="matte"/>
        <geom name="hidden" type="sphere" size="0.1" pos="9 9 9" group="4" material="matte"/>
        <geom name="invisible" type="sphere" size="0.1" pos="-9 0 0" rgba="1 1 1 0"/>
      </worldbody></mujoco>"""
    path = tmp_path / "glass.xml"
    path.write_text(xml)
    model, data = load_capture_model(path)
    m = scene_manifest(model, data, "glass", str(path))
    assert m["transparent_geoms"] == ["cup", "tint"]
    assert m["specular"] is False and m["shiny_geoms"] == []
    lo, hi = np.array(m["bounds"])
    assert np.allclose(lo[0], -1.1) and np.allclose(hi[0], 0.55)  # no plane, no hidden geoms
    assert lo[2] == pytest.approx(0.0) and hi[2] == pytest.approx(0.6)
    json.dumps(m)


def test_blender_format_and_cli(tmp_path, capsys):
    parser = add_capture_arguments(argparse.ArgumentParser())
    args = parser.parse_args(["--out", str(tmp_path / "bl"), "--views", "2", "--test-views", "1",
                              "--size", "40", "32", "--rig", "orbit", "--format", "blender",
                              "--no-progress"])
    out = run_capture(args)
    assert "3 frames" in capsys.readouterr().out
    train = json.loads((out / "transforms_train.json").read_text())
    test = json.loads((out / "transforms_test.json").read_text())
    fy = 0.5 * 32 / math.tan(math.radians(30.0) / 2)  # the tabletop's fovy
    assert train["camera_angle_x"] == pytest.approx(2 * math.atan(20 / fy))
    assert len(train["frames"]) == 2 and len(test["frames"]) == 1
    for doc, split in ((train, "train"), (test, "test")):
        assert doc["scene"]["name"] == "tabletop"
        for i, fr in enumerate(doc["frames"]):
            assert fr["file_path"] == f"./{split}/r_{i}"
            img = cv2.imread(str(out / (fr["file_path"] + ".png")))
            assert img.shape == (32, 40, 3)
            assert np.load(out / fr["depth_file_path"]).shape == (32, 40)
    args = parser.parse_args(["--out", str(tmp_path / "bl"), "--views", "1", "--test-views", "0",
                              "--size", "32", "--format", "blender", "--no-manifest",
                              "--no-progress", "--overwrite"])
    run_capture(args)  # replaces the previous dataset
    assert "scene" not in json.loads((out / "transforms_train.json").read_text())
    assert not (out / "transforms_test.json").exists()


def test_capture_is_atomic(tmp_path, monkeypatch):
    bad = tmp_path / "poses.json"
    good = look_at([3, 0, 2], [0, 0, 0.75]).tolist()
    bad.write_text(json.dumps([good, np.diag([1.0, 1.0, 3.0, 1.0]).tolist()]))
    out = tmp_path / "ds"
    with pytest.raises(ValueError, match="poses.json"):
        capture("tabletop", small_rig(kind="explicit", count=0, poses_file=bad), None, out,
                progress=False)
    assert not out.exists()

    # An existing dataset survives a capture that fails midway, and no partial folder remains.
    capture("tabletop", small_rig(count=1), None, out, progress=False)
    before = (out / "transforms.json").read_text()
    real_render, calls = CaptureCamera.render, []

    def failing_render(self, c2w, where="pose") -> Frame:
        calls.append(where)
        if len(calls) == 2:
            raise RuntimeError("simulated crash")
        return real_render(self, c2w, where)

    monkeypatch.setattr(capture_mod.CaptureCamera, "render", failing_render)
    with pytest.raises(RuntimeError, match="simulated crash"):
        capture("tabletop", small_rig(count=3), None, out, progress=False, overwrite=True)
    assert (out / "transforms.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "poses.json"]

    precious = tmp_path / "notes"
    precious.mkdir()
    (precious / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not made by nerfbot"):
        capture("tabletop", small_rig(count=1), None, precious, progress=False)
    assert (precious / "keep.txt").read_text() == "mine"


def test_renderer_failure_names_backend(monkeypatch, tabletop):
    from sims import gl

    def broken(*a, **k):
        raise mujoco.FatalError("gladLoadGL error")

    monkeypatch.setattr(mujoco, "Renderer", broken)
    with pytest.raises(RuntimeError, match="MUJOCO_GL=.*osmesa"):
        gl.make_renderer(tabletop[0], SIZE, SIZE)


def test_size_override_and_mismatched_rigs(tabletop, tmp_path):
    rig = small_rig(count=1)
    with pytest.raises(ValueError, match="share image size"):
        capture("tabletop", rig, replace(rig, width=64), tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()
