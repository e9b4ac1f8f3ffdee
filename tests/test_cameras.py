"""Cameras and ray generation (nerfbot.ops.cameras): pixel-centre convention, optical axis,
z-depth factor, OpenGL <-> OpenCV conversion, look_at, pose validation, downscaled rays."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nerfbot.ops.cameras import (Cameras, check_pose, focal_from_fov, look_at, opencv_to_opengl,
                                 opengl_to_opencv, orbit_poses, pixel_rays)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    c2w = np.eye(4)
    c2w[:3, :3] = random_rotation(rng)
    c2w[:3, 3] = rng.normal(size=3)
    return c2w


def one_camera(c2w, fx, fy, cx, cy, w, h) -> Cameras:
    return Cameras.from_numpy(np.asarray(c2w)[None], [[fx, fy, cx, cy]], [[w, h]])


# ----------------------------------------------------------------------------- pixel convention

def test_pixel_centre_convention_2x2():
    """Pixel (0, 0) of a 2x2 image with cx = cy = 1 is centred at image point (0.5, 0.5): its
    ray goes up and to the left of the optical axis (x right, y up, looking along -z)."""
    cams = one_camera(np.eye(4), 1.0, 1.0, 1.0, 1.0, 2, 2)
    rays = cams.rays(0)
    assert len(rays) == 4
    d = rays.directions.double()
    # row-major: (u, v) = (0, 0), (1, 0), (0, 1), (1, 1)
    expect = torch.tensor([[-0.5, 0.5, -1.0], [0.5, 0.5, -1.0], [-0.5, -0.5, -1.0],
                           [0.5, -0.5, -1.0]], dtype=torch.float64)
    expect = expect / expect.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(d, expect, rtol=0, atol=1e-7)
    # the ray through pixel (0, 0) meets the image plane z = -1 at (x, y) = (-0.5, +0.5)
    hit = d[0] / -d[0, 2]
    torch.testing.assert_close(hit[:2], torch.tensor([-0.5, 0.5], dtype=torch.float64),
                               rtol=0, atol=1e-7)
    assert torch.equal(rays.origins, torch.zeros(4, 3))


def test_image_rays_equal_pixel_rays_bitwise_and_are_not_shared():
    """Cameras.rays caches the camera-frame rays of an intrinsics: its rays are bitwise the
    pixel_rays of the pixel centres, at full and lower resolution, and writing into one
    image's rays does not reach the next image's."""
    poses = np.stack([random_pose(s) for s in (1, 2)])
    cams = Cameras.from_numpy(poses, [[30.0, 31.0, 16.0, 12.5]] * 2, [[32, 24]] * 2)
    for index in (0, 1):
        for k in (1, 2, 3):
            w, h = 32 // k, 24 // k
            sx, sy = 32 / w, 24 / h
            v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32),
                                  torch.arange(w, dtype=torch.float32), indexing="ij")
            ref = pixel_rays(cams.c2w[index], cams.fx[index], cams.fy[index], cams.cx[index],
                             cams.cy[index], (u.reshape(-1) + 0.5) * sx,
                             (v.reshape(-1) + 0.5) * sy, sx, sy)
            got = cams.rays(index, k)
            for name in ("origins", "directions", "z_per_t", "radii"):
                assert torch.equal(getattr(got, name), getattr(ref, name)), (index, k, name)
    first = cams.rays(0)
    first.z_per_t.mul_(2.0)
    first.radii.zero_()
    again = cams.rays(0)
    assert not torch.equal(again.z_per_t, first.z_per_t) and bool((again.radii > 0).all())


def test_centre_ray_of_odd_image_is_the_optical_axis():
    c2w = random_pose(0)
    w, h = 7, 5
    cams = one_camera(c2w, 6.0, 5.0, w / 2, h / 2, w, h)
    rays = cams.rays(0)
    centre = (h // 2) * w + w // 2
    axis = -torch.from_numpy(c2w[:3, 2]).float()  # the camera looks along its -z column
    torch.testing.assert_close(rays.directions[centre], axis, rtol=0, atol=1e-6)
    assert rays.z_per_t[centre].item() == pytest.approx(1.0, abs=1e-7)
    torch.testing.assert_close(rays.origins, torch.from_numpy(c2w[:3, 3]).float().expand(w * h, 3))


def test_directions_unit_and_z_per_t_is_cosine_to_axis():
    c2w = random_pose(1)
    cams = one_camera(c2w, 20.0, 18.0, 15.3, 11.7, 32, 24)
    rays = cams.rays(0)
    d = rays.directions.double()
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d), dtype=torch.float64), rtol=0,
                               atol=1e-6)
    axis = -torch.from_numpy(c2w[:3, 2])
    torch.testing.assert_close(rays.z_per_t.double(), d @ axis, rtol=0, atol=1e-6)
    assert float(rays.z_per_t.min()) > 0.5 and float(rays.z_per_t.max()) <= 1.0
    # z-depth = t * z_per_t: the point at distance t has that depth along the optical axis
    t = 2.5
    p = rays.origins.double() + t * d
    z = (p - torch.from_numpy(c2w[:3, 3])) @ axis
    torch.testing.assert_close(z, t * rays.z_per_t.double(), rtol=0, atol=1e-5)


def test_rays_reproject_to_their_pixels_with_opencv_intrinsics():
    """Ray through (px, py), converted to the OpenCV convention, projects back to (px, py) with
    u = fx X / Z + cx, v = fy Y / Z + cy: the pixel convention agrees with cv2's."""
    c2w = random_pose(2)
    fx, fy, cx, cy, w, h = 30.0, 28.0, 16.4, 11.2, 32, 24
    rays = one_camera(c2w, fx, fy, cx, cy, w, h).rays(0)
    v, u = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    px, py = u.reshape(-1) + 0.5, v.reshape(-1) + 0.5
    points = rays.origins.double().numpy() + 3.0 * rays.directions.double().numpy()
    cv = opengl_to_opencv(c2w)
    cam = (points - cv[:3, 3]) @ cv[:3, :3]  # world -> OpenCV camera frame
    assert (cam[:, 2] > 0).all()  # in front of the camera: +z forward
    np.testing.assert_allclose(fx * cam[:, 0] / cam[:, 2] + cx, px, atol=1e-4)
    np.testing.assert_allclose(fy * cam[:, 1] / cam[:, 2] + cy, py, atol=1e-4)


def test_pixel_rays_batched_poses_match_single_pose():
    poses = np.stack([random_pose(s) for s in range(5)])
    px = torch.tensor([0.5, 3.2, 10.0, 7.7, 1.0])
    py = torch.tensor([2.5, 0.1, 5.0, 9.9, 4.0])
    batched = pixel_rays(torch.from_numpy(poses).float(), 9.0, 8.0, 5.0, 4.0, px, py)
    for i in range(5):
        single = pixel_rays(torch.from_numpy(poses[i]).float(), 9.0, 8.0, 5.0, 4.0, px[i:i + 1],
                            py[i:i + 1])
        torch.testing.assert_close(batched.directions[i], single.directions[0], rtol=0, atol=1e-6)
        torch.testing.assert_close(batched.origins[i], single.origins[0], rtol=0, atol=0)
        torch.testing.assert_close(batched.z_per_t[i], single.z_per_t[0], rtol=0, atol=1e-7)


# ----------------------------------------------------------------------------- downscale

@pytest.mark.parametrize("w,h,k", [(8, 6, 2), (5, 7, 2), (9, 9, 3), (12, 10, 1)])
def test_rays_downscale_keeps_the_field_of_view(w, h, k):
    """A downscaled image is the same camera at w // k x h // k pixels with intrinsics scaled
    by the exact size ratio: its rays go through the centres of the coarse pixels."""
    c2w = random_pose(3)
    fx, fy, cx, cy = 11.0, 10.0, w / 2 + 0.3, h / 2 - 0.2
    cams = one_camera(c2w, fx, fy, cx, cy, w, h)
    rays = cams.rays(0, downscale=k)
    ws, hs = w // k, h // k
    assert len(rays) == ws * hs
    sx, sy = ws / w, hs / h
    small = one_camera(c2w, fx * sx, fy * sy, cx * sx, cy * sy, ws, hs).rays(0)
    torch.testing.assert_close(rays.directions, small.directions, rtol=0, atol=1e-6)
    torch.testing.assert_close(rays.z_per_t, small.z_per_t, rtol=0, atol=1e-6)
    # the corner rays of the full and the coarse image bound the same field of view
    full = cams.rays(0)
    ang = lambda r: torch.acos((r.directions @ -torch.from_numpy(c2w[:3, 2]).float()).clamp(-1, 1))
    assert float(ang(rays).max()) <= float(ang(full).max()) + 1e-6


# ----------------------------------------------------------------------------- conventions

def test_opengl_to_opencv_involution_flips_y_and_z():
    poses = np.stack([random_pose(s) for s in range(4)])
    cv = opengl_to_opencv(poses)
    assert cv.shape == (4, 4, 4) and cv.dtype == np.float64
    np.testing.assert_array_equal(opencv_to_opengl(cv), poses)
    np.testing.assert_array_equal(cv[:, :, 0], poses[:, :, 0])
    np.testing.assert_array_equal(cv[:, :, 1], -poses[:, :, 1])
    np.testing.assert_array_equal(cv[:, :, 2], -poses[:, :, 2])
    np.testing.assert_array_equal(cv[:, :, 3], poses[:, :, 3])
    for p in cv:
        check_pose(p, "converted")  # still a rigid, right-handed pose


def test_look_at_is_rigid_and_looks_at_the_target():
    rng = np.random.default_rng(4)
    for _ in range(20):
        eye, target = rng.normal(size=3) * 3, rng.normal(size=3)
        c2w = look_at(eye, target)
        check_pose(c2w, "look_at")
        np.testing.assert_allclose(c2w[:3, 3], eye)
        fwd = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(-c2w[:3, 2], fwd, atol=1e-12)
        assert abs(c2w[2, 0]) < 1e-12  # camera x axis horizontal (world z up)
        assert c2w[2, 1] > 0  # camera y axis points upwards
        # the centre ray of a camera at this pose hits the target
        rays = pixel_rays(torch.from_numpy(c2w), 10.0, 10.0, 5.0, 5.0,
                          torch.tensor([5.0], dtype=torch.float64),
                          torch.tensor([5.0], dtype=torch.float64))
        np.testing.assert_allclose(rays.directions[0].numpy(), fwd, atol=1e-12)
    # looking straight down (parallel to up) still gives a rigid pose looking down
    down = look_at([0.0, 0.0, 2.0], [0.0, 0.0, 0.0])
    check_pose(down, "down")
    np.testing.assert_allclose(-down[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)
    with pytest.raises(ValueError, match="coincide"):
        look_at([1.0, 2.0, 3.0], [1.0, 2.0, 3.0])


def test_orbit_poses_look_at_the_target_from_the_ring():
    target = np.array([0.1, -0.2, 0.3])
    poses = orbit_poses(target, 2.0, 30.0, 6)
    assert poses.shape == (6, 4, 4)
    for p in poses:
        check_pose(p, "orbit")
        assert np.linalg.norm(p[:3, 3] - target) == pytest.approx(2.0)
        assert p[2, 3] - target[2] == pytest.approx(2.0 * math.sin(math.radians(30.0)))
        fwd = (target - p[:3, 3]) / 2.0
        np.testing.assert_allclose(-p[:3, 2], fwd, atol=1e-12)


def test_focal_from_fov():
    assert focal_from_fov(90.0, 64) == pytest.approx(32.0, rel=1e-12)
    assert focal_from_fov(60.0, 100) == pytest.approx(50.0 / math.tan(math.pi / 6), rel=1e-12)
    for bad in (0.0, 180.0, -5.0):
        with pytest.raises(ValueError, match="field of view"):
            focal_from_fov(bad, 64)


# ----------------------------------------------------------------------------- check_pose

WHERE = "scene/transforms.json: frames[3].transform_matrix"


def test_check_pose_accepts_rigid_and_3x4():
    p = random_pose(5)
    out = check_pose(p.astype(np.float32), WHERE)
    assert out.shape == (4, 4) and out.dtype == np.float64
    np.testing.assert_allclose(out, p, atol=1e-6)
    np.testing.assert_array_equal(check_pose(p[:3].tolist(), WHERE), p)


@pytest.mark.parametrize("kind", ["nan", "inf", "scaled", "sheared", "reflection", "shape",
                                  "last_row", "shape_4x3"])
def test_check_pose_rejects_with_a_message_naming_the_field(kind):
    p = random_pose(6)
    if kind == "nan":
        p[1, 2] = np.nan
    elif kind == "inf":
        p[0, 3] = np.inf
    elif kind == "scaled":
        p[:3, :3] *= 1.01
    elif kind == "sheared":
        shear = np.eye(3)
        shear[0, 1] = 0.05
        p[:3, :3] = p[:3, :3] @ shear
    elif kind == "reflection":
        p[:3, 0] = -p[:3, 0]
    elif kind == "shape":
        p = p[:3, :3]
    elif kind == "last_row":
        p[3] = [0.0, 0.0, 0.1, 1.0]
    elif kind == "shape_4x3":
        p = p[:, :3]
    with pytest.raises(ValueError) as err:
        check_pose(p, WHERE)
    assert WHERE in str(err.value)


def test_check_pose_tolerance():
    p = random_pose(7)
    p[:3, :3] *= 1.0 + 1e-6  # far below the default tolerance of 1e-4
    check_pose(p, WHERE)
    with pytest.raises(ValueError, match="rigid"):
        check_pose(p, WHERE, tol=1e-8)


# ----------------------------------------------------------------------------- Cameras container

def test_cameras_indexing_keeps_a_batch_dimension():
    poses = np.stack([random_pose(s) for s in range(3)])
    intr = [[10.0, 11.0, 4.0, 3.0], [20.0, 21.0, 8.0, 6.0], [30.0, 31.0, 12.0, 9.0]]
    cams = Cameras.from_numpy(poses, intr, [[8, 6], [16, 12], [24, 18]])
    assert len(cams) == 3
    one = cams[1]
    assert len(one) == 1 and one.fx.shape == (1,) and int(one.width[0]) == 16
    torch.testing.assert_close(one.rays(0).directions, cams.rays(1).directions, rtol=0, atol=0)
    assert len(cams.rays(2)) == 24 * 18


# ----------------------------------------------------------------------------- supersampling

def _project(rays, c2w, fx, fy, cx, cy) -> np.ndarray:
    """(R, 2) image points (pixels) where ``rays`` of camera ``c2w`` cross the image plane."""
    points = rays.origins.double().numpy() + 3.0 * rays.directions.double().numpy()
    cv = opengl_to_opencv(c2w)
    cam = (points - cv[:3, 3]) @ cv[:3, :3]
    return np.stack([fx * cam[:, 0] / cam[:, 2] + cx, fy * cam[:, 1] / cam[:, 2] + cy], -1)


@pytest.mark.parametrize("s,k", [(2, 1), (3, 1), (2, 2)])
def test_supersampled_rays_go_through_the_cell_centres_of_their_pixel(s, k):
    """rays(i, downscale=k, supersample=s): s x s rays per (downscaled) pixel through the
    centres of an s x s grid of cells over it, row-major over the finer grid; a pixel's rays
    average to its centre ray's image point."""
    c2w = random_pose(4)
    fx, fy, cx, cy, w, h = 30.0, 28.0, 16.4, 11.2, 12, 8
    cams = one_camera(c2w, fx, fy, cx, cy, w, h)
    rays = cams.rays(0, downscale=k, supersample=s)
    ws, hs = w // k, h // k
    assert len(rays) == ws * s * hs * s
    uv = _project(rays, c2w, fx, fy, cx, cy).reshape(hs, s, ws, s, 2)
    pixel = w / ws  # a downscaled pixel's width in full-resolution pixels (here exactly k)
    cells = (np.arange(s) + 0.5) / s
    v, u = np.meshgrid(np.arange(hs), np.arange(ws), indexing="ij")
    for a in range(s):
        for b in range(s):
            np.testing.assert_allclose(uv[:, a, :, b, 0], (u + cells[b]) * pixel, atol=1e-4)
            np.testing.assert_allclose(uv[:, a, :, b, 1], (v + cells[a]) * pixel, atol=1e-4)
    centre = _project(cams.rays(0, downscale=k), c2w, fx, fy, cx, cy).reshape(hs, ws, 2)
    np.testing.assert_allclose(uv.mean((1, 3)), centre, atol=1e-4)
    with pytest.raises(ValueError, match="supersample"):
        cams.rays(0, supersample=0)
