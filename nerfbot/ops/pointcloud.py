"""Depth maps → world-frame point clouds with normals (open3d), from any depth source.

A depth map is z-depth in metres (NaN / inf / <= 0 = no depth) seen by a pinhole camera with a
c2w pose in the project's OpenGL convention; pixel centres sit at +0.5. open3d back-projects with
OpenCV conventions and pixel centres at integer coordinates, so the principal point is shifted by
half a pixel and the pose converted once, here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Iterable, Optional

import numpy as np
import open3d as o3d

if TYPE_CHECKING:
    import open3d as o3d

# open3d is imported where it is used: depth_discontinuities serves sims' depth sensor, and a
# capture should not pay for (or need the system libraries of) open3d.

from nerfbot.ops.cameras import opengl_to_opencv


def depth_discontinuities(depth: np.ndarray, rel_jump: float) -> np.ndarray:
    """(H, W) bool: pixels with a 4-neighbour whose z-depth differs by more than ``rel_jump``
    times the nearer of the two (both sides of the jump are marked). Non-finite depths count
    as very far. These are the "flying pixels" of depth sensors and the blended silhouettes of a
    radiance field's expected depth."""
    z = np.where(np.isfinite(depth), np.asarray(depth, dtype=np.float64), 1e6)
    out = np.zeros(z.shape, dtype=bool)
    dy = np.abs(np.diff(z, axis=0)) > rel_jump * np.minimum(z[1:], z[:-1])
    dx = np.abs(np.diff(z, axis=1)) > rel_jump * np.minimum(z[:, 1:], z[:, :-1])
    out[1:] |= dy
    out[:-1] |= dy
    out[:, 1:] |= dx
    out[:, :-1] |= dx
    return out


def _intrinsic(fx: float, fy: float, cx: float, cy: float, width: int, height: int):
    return o3d.camera.PinholeCameraIntrinsic(int(width), int(height), float(fx), float(fy),
                                             float(cx) - 0.5, float(cy) - 0.5)


def depth_to_cloud(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                   c2w: np.ndarray, *, rgb: Optional[np.ndarray] = None, max_depth: float = 100.0,
                   normals: bool = True, normal_radius: float = 0.01, normal_max_nn: int = 30,
                   stride: int = 1, max_edge_jump: Optional[float] = None
                   ) -> o3d.geometry.PointCloud:
    """Back-project one z-depth map into a world-frame point cloud.

    Args:
        depth: (H, W) z-depth, metres; non-finite or non-positive pixels are skipped.
        fx, fy, cx, cy: intrinsics in pixels (pixel centres at +0.5).
        c2w: (4, 4) camera-to-world pose, OpenGL convention.
        rgb: optional (H, W, 3) colours (uint8 or float in [0, 1]).
        max_depth: depths beyond this (metres) are skipped.
        normals: estimate normals (open3d, hybrid radius / k-NN search) and orient them towards
            the camera centre, so they point out of the surfaces the camera saw.
        stride: use every ``stride``-th pixel.
        max_edge_jump: drop pixels at depth discontinuities larger than this fraction of the
            depth (:func:`depth_discontinuities`); None keeps them.

    Returns:
        An open3d PointCloud in world coordinates (metres).
    """
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    height, width = depth.shape
    keep = np.isfinite(depth) & (depth > 0) & (depth <= max_depth)
    if max_edge_jump is not None:
        keep &= ~depth_discontinuities(depth, max_edge_jump)
    clean = np.where(keep, depth, 0.0)
    clean = np.ascontiguousarray(clean, dtype=np.float32)
    extrinsic = np.linalg.inv(opengl_to_opencv(np.asarray(c2w, dtype=np.float64)))
    intr = _intrinsic(fx, fy, cx, cy, width, height)
    if rgb is not None:
        colour = np.asarray(rgb)
        if colour.shape[:2] != depth.shape:
            raise ValueError(f"rgb {colour.shape} and depth {depth.shape} differ in size")
        colour = colour.astype(np.uint8) if colour.dtype == np.uint8 else \
            (np.clip(colour, 0, 1) * 255).astype(np.uint8)
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(colour[..., :3])), o3d.geometry.Image(clean),
            depth_scale=1.0, depth_trunc=float(max_depth), convert_rgb_to_intensity=False)
        cloud = o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, intr, extrinsic)
        if stride > 1:
            cloud = cloud.uniform_down_sample(stride * stride)
    else:
        cloud = o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(clean), intr, extrinsic, depth_scale=1.0,
            depth_trunc=float(max_depth), stride=int(stride))
    if normals and len(cloud.points) >= 3:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius,
                                                                    max_nn=normal_max_nn))
        cloud.orient_normals_towards_camera_location(np.asarray(c2w, dtype=np.float64)[:3, 3])
    return cloud


def fuse_clouds(clouds: Iterable[o3d.geometry.PointCloud],
                voxel: Optional[float] = None) -> o3d.geometry.PointCloud:
    """Merge clouds (keeping their normals), optionally voxel-downsampled (``voxel`` metres)."""
    merged = o3d.geometry.PointCloud()
    for cloud in clouds:
        merged += cloud
    if voxel and len(merged.points):
        merged = merged.voxel_down_sample(float(voxel))
    return merged


def cloud_arrays(cloud: o3d.geometry.PointCloud) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """(points (N, 3) float64, normals (N, 3) float64 or None) of an open3d cloud."""
    points = np.asarray(cloud.points, dtype=np.float64)
    normals = np.asarray(cloud.normals, dtype=np.float64) if cloud.has_normals() else None
    return points, normals
