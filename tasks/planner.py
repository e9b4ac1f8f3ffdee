"""Antipodal grasp planner for a parallel-jaw gripper on a point cloud of objects on a table.

The input is a world-frame point cloud (metres, z up, horizontal table) from any depth source:
a fused multi-view depth cloud, a radiance-field depth render, a real depth camera. It may be
noisy, hold floaters, and miss much of a transparent object. Pipeline (:func:`plan_grasps`):

1. :func:`prepare_cloud` -- drop non-finite points, voxel downsample, radius and statistical
   outlier removal (open3d), keep the given normals or estimate them (open3d).
2. :func:`fit_table` -- RANSAC plane (open3d ``segment_plane``) restricted to near-horizontal
   planes, or a given ``table_z``; also measures the table's noise band.
3. :func:`segment_objects` -- points above the table band, clustered with open3d DBSCAN;
   :func:`select_clusters` keeps the cluster(s) near an optional ``target`` (x, y) hint.
4. :func:`orient_normals_outward` -- only for normals estimated here without a viewpoint.
5. :func:`antipodal_candidates` -- contact pairs (p, q) on one (locally smoothed) cluster whose
   connecting line lies in both friction cones and is within ``max_axis_tilt_deg`` of horizontal.
6. :func:`collision_free` -- the open fingers and the palm, swept from ``approach_height`` above
   the grasp down to it, contain no scene point; the fingertips clear the table.
7. score, sort, suppress near-duplicates, return :class:`~tasks.grasp_pose.Grasp` objects.

Gripper collision model (gripper frame, see :meth:`tasks.grasp_pose.Grasp.rotation`; origin at
the TCP, x = closing axis, z = up towards the palm), all from :class:`sims.gripper.GripperGeometry`:
two finger boxes ``finger_thickness`` (x) by ``finger_width`` (y) by ``finger_length`` (z) with
inner faces at x = +-open_width/2, z from -tcp_height to finger_length - tcp_height; a palm box
x in +-(max_opening/2 + finger_thickness), y in +-palm_width/2, z from finger_length - tcp_height
up by palm_height. Approach is straight down, so every box sweeps straight up.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
from scipy.sparse import coo_matrix, identity
from scipy.spatial import cKDTree

from sims.gripper import GRIPPER, GripperGeometry
from tasks.grasp_pose import Grasp

log = logging.getLogger(__name__)

#: Averaged (voxel-downsampled) normals shorter than this are unreliable (opposite normals of a
#: thin wall cancelled): they become zero, i.e. "unknown" -- never a contact, still an obstacle.
_MIN_NORMAL_NORM = 0.5


@dataclass(frozen=True)
class PlannerConfig:
    """Planner parameters (lengths in metres, angles in degrees).

    Attributes:
        friction: Coulomb friction coefficient mu; friction-cone half-angle atan(mu).
        max_axis_tilt_deg: largest angle of the contact line (p -> q) from horizontal. The
            approach is always straight down, so the gripper's closing axis is the horizontal
            projection of the contact line.
        width_margin: open width = contact width + this (must be <= ``max_opening``).
        min_width: smallest contact width (rejects pinches of thin walls and noise pairs).
        smoothing_radius: contact points and normals are averaged over this radius (same side
            of the surface only) before the antipodal test, against depth noise (0 disables).
        table_clearance: smallest height of the fingertips above the table plane.
        min_object_height: points this far above the table belong to objects (raised to 4 sigma
            of the measured table noise when that is larger).
        approach_height: the finger and palm boxes sweep from this height above the grasp down
            to it; the swept volume must be free of points.
        num_samples: contact points p sampled per planning call (shared between clusters).
        pairs_per_sample: best opposite contacts q kept per sampled p.
        max_grasps: at most this many grasps returned (after near-duplicate suppression).
        nms_distance: grasps whose centres are closer than this and whose axes differ by less
            than ``nms_angle_deg`` are duplicates; the better one is kept.
        nms_angle_deg: see ``nms_distance``.
        voxel_size: voxel downsampling size (0 disables downsampling).
        normal_radius: neighbourhood radius for normal estimation.
        normal_max_nn: most neighbours used for a normal.
        outlier_neighbors: statistical outlier removal: neighbours per point (0 disables).
        outlier_std_ratio: statistical outlier removal: standard-deviation ratio.
        outlier_radius: radius outlier removal: points with fewer than ``outlier_min_points``
            points (themselves included) within this radius are dropped. Absolute, so it also
            removes isolated floaters right next to an object, which the statistical test
            misses when floaters are many (0 disables).
        outlier_min_points: see ``outlier_radius``.
        plane_distance: RANSAC inlier distance for the table plane.
        plane_iterations: RANSAC iterations.
        max_table_tilt_deg: largest angle of the table normal from +z.
        cluster_eps: DBSCAN neighbourhood radius (must be below the gap between objects).
        cluster_min_points: DBSCAN core-point neighbour count.
        min_cluster_points: smaller clusters are not grasped (they remain obstacles).
        ignore_unclustered: points above the table that DBSCAN calls noise (isolated floaters)
            are not obstacles. False treats every remaining point as an obstacle.
        center_scale: centring term falls linearly to 0 at this horizontal distance of the grasp
            centre from the cluster's vertical axis.
        height_scale: height term saturates at this clearance (fingertips over the table, palm
            over the object, contact below the object's local top).
        weight_friction, weight_center, weight_height, weight_width: score weights; the score is
            their weighted sum of terms in [0, 1], divided by the total weight. Terms: friction
            1 - (worst cone angle / cone half-angle)^2 (flat near 0 so normal noise of a few
            degrees matters little); centre 1 - offset / ``center_scale``; height
            min(fingertip-table gap, palm-object gap, object top above the contact) /
            ``height_scale``; width 1 - width / (max_opening - width_margin) (narrower grasps
            need less free space and keep the fingers near the object).
        seed: seed for the sampling and for open3d's RANSAC.
    """

    friction: float = 0.5
    max_axis_tilt_deg: float = 15.0
    width_margin: float = 0.02
    min_width: float = 0.01
    smoothing_radius: float = 0.005
    table_clearance: float = 0.005
    min_object_height: float = 0.005
    approach_height: float = 0.15
    num_samples: int = 400
    pairs_per_sample: int = 2
    max_grasps: int = 20
    nms_distance: float = 0.005
    nms_angle_deg: float = 10.0
    voxel_size: float = 0.003
    normal_radius: float = 0.01
    normal_max_nn: int = 30
    outlier_neighbors: int = 20
    outlier_std_ratio: float = 2.0
    outlier_radius: float = 0.008
    outlier_min_points: int = 4
    plane_distance: float = 0.004
    plane_iterations: int = 500
    max_table_tilt_deg: float = 10.0
    cluster_eps: float = 0.01
    cluster_min_points: int = 10
    min_cluster_points: int = 30
    ignore_unclustered: bool = True
    center_scale: float = 0.02
    height_scale: float = 0.02
    weight_friction: float = 0.35
    weight_center: float = 0.25
    weight_height: float = 0.2
    weight_width: float = 0.2
    seed: int = 0

    def __post_init__(self):
        positive = ("friction", "width_margin", "approach_height", "plane_distance",
                    "normal_radius", "cluster_eps", "center_scale", "height_scale")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("min_width", "table_clearance", "min_object_height", "voxel_size",
                     "nms_distance", "smoothing_radius", "outlier_radius", "weight_friction",
                     "weight_center", "weight_height", "weight_width"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PlannerConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.max_axis_tilt_deg < 90 or not 0 <= self.max_table_tilt_deg < 90:
            raise ValueError("PlannerConfig tilt angles must be in [0, 90) degrees")
        if self.num_samples < 1 or self.pairs_per_sample < 1 or self.max_grasps < 1:
            raise ValueError("PlannerConfig num_samples, pairs_per_sample, max_grasps must be >= 1")
        if (self.weight_friction + self.weight_center + self.weight_height
                + self.weight_width) <= 0:
            raise ValueError("PlannerConfig score weights must not all be 0")

    @property
    def cone_half_angle(self) -> float:
        """Friction-cone half-angle atan(mu), radians."""
        return math.atan(self.friction)


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


@dataclass(frozen=True)
class AntipodalPairs:
    """Antipodal contact pairs on one cluster (K pairs).

    Attributes:
        p, q: (K, 3) contact points (smoothed, see :func:`smooth_surface`), metres.
        width: (K,) contact distance |q - p|, metres.
        axis: (K, 3) horizontal unit closing axis: the projection of q - p, its sign made
            canonical (x > 0, or y > 0 when x = 0) as the gripper is symmetric; world frame.
        tilt: (K,) angle of q - p from horizontal, radians.
        angle_p, angle_q: (K,) angle of q - p from -n_p and from n_q (both within the friction
            cone), radians.
    """

    p: np.ndarray
    q: np.ndarray
    width: np.ndarray
    axis: np.ndarray
    tilt: np.ndarray
    angle_p: np.ndarray
    angle_q: np.ndarray

    def __len__(self) -> int:
        return len(self.width)

    @property
    def center(self) -> np.ndarray:
        """(K, 3) grasp centres (p + q) / 2, metres."""
        return 0.5 * (self.p + self.q)

    def subset(self, index) -> "AntipodalPairs":
        """The pairs selected by a boolean mask or an index array."""
        return AntipodalPairs(*(getattr(self, f)[index] for f in
                                ("p", "q", "width", "axis", "tilt", "angle_p", "angle_q")))


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


# ----------------------------------------------------------------------------- candidates


def smooth_surface(points, normals, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Average each point and normal with its neighbours on the same side of the surface.

    Neighbours are the points within ``radius`` whose normals make less than 60 deg with the
    point's normal (so the two faces of a thin wall are not mixed). Points with unknown (zero)
    normals are left unchanged.

    Args:
        points: (N, 3) points, metres.
        normals: (N, 3) unit (or zero) normals.
        radius: neighbourhood radius, metres.

    Returns:
        (N, 3) smoothed points and (N, 3) smoothed unit (or zero) normals.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 2:
        return pts.copy(), nrm.copy()
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        pairs = pairs[np.einsum("ij,ij->i", nrm[pairs[:, 0]], nrm[pairs[:, 1]]) > 0.5]
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    adj = coo_matrix((np.ones(len(i)), (i, j)), shape=(len(pts), len(pts))).tocsr()
    adj = adj + identity(len(pts), format="csr")
    count = np.asarray(adj.sum(axis=1)).ravel()
    smooth_p = (adj @ pts) / count[:, None]
    smooth_n = _normalize_rows(adj @ nrm)
    known = nrm.any(axis=1)
    return np.where(known[:, None], smooth_p, pts), np.where(known[:, None], smooth_n, 0.0)


def antipodal_candidates(points, normals, *, sample: np.ndarray | None = None,
                         geometry: GripperGeometry = GRIPPER,
                         config: PlannerConfig = PlannerConfig(),
                         rng: np.random.Generator | None = None) -> AntipodalPairs:
    """Antipodal contact pairs on one object's points.

    The points and normals are first smoothed (:func:`smooth_surface`, ``smoothing_radius``) so
    that depth noise does not bias the contact width or the friction angles. A pair (p, q) of
    smoothed points with outward normals n_p, n_q is kept when, for a = (q - p) / |q - p|: the
    angle between a and -n_p and the angle between a and n_q are both within the friction cone
    atan(mu); a is within ``max_axis_tilt_deg`` of horizontal; and ``min_width`` <= |q - p| <=
    ``max_opening - width_margin``. For each sampled p the ``pairs_per_sample`` best q (smallest
    larger cone angle) are kept.

    Args:
        points: (N, 3) object points, metres.
        normals: (N, 3) outward unit normals (zero = unknown, never a contact).
        sample: optional indices of the contact points p to try; default: ``num_samples``
            random points among those whose normals can meet a near-horizontal axis.
        geometry: gripper (``max_opening``).
        config: thresholds (see :class:`PlannerConfig`).
        rng: random generator for the sampling (default: seeded with ``config.seed``).

    Returns:
        The pairs (possibly none).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if pts.shape != nrm.shape:
        raise ValueError(f"normals shape {nrm.shape} does not match points shape {pts.shape}")
    rng = np.random.default_rng(config.seed) if rng is None else rng
    cone = config.cone_half_angle
    cos_cone = math.cos(cone)
    sin_tilt = math.sin(math.radians(config.max_axis_tilt_deg))
    max_width = geometry.max_opening - config.width_margin
    # a normal can only lie within the cone of a near-horizontal axis if it is not too vertical
    nz_limit = math.sin(min(math.pi / 2, cone + math.radians(config.max_axis_tilt_deg)))
    if config.smoothing_radius > 0:
        pts, nrm = smooth_surface(pts, nrm, config.smoothing_radius)
    usable = np.flatnonzero(nrm.any(axis=1) & (np.abs(nrm[:, 2]) <= nz_limit))
    empty = AntipodalPairs(*(np.zeros((0, 3)),) * 2, np.zeros(0), np.zeros((0, 3)),
                           *(np.zeros(0),) * 3)
    if len(usable) < 2 or max_width <= config.min_width:
        return empty
    if sample is None:
        count = min(config.num_samples, len(usable))
        sample = rng.choice(usable, size=count, replace=False)
    else:
        sample = np.asarray(sample, dtype=np.int64)
        sample = sample[np.isin(sample, usable)]
    q_pts, q_nrm = pts[usable], nrm[usable]
    k = min(config.pairs_per_sample, len(usable))
    chunk = max(1, 400_000 // len(usable))
    out_p, out_q, out_ap, out_aq = [], [], [], []
    for start in range(0, len(sample), chunk):
        idx = sample[start:start + chunk]
        d = q_pts[None, :, :] - pts[idx, None, :]  # (m, n, 3)
        w = np.linalg.norm(d, axis=2)
        a = d / np.maximum(w, 1e-12)[..., None]
        cos_p = -np.einsum("mnk,mk->mn", a, nrm[idx])
        cos_q = np.einsum("mnk,nk->mn", a, q_nrm)
        ok = ((w >= config.min_width) & (w <= max_width) & (np.abs(a[..., 2]) <= sin_tilt)
              & (cos_p >= cos_cone) & (cos_q >= cos_cone))
        worst = np.where(ok, np.minimum(cos_p, cos_q), -np.inf)  # larger = better
        if k < worst.shape[1]:
            best = np.argpartition(-worst, k - 1, axis=1)[:, :k]
        else:
            best = np.broadcast_to(np.arange(k), worst.shape)
        rows = np.repeat(np.arange(len(idx)), k)
        cols = best.ravel()
        good = np.isfinite(worst[rows, cols])
        rows, cols = rows[good], cols[good]
        out_p.append(idx[rows])
        out_q.append(usable[cols])
        out_ap.append(np.arccos(np.clip(cos_p[rows, cols], -1.0, 1.0)))
        out_aq.append(np.arccos(np.clip(cos_q[rows, cols], -1.0, 1.0)))
    if not out_p or sum(len(x) for x in out_p) == 0:
        return empty
    ip, iq = np.concatenate(out_p), np.concatenate(out_q)
    p, q = pts[ip], pts[iq]
    d = q - p
    width = np.linalg.norm(d, axis=1)
    horiz = d.copy()
    horiz[:, 2] = 0.0
    axis = _normalize_rows(horiz)
    # one canonical sign per axis (the gripper is symmetric): x > 0, or y > 0 when x == 0
    flip = (axis[:, 0] < 0) | ((axis[:, 0] == 0) & (axis[:, 1] < 0))
    axis[flip] *= -1.0
    tilt = np.arcsin(np.clip(np.abs(d[:, 2]) / np.maximum(width, 1e-12), 0.0, 1.0))
    return AntipodalPairs(p=p, q=q, width=width, axis=axis, tilt=tilt,
                          angle_p=np.concatenate(out_ap), angle_q=np.concatenate(out_aq))


# ----------------------------------------------------------------------------- collisions


def _gripper_extent(geometry: GripperGeometry) -> float:
    """Horizontal radius (about the TCP) of everything the gripper occupies, metres."""
    half_x = geometry.max_opening / 2 + geometry.finger_thickness
    half_y = max(geometry.finger_width, geometry.palm_width) / 2
    return math.hypot(half_x, half_y)


def sweep_check(centers, axes, open_widths, obstacles, *, table: TablePlane | None = None,
                geometry: GripperGeometry = GRIPPER, config: PlannerConfig = PlannerConfig(),
                chunk_pairs: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Collision test of top-down grasps, with the local object top between the fingers.

    Args:
        centers: (K, 3) TCP positions, metres.
        axes: (K, 3) closing axes (only the horizontal part is used: the approach is straight
            down, so the gripper's z is world z).
        open_widths: (K,) finger opening (inner faces at +-open_width/2), metres.
        obstacles: (M, 3) scene points, metres.
        table: support plane; when given, every fingertip corner must be at least
            ``max(table_clearance, table.object_height(config))`` above it.
        geometry, config: gripper boxes and ``approach_height`` / ``table_clearance``.
        chunk_pairs: memory bound on (candidate, point) pairs per step.

    Returns:
        free: (K,) bool, no obstacle point inside the finger boxes or the palm box swept from
        ``approach_height`` above the grasp down to it, and the fingertips clear the table.
        top: (K,) highest obstacle point between the open fingers (|x| < open_width/2,
        |y| <= palm_width/2, above the fingertips), as a height above the TCP, metres;
        -inf where there is none.
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    ax = np.asarray(axes, dtype=np.float64).reshape(-1, 3).copy()
    ow = np.broadcast_to(np.asarray(open_widths, dtype=np.float64), (len(c),))
    obs = np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)
    g = geometry
    ax[:, 2] = 0.0
    u = _normalize_rows(ax)
    v = np.stack([-u[:, 1], u[:, 0], np.zeros(len(u))], axis=1)  # y = z x x
    free = np.ones(len(c), dtype=bool)
    top = np.full(len(c), -np.inf)
    tip = -g.tcp_height
    finger_top = tip + g.finger_length + config.approach_height
    palm_lo = tip + g.finger_length
    palm_hi = palm_lo + g.palm_height + config.approach_height
    palm_x = g.max_opening / 2 + g.finger_thickness
    if table is not None:
        floor = max(config.table_clearance, table.object_height(config))
        for sx in (-1.0, 1.0):
            for dx in (0.0, g.finger_thickness):
                for sy in (-1.0, 1.0):
                    corner = (c + (sx * (ow / 2 + dx))[:, None] * u
                              + (sy * g.finger_width / 2) * v)
                    corner[:, 2] += tip
                    free &= table.height(corner) >= floor
    if len(obs) == 0 or len(c) == 0:
        return free, top
    tree = cKDTree(obs[:, :2])
    reach = _gripper_extent(g) + 1e-6
    lo_c, hi_c = c[:, :2].min(axis=0), c[:, :2].max(axis=0)
    near = np.asarray(tree.query_ball_point(0.5 * (lo_c + hi_c),
                                            0.5 * float(np.linalg.norm(hi_c - lo_c)) + reach),
                      dtype=np.int64)
    if len(near) == 0:
        return free, top
    pts = obs[near]
    step = max(1, chunk_pairs // len(pts))
    for s in range(0, len(c), step):
        sl = slice(s, s + step)
        d = pts[None, :, :] - c[sl, None, :]  # (k, m, 3)
        lx = np.abs(np.einsum("kmj,kj->km", d[..., :2], u[sl, :2]))
        ly = np.abs(np.einsum("kmj,kj->km", d[..., :2], v[sl, :2]))
        lz = d[..., 2]
        half = ow[sl, None] / 2
        finger = ((lx >= half) & (lx <= half + g.finger_thickness)
                  & (ly <= g.finger_width / 2) & (lz >= tip) & (lz <= finger_top))
        palm = (lx <= palm_x) & (ly <= g.palm_width / 2) & (lz >= palm_lo) & (lz <= palm_hi)
        free[sl] &= ~(finger | palm).any(axis=1)
        between = (lx < half) & (ly <= g.palm_width / 2) & (lz >= tip)
        top[sl] = np.where(between, lz, -np.inf).max(axis=1)
    return free, top


def collision_free(centers, axes, open_widths, obstacles, *, table: TablePlane | None = None,
                   geometry: GripperGeometry = GRIPPER,
                   config: PlannerConfig = PlannerConfig()) -> np.ndarray:
    """(K,) bool: the top-down grasps are free of collisions (see :func:`sweep_check`).

    Args:
        centers: (K, 3) TCP positions, metres.
        axes: (K, 3) closing axes (horizontal part used).
        open_widths: (K,) or scalar finger opening, metres.
        obstacles: (M, 3) scene points, metres (the whole cleaned cloud, table included: table
            points lie below the fingertips when the fingertips clear the table).
        table: support plane for the fingertip clearance (None: no table test).
        geometry, config: gripper and planner parameters.
    """
    return sweep_check(centers, axes, open_widths, obstacles, table=table,
                       geometry=geometry, config=config)[0]


def grasp_collision_free(grasp: Grasp, obstacles, *, open_width: float | None = None,
                         table: TablePlane | None = None, geometry: GripperGeometry = GRIPPER,
                         config: PlannerConfig = PlannerConfig()) -> bool:
    """:func:`collision_free` for one :class:`Grasp`; the opening defaults to
    ``grasp.info["open_width"]`` or else ``width + width_margin`` (capped at max_opening)."""
    if open_width is None:
        open_width = grasp.info.get("open_width",
                                    min(grasp.width + config.width_margin, geometry.max_opening))
    return bool(collision_free(np.asarray(grasp.center)[None], np.asarray(grasp.axis)[None],
                               [open_width], obstacles, table=table, geometry=geometry,
                               config=config)[0])


# ----------------------------------------------------------------------------- planning


def _suppress_duplicates(centers: np.ndarray, axes: np.ndarray, order: np.ndarray,
                         config: PlannerConfig) -> list[int]:
    """Greedy non-maximum suppression over ``order`` (best first); returns kept indices."""
    kept: list[int] = []
    cos_nms = math.cos(math.radians(config.nms_angle_deg))
    for i in order:
        if kept:
            k = np.asarray(kept)
            close = np.linalg.norm(centers[k] - centers[i], axis=1) < config.nms_distance
            parallel = np.abs(axes[k] @ axes[i]) > cos_nms
            if (close & parallel).any():
                continue
        kept.append(int(i))
        if len(kept) >= config.max_grasps:
            break
    return kept


def plan_grasps(points, normals=None, *, target=None, target_radius: float = 0.08,
                table_z: float | None = None, viewpoint=None,
                geometry: GripperGeometry = GRIPPER,
                config: PlannerConfig = PlannerConfig()) -> list[Grasp]:
    """Top-down parallel-jaw grasps on the objects of a tabletop point cloud, best first.

    Args:
        points: (N, 3) world-frame points, metres, z up; any depth source.
        normals: optional (N, 3) outward normals (e.g. oriented towards each view's camera before
            merging); kept (never flipped). Without them, normals are estimated and oriented
            towards ``viewpoint`` if given, else away from each object's centroid.
        target: optional (x, y), metres: grasp only the cluster(s) with points within
            ``target_radius`` of it; nothing there -> [].
        target_radius: see ``target``, metres.
        table_z: known table height, metres (default: RANSAC fit).
        viewpoint: optional (3,) camera position for orienting estimated normals.
        geometry: gripper dimensions.
        config: planner parameters.

    Returns:
        Up to ``config.max_grasps`` grasps sorted by score (descending). ``Grasp.width`` is the
        contact width; ``info`` holds ``open_width`` (width + margin), the score terms
        (``friction``, ``center``, ``height``, ``width_term``), the cone angles and axis tilt
        (degrees), the contacts, the cluster label and the table height.

    Raises:
        ValueError: bad shapes or arguments. Non-finite points are dropped (logged); an empty
        cloud, no table or no graspable object gives [].
    """
    if target is not None:
        target = np.asarray(target, dtype=np.float64).reshape(-1)
        if target.shape != (2,) or not np.isfinite(target).all():
            raise ValueError(f"target must be a finite (x, y) pair, got {target}")
    if not target_radius > 0:
        raise ValueError(f"target_radius must be > 0, got {target_radius}")
    if table_z is not None and not np.isfinite(table_z):
        raise ValueError(f"table_z must be finite, got {table_z}")
    if viewpoint is not None:
        viewpoint = np.asarray(viewpoint, dtype=np.float64).reshape(-1)
        if viewpoint.shape != (3,):
            raise ValueError(f"viewpoint must have shape (3,), got {viewpoint.shape}")
    if normals is not None and np.shape(normals) != np.shape(points):
        raise ValueError(f"normals shape {np.shape(normals)} does not match points shape "
                         f"{np.shape(points)}")

    pts, nrm = prepare_cloud(points, normals, viewpoint=viewpoint, table_z=table_z,
                             config=config)
    if len(pts) == 0:
        log.info("plan_grasps: empty cloud")
        return []
    table = fit_table(pts, table_z=table_z, config=config)
    if table is None:
        return []
    labels = segment_objects(pts, table, config=config)
    if normals is None and viewpoint is None:
        nrm = orient_normals_outward(pts, nrm, labels, table)
    chosen = select_clusters(pts, labels, target, target_radius, config.min_cluster_points)
    if not chosen:
        log.info("plan_grasps: no object%s", "" if target is None else
                 f" within {target_radius:.3f} m of target {np.round(target, 3).tolist()}")
        return []

    height = table.height(pts)
    obstacle = height > table.object_height(config)
    if config.ignore_unclustered:
        obstacle &= labels >= 0
    obstacles = pts[obstacle]

    rng = np.random.default_rng(config.seed)
    sizes = np.array([(labels == c).sum() for c in chosen], dtype=np.float64)
    quota = np.maximum(1, np.round(config.num_samples * sizes / sizes.sum())).astype(int)
    cone = config.cone_half_angle
    max_contact = geometry.max_opening - config.width_margin
    wsum = (config.weight_friction + config.weight_center + config.weight_height
            + config.weight_width)

    rows: list[dict] = []
    for label, n_samples in zip(chosen, quota):
        sel = labels == label
        c_pts, c_nrm = pts[sel], nrm[sel]
        pairs = antipodal_candidates(c_pts, c_nrm, geometry=geometry, rng=rng,
                                     config=replace(config, num_samples=int(n_samples)))
        log.debug("plan_grasps: cluster %d (%d points): %d antipodal pairs",
                  label, len(c_pts), len(pairs))
        if len(pairs) == 0:
            continue
        center = pairs.center
        open_w = np.minimum(pairs.width + config.width_margin, geometry.max_opening)
        free, top = sweep_check(center, pairs.axis, open_w, obstacles, table=table,
                                geometry=geometry, config=config)
        log.debug("plan_grasps: cluster %d: %d of %d collision-free", label, int(free.sum()),
                  len(pairs))
        if not free.any():
            continue
        pairs, center, open_w, top = pairs.subset(free), center[free], open_w[free], top[free]
        axis_xy = cluster_axis(c_pts)
        # score terms, each in [0, 1]
        s_fric = np.clip(1.0 - (np.maximum(pairs.angle_p, pairs.angle_q) / cone) ** 2, 0, 1)
        off = np.linalg.norm(center[:, :2] - axis_xy, axis=1)
        s_center = np.clip(1.0 - off / config.center_scale, 0.0, 1.0)
        tip_gap = table.height(center) - geometry.tcp_height - max(
            config.table_clearance, table.object_height(config))
        palm_gap = geometry.finger_length - geometry.tcp_height - top  # palm underside - top
        depth = top  # how far the object's local top is above the contact
        clearance = np.minimum(np.minimum(tip_gap, palm_gap), depth)
        s_height = np.clip(clearance / config.height_scale, 0.0, 1.0)
        s_width = np.clip(1.0 - pairs.width / max_contact, 0.0, 1.0)
        score = (config.weight_friction * s_fric + config.weight_center * s_center
                 + config.weight_height * s_height + config.weight_width * s_width) / wsum
        for i in range(len(pairs)):
            rows.append(dict(center=center[i], axis=pairs.axis[i], width=float(pairs.width[i]),
                             score=float(score[i]), info={
                                 "open_width": float(open_w[i]),
                                 "friction": float(s_fric[i]), "center": float(s_center[i]),
                                 "height": float(s_height[i]), "width_term": float(s_width[i]),
                                 "angle_p_deg": float(np.degrees(pairs.angle_p[i])),
                                 "angle_q_deg": float(np.degrees(pairs.angle_q[i])),
                                 "tilt_deg": float(np.degrees(pairs.tilt[i])),
                                 "axis_offset": float(off[i]),
                                 "contact_p": pairs.p[i].tolist(),
                                 "contact_q": pairs.q[i].tolist(),
                                 "cluster": int(label), "table_z": table.z}))
    if not rows:
        log.info("plan_grasps: no collision-free antipodal grasp on %d cluster(s)", len(chosen))
        return []
    scores = np.array([r["score"] for r in rows])
    order = np.argsort(-scores, kind="stable")
    kept = _suppress_duplicates(np.array([r["center"] for r in rows]),
                                np.array([r["axis"] for r in rows]), order, config)
    grasps = [Grasp(center=np.asarray(rows[i]["center"], dtype=np.float64).copy(),
                    axis=np.asarray(rows[i]["axis"], dtype=np.float64).copy(),
                    width=rows[i]["width"], score=rows[i]["score"], info=rows[i]["info"])
              for i in kept]
    log.info("plan_grasps: %d grasp(s) from %d candidate(s) on %d cluster(s); best score %.3f",
             len(grasps), len(rows), len(chosen), grasps[0].score)
    return grasps

