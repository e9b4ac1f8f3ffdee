"""Smooth camera paths through keyframe poses: positions on a cubic spline, rotations by
spherical linear interpolation (scipy), keyframes equally spaced in time.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp


def interpolate_poses(keyframes: np.ndarray, frames: int) -> np.ndarray:
    """``frames`` camera-to-world poses (frames, 4, 4) along keyframes (K, 4, 4) (or (K, 3, 4);
    OpenGL convention, metres), the first and last frames on the first and last keyframe.

    Keyframe k sits at time k / (K - 1); the camera centres follow a natural cubic spline
    through the keyframes' centres over that time (a straight line for K = 2), the rotations
    the slerp between neighbouring keyframes. One keyframe gives ``frames`` copies of it.
    ValueError for no keyframes, frames < 1 or a rotation part that is not a rotation."""
    keys = np.asarray(keyframes, dtype=np.float64)
    if keys.ndim != 3 or keys.shape[1:] not in ((4, 4), (3, 4)) or not len(keys):
        raise ValueError(f"keyframes must be (K, 4, 4) or (K, 3, 4) with K >= 1, got "
                         f"{keys.shape}")
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rot = keys[:, :3, :3]
    if not np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-4) or \
            not np.allclose(np.linalg.det(rot), 1.0, atol=1e-4):
        raise ValueError("keyframes' rotation parts must be rotations (orthonormal, det +1)")
    out = np.tile(np.eye(4), (frames, 1, 1))
    if len(keys) == 1:
        out[:, :3, :] = keys[0, :3, :]
        return out
    times = np.linspace(0.0, 1.0, len(keys))
    t = np.linspace(0.0, 1.0, frames)
    centres = keys[:, :3, 3]
    if len(keys) == 2:
        out[:, :3, 3] = centres[0] + t[:, None] * (centres[1] - centres[0])
    else:
        out[:, :3, 3] = CubicSpline(times, centres, bc_type="natural")(t)
    out[:, :3, :3] = Slerp(times, Rotation.from_matrix(rot))(t).as_matrix()
    return out
