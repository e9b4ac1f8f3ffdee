"""Pinhole cameras, c2w poses and ray generation, in the OpenGL / nerfstudio convention.

Convention (the project contract, see DESIGN.md): a pose is a camera-to-world 4x4 matrix whose
rotation columns are the camera's x (right), y (up) and z (backwards: the camera looks along -z)
axes in world coordinates. MuJoCo cameras use the same axes. The OpenCV convention (x right,
y down, z forward) appears only at library boundaries, through :func:`opengl_to_opencv`.

Pixel (u, v) has its centre at (u + 0.5, v + 0.5) in image coordinates whose origin is the top-left
corner of the top-left pixel; ``v`` grows downwards.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

# Flips the camera's y and z axes: OpenGL camera frame <-> OpenCV camera frame (an involution).
_GL_CV_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(c2w: np.ndarray) -> np.ndarray:
    """Convert c2w pose(s) (..., 4, 4) between the OpenGL and OpenCV camera conventions.

    The conversion is its own inverse, so it also maps OpenCV poses back to OpenGL.
    """
    return np.asarray(c2w, dtype=np.float64) @ _GL_CV_FLIP


opencv_to_opengl = opengl_to_opencv


def focal_from_fov(fov_deg: float, size_px: int) -> float:
    """Focal length in pixels for a full field of view ``fov_deg`` across ``size_px`` pixels."""
    if not 0.0 < fov_deg < 180.0:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_deg}")
    return 0.5 * size_px / math.tan(math.radians(fov_deg) / 2.0)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """c2w (4, 4) float64 of a camera at ``eye`` looking at ``target``, world ``up`` kept upright.

    Falls back to world y as the up hint when the viewing direction is parallel to ``up``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    norm = np.linalg.norm(forward)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"look_at: eye {eye.tolist()} and target coincide")
    forward /= norm
    up = np.asarray(up, dtype=np.float64)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, -forward, eye
    return c2w


def spherical_eye(target, radius: float, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3,) camera position at ``radius`` from ``target``, azimuth from +x, elevation from xy."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    offset = radius * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    return np.asarray(target, dtype=np.float64) + offset


def orbit_poses(target, radius: float, elevation_deg: float, count: int,
                azimuth_offset_deg: float = 0.0) -> np.ndarray:
    """(count, 4, 4) c2w poses on a ring around ``target``, evenly spaced azimuths, z up."""
    step = 360.0 / count
    return np.stack([look_at(spherical_eye(target, radius, azimuth_offset_deg + i * step,
                                           elevation_deg), target) for i in range(count)])


def check_pose(c2w: np.ndarray, where: str, tol: float = 1e-4) -> np.ndarray:
    """Validate one c2w matrix and return it as float64 (4, 4).

    Raises ``ValueError`` naming ``where`` (file and field) if the matrix has the wrong shape, is
    not finite, or its rotation is not orthonormal with determinant +1 (within ``tol``).
    """
    m = np.asarray(c2w, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4):
        raise ValueError(f"{where}: expected a 4x4 (or 3x4) matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{where}: pose contains non-finite values (NaN or inf)")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=tol):
        raise ValueError(f"{where}: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    err = np.abs(rot.T @ rot - np.eye(3)).max()
    det = np.linalg.det(rot)
    if err > tol or abs(det - 1.0) > tol:
        raise ValueError(
            f"{where}: pose is not rigid (rotation orthonormality error {err:.2e}, det {det:.4f}); "
            "scaled or sheared poses are not supported"
        )
    return m


@dataclass
class Cameras:
    """A batch of N pinhole cameras (undistorted).

    Attributes:
        c2w: (N, 4, 4) float32 camera-to-world poses, OpenGL convention, metres.
        fx, fy, cx, cy: (N,) float32 intrinsics in pixels.
        width, height: (N,) int64 image sizes in pixels.
    """

    c2w: torch.Tensor
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    @staticmethod
    def from_numpy(c2w, intrinsics, sizes) -> "Cameras":
        """Build from c2w (N, 4, 4), intrinsics (N, 4) = fx, fy, cx, cy, sizes (N, 2) = w, h."""
        intr = torch.as_tensor(np.asarray(intrinsics), dtype=torch.float32).reshape(-1, 4)
        sz = torch.as_tensor(np.asarray(sizes), dtype=torch.int64).reshape(-1, 2)
        return Cameras(
            c2w=torch.as_tensor(np.asarray(c2w), dtype=torch.float32).reshape(-1, 4, 4),
            fx=intr[:, 0].contiguous(),
            fy=intr[:, 1].contiguous(),
            cx=intr[:, 2].contiguous(),
            cy=intr[:, 3].contiguous(),
            width=sz[:, 0].contiguous(),
            height=sz[:, 1].contiguous(),
        )

    @staticmethod
    def pinhole(c2w, fov_y_deg: float, width: int, height: int) -> "Cameras":
        """Cameras of square pixels and centred principal point from c2w (4, 4) or (N, 4, 4)
        poses and a vertical field of view in degrees."""
        poses = np.asarray(c2w, dtype=np.float64).reshape(-1, 4, 4)
        f = focal_from_fov(fov_y_deg, height)
        n = len(poses)
        return Cameras.from_numpy(poses, np.tile([f, f, width / 2.0, height / 2.0], (n, 1)),
                                  np.tile([width, height], (n, 1)))

    def __getitem__(self, idx) -> "Cameras":
        def pick(t):
            out = t[idx]
            return out.unsqueeze(0) if out.dim() == t.dim() - 1 else out

        return Cameras(*(pick(getattr(self, f)) for f in
                         ("c2w", "fx", "fy", "cx", "cy", "width", "height")))

    def to(self, device) -> "Cameras":
        return Cameras(*(getattr(self, f).to(device) for f in
                         ("c2w", "fx", "fy", "cx", "cy", "width", "height")))

    def rays(self, index: int, downscale: int = 1, supersample: int = 1) -> "Rays":
        """All rays of camera ``index`` in row-major pixel order, (H*W,) rays.

        ``downscale`` > 1 renders a smaller image of the same field of view (pixel centres of
        the coarser grid). ``supersample`` S > 1 gives S x S rays per pixel instead, through the
        centres of an S x S grid of cells in each pixel: (H*S * W*S,) rays, row-major over that
        finer grid (``reshape(H, S, W, S)`` groups them by pixel).
        """
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        w = int(self.width[index]) // downscale
        h = int(self.height[index]) // downscale
        sx, sy = float(self.width[index]) / w, float(self.height[index]) / h
        dir_cam, z_per_t, radii = _image_rays_in_camera(
            w * supersample, h * supersample, sx / supersample, sy / supersample,
            *(float(getattr(self, k)[index]) for k in ("fx", "fy", "cx", "cy")))
        c2w = self.c2w[index]
        dev = c2w.device
        directions = dir_cam.to(dev) @ c2w[:3, :3].T
        return Rays(c2w[:3, 3].expand_as(directions).contiguous(), directions,
                    z_per_t.to(dev, copy=True), radii.to(dev, copy=True))

    def corner_rays(self, index: int, downscale: int = 1) -> "Rays":
        """Rays through the corners of camera ``index``'s pixels: ((H+1) * (W+1),) rays,
        row-major over the (H+1) x (W+1) grid of corners. Corner (i, j) is the top-left corner
        of pixel (i, j), so pixel (i, j) has corners (i, j), (i, j+1), (i+1, j) and (i+1, j+1),
        each shared with the pixels around it. ``downscale`` as in :meth:`rays`."""
        w = int(self.width[index]) // downscale
        h = int(self.height[index]) // downscale
        sx, sy = float(self.width[index]) / w, float(self.height[index]) / h
        dev = self.c2w.device
        v, u = torch.meshgrid(torch.arange(h + 1, dtype=torch.float32, device=dev),
                              torch.arange(w + 1, dtype=torch.float32, device=dev),
                              indexing="ij")
        return pixel_rays(self.c2w[index], self.fx[index], self.fy[index], self.cx[index],
                          self.cy[index], u.reshape(-1) * sx, v.reshape(-1) * sy, sx, sy)

    def scaled(self, factor: float) -> "Cameras":
        """The same cameras imaging at ``factor`` times the resolution (``scaled(1 / K)``: K
        times fewer pixels per side, K times larger pixels). Sizes round down to whole pixels
        (at least 1; ``W // K`` for ``1 / K``, as :meth:`rays` with ``downscale=K``) and the
        intrinsics scale by the exact size ratios per axis, so each image still spans the same
        field of view, as a ``cv2.resize`` of the image does."""
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"camera scale factor must be finite and > 0, got {factor}")

        def size(n):  # the epsilon keeps 24 * (1 / 3) at 8, not 7
            return torch.clamp(torch.floor(n.double() * factor + 1e-6), min=1).to(torch.int64)

        width, height = size(self.width), size(self.height)
        sx = (width.double() / self.width.double()).float()
        sy = (height.double() / self.height.double()).float()
        return Cameras(self.c2w.clone(), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                       width, height)


@dataclass
class Rays:
    """A bundle of R rays.

    Attributes:
        origins: (R, 3) float32 ray origins in world metres.
        directions: (R, 3) float32 unit directions; distance along a ray is ``t`` in metres.
        z_per_t: (R,) float32, z-depth per unit ray distance (cosine to the optical axis), so
            ``z_depth = t * z_per_t``.
        radii: (R,) float32 or None: the radius of the cone through the ray's pixel per unit
            ray distance (at distance ``t`` the cone's radius is ``t * radii`` metres), set by
            :func:`pixel_rays`; mip-NeRF's ``2 / sqrt(12)`` times the pixel's width. None for
            rays that do not come from pixels.
    """

    origins: torch.Tensor
    directions: torch.Tensor
    z_per_t: torch.Tensor
    radii: Optional[torch.Tensor] = None

    def __len__(self) -> int:
        return int(self.origins.shape[0])

    def __getitem__(self, idx) -> "Rays":
        return Rays(self.origins[idx], self.directions[idx], self.z_per_t[idx],
                    None if self.radii is None else self.radii[idx])

    def to(self, device) -> "Rays":
        return Rays(self.origins.to(device), self.directions.to(device), self.z_per_t.to(device),
                    None if self.radii is None else self.radii.to(device))

    @staticmethod
    def cat(bundles: list["Rays"]) -> "Rays":
        """One bundle of the rays of ``bundles``, in order (radii kept only if all have them)."""
        radii = [b.radii for b in bundles]
        return Rays(torch.cat([b.origins for b in bundles]),
                    torch.cat([b.directions for b in bundles]),
                    torch.cat([b.z_per_t for b in bundles]),
                    None if any(r is None for r in radii) else torch.cat(radii))


#: mip-NeRF's cone radius in pixel widths: a disk of this radius has the variance of a pixel
#: square (1 / 12 per axis).
PIXEL_RADIUS = 2.0 / math.sqrt(12.0)


def pixel_rays(c2w: torch.Tensor, fx, fy, cx, cy, px: torch.Tensor, py: torch.Tensor,
               pixel_w=1.0, pixel_h=1.0) -> Rays:
    """Rays through image points (px, py), given in pixel units (pixel centres at +0.5).

    Args:
        c2w: (4, 4) or (R, 4, 4) camera-to-world, OpenGL convention.
        fx, fy, cx, cy: scalars or (R,) tensors, pixels.
        px, py: (R,) image coordinates in pixels, x to the right, y downwards.
        pixel_w, pixel_h: size of the pixels the rays stand for, in pixels of these intrinsics
            (> 1 for an image rendered at a lower resolution); sets ``Rays.radii``.
    """
    dir_cam, z_per_t, radii = camera_frame_rays(fx, fy, cx, cy, px, py, pixel_w, pixel_h)
    rot = c2w[..., :3, :3]
    if rot.dim() == 2:
        directions = dir_cam @ rot.T
        origins = c2w[:3, 3].expand_as(directions)
    else:
        directions = torch.einsum("rij,rj->ri", rot, dir_cam)
        origins = c2w[:, :3, 3]
    return Rays(origins.contiguous(), directions.contiguous(), z_per_t, radii)


def camera_frame_rays(fx, fy, cx, cy, px: torch.Tensor, py: torch.Tensor, pixel_w=1.0,
                      pixel_h=1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The camera-frame half of :func:`pixel_rays` (same arguments, no pose): unit directions
    (R, 3) in the camera's OpenGL frame, z_per_t (R,) and radii (R,)."""
    dir_cam = torch.stack([(px - cx) / fx, -(py - cy) / fy, -torch.ones_like(px)], dim=-1)
    norm = dir_cam.norm(dim=-1, keepdim=True)
    dir_cam = dir_cam / norm
    z_per_t = (1.0 / norm.squeeze(-1)).contiguous()
    # mip-NeRF: the pixel's width on the z = 1 image plane, times 2 / sqrt(12); along the unit
    # direction that plane lies at distance 1 / z_per_t, so the radius per metre is scaled by z_per_t
    width = torch.sqrt(torch.as_tensor(pixel_w * pixel_h / (fx * fy), dtype=torch.float32))
    radii = (PIXEL_RADIUS * width * z_per_t).contiguous()
    return dir_cam, z_per_t, radii


@functools.lru_cache(maxsize=8)
def _image_rays_in_camera(w: int, h: int, sx: float, sy: float, fx: float, fy: float,
                          cx: float, cy: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`camera_frame_rays` of every pixel of a W x H image (row-major), pixels ``sx`` x
    ``sy`` of the intrinsics wide. Cached: the cameras of a dataset share their intrinsics, and
    these are most of the work of a pose's rays (callers must not write into the tensors)."""
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32),
                          torch.arange(w, dtype=torch.float32), indexing="ij")
    px = (u.reshape(-1) + 0.5) * sx
    py = (v.reshape(-1) + 0.5) * sy
    f32 = (lambda x: torch.tensor(x, dtype=torch.float32))
    return camera_frame_rays(f32(fx), f32(fy), f32(cx), f32(cy), px, py, sx, sy)
