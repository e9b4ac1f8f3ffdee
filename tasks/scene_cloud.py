"""A tabletop scene as a point cloud: clean it, find the table, split the objects on it.

The input is a world-frame point cloud (metres, z up, horizontal table) from any depth source:
a fused multi-view depth cloud, a radiance-field depth render, a real depth camera. It may be
noisy, hold floaters, and miss much of a transparent object. :func:`prepare_cloud` drops
non-finite points, voxel downsamples, removes radius and statistical outliers and keeps or
estimates normals (open3d); :func:`fit_table` fits the near-horizontal support plane
(:class:`TablePlane`) and measures its noise; :func:`segment_objects` clusters the points above
it into objects (open3d DBSCAN) and :func:`select_clusters` picks those near a target;
:func:`orient_normals_outward` orients normals of unknown sign; :func:`cluster_axis` locates an
object's vertical axis.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from tasks.planner_config import PlannerConfig

log = logging.getLogger(__name__)

#: Averaged (voxel-downsampled) normals shorter than this are unreliable (opposite normals of a
#: thin wall cancelled): they become zero, i.e. "unknown" -- never a contact, still an obstacle.
_MIN_NORMAL_NORM = 0.5


@dataclass(frozen=True)
class TablePlane:
    """The support plane.

    Attributes:
        normal: (3,) unit normal pointing up (n_z > 0).
        offset: d of the plane n . x + d = 0, metres.
        z: median height of the plane's inlier points (the table height), metres.
        noise: robust standard deviation of the table points about the plane, metres.
        inliers: (K,) int indices of the inlier points in the cloud the plane was fitted to.
    """

    normal: np.ndarray
    offset: float
    z: float
    noise: float = 0.0
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def height(self, points: np.ndarray) -> np.ndarray:
        """(N,) signed height of (N, 3) points above the plane, metres."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset

    def object_height(self, config: PlannerConfig) -> float:
        """Height above the plane where objects start: ``min_object_height`` or 4 sigma of the
        table noise, whichever is larger. Also the fingertips' effective clearance floor."""
        return max(config.min_object_height, 4.0 * self.noise)


# ----------------------------------------------------------------------------- input checks


def _as_cloud(points, normals=None) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate (N, 3) points and optional (N, 3) normals; drop rows with non-finite points.

    Non-finite normals become zero ("unknown"). Raises ValueError for bad shapes.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals shape {nrm.shape} does not match points shape {pts.shape}")
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        log.warning("dropped %d non-finite point(s) of %d", int((~finite).sum()), len(pts))
        pts = pts[finite]
        nrm = None if nrm is None else nrm[finite]
    if nrm is not None:
        bad = ~np.isfinite(nrm).all(axis=1)
        if bad.any():
            log.warning("%d non-finite normal(s) set to unknown", int(bad.sum()))
            nrm = nrm.copy()
            nrm[bad] = 0.0
    return pts, nrm


def _normalize_rows(v: np.ndarray, min_norm: float = 1e-9) -> np.ndarray:
    """Rows scaled to unit length; rows shorter than ``min_norm`` become zero."""
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    ok = norm > min_norm
    return np.where(ok, v / np.where(ok, norm, 1.0), 0.0)


def _o3d_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(normals)
    return pcd


# ----------------------------------------------------------------------------- cloud preparation


def prepare_cloud(points, normals=None, *, viewpoint=None, table_z: float | None = None,
                  config: PlannerConfig = PlannerConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Clean a world-frame cloud: non-finite rows dropped, voxel downsample, radius and
    statistical outlier removal, normals kept or estimated.

    The statistical outlier removal (open3d) compares each point's mean neighbour distance with
    the distribution over its group, so it runs separately on the points above the table and on
    the rest (table and below; table from :func:`fit_table` on the downsampled cloud): a dense
    table would otherwise make a sparser object (glass seen poorly) look like outliers.

    Args:
        points: (N, 3) points, metres.
        normals: optional (N, 3) normals, already oriented outward (e.g. towards the camera
            that saw each point). They are averaged per voxel and re-normalised, never flipped;
            averages that cancel (two sides of a thin wall) become zero = unknown.
        viewpoint: optional (3,) camera position; estimated normals are oriented towards it.
            Without it (and without ``normals``) the estimated normals have arbitrary signs:
            orient them with :func:`orient_normals_outward` once the objects are segmented.
        table_z: known table height, metres (else RANSAC), for the outlier-removal groups.
        config: planner configuration (``voxel_size``, ``outlier_*``, ``normal_*``, table fit).

    Returns:
        (M, 3) points and (M, 3) normals (unit, or zero where unknown), M <= N.

    Raises:
        ValueError: bad shapes.
    """
    pts, nrm = _as_cloud(points, normals)
    if len(pts) == 0:
        return pts, np.zeros((0, 3))
    if nrm is not None:
        nrm = _normalize_rows(nrm)
    pcd = _o3d_cloud(pts, nrm)
    if config.voxel_size > 0:
        pcd = pcd.voxel_down_sample(config.voxel_size)
    n_voxel = len(pcd.points)
    if config.outlier_radius > 0 and config.outlier_min_points > 1:
        pcd, _ = pcd.remove_radius_outlier(nb_points=config.outlier_min_points,
                                           radius=config.outlier_radius)
    n_radius = len(pcd.points)
    if config.outlier_neighbors > 0:
        vox = np.asarray(pcd.points)
        plane = fit_table(vox, table_z=table_z, config=config)
        groups = [np.arange(n_radius)]
        if plane is not None:
            above = plane.height(vox) > plane.object_height(config)
            groups = [np.flatnonzero(above), np.flatnonzero(~above)]
        keep = []
        for group in groups:
            if len(group) > config.outlier_neighbors:
                _, idx = pcd.select_by_index(group).remove_statistical_outlier(
                    nb_neighbors=config.outlier_neighbors, std_ratio=config.outlier_std_ratio)
                group = group[np.asarray(idx, dtype=np.int64)]
            keep.append(group)
        pcd = pcd.select_by_index(np.sort(np.concatenate(keep)))
    log.debug("prepare_cloud: %d points -> %d after voxel %.4f m -> %d after radius, %d after "
              "statistical outlier removal", len(pts), n_voxel, config.voxel_size, n_radius,
              len(pcd.points))
    if nrm is not None:
        out_n = _normalize_rows(np.asarray(pcd.normals), _MIN_NORMAL_NORM)
        n_unknown = int((~out_n.any(axis=1)).sum())
        if n_unknown:
            log.debug("prepare_cloud: %d averaged normal(s) too short, set to unknown", n_unknown)
        return np.asarray(pcd.points).copy(), out_n
    if len(pcd.points) >= 3:
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(
            radius=config.normal_radius, max_nn=config.normal_max_nn))
        if viewpoint is not None:
            pcd.orient_normals_towards_camera_location(
                np.asarray(viewpoint, dtype=np.float64).reshape(3))
        out_n = _normalize_rows(np.asarray(pcd.normals))
    else:
        out_n = np.zeros((len(pcd.points), 3))
    return np.asarray(pcd.points).copy(), out_n


def fit_table(points, *, table_z: float | None = None,
              config: PlannerConfig = PlannerConfig()) -> TablePlane | None:
    """The table plane: the largest near-horizontal RANSAC plane, or the plane z = ``table_z``.

    RANSAC (open3d ``segment_plane``, seeded with ``config.seed``) is run up to 5 times; planes
    tilted more than ``max_table_tilt_deg`` (walls, box sides) are removed and the search goes on.

    Args:
        points: (N, 3) points, metres.
        table_z: known table height, metres; skips RANSAC.
        config: ``plane_distance``, ``plane_iterations``, ``max_table_tilt_deg``, ``seed``.

    Returns:
        The plane, with its noise measured from the points near it; None when no near-horizontal
        plane with at least 3 % of the points (and 50 points) was found.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if table_z is not None:
        normal, offset = np.array([0.0, 0.0, 1.0]), -float(table_z)
        inliers = np.flatnonzero(np.abs(pts[:, 2] - table_z) <= config.plane_distance)
    else:
        o3d.utility.random.seed(int(config.seed))
        remaining = np.arange(len(pts))
        min_inliers = max(50, int(0.03 * len(pts)))
        cos_tilt = math.cos(math.radians(config.max_table_tilt_deg))
        found = None
        for _ in range(5):
            if len(remaining) < min_inliers:
                break
            model, idx = _o3d_cloud(pts[remaining]).segment_plane(
                distance_threshold=config.plane_distance, ransac_n=3,
                num_iterations=config.plane_iterations)
            idx = np.asarray(idx, dtype=np.int64)
            if len(idx) < min_inliers:
                break
            n = np.asarray(model[:3], dtype=np.float64)
            scale = np.linalg.norm(n)
            n, d = n / scale, float(model[3]) / scale
            if abs(n[2]) >= cos_tilt:
                if n[2] < 0:
                    n, d = -n, -d
                found = (n, d, remaining[idx])
                break
            log.debug("fit_table: skipped a plane tilted %.1f deg (%d inliers)",
                      math.degrees(math.acos(min(1.0, abs(n[2])))), len(idx))
            remaining = np.delete(remaining, idx)
        if found is None:
            log.warning("fit_table: no near-horizontal plane found in %d points", len(pts))
            return None
        normal, offset, inliers = found
    h = pts @ normal + offset
    band = np.abs(h) < max(3.0 * config.plane_distance, 0.01)
    noise = float(1.4826 * np.median(np.abs(h[band]))) if band.any() else 0.0
    z = float(np.median(pts[inliers, 2])) if len(inliers) else float(-offset / normal[2])
    plane = TablePlane(normal=normal, offset=float(offset), z=z, noise=noise, inliers=inliers)
    log.debug("fit_table: z = %.4f m, normal %s, noise %.4f m, %d inliers",
              z, np.round(normal, 4), noise, len(inliers))
    return plane


def segment_objects(points, table: TablePlane, *,
                    config: PlannerConfig = PlannerConfig()) -> np.ndarray:
    """Cluster the points above the table into objects (open3d DBSCAN).

    Args:
        points: (N, 3) points, metres.
        table: the support plane; points higher than ``table.object_height(config)`` above it
            are clustered.
        config: ``cluster_eps``, ``cluster_min_points``.

    Returns:
        (N,) int labels: 0, 1, ... clusters by decreasing size; -1 table, below the table, or
        DBSCAN noise (isolated points, e.g. floaters). Small clusters are kept: they are
        obstacles even when :func:`select_clusters` does not grasp them.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    labels = np.full(len(pts), -1, dtype=np.int64)
    above = np.flatnonzero(table.height(pts) > table.object_height(config))
    if len(above) == 0:
        return labels
    raw = np.asarray(_o3d_cloud(pts[above]).cluster_dbscan(
        eps=config.cluster_eps, min_points=config.cluster_min_points), dtype=np.int64)
    ids, counts = np.unique(raw[raw >= 0], return_counts=True)
    order = ids[np.argsort(-counts, kind="stable")]
    remap = np.full(raw.max() + 2 if len(raw) else 1, -1, dtype=np.int64)
    remap[order] = np.arange(len(order))
    labels[above] = remap[raw]  # raw == -1 indexes the last entry, which stays -1
    log.debug("segment_objects: %d points above the table -> %d cluster(s) %s, %d noise",
              len(above), len(order), sorted(counts.tolist(), reverse=True),
              int((labels[above] < 0).sum()))
    return labels


def select_clusters(points, labels, target=None, radius: float = 0.08,
                    min_points: int = 1) -> list[int]:
    """Labels of the clusters to grasp.

    Args:
        points: (N, 3) points, metres.
        labels: (N,) cluster labels from :func:`segment_objects`.
        target: optional (x, y) world position, metres: only clusters with a point within
            ``radius`` (horizontal distance) of it are selected. None selects every cluster.
        radius: see ``target``, metres.
        min_points: clusters with fewer points are not selected.

    Returns:
        Sorted cluster labels (possibly empty).
    """
    labels = np.asarray(labels)
    clusters, counts = np.unique(labels[labels >= 0], return_counts=True)
    clusters = clusters[counts >= min_points]
    if target is None:
        return [int(c) for c in clusters]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    xy = np.asarray(target, dtype=np.float64).reshape(2)
    near = (labels >= 0) & (np.linalg.norm(pts[:, :2] - xy, axis=1) <= radius)
    return [int(c) for c in np.intersect1d(clusters, labels[near])]


def orient_normals_outward(points, normals, labels, table: TablePlane | None = None) -> np.ndarray:
    """Flip normals of unknown sign so they point out of the objects.

    Object points (label >= 0) get normals pointing away from their cluster's centroid (right
    for convex objects and for the outside of glasses, bottles and bowls); every other point
    (table, noise) gets normals pointing up along the table normal (or +z).

    Args:
        points: (N, 3) points, metres.
        normals: (N, 3) normals (unit or zero), any sign.
        labels: (N,) cluster labels (-1 = not an object).
        table: the support plane (for "up"); None uses +z.

    Returns:
        (N, 3) re-oriented normals (a new array).
    """
    pts = np.asarray(points, dtype=np.float64)
    nrm = np.array(normals, dtype=np.float64, copy=True)
    labels = np.asarray(labels)
    up = np.array([0.0, 0.0, 1.0]) if table is None else table.normal
    ref = np.broadcast_to(up, nrm.shape).copy()
    for c in np.unique(labels[labels >= 0]):
        sel = labels == c
        ref[sel] = pts[sel] - pts[sel].mean(axis=0)
    flip = np.einsum("ij,ij->i", nrm, ref) < 0
    nrm[flip] *= -1.0
    return nrm


def cluster_axis(points) -> np.ndarray:
    """(2,) horizontal position of a cluster's vertical axis: the mid-range of the 2nd-98th
    percentiles of x and y (robust to stray points, unbiased by uneven sampling density)."""
    xy = np.asarray(points, dtype=np.float64).reshape(-1, 3)[:, :2]
    lo, hi = np.percentile(xy, [2.0, 98.0], axis=0)
    return 0.5 * (lo + hi)
