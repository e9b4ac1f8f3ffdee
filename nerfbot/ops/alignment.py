"""Similarity transforms between two frames, and the errors of one set of camera poses against
another.

Structure from motion recovers cameras up to a similarity (scale, rotation, translation): its
poses are compared with true ones after the least-squares similarity that maps the recovered
camera centres onto the true centres (Umeyama 1991, closed form by SVD).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + translation`` (float64; rotation (3, 3) with det +1)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    @staticmethod
    def identity() -> "Similarity":
        return Similarity(1.0, np.eye(3), np.zeros(3))

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix of the transform."""
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def points(self, xyz: np.ndarray) -> np.ndarray:
        """Transform points (..., 3)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        return self.scale * xyz @ self.rotation.T + self.translation

    def poses(self, c2w: np.ndarray) -> np.ndarray:
        """Transform c2w poses (..., 4, 4): rotations turn, centres move as points; the result
        stays rigid (the scale changes distances, not the cameras' axes)."""
        c2w = np.asarray(c2w, dtype=np.float64)
        out = c2w.copy()
        out[..., :3, :3] = self.rotation @ c2w[..., :3, :3]
        out[..., :3, 3] = self.points(c2w[..., :3, 3])
        return out

    def then(self, other: "Similarity") -> "Similarity":
        """The transform applying ``self`` first, then ``other``."""
        return Similarity(other.scale * self.scale, other.rotation @ self.rotation,
                          other.points(self.translation))


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> Similarity:
    """The similarity minimising ``sum |target_i - (s R source_i + t)|^2`` (Umeyama 1991).

    Args:
        source, target: (N, 3) corresponding points, N >= 3, not all on one line.
        with_scale: False fixes s = 1 (a rigid transform).

    Raises:
        ValueError: mismatched shapes, non-finite input, or points too degenerate (fewer than
            three, or collinear) to fix a rotation.
    """
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != tgt.shape:
        raise ValueError(f"umeyama: expected two (N, 3) arrays of equal shape, got {src.shape} "
                         f"and {tgt.shape}")
    if len(src) < 3:
        raise ValueError(f"umeyama: need at least 3 point pairs, got {len(src)}")
    if not (np.isfinite(src).all() and np.isfinite(tgt).all()):
        raise ValueError("umeyama: points must be finite")
    mu_s, mu_t = src.mean(0), tgt.mean(0)
    ds, dt = src - mu_s, tgt - mu_t
    var_s = float((ds ** 2).sum()) / len(src)
    cov = dt.T @ ds / len(src)
    u, d, vt = np.linalg.svd(cov)
    spread = max(var_s, float((dt ** 2).sum()) / len(src))
    if var_s <= 0.0 or d[1] <= 1e-12 * spread:
        raise ValueError("umeyama: the points are collinear or coincide; a rotation needs three "
                         "points that span a plane")
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rotation = u @ np.diag(sign) @ vt
    scale = float((d * sign).sum() / var_s) if with_scale else 1.0
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def robust_umeyama(source: np.ndarray, target: np.ndarray, rounds: int = 5,
                   factor: float = 3.0) -> tuple[Similarity, np.ndarray]:
    """:func:`umeyama` refitted on the inliers: pairs whose residual exceeds ``factor`` x the
    median residual are dropped, up to ``rounds`` times (one wrongly posed camera must not tilt
    the frame of all the others).

    Returns:
        (the similarity, (N,) bool inlier mask of the final fit).
    """
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    inliers = np.ones(len(src), dtype=bool)
    sim = umeyama(src, tgt)
    for _ in range(rounds):
        residual = np.linalg.norm(sim.points(src) - tgt, axis=1)
        keep = residual <= factor * max(float(np.median(residual)), 1e-12)
        if keep.sum() < 3 or np.array_equal(keep, inliers):
            break
        inliers = keep
        sim = umeyama(src[inliers], tgt[inliers])
    return sim, inliers


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(...,) angle in degrees of the rotation taking rotations ``a`` (..., 3, 3) to ``b``."""
    rel = np.swapaxes(np.asarray(a, dtype=np.float64), -1, -2) @ np.asarray(b, dtype=np.float64)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    # atan2 of sine and cosine: arccos alone loses precision near 0 (1e-16 -> 1e-6 degrees)
    axis = np.stack([rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0],
                     rel[..., 1, 0] - rel[..., 0, 1]], axis=-1)
    sin = np.linalg.norm(axis, axis=-1) / 2.0
    return np.degrees(np.arctan2(sin, cos))


@dataclass(frozen=True)
class PoseErrors:
    """Errors of estimated poses against true ones after aligning the estimate.

    Attributes:
        alignment: the similarity applied to the estimated poses (estimated -> true frame).
        rotation_deg: (N,) angle between each aligned and true camera rotation, degrees.
        translation: (N,) distance between aligned and true camera centres, true units.
        scene_size: diagonal of the true camera centres' bounding box, true units.
        inliers: (N,) bool, the cameras the alignment was fitted to.
    """

    alignment: Similarity
    rotation_deg: np.ndarray
    translation: np.ndarray
    scene_size: float
    inliers: np.ndarray

    @property
    def translation_percent(self) -> np.ndarray:
        """(N,) centre errors as a percentage of :attr:`scene_size`."""
        return 100.0 * self.translation / self.scene_size

    def summary(self) -> dict:
        """Medians and maxima (degrees, percent of the scene size, true units)."""
        return {
            "cameras": int(len(self.rotation_deg)),
            "alignment_inliers": int(self.inliers.sum()),
            "rotation_deg_median": float(np.median(self.rotation_deg)),
            "rotation_deg_max": float(np.max(self.rotation_deg)),
            "translation_median": float(np.median(self.translation)),
            "translation_percent_median": float(np.median(self.translation_percent)),
            "translation_percent_max": float(np.max(self.translation_percent)),
            "scene_size": self.scene_size,
            "alignment_scale": self.alignment.scale,
        }


def pose_errors(estimated_c2w: np.ndarray, true_c2w: np.ndarray,
                align: bool = True) -> PoseErrors:
    """Rotation and centre errors of ``estimated_c2w`` (N, 4, 4) against ``true_c2w`` (N, 4, 4).

    With ``align`` the estimate is first mapped by the similarity of the camera centres
    (:func:`robust_umeyama`; SfM poses are known up to one); otherwise the poses are compared as
    they are. Errors are reported for every camera, inlier of the alignment or not.
    """
    est = np.asarray(estimated_c2w, dtype=np.float64)
    true = np.asarray(true_c2w, dtype=np.float64)
    if est.shape != true.shape or est.shape[-2:] != (4, 4) or est.ndim != 3:
        raise ValueError(f"pose_errors: expected two (N, 4, 4) arrays of equal shape, got "
                         f"{est.shape} and {true.shape}")
    if align:
        alignment, inliers = robust_umeyama(est[:, :3, 3], true[:, :3, 3])
    else:
        alignment, inliers = Similarity.identity(), np.ones(len(est), dtype=bool)
    aligned = alignment.poses(est)
    centres = true[:, :3, 3]
    size = float(np.linalg.norm(centres.max(0) - centres.min(0)))
    return PoseErrors(
        alignment=alignment,
        rotation_deg=rotation_angle_deg(aligned[:, :3, :3], true[:, :3, :3]),
        translation=np.linalg.norm(aligned[:, :3, 3] - centres, axis=1),
        scene_size=size if size > 0 else 1.0,
        inliers=inliers,
    )
