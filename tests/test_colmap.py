"""Poses from images: similarity alignment, the COLMAP model reader, and structure from motion
with the real pycolmap on a small simulated scene."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pycolmap
import pytest

from nerfbot.app.cli import main as nerfbot_main
from nerfbot.data import DatasetError, load_dataset
from nerfbot.data.colmap import (c2w_from_cam_from_world, cam_from_world_from_c2w,
                                 require_pycolmap)
from nerfbot.ops.alignment import Similarity, pose_errors, robust_umeyama, umeyama
from nerfbot.ops.cameras import look_at
from nerfbot.sfm.dataset import dataset_input, images_input, poses_from_images
from nerfbot.sfm.pipeline import MIN_PAIRS_AGREEING, SfmOptions, pose_agreement, run_sfm

pytestmark = pytest.mark.slow(35)


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_umeyama_recovers_a_known_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    truth = Similarity(2.5, _random_rotation(rng), np.array([10.0, -5.0, 3.0]))
    fit = umeyama(src, truth.points(src))
    assert fit.scale == pytest.approx(2.5, abs=1e-12)
    np.testing.assert_allclose(fit.rotation, truth.rotation, atol=1e-12)
    np.testing.assert_allclose(fit.translation, truth.translation, atol=1e-10)
    rigid = umeyama(src, Similarity(1.0, truth.rotation, truth.translation).points(src),
                    with_scale=False)
    assert rigid.scale == 1.0
    np.testing.assert_allclose(rigid.rotation, truth.rotation, atol=1e-12)


def test_umeyama_refuses_degenerate_points_and_the_robust_fit_ignores_an_outlier():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        umeyama(line, line)
    with pytest.raises(ValueError, match="at least 3"):
        umeyama(line[:2], line[:2])
    rng = np.random.default_rng(1)
    src = rng.normal(size=(30, 3))
    truth = Similarity(0.7, _random_rotation(rng), np.array([1.0, 2.0, 3.0]))
    tgt = truth.points(src)
    tgt[4] += 50.0  # one camera posed far off
    plain = umeyama(src, tgt)
    robust, inliers = robust_umeyama(src, tgt)
    assert not inliers[4] and inliers.sum() == 29
    np.testing.assert_allclose(robust.rotation, truth.rotation, atol=1e-9)
    assert abs(plain.scale - 0.7) > 1e-3  # what the outlier does to the plain fit


def test_pose_errors_are_zero_up_to_a_similarity_and_measure_a_turned_camera():
    rng = np.random.default_rng(2)
    true = np.stack([look_at(rng.uniform(-3, 3, 3) + [0, 0, 4], [0, 0, 0]) for _ in range(8)])
    moved = Similarity(3.0, _random_rotation(rng), np.array([5.0, 1.0, -2.0])).poses(true)
    errors = pose_errors(moved, true)
    assert errors.rotation_deg.max() < 1e-6 and errors.translation.max() < 1e-9
    turned = moved.copy()
    angle = np.radians(2.0)
    spin = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                     [0, 0, 1]])
    turned[3, :3, :3] = turned[3, :3, :3] @ spin   # about the camera's own axis
    errors = pose_errors(turned, true)
    assert errors.rotation_deg[3] == pytest.approx(2.0, abs=1e-9)
    assert np.delete(errors.rotation_deg, 3).max() < 1e-6


def test_colmap_pose_conversion_round_trips_and_looks_down_the_optical_axis():
    c2w = look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    cam_from_world = cam_from_world_from_c2w(c2w)
    np.testing.assert_allclose(c2w_from_cam_from_world(cam_from_world), c2w, atol=1e-12)
    # the look-at target lies on COLMAP's +z (OpenCV: the camera looks along +z)
    target_in_camera = cam_from_world @ np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(target_in_camera[:2], 0.0, atol=1e-12)
    assert target_in_camera[2] == pytest.approx(np.sqrt(14.0))


def _write_model(dataset, project, camera_model="PINHOLE", binary=True):
    """Write a dataset's poses and intrinsics as a COLMAP project (images/ + sparse/0)."""
    rec = pycolmap.Reconstruction()
    fx, fy, cx, cy = dataset.intrinsics[0]
    w, h = (int(v) for v in dataset.sizes[0])
    params = {"PINHOLE": [fx, fy, cx, cy], "SIMPLE_RADIAL": [fx, cx, cy, 0.0],
              "FULL_OPENCV": [fx, fy, cx, cy] + [0.0] * 8}[camera_model]
    rec.add_camera_with_trivial_rig(pycolmap.Camera(camera_id=1, model=camera_model, width=w,
                                                    height=h, params=params))
    (project / "images").mkdir(parents=True)
    for i, rel in enumerate(dataset.file_paths):
        name = f"view_{i:03d}.png"
        shutil.copyfile(dataset.root / rel, project / "images" / name)
        image = pycolmap.Image(name=name, camera_id=1, image_id=i + 1)
        pose = pycolmap.Rigid3d(cam_from_world_from_c2w(dataset.c2w[i]))
        rec.add_image_with_trivial_frame(image, pose)
    model = project / "sparse" / "0"
    model.mkdir(parents=True)
    (rec.write_binary if binary else rec.write_text)(str(model))
    return model


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_model_round_trips_through_the_reader(tiny_capture, tmp_path, binary):
    original = load_dataset(tiny_capture[0])
    project = tmp_path / "project"
    model = _write_model(original, project, binary=binary)
    for path in (project, model):   # the project folder, or the model folder itself
        loaded = load_dataset(path)
        assert loaded.format == "colmap" and len(loaded.images) == len(original.images)
        np.testing.assert_allclose(loaded.c2w, original.c2w, atol=1e-9)
        np.testing.assert_allclose(loaded.intrinsics, original.intrinsics, atol=1e-9)
        np.testing.assert_array_equal(loaded.images[5], original.images[5])
    assert loaded.file_paths[0] == "images/view_000.png"


def test_colmap_reader_names_what_is_wrong(tiny_capture, tmp_path):
    original = load_dataset(tiny_capture[0])
    project = tmp_path / "p1"
    _write_model(original, project, camera_model="FULL_OPENCV")
    with pytest.raises(DatasetError, match="FULL_OPENCV is not supported"):
        load_dataset(project)
    project = tmp_path / "p2"
    _write_model(original, project)
    shutil.rmtree(project / "images")
    with pytest.raises(DatasetError, match="no images/ folder"):
        load_dataset(project)
    project = tmp_path / "p3"
    model = _write_model(original, project)
    (model / "images.bin").write_bytes(b"\x07" * 10)
    with pytest.raises(DatasetError, match="cannot read the COLMAP model"):
        load_dataset(project)


def test_pycolmap_release_is_checked(monkeypatch):
    require_pycolmap()  # the installed release is the pinned one
    monkeypatch.setattr(pycolmap, "__version__", "3.11.1")
    with pytest.raises(RuntimeError, match=r"pycolmap 4\.2\.x, found 3\.11\.1.*pip install"):
        require_pycolmap()


@pytest.fixture(scope="module")
def textured_capture(tmp_path_factory):
    """A 192x192 capture of a frame-filling textured workspace, 24 + 4 views."""
    from sims.capture import capture
    from sims.rigs import default_rig, make_test_rig

    out = tmp_path_factory.mktemp("sfm") / "workspace"
    rig = default_rig("workspace:1", count=24, width=192, height=192, seed=0)
    capture("workspace:1", rig, make_test_rig(rig, 4), out, progress=False)
    return out


def test_sfm_registers_a_simulated_scene_with_small_pose_errors(textured_capture, tmp_path):
    out = tmp_path / "posed"
    report = poses_from_images(dataset_input(textured_capture), out,
                               SfmOptions(threads=1), progress=False)
    assert report["registered"] >= 26   # of 28
    # posed from the features without a twin in their own image, refined with all of them
    assert 0 < report["features"]["kept"] < report["features"]["features"]
    assert report["seconds"]["all_features"] > 0
    errors = report["pose_errors"]
    assert errors["rotation_deg_median"] < 0.5
    assert errors["translation_percent_median"] < 1.0
    posed = load_dataset(out)           # the written dataset: metres, the scene's frame
    truth = load_dataset(textured_capture)
    index = {p: i for i, p in enumerate(truth.file_paths)}
    true_c2w = truth.c2w[[index[p] for p in posed.file_paths]]
    direct = pose_errors(posed.c2w, true_c2w, align=False)
    assert np.median(direct.translation_percent) < 1.0
    assert np.median(direct.rotation_deg) < 0.5
    assert posed.manifest is not None and posed.depths[0] is not None
    # sparse depth for DS-NeRF: the keypoints' depths agree with the rendered depth there
    rel = []
    for keys, depth in zip(posed.keypoints, posed.depths):
        assert keys is not None and len(keys) > 10
        z = depth[keys[:, 1].astype(int), keys[:, 0].astype(int)]
        ok = np.isfinite(z)
        rel.append(np.abs(keys[ok, 2] - z[ok]) / z[ok])
    rel = np.concatenate(rel)
    assert np.median(rel) < 0.01
    sigma = np.concatenate([k[:, 3] / k[:, 2] for k in posed.keypoints])
    assert 0.0 < np.median(sigma) < 0.05 and sigma.std() > 0   # widths vary with each point
    for keys, (fx, fy, _, _) in zip(posed.keypoints, posed.intrinsics):
        # never narrower than one training pixel's footprint
        assert np.all(keys[:, 3] >= keys[:, 2] / max(fx, fy) * (1 - 1e-5))
    assert set(posed.splits["test"]) and len(posed.splits["test"]) <= 4
    report_file = json.loads((out / "sfm_report.json").read_text())
    assert report_file["registered"] == report["registered"]
    assert (out / "sparse_pc.ply").stat().st_size > 0


def test_images_with_a_small_share_of_the_typical_observations_lose_their_pose():
    from types import SimpleNamespace

    from nerfbot.sfm.pipeline import MIN_IMAGE_POINTS, _weak_images

    def rec(counts):
        return SimpleNamespace(images={i: SimpleNamespace(has_pose=True, num_points3D=c, name=i)
                                       for i, c in enumerate(counts)})

    # the tabletop at 1024 px: a view 180 degrees off on 25 repeated-texture matches; a weak
    # but correct one on 37; the median image on 234
    assert [im.name for im in _weak_images(rec([25, 37, 54, 234, 240, 250, 260]))] == [0]
    assert [im.name for im in _weak_images(rec([MIN_IMAGE_POINTS - 1, 40, 44, 50]))] == [0]
    # large images: under a tenth of the median image's observations
    assert [im.name for im in _weak_images(rec([100, 1500, 1600, 1700]))] == [0]
    assert _weak_images(rec([])) == []


def test_guided_matching_verifies_more_matches_and_the_best_mapping_run_is_kept(
        textured_capture, tmp_path):
    sfm_input = dataset_input(textured_capture)
    results = {}
    for guided in (False, True):
        results[guided] = run_sfm(sfm_input.root, sfm_input.names, tmp_path / f"guided-{guided}",
                                  sfm_input.camera,
                                  SfmOptions(threads=1, guided_matching=guided,
                                             mapper_runs=1 if not guided else 2),
                                  progress=False)
        assert results[guided].summary()["inlier_matches"] == results[guided].inlier_matches
    assert results[True].inlier_matches > 1.05 * results[False].inlier_matches > 0
    runs = results[True].mapper_runs
    assert [r["seed"] for r in runs] == [0, 1] and len(results[False].mapper_runs) == 1
    for r in runs:   # a sound model explains a good share of the verified matches
        assert r["registered"] >= 26 and 0.1 * results[True].inlier_matches < \
            r["explained_matches"] < results[True].inlier_matches
    with pytest.raises(ValueError, match="mapper_runs"):
        SfmOptions(mapper_runs=0).check()
    # the verified matches agree with the recovered poses, and stop agreeing with wrong ones
    agreement = results[True].agreement
    assert agreement["pairs_agreeing"] > 0.8 and agreement["matches_agreeing"] > 0.8
    assert results[True].summary()["agreement"] == agreement
    rec = results[True].reconstruction
    scale = np.median([np.linalg.norm(im.projection_center()) for im in rec.images.values()
                       if im.has_pose])
    for k, im in enumerate(im for im in rec.images.values() if im.has_pose):
        if k % 2:   # every other view moved sideways by a fifth of the cameras' distance
            pose = im.cam_from_world()
            rec.frames[im.frame_id].rig_from_world = pycolmap.Rigid3d(
                pose.rotation, pose.translation + np.array([0.2 * scale, 0.0, 0.0]))
    wrong = pose_agreement(rec, tmp_path / "guided-True" / "database.db")
    assert wrong["pairs"] == agreement["pairs"] and wrong["pairs_agreeing"] < MIN_PAIRS_AGREEING


def test_nerfbot_colmap_on_plain_images_orients_up_and_refuses_an_existing_folder(
        textured_capture, tmp_path, capsys):
    images = tmp_path / "photos"
    shutil.copytree(textured_capture / "images", images)
    out = tmp_path / "posed"
    code = nerfbot_main(["colmap", str(images), "--out", str(out), "--downscale", "2",
                         "--no-progress"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "registered" in printed and "COLMAP's arbitrary unit" in printed
    posed = load_dataset(out)
    assert tuple(posed.sizes[0]) == (96, 96)
    up = posed.c2w[:, :3, 1].mean(0)
    assert up[2] / np.linalg.norm(up) > 0.999   # the mean camera up is +z
    # the estimated focal length (SIMPLE_RADIAL) lands near the true one, halved
    truth = load_dataset(textured_capture)
    assert posed.intrinsics[0, 0] == pytest.approx(truth.intrinsics[0, 0] / 2, rel=0.05)
    assert nerfbot_main(["colmap", str(images), "--out", str(out), "--no-progress"]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        nerfbot_main(["colmap", str(images), "--out", str(tmp_path / "other"),
                      "--drop-repeated", "3"])
    assert "--drop-repeated: expected a number from 0 to 2, got '3'" in capsys.readouterr().err


def test_images_input_needs_two_images(tmp_path):
    (tmp_path / "one.png").write_bytes(b"")
    with pytest.raises(DatasetError, match="found 1 images"):
        images_input(tmp_path)


def test_a_failed_reconstruction_leaves_no_folder_behind(tmp_path, capsys):
    images = tmp_path / "blank"
    images.mkdir()
    for i in range(3):   # nothing to match
        cv2.imwrite(str(images / f"{i}.png"), np.full((64, 64, 3), 90 + i, np.uint8))
    out = tmp_path / "posed"
    assert nerfbot_main(["colmap", str(images), "--out", str(out), "--no-progress"]) == 2
    assert "found no model" in capsys.readouterr().err
    assert not out.exists()
    out.mkdir()   # an empty folder the user made stays, empty
    assert nerfbot_main(["colmap", str(images), "--out", str(out), "--no-progress"]) == 2
    assert out.is_dir() and not any(out.iterdir())


def test_a_descriptor_with_a_distant_twin_in_its_own_image_is_repeated():
    from nerfbot.sfm.repeats import MIN_SEPARATION_PX, nearest_twin_distance

    rng = np.random.default_rng(0)
    tile, unique, other = (rng.integers(0, 255, 128) for _ in range(3))
    xy = np.array([[10, 10], [200, 10], [10, 200], [100, 100],
                   [300, 300], [300 + MIN_SEPARATION_PX / 2, 300]], np.float32)
    descriptors = np.stack([tile, tile + 1, 2 * tile, unique, other, other])
    d = nearest_twin_distance(xy, descriptors)
    assert d[:3].max() < 0.02            # three copies of one patch (at any contrast)
    assert d[3] > 0.3                    # a patch seen once
    assert d[4] == d[5] == pytest.approx(d[4])
    assert d[4] > 0.3                    # one detection reported twice is not a repeat
    assert nearest_twin_distance(xy[:1], descriptors[:1])[0] == 2.0
    assert nearest_twin_distance(np.zeros((0, 2)), np.zeros((0, 128))).shape == (0,)
    with pytest.raises(ValueError, match="6 keypoints but 5"):
        nearest_twin_distance(xy, descriptors[:5])


def test_features_of_a_tiled_texture_are_dropped_and_a_unique_patch_keeps_its_own(tmp_path):
    from nerfbot.sfm.repeats import drop_repeated_features

    rng = np.random.default_rng(1)
    def texture(size):
        noise = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 2.0)
        return cv2.normalize(noise, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    image = np.tile(texture(96), (4, 4))         # one tile repeated 4 x 4 times, 384 px
    image[96:192, 96:192] = texture(96)          # but one tile is unlike the others
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.png"), image)
    database = tmp_path / "database.db"
    pycolmap.extract_features(database, tmp_path / "images", device=pycolmap.Device.cpu)
    stats = drop_repeated_features(database, 0.3)
    db = pycolmap.Database.open(str(database))
    try:
        image_id = db.read_all_images()[0].image_id
        kept = db.read_keypoints(image_id)[:, :2]
        assert len(db.read_descriptors(image_id).data) == len(kept) == stats["kept"]
    finally:
        db.close()
    assert stats["features"] > 300 and 0 < stats["kept"] < 0.4 * stats["features"]
    inside = ((kept >= 96 - 4) & (kept < 192 + 4)).all(1)
    # the unique tile is 1/16 of the image and holds most of what is kept
    assert inside.mean() > 0.5, (inside.mean(), stats)


def test_poses_from_the_distinct_features_are_refined_with_every_feature(textured_capture,
                                                                         tmp_path):
    sfm_input = dataset_input(textured_capture)
    results = {every: run_sfm(sfm_input.root, sfm_input.names, tmp_path / f"every-{every}",
                              sfm_input.camera,
                              SfmOptions(threads=1, mapper_runs=1, refine_all_features=every),
                              progress=False)
               for every in (False, True)}
    first, second = results[False], results[True]
    assert first.features == second.features and first.features["kept"] < \
        first.features["features"]
    assert "all_features" in second.seconds and "all_features" not in first.seconds
    assert len(second.registered) >= len(first.registered) - 1 >= 25
    # the features dropped as repeats come back as points once the poses are known
    assert second.reconstruction.num_points3D() > 1.3 * first.reconstruction.num_points3D()
    assert second.reconstruction.compute_mean_reprojection_error() < 1.0
