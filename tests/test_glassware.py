"""The glassware scene family and the simulated depth sensor, with real MuJoCo rendering."""

from __future__ import annotations

import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from nerfbot.data import load_dataset
from sims.capture import capture
from sims.glassware import object_names, vessel_mesh, vessels
from sims.rigs import default_rig, make_test_rig
from sims.scene import load_model, resolve_scene
from sims.sensor import DepthSensorModel, valid_fraction


def test_vessels_are_watertight_meshes_of_five_shapes():
    shapes = vessels()
    assert len({v.name for v in shapes}) == 5
    for v in shapes:
        mesh = vessel_mesh(v)
        assert mesh.is_watertight, v.name
        assert mesh.volume > 0, v.name
        lo, hi = mesh.bounds
        assert abs(lo[2]) < 1e-9 and 0.05 < hi[2] < 0.25, v.name     # stands on z = 0
        assert 2 * v.radius <= 0.11, v.name                             # fits the gripper


def test_placement_is_seeded_and_objects_do_not_overlap(tmp_path, monkeypatch):
    import mujoco

    monkeypatch.setenv("NERFBOT_CACHE", str(tmp_path))
    assert resolve_scene("glassware:3").read_text() == resolve_scene("glassware:3").read_text()
    assert resolve_scene("glassware:3").read_text() != resolve_scene("glassware:4").read_text()
    assert resolve_scene("glassware") == resolve_scene("glassware:0")
    with pytest.raises(ValueError, match="integer"):
        resolve_scene("glassware:x")
    model = load_model("glassware:3")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    glass, opaque = object_names()
    xy = np.array([data.body(n).xpos[:2] for n in glass + opaque])
    gaps = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(xy))
    assert gaps.min() > 0.15                      # room for the fingers between objects
    for _ in range(250):                          # objects rest on the table: 0.5 s, no drift
        mujoco.mj_step(model, data)
    xy_after = np.array([data.body(n).xpos[:2] for n in glass + opaque])
    assert np.abs(xy_after - xy).max() < 1e-3


def test_glazed_scene_is_the_glassware_scene_without_the_glass(tmp_path, monkeypatch):
    import mujoco

    from nerfbot.train.auto import choose_from_manifest
    from sims.manifest import scene_manifest

    monkeypatch.setenv("NERFBOT_CACHE", str(tmp_path))
    glass, opaque = object_names()
    full, glazed = load_model("glassware:3"), load_model("glazed:3")
    d_full, d_glazed = mujoco.MjData(full), mujoco.MjData(glazed)
    mujoco.mj_forward(full, d_full)
    mujoco.mj_forward(glazed, d_glazed)
    for name in opaque:                           # the look-alikes stand where they stood
        assert np.allclose(d_glazed.body(name).xpos, d_full.body(name).xpos)
    for name in glass:
        assert mujoco.mj_name2id(glazed, mujoco.mjtObj.mjOBJ_BODY, name) == -1
    manifest = scene_manifest(glazed, d_glazed, "glazed:3", str(resolve_scene("glazed:3")))
    assert manifest["transparent_geoms"] == [] and manifest["specular"]
    assert sorted(manifest["objects"]) == sorted(opaque)
    assert sorted(manifest["shiny_geoms"]) == sorted(opaque)      # glazed: specular 0.5
    choice = choose_from_manifest(manifest)
    assert choice.method == "ngp" and choice.options.get("sh_degree") is None
    full_manifest = scene_manifest(full, d_full, "glassware:3", str(resolve_scene("glassware:3")))
    assert sorted(full_manifest["transparent_geoms"]) == sorted(glass)


def test_sensor_model_noise_grows_with_depth_and_glass_modes():
    rng = np.random.default_rng(0)
    near = np.full((64, 64), 0.5)
    far = np.full((64, 64), 3.0)
    clean = DepthSensorModel(edge_jump=0, dropout=0, quantization=0)
    no_mask = np.zeros((64, 64), bool)
    err_near = np.nanstd(clean.read(near, no_mask) - near)
    err_far = np.nanstd(clean.read(far, no_mask) - far)
    assert err_far > 5 * err_near
    assert abs(err_far - clean.sigma(3.0)) < 0.2 * clean.sigma(3.0)
    glass = np.zeros((64, 64), bool)
    glass[20:40, 20:40] = True
    behind = DepthSensorModel(transparent="behind", dropout=0).read(far, glass)
    invalid = DepthSensorModel(transparent="invalid", dropout=0).read(far, glass)
    assert valid_fraction(behind, glass) == 1.0
    assert valid_fraction(invalid, glass) == 0.0
    assert valid_fraction(invalid, ~glass) == 1.0
    out_of_range = DepthSensorModel(max_range=2.0).read(far, no_mask)
    assert np.isnan(out_of_range).all()
    with pytest.raises(ValueError, match="transparent"):
        DepthSensorModel(transparent="sometimes")
    del rng


@pytest.fixture(scope="module")
def glass_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("glass") / "glassware"
    rig = default_rig("glassware", count=4, width=48, height=48, seed=0)
    capture("glassware", rig, make_test_rig(rig, 1), out, progress=False,
            sensor=DepthSensorModel(transparent="behind"))
    return load_dataset(out)


def test_capture_writes_ground_truth_with_opaque_glass_and_a_sensor_that_sees_through(glass_capture):
    ds = glass_capture
    manifest = ds.manifest
    assert sorted(manifest["transparent_geoms"]) == sorted(object_names()[0])
    assert manifest["depth_sensor"]["transparent"] == "behind"
    ids = [int(g) for g, n in manifest["geoms"].items() if n in manifest["transparent_geoms"]]
    glass_px = total = behind = 0
    for i in range(len(ds)):
        seg, gt, sensor = ds.segmentations[i], ds.depths[i], ds.sensor_depths[i]
        glass = np.isin(seg, ids)
        assert np.isfinite(gt[glass]).all()          # ground truth: glass is a surface
        have = glass & np.isfinite(sensor)
        glass_px += int(glass.sum())
        total += int(have.sum())
        behind += int((sensor[have] > gt[have] + 0.01).sum())
    assert glass_px > 20
    # the sensor sees past the glass: where it returns depth on glass pixels, it is behind it
    assert behind > 0.8 * total
