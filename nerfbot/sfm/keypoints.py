"""Sparse depth for DS-NeRF: every 3D point an image sees, as (u, v, z-depth, sigma) rows.

The width of a keypoint's depth Gaussian comes from its point's reprojection error: an error of
e pixels at depth z displaces the point e z / f sideways; seen from cameras whose rays to it
meet at angle theta at most, that uncertainty stretches to (e z / f) / sin(theta) along the
viewing ray. The error is floored at :data:`MIN_ERROR_PX` (a point that fits exactly is not
known exactly) and sin(theta) at :data:`MIN_SIN_ANGLE` (nearly parallel rays fix no depth; the
mapper drops points under 1.5 degrees anyway). The width is at least the footprint z / f' of
one pixel of the image the field trains on (focal f' after resizing): the keypoint supervises
that pixel's rays, which spread over that much of the surface. Narrower targets cost the
tabletop's few-view runs PSNR (BENCHMARKS.md, section 12).
"""

from __future__ import annotations

import numpy as np
import pycolmap

#: Smallest reprojection error assumed for a point, pixels.
MIN_ERROR_PX = 0.5
#: Smallest sine of a point's triangulation angle used for its depth's width.
MIN_SIN_ANGLE = 0.05


def image_keypoints(rec: "pycolmap.Reconstruction", scale_x: float = 1.0,
                    scale_y: float = 1.0) -> dict[str, np.ndarray]:
    """Image name -> (K, 4) float32 keypoints of every registered image: u, v in pixels of the
    image resized by (``scale_x``, ``scale_y``) (centres at +0.5, distorted as the image is),
    z-depth and its standard deviation in the reconstruction's units."""
    images = {i: im for i, im in rec.images.items() if im.has_pose}
    centres = {i: np.asarray(im.projection_center()) for i, im in images.items()}
    # per point: the widest angle between its viewing rays, per observing image
    widest: dict[tuple[int, int], float] = {}
    for pid, point in rec.points3D.items():
        ids = [el.image_id for el in point.track.elements if el.image_id in images]
        if len(ids) < 2:
            continue
        rays = np.stack([point.xyz - centres[i] for i in ids])
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        cos = np.clip(rays @ rays.T, -1.0, 1.0)
        sin_widest = np.sqrt(1.0 - cos.min(axis=1) ** 2)
        for i, s in zip(ids, sin_widest):
            widest[(i, pid)] = float(s)
    out = {}
    for i, im in images.items():
        m = im.cam_from_world().matrix()
        camera = rec.cameras[im.camera_id]
        focal = float(camera.mean_focal_length())
        train_focal = focal * min(scale_x, scale_y)
        rows = []
        for p2d in im.points2D:
            if not p2d.has_point3D():
                continue
            pid = p2d.point3D_id
            s = widest.get((i, pid))
            if s is None:
                continue
            point = rec.points3D[pid]
            z = float(m[2, :3] @ point.xyz + m[2, 3])
            if z <= 0:
                continue
            error = max(float(point.error), MIN_ERROR_PX)
            sigma = max(error * z / focal / max(s, MIN_SIN_ANGLE), z / train_focal)
            u, v = p2d.xy
            rows.append((u * scale_x, v * scale_y, z, sigma))
        out[im.name] = np.asarray(rows, dtype=np.float32).reshape(-1, 4)
    return out
