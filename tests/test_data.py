"""Dataset readers on tiny synthetic datasets built on the fly (16x12 images, a few frames)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from nerfbot.data import Dataset, DatasetError, estimate_bounds_from_cameras, load_dataset
from nerfbot.data.bounds import estimate_bounds_with_rule
from nerfbot.ops.cameras import look_at

W, H = 16, 12
FL = 14.0


# ----------------------------------------------------------------------------- builders

def ring_poses(n: int, radius: float = 2.0, height: float = 0.6, target=(0.1, -0.2, 0.3)):
    """n c2w (4, 4) on a ring around ``target``, all looking at it."""
    t = np.asarray(target)
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = t + np.array([radius * math.cos(a), radius * math.sin(a), height])
        poses.append(look_at(eye, t))
    return poses


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    """Write an RGB(A) uint8/uint16 array with cv2 (which expects BGR(A))."""
    path.parent.mkdir(parents=True, exist_ok=True)
    code = cv2.COLOR_RGBA2BGRA if rgb.shape[-1] == 4 else cv2.COLOR_RGB2BGR
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, code))


def frame_image(i: int, w: int = W, h: int = H) -> np.ndarray:
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)


def write_json(path: Path, meta: dict) -> None:
    path.write_text(json.dumps(meta, indent=2))


def make_nerfstudio(root: Path, n: int = 4, sizes=None, per_frame: bool = False,
                    write: bool = True) -> dict:
    """Write n images (sizes[i] or 16x12) and return (and write) a transforms.json dict."""
    root.mkdir(parents=True, exist_ok=True)
    frames = []
    for i, c2w in enumerate(ring_poses(n)):
        w, h = sizes[i] if sizes else (W, H)
        write_rgb(root / "images" / f"frame_{i:03d}.png", frame_image(i, w, h))
        frame = {"file_path": f"images/frame_{i:03d}.png", "transform_matrix": c2w.tolist()}
        if per_frame:
            frame.update(fl_x=FL + i, fl_y=FL + i, cx=w / 2, cy=h / 2, w=w, h=h)
        frames.append(frame)
    meta = {"camera_model": "OPENCV", "frames": frames}
    if not per_frame:
        meta.update(fl_x=FL, fl_y=FL + 1, cx=8.5, cy=6.0, w=W, h=H)
    if write:
        write_json(root / "transforms.json", meta)
    return meta


def make_blender(root: Path, counts=(3, 1, 2), rgba: bool = True, times=None) -> dict:
    """Blender layout: transforms_{train,val,test}.json, file paths without extension."""
    metas = {}
    k = 0
    poses = ring_poses(sum(counts), radius=4.0)
    for split, n in zip(("train", "val", "test"), counts):
        frames = []
        for i in range(n):
            img = frame_image(k)
            if rgba:
                alpha = np.full((H, W, 1), 255, np.uint8)
                alpha[0, 0] = 0          # fully transparent pixel
                alpha[0, 1] = 128        # half transparent pixel
                img = np.concatenate([img, alpha], axis=2)
            write_rgb(root / split / f"r_{i}.png", img)
            frame = {"file_path": f"./{split}/r_{i}", "rotation": 0.1,
                     "transform_matrix": poses[k].tolist()}
            if times is not None and times.get((split, i)) is not None:
                frame["time"] = times[(split, i)]
            frames.append(frame)
            k += 1
        metas[split] = {"camera_angle_x": 0.69, "frames": frames}
        write_json(root / f"transforms_{split}.json", metas[split])
    return metas


# ----------------------------------------------------------------------------- nerfstudio

def test_nerfstudio_global_intrinsics(tmp_path):
    meta = make_nerfstudio(tmp_path)
    ds = load_dataset(tmp_path)
    assert isinstance(ds, Dataset) and ds.format == "nerfstudio" and len(ds) == 4
    assert ds.root == tmp_path
    assert ds.file_paths[2] == "images/frame_002.png"
    np.testing.assert_array_equal(ds.images[1], frame_image(1))
    assert ds.images[0].dtype == np.uint8 and ds.images[0].shape == (H, W, 3)
    assert all(a is None for a in ds.alphas) and ds.background == "learned"
    np.testing.assert_allclose(ds.intrinsics, [[FL, FL + 1, 8.5, 6.0]] * 4)
    np.testing.assert_array_equal(ds.sizes, [[W, H]] * 4)
    np.testing.assert_allclose(ds.c2w[3], np.asarray(meta["frames"][3]["transform_matrix"]))
    assert ds.c2w.dtype == np.float64 and ds.c2w.shape == (4, 4, 4)
    assert ds.splits == {"train": [1, 2, 3], "test": [0]}      # every 8th frame is test
    assert ds.times is None and ds.joints is None and ds.manifest is None
    assert ds.depths == [None] * 4 and ds.masks == [None] * 4
    assert ds.aabb.shape == (2, 3) and ds.aabb_source == "cameras"
    cams = ds.cameras(ds.indices("train"))
    assert len(cams) == 3
    # a JSON file path works too
    assert len(load_dataset(tmp_path / "transforms.json")) == 4


def test_nerfstudio_per_frame_intrinsics_mixed_sizes(tmp_path):
    sizes = [(16, 12), (20, 10), (16, 12), (8, 8)]
    make_nerfstudio(tmp_path, sizes=sizes, per_frame=True)
    ds = load_dataset(tmp_path)
    np.testing.assert_array_equal(ds.sizes, sizes)
    assert [img.shape[:2] for img in ds.images] == [(h, w) for w, h in sizes]
    np.testing.assert_allclose(ds.intrinsics[1], [FL + 1, FL + 1, 10.0, 5.0])


def test_per_frame_overrides_global_and_defaults(tmp_path):
    meta = make_nerfstudio(tmp_path, write=False)
    del meta["fl_y"], meta["cx"], meta["cy"]
    meta["frames"][2]["fl_x"] = 30.0
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    np.testing.assert_allclose(ds.intrinsics[0], [FL, FL, W / 2, H / 2])   # fl_y <- fl_x
    np.testing.assert_allclose(ds.intrinsics[2], [30.0, 30.0, W / 2, H / 2])


def test_instant_ngp_fov_keys(tmp_path):
    meta = make_nerfstudio(tmp_path, write=False)
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        del meta[key]
    meta["camera_angle_x"] = 1.0                       # radians
    write_json(tmp_path / "transforms.json", meta)
    fx = 0.5 * W / math.tan(0.5)
    np.testing.assert_allclose(load_dataset(tmp_path).intrinsics[0], [fx, fx, W / 2, H / 2])
    del meta["camera_angle_x"]
    meta["x_fov"] = 60.0                               # degrees
    write_json(tmp_path / "transforms.json", meta)
    fx = 0.5 * W / math.tan(math.radians(30.0))
    np.testing.assert_allclose(load_dataset(tmp_path).intrinsics[0, :2], [fx, fx])


def test_split_lists_match_normalised_paths(tmp_path):
    meta = make_nerfstudio(tmp_path, write=False)
    meta["train_filenames"] = ["./images/frame_000.png", "images/frame_002.png"]
    meta["val_filenames"] = ["images/../images/frame_003.png"]
    meta["test_filenames"] = ["images/frame_001.png"]
    meta["frames"][1]["file_path"] = "./images/frame_001.png"
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    assert ds.splits == {"train": [0, 2], "val": [3], "test": [1]}


def test_default_splits_every_eighth(tmp_path):
    make_nerfstudio(tmp_path, n=17)
    ds = load_dataset(tmp_path)
    assert ds.splits["test"] == [0, 8, 16]
    assert ds.splits["train"] == [i for i in range(17) if i % 8]


def test_uint16_and_grey_images(tmp_path):
    make_nerfstudio(tmp_path)
    img16 = (frame_image(0).astype(np.uint16) * 257)
    write_rgb(tmp_path / "images" / "frame_000.png", img16)
    grey = frame_image(1)[:, :, 0]
    cv2.imwrite(str(tmp_path / "images" / "frame_001.png"), grey)
    ds = load_dataset(tmp_path)
    np.testing.assert_array_equal(ds.images[0], frame_image(0))
    np.testing.assert_array_equal(ds.images[1], np.repeat(grey[:, :, None], 3, axis=2))


def test_rgb_source_with_user_background_colour(tmp_path):
    make_nerfstudio(tmp_path)
    ds = load_dataset(tmp_path, background=(0.0, 0.5, 1.0))
    assert ds.background == (0.0, 0.5, 1.0)
    np.testing.assert_array_equal(ds.images[0], frame_image(0))      # nothing composited
    with pytest.raises(ValueError, match="background"):
        load_dataset(tmp_path, background="purple")


# ----------------------------------------------------------------------------- Blender / D-NeRF

@pytest.mark.parametrize("background, value", [(None, 255), ("white", 255), ("black", 0)])
def test_blender_rgba_composited(tmp_path, background, value):
    make_blender(tmp_path)
    ds = load_dataset(tmp_path, background=background)
    assert ds.format == "blender" and len(ds) == 6
    assert ds.splits == {"train": [0, 1, 2], "val": [3], "test": [4, 5]}
    assert ds.file_paths[0] == "./train/r_0"
    src = frame_image(0)
    np.testing.assert_array_equal(ds.images[0][0, 0], [value] * 3)          # alpha 0
    a = 128 / 255
    expected = np.rint(src[0, 1] * a + value * (1 - a))
    np.testing.assert_allclose(ds.images[0][0, 1], expected, atol=1)        # alpha 128
    np.testing.assert_array_equal(ds.images[0][5:, :], src[5:, :])          # opaque
    assert ds.alphas[0][0, 0] == 0 and ds.alphas[0][0, 1] == 128 and ds.alphas[0][3, 3] == 255
    assert ds.background == (float(value / 255),) * 3
    fx = 0.5 * W / math.tan(0.69 / 2)
    np.testing.assert_allclose(ds.intrinsics[0], [fx, fx, W / 2, H / 2])
    assert ds.times is None


def test_rgba_images_with_opaque_alpha_are_rgb_images(tmp_path):
    """An RGBA export whose alpha is 255 everywhere is an opaque image: the background is
    learned (as for RGB), no alpha is kept, and the pixels are the file's RGB; one frame with
    real transparency makes the dataset a composited one again."""
    make_blender(tmp_path)
    for p in tmp_path.rglob("r_*.png"):
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        img[..., 3] = 255
        cv2.imwrite(str(p), img)
    ds = load_dataset(tmp_path)
    assert ds.background == "learned" and all(a is None for a in ds.alphas)
    np.testing.assert_array_equal(ds.images[0], frame_image(0))
    img = cv2.imread(str(tmp_path / "train" / "r_1.png"), cv2.IMREAD_UNCHANGED)
    img[0, 0, 3] = 0
    cv2.imwrite(str(tmp_path / "train" / "r_1.png"), img)
    mixed = load_dataset(tmp_path)
    assert mixed.background == (1.0, 1.0, 1.0)
    assert mixed.alphas[0] is None and mixed.alphas[1][0, 0] == 0
    np.testing.assert_array_equal(mixed.images[1][0, 0], [255, 255, 255])


def test_dnerf_time_defaults(tmp_path):
    make_blender(tmp_path, counts=(3, 1, 2), times={("test", 1): 0.25})
    ds = load_dataset(tmp_path / "transforms_train.json")
    assert ds.format == "dnerf"
    # train: i / (N - 1) per split; val: single frame -> 0; test: [0 (default), 0.25 (given)]
    np.testing.assert_allclose(ds.times, [0.0, 0.5, 1.0, 0.0, 0.0, 0.25])
    assert ds.times.dtype == np.float32


# ----------------------------------------------------------------------------- distortion

def _pattern(w: int, h: int) -> np.ndarray:
    """A smooth grid-like RGB pattern (bilinear round trips keep it)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    g = 128 + 100 * np.sin(2 * np.pi * x / 16) * np.sin(2 * np.pi * y / 16)
    return np.stack([g, 255 - g, np.full_like(g, 90)], axis=-1).round().astype(np.uint8)


def _distort(img: np.ndarray, k_cv: np.ndarray, coeffs, fisheye: bool) -> np.ndarray:
    """Render what a distorting lens would see of ``img`` (an ideal pinhole image)."""
    h, w = img.shape[:2]
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([x, y], axis=-1).reshape(-1, 1, 2)
    d = np.asarray(coeffs, dtype=np.float64)
    und = (cv2.fisheye.undistortPoints(pts, k_cv, d, P=k_cv) if fisheye
           else cv2.undistortPoints(pts, k_cv, d, P=k_cv)).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(img, und[..., 0], und[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT)


@pytest.mark.parametrize("model, coeffs", [
    ("OPENCV", {"k1": 0.3, "k2": 0.05, "p1": 0.002, "p2": -0.001}),
    ("OPENCV_FISHEYE", {"k1": 0.08, "k2": -0.02, "k3": 0.01, "k4": -0.005}),
])
def test_undistortion_recovers_pinhole_image(tmp_path, model, coeffs):
    w, h, f, cx, cy = 64, 48, 50.0, 32.0, 24.0
    k_cv = np.array([[f, 0, cx - 0.5], [0, f, cy - 0.5], [0, 0, 1.0]])
    ideal = _pattern(w, h)
    order = ("k1", "k2", "p1", "p2") if model == "OPENCV" else ("k1", "k2", "k3", "k4")
    distorted = _distort(ideal, k_cv, [coeffs[k] for k in order], model != "OPENCV")
    write_rgb(tmp_path / "img.png", distorted)
    depth = np.linspace(0.5, 3.0, w * h, dtype=np.float32).reshape(h, w)
    np.save(tmp_path / "depth.npy", depth)
    meta = {"camera_model": model, "fl_x": f, "fl_y": f, "cx": cx, "cy": cy, "w": w, "h": h,
            **coeffs, "frames": [{"file_path": "img.png", "depth_file_path": "depth.npy",
                                  "transform_matrix": np.eye(4).tolist()}]}
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    inner = (slice(8, -8), slice(8, -8))
    err = np.abs(ds.images[0][inner].astype(float) - ideal[inner]).mean()
    before = np.abs(distorted[inner].astype(float) - ideal[inner]).mean()
    assert err < 1.5 and before > 4 * err, (err, before)
    np.testing.assert_allclose(ds.intrinsics[0], [f, f, cx, cy])           # same K
    # nearest-neighbour remap: every depth value is a source value or NaN
    d = ds.depths[0]
    assert np.isin(d[np.isfinite(d)], depth).all()
    assert ds.extras["undistorted"] == [True]
    if model == "OPENCV":          # pincushion: corners have no source pixels
        assert ds.masks[0] is not None and not ds.masks[0][0, 0] and ds.masks[0][24, 32]
        assert np.isnan(d[~ds.masks[0]]).mean() > 0.5


def test_zero_coefficients_leave_image_untouched(tmp_path):
    meta = make_nerfstudio(tmp_path, write=False)
    meta.update(k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    np.testing.assert_array_equal(ds.images[2], frame_image(2))
    assert ds.masks == [None] * 4


# ----------------------------------------------------------------------------- depth & extras

def test_depth_npy_and_png_mm_agree(tmp_path):
    meta = make_nerfstudio(tmp_path, n=2, write=False)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.2, 5.0, size=(H, W)).astype(np.float32)
    depth_mm = np.rint(depth * 1000).astype(np.uint16)
    depth_mm[0, 0] = 0                                   # unknown
    npy = depth_mm.astype(np.float32) / 1000
    npy[0, 0] = np.nan
    npy[1, 1] = np.inf                                   # no surface
    np.save(tmp_path / "d0.npy", npy)
    cv2.imwrite(str(tmp_path / "d1.png"), depth_mm)
    meta["frames"][0]["depth_file_path"] = "d0.npy"
    meta["frames"][1]["depth_path"] = "d1.png"           # instant-ngp spelling
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    a, b = ds.depths
    assert a.dtype == np.float32 and b.dtype == np.float32 and a.shape == (H, W)
    assert np.isnan(a[0, 0]) and np.isnan(b[0, 0]) and np.isinf(a[1, 1])
    ok = np.isfinite(a)
    np.testing.assert_allclose(a[ok], b[ok], atol=1e-6)
    # a top-level unit scale changes the PNG reading
    meta["depth_unit_scale_factor"] = 1e-4
    write_json(tmp_path / "transforms.json", meta)
    np.testing.assert_allclose(load_dataset(tmp_path).depths[1][ok], b[ok] / 10, rtol=1e-6)


def test_mask_segmentation_time_joints_manifest(tmp_path):
    meta = make_nerfstudio(tmp_path, write=False)
    mask = np.zeros((H, W), np.uint8)
    mask[2:5, 3:9] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    seg = np.arange(H * W, dtype=np.int32).reshape(H, W) - 1
    np.save(tmp_path / "seg.npy", seg)
    for i, fr in enumerate(meta["frames"]):
        fr.update(mask_path="mask.png", segmentation_path="seg.npy", time=i / 3,
                  joints={"hinge": 0.1 * i, "slide": -0.02})
    meta["scene"] = {"bounds": [[-0.5, -0.4, 0.0], [0.5, 0.4, 0.2]], "dynamic": True}
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    np.testing.assert_array_equal(ds.masks[0], mask > 0)
    assert ds.segmentations[1].dtype == np.int32
    np.testing.assert_array_equal(ds.segmentations[1], seg)
    np.testing.assert_allclose(ds.times, [0, 1 / 3, 2 / 3, 1], rtol=1e-6)
    assert ds.joints[2] == {"hinge": pytest.approx(0.2), "slide": -0.02}
    assert ds.manifest["dynamic"] is True


# ----------------------------------------------------------------------------- bounds

def test_camera_bounds_contain_target_and_exclude_cameras(tmp_path):
    make_nerfstudio(tmp_path, n=6)
    ds = load_dataset(tmp_path)
    target = np.array([0.1, -0.2, 0.3])
    assert ds.aabb_source == "cameras" and ds.extras["bounds_rule"] == "axes"
    assert np.all(ds.aabb[0] < target) and np.all(target < ds.aabb[1])
    np.testing.assert_allclose(ds.aabb.mean(axis=0), target, atol=1e-6)
    for c in ds.c2w[:, :3, 3]:
        assert np.any(c < ds.aabb[0]) or np.any(c > ds.aabb[1])


def test_estimate_bounds_public_function_and_parallel_fallback():
    poses = np.stack(ring_poses(5, radius=3.0, height=1.0, target=(0, 0, 0)))
    intr = np.tile([20.0, 20.0, 16.0, 12.0], (5, 1))
    sizes = np.tile([32, 24], (5, 1))
    box = estimate_bounds_from_cameras(poses, intr, sizes)
    assert box.shape == (2, 3) and np.all(box[0] < 0) and np.all(box[1] > 0)
    # the cap: the cube's half-size stays below 0.9 x the nearest camera's inf-norm distance
    half = (box[1] - box[0]) / 2
    assert half[0] <= 0.9 * np.abs(poses[:, :3, 3]).max(axis=1).min() + 1e-9
    # parallel axes (a forward-facing rig): box around the look points, cameras outside
    par = np.stack([look_at((x, 0.0, 0.5), (x, 2.0, 0.5)) for x in (-0.2, 0.0, 0.2)])
    box = estimate_bounds_from_cameras(par, intr[:3], sizes[:3])
    assert np.all(np.isfinite(box))
    look = np.array([0.0, 1.0, 0.5])                   # 1 m (the floor) ahead of the middle camera
    assert np.all(box[0] < look) and np.all(look < box[1])
    for c in par[:, :3, 3]:
        assert np.any(c < box[0]) or np.any(c > box[1])


@settings(max_examples=40, deadline=None, database=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 9), radius=st.floats(0.3, 8.0),
       fov=st.floats(20.0, 120.0))
def test_camera_bounds_property(seed, n, radius, fov):
    """Cameras looking at one point: the box is centred on it and no camera is inside."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-2, 2, 3)
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    eyes = target + radius * rng.uniform(0.7, 1.3, (n, 1)) * dirs
    poses = np.stack([look_at(e, target) for e in eyes])
    f = 0.5 * 32 / math.tan(math.radians(fov) / 2)
    box, rule = estimate_bounds_with_rule(poses, np.tile([f, f, 16, 12], (n, 1)),
                                          np.tile([32, 24], (n, 1)))
    assume(rule in ("axes", "footprint"))
    assert np.all(box[1] > box[0])
    if rule == "footprint":      # cameras on one side: the cube grown by the ground they see
        assert np.all(box[0] < target) and np.all(target < box[1])
        reach = float(np.median(np.linalg.norm(eyes - target, axis=1)))
        assert np.all(box[0] >= target - reach * (1 + 1e-9))
        assert np.all(box[1] <= target + reach * (1 + 1e-9))
        return
    np.testing.assert_allclose(box.mean(axis=0), target, atol=1e-6 * radius + 1e-9)
    for e in eyes:
        assert np.any(e < box[0]) or np.any(e > box[1])


def test_camera_bounds_hold_the_ground_a_hemisphere_sees():
    """Cameras on a hemisphere over a table see the table beyond the cube their axes meet in:
    the box holds every point of the table's plane that a quarter of the cameras see, no
    farther than the cameras stand, and keeps the cube's height."""
    from nerfbot.data.bounds import GROUND_COVERAGE

    target = np.array([0.1, -0.2, 0.75])
    n, dist = 40, 0.8
    elevations = np.radians([30.0, 43.0, 57.0, 70.0])
    eyes = [target + dist * np.array([math.cos(elevations[k % 4]) * math.cos(2 * math.pi * k / n),
                                      math.cos(elevations[k % 4]) * math.sin(2 * math.pi * k / n),
                                      math.sin(elevations[k % 4])]) for k in range(n)]
    poses = np.stack([look_at(e, target) for e in eyes])
    f = 0.5 * 32 / math.tan(math.radians(40) / 2)
    intr, sizes = np.tile([f, f, 16, 12], (n, 1)), np.tile([32, 24], (n, 1))
    box, rule = estimate_bounds_with_rule(poses, intr, sizes)
    assert rule == "footprint"
    half = 1.1 * dist * math.tan(math.radians(40) / 2)       # the axes' cube (fov: the width)
    np.testing.assert_allclose(box[:, 2], [target[2] - half, target[2] + half], atol=1e-9)
    assert np.all(box[1, :2] - box[0, :2] > 2.2 * half)      # the ground: wider than the cube
    assert np.all(np.abs(box[:, :2] - target[:2]) <= dist + 1e-9)

    def coverage(x):
        w2c = np.linalg.inv(poses)
        c = np.einsum("nij,j->ni", w2c[:, :3, :3], x) + w2c[:, :3, 3]
        z = -c[:, 2]
        u, v = c[:, 0] / z * f + 16, -c[:, 1] / z * f + 12
        return float(np.mean((z > 0) & (u >= 0) & (u <= 32) & (v >= 0) & (v <= 24)))

    rng = np.random.default_rng(1)
    inside = 0
    for _ in range(300):
        r, a = rng.uniform(0, dist), rng.uniform(0, 2 * math.pi)
        x = target + np.array([r * math.cos(a), r * math.sin(a), 0.0])
        if coverage(x) >= GROUND_COVERAGE + 0.03:   # clear of the probe grid's spacing
            inside += 1
            assert np.all(box[0] <= x) and np.all(x <= box[1]), (x, box)
    assert inside > 50


def test_manifest_bounds_padded_and_aabb_override(tmp_path):
    meta = make_nerfstudio(tmp_path, write=False)
    meta["scene"] = {"bounds": [[-0.5, -0.4, 0.0], [0.5, 0.4, 0.1]]}
    write_json(tmp_path / "transforms.json", meta)
    ds = load_dataset(tmp_path)
    assert ds.aabb_source == "manifest"
    # 5 % of the extent per side, at least 1 cm
    np.testing.assert_allclose(ds.aabb, [[-0.55, -0.44, -0.01], [0.55, 0.44, 0.11]])
    user = [[-1, -1, -1], [1, 1, 2]]
    ds = load_dataset(tmp_path, aabb=user)
    assert ds.aabb_source == "user"
    np.testing.assert_allclose(ds.aabb, user)
    with pytest.raises(ValueError, match="aabb"):
        load_dataset(tmp_path, aabb=[[0, 0, 0], [0, 1, 1]])


# ----------------------------------------------------------------------------- writer round trip

@pytest.mark.parametrize("fmt", ["nerfstudio", "blender"])
def test_round_trip_with_project_writers(tmp_path, fmt):
    from nerfbot.data.writers import open_writer

    fx = 0.5 * W / math.tan(0.4)
    writer = open_writer(fmt, tmp_path, fx, fx, W / 2, H / 2, W, H)
    poses = ring_poses(5)
    depth = np.full((H, W), 1.5, np.float32)
    depth[0, :] = np.inf
    seg = np.full((H, W), -1, np.int32)
    seg[4:8, 4:8] = 7
    for i, c2w in enumerate(poses):
        writer.add_frame(frame_image(i), c2w, split="test" if i == 4 else "train", depth=depth,
                         segmentation=seg, time=i / 4, joints={"hinge": 0.1 * i})
    manifest = {"bounds": [[-0.2, -0.3, 0.0], [0.4, 0.1, 0.5]], "dynamic": True}
    writer.finish(manifest)
    ds = load_dataset(tmp_path)
    assert ds.format == ("nerfstudio" if fmt == "nerfstudio" else "dnerf")
    assert ds.indices("train") == [0, 1, 2, 3] and ds.indices("test") == [4]
    np.testing.assert_array_equal(ds.images[3], frame_image(3))
    np.testing.assert_allclose(ds.c2w, np.stack(poses), atol=1e-12)
    np.testing.assert_allclose(ds.intrinsics[0], [fx, fx, W / 2, H / 2], rtol=1e-9)
    np.testing.assert_array_equal(ds.depths[2], depth)
    np.testing.assert_array_equal(ds.segmentations[1], seg)
    np.testing.assert_allclose(ds.times, [0, 0.25, 0.5, 0.75, 1.0])
    assert ds.joints[4]["hinge"] == pytest.approx(0.4)
    assert ds.manifest == manifest and ds.aabb_source == "manifest"
    assert ds.masks == [None] * 5 and ds.background == "learned"


# ----------------------------------------------------------------------------- malformed input

@pytest.fixture
def ns(tmp_path):
    """A valid nerfstudio dataset; returns (root, meta, save) where save() rewrites the JSON."""
    meta = make_nerfstudio(tmp_path)

    def save():
        write_json(tmp_path / "transforms.json", meta)

    return tmp_path, meta, save


def test_error_missing_dataset(tmp_path):
    with pytest.raises(DatasetError, match=r"nowhere: dataset not found"):
        load_dataset(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match=r"transforms\.json: dataset not found"):
        load_dataset(tmp_path / "transforms.json")
    with pytest.raises(DatasetError, match=r"not a dataset folder: no transforms\.json"):
        load_dataset(tmp_path)


def test_blender_without_train_file_and_missing_split_files(tmp_path):
    make_blender(tmp_path)
    (tmp_path / "transforms_train.json").unlink()
    ds = load_dataset(tmp_path / "transforms_test.json")
    assert ds.splits == {"val": [0], "test": [1, 2]}
    for split in ("val", "test"):
        (tmp_path / f"transforms_{split}.json").unlink()
    with pytest.raises(DatasetError, match=r"not a dataset folder"):
        load_dataset(tmp_path)
    with pytest.raises(DatasetError, match=r"transforms_val\.json: dataset not found"):
        load_dataset(tmp_path / "transforms_val.json")


def test_error_bad_json(ns):
    root, _, _ = ns
    (root / "transforms.json").write_text('{\n  "fl_x": 14,\n  "frames": [,]\n}')
    with pytest.raises(DatasetError, match=r"transforms\.json: invalid JSON at line 3, column 14"):
        load_dataset(root)


def test_error_missing_image(ns):
    root, _, _ = ns
    (root / "images" / "frame_002.png").unlink()
    with pytest.raises(DatasetError,
                       match=r"transforms\.json: frames\[2\]\.file_path: image file not found: "
                             r".*frame_002\.png"):
        load_dataset(root)


def test_error_unreadable_image(ns):
    root, _, _ = ns
    (root / "images" / "frame_001.png").write_bytes(b"not a png at all")
    with pytest.raises(DatasetError,
                       match=r"transforms\.json: frames\[1\]\.file_path: cannot read image file "
                             r".*frame_001\.png"):
        load_dataset(root)


def test_error_image_size_mismatch(ns):
    root, meta, save = ns
    meta["w"] = 20
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[0\]\.file_path: image .*"
                                           r"frame_000\.png is 16x12 \(w x h\) but w is declared "
                                           r"as 20 \(.*transforms\.json: w\)"):
        load_dataset(root)


def test_error_mixed_sizes_without_per_frame_intrinsics(ns):
    root, meta, save = ns
    del meta["w"], meta["h"]
    save()
    write_rgb(root / "images" / "frame_003.png", frame_image(3, 20, 10))
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[3\]\.file_path: image .* "
                                           r"is 20x10 but .*frames\[0\] is 16x12; .*per-frame"):
        load_dataset(root)


@pytest.mark.parametrize("bad, message", [
    (lambda m: m.__setitem__(0, [float("nan"), 0, 0, 0]), "pose contains non-finite"),
    (lambda m: [row.__setitem__(0, row[0] * 2) for row in m[:3]], "pose is not rigid"),
    (lambda m: m.__setitem__(3, [0, 0, 1, 1]), "last row"),
    (lambda m: m.__setitem__(1, "x"), "expected a 4x4 matrix"),
])
def test_error_bad_pose(ns, bad, message):
    root, meta, save = ns
    bad(meta["frames"][3]["transform_matrix"])
    save()
    with pytest.raises(DatasetError,
                       match=rf"transforms\.json: frames\[3\]\.transform_matrix: .*{message}"):
        load_dataset(root)


def test_error_missing_required_fields(ns):
    root, meta, save = ns
    del meta["frames"][2]["transform_matrix"]
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[2\]\.transform_matrix: missing"):
        load_dataset(root)
    meta["frames"][2]["transform_matrix"] = np.eye(4).tolist()
    del meta["frames"][1]["file_path"]
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[1\]\.file_path: missing"):
        load_dataset(root)
    meta["frames"][1]["file_path"] = "images/frame_001.png"
    del meta["fl_x"], meta["fl_y"]
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[0\]: no intrinsics"):
        load_dataset(root)
    meta["fl_x"] = -3.0
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: fl_x: must be > 0"):
        load_dataset(root)
    meta["frames"] = []
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames: empty"):
        load_dataset(root)
    del meta["frames"]
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames: missing"):
        load_dataset(root)


@pytest.mark.parametrize("field", ["file_path", "depth_file_path", "mask_path",
                                   "segmentation_path"])
@pytest.mark.parametrize("value, message", [
    ("../outside.png", "escapes the dataset folder"),
    ("images/../../outside.png", "escapes the dataset folder"),
    ("/etc/passwd", "absolute path"),
])
def test_error_path_escapes_root(ns, field, value, message):
    root, meta, save = ns
    outside = root.parent / "outside.png"
    write_rgb(outside, frame_image(9))                  # exists, so only the escape is wrong
    meta["frames"][1][field] = value
    save()
    with pytest.raises(DatasetError,
                       match=rf"transforms\.json: frames\[1\]\.{field}: .*{message}"):
        load_dataset(root)


def test_error_depth_shape_and_negative(ns):
    root, meta, save = ns
    np.save(root / "small.npy", np.ones((H - 1, W), np.float32))
    meta["frames"][0]["depth_file_path"] = "small.npy"
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[0\]\.depth_file_path: "
                                           r"depth map .*small\.npy has shape \(11, 16\)"):
        load_dataset(root)
    neg = np.ones((H, W), np.float32)
    neg[3, 4] = -0.5
    np.save(root / "neg.npy", neg)
    meta["frames"][0]["depth_file_path"] = "neg.npy"
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[0\]\.depth_file_path: "
                                           r"depth .*neg\.npy has 1 negative"):
        load_dataset(root)


def test_error_mask_and_segmentation_shape(ns):
    root, meta, save = ns
    cv2.imwrite(str(root / "m.png"), np.ones((4, 4), np.uint8))
    meta["frames"][2]["mask_path"] = "m.png"
    save()
    with pytest.raises(DatasetError, match=r"frames\[2\]\.mask_path: mask .* has shape"):
        load_dataset(root)
    del meta["frames"][2]["mask_path"]
    np.save(root / "s.npy", np.zeros((H, W), np.float32))
    meta["frames"][2]["segmentation_path"] = "s.npy"
    save()
    with pytest.raises(DatasetError, match=r"frames\[2\]\.segmentation_path: .*expected integers"):
        load_dataset(root)


def test_error_split_names_unknown_file(ns):
    root, meta, save = ns
    meta["train_filenames"] = ["images/frame_000.png"]
    meta["test_filenames"] = ["images/frame_001.png", "images/nope.png"]
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: test_filenames\[1\]: "
                                           r"'images/nope\.png' is not the file_path of any frame"):
        load_dataset(root)


@pytest.mark.parametrize("value", [1.5, -0.1, float("nan"), "0.5"])
def test_error_time_out_of_range(ns, value):
    root, meta, save = ns
    for fr in meta["frames"]:
        fr["time"] = 0.5
    meta["frames"][2]["time"] = value
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[2\]\.time: "):
        load_dataset(root)


def test_error_time_on_some_frames_only(ns):
    root, meta, save = ns
    meta["frames"][0]["time"] = 0.0
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[1\]\.time: missing"):
        load_dataset(root)


def test_error_bad_manifest_bounds(ns):
    root, meta, save = ns
    meta["scene"] = {"bounds": [[0, 0, 0], [1, float("nan"), 1]]}
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: scene\.bounds: .*finite"):
        load_dataset(root)
    meta["scene"] = {"bounds": [[0, 0], [1, 1]]}
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: scene\.bounds: expected shape"):
        load_dataset(root)


def test_error_distortion_model(ns):
    root, meta, save = ns
    meta["camera_model"] = "EQUIRECTANGULAR"
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: camera_model: unsupported"):
        load_dataset(root)
    meta["camera_model"] = "OPENCV"
    meta["frames"][1]["k4"] = 0.1
    save()
    with pytest.raises(DatasetError, match=r"transforms\.json: frames\[1\]\.k4: k4 is not"):
        load_dataset(root)
