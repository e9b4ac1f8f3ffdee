"""Antipodal grasp planner for a parallel-jaw gripper on a point cloud of objects on a table.

The input is a world-frame point cloud (metres, z up, horizontal table) from any depth source
(see :mod:`tasks.scene_cloud`). Pipeline (:func:`plan_grasps`, parameters in
:class:`~tasks.planner_config.PlannerConfig`):

1. :func:`~tasks.scene_cloud.prepare_cloud` -- drop non-finite points, voxel downsample, radius
   and statistical outlier removal (open3d), keep the given normals or estimate them (open3d).
2. :func:`~tasks.scene_cloud.fit_table` -- RANSAC plane (open3d ``segment_plane``) restricted to
   near-horizontal planes, or a given ``table_z``; also measures the table's noise band.
3. :func:`~tasks.scene_cloud.segment_objects` -- points above the table band, clustered with
   open3d DBSCAN; :func:`~tasks.scene_cloud.select_clusters` keeps the cluster(s) near an
   optional ``target`` (x, y) hint.
4. :func:`~tasks.scene_cloud.orient_normals_outward` -- only for normals estimated there without
   a viewpoint.
5. :func:`antipodal_candidates` (this module) -- contact pairs (p, q) on one (locally smoothed)
   cluster whose connecting line lies in both friction cones and is within
   ``max_axis_tilt_deg`` of horizontal.
6. :func:`~tasks.gripper_collision.sweep_check` -- the open fingers and the palm, swept from
   ``approach_height`` above the grasp down to it, contain no scene point; the fingertips clear
   the table (box model in :mod:`tasks.gripper_collision`).
7. score, sort, suppress near-duplicates (this module), return
   :class:`~tasks.grasp_pose.Grasp` objects.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix, identity
from scipy.spatial import cKDTree

from sims.gripper import GRIPPER, GripperGeometry
from tasks.grasp_pose import Grasp
from tasks.gripper_collision import sweep_check
from tasks.planner_config import PlannerConfig
from tasks.scene_cloud import (_normalize_rows, cluster_axis, fit_table, orient_normals_outward,
                               prepare_cloud, segment_objects, select_clusters)

log = logging.getLogger(__name__)


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
