"""Surfaces of a trained field and how far they lie from a true surface: marching cubes on the
density grid, surface sampling, camera visibility and the Chamfer distance.

Marching cubes uses ``skimage.measure.marching_cubes`` when scikit-image is installed, else
open3d's flying-edges isosurface (``TriangleMesh.create_isosurfaces``; open3d is a core
dependency). Visibility tests and point-to-surface distances use open3d's ``RaycastingScene``
(Embree).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial import cKDTree

from nerfbot.query.density import default_density_threshold, density_grid

#: Distance (metres) within which a sample counts as matched in F-scores: 1 cm.
DEFAULT_FSCORE_DISTANCE = 0.01

try:  # optional: open3d's isosurfaces otherwise
    from skimage.measure import marching_cubes as skimage_marching_cubes
except ImportError:
    skimage_marching_cubes = None


def marching_cubes(volume: np.ndarray, level: float, backend: str = "auto"
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Isosurface of ``volume`` (X, Y, Z) at ``level``: vertices (V, 3) in index coordinates
    (i, j, k) and triangles (F, 3). Empty arrays when the volume never crosses ``level``.

    backend: "skimage", "open3d" or "auto" (scikit-image if installed, else open3d).
    """
    volume = np.ascontiguousarray(volume, np.float32)
    if not (volume.min() < level < volume.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    if backend == "auto":
        backend = "open3d" if skimage_marching_cubes is None else "skimage"
    if backend == "skimage":
        if skimage_marching_cubes is None:
            raise ValueError("marching-cubes backend 'skimage' needs scikit-image (pip install "
                             "scikit-image)")
        verts, faces, _, _ = skimage_marching_cubes(volume, level)
        return np.asarray(verts, float), np.asarray(faces, np.int64)
    if backend == "open3d":
        mesh = o3d.t.geometry.TriangleMesh.create_isosurfaces(o3d.core.Tensor(volume), [float(level)])
        if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        verts = mesh.vertex.positions.numpy().astype(float)[:, ::-1]  # (x, y, z) = (k, j, i)
        return np.ascontiguousarray(verts), mesh.triangle.indices.numpy().astype(np.int64)
    raise ValueError(f"unknown marching-cubes backend {backend!r} (auto, skimage, open3d)")


def field_mesh(model, resolution: int = 128, threshold: Optional[float] = None, bounds=None,
               chunk: int = 1 << 16, backend: str = "auto",
               respect_occupancy: bool = True, cond=None) -> trimesh.Trimesh:
    """Mesh of a trained model's density field: marching cubes on a grid over ``bounds``.

    Args:
        model: a :class:`~nerfbot.models.base.Model` (its ``field`` answers ``density``).
        resolution: grid cells along the longest side of ``bounds``.
        threshold: density (1/m) of the surface; None: :func:`default_density_threshold` of the
            model's bounds.
        bounds: (2, 3) region to mesh, metres (default: the model's ``aabb``). Pass the scene's
            content bounds to mesh only the content.
        backend: marching-cubes implementation, see :func:`marching_cubes`.
        respect_occupancy: zero density where the occupancy grid (if any) is empty.
        cond: (D,) condition vector of a conditioned model (a time, joint values); None for
            static ones.

    Returns:
        A world-frame trimesh (metres); empty (no faces) when no density reaches the threshold.
        The volume is padded with empty space, so surfaces that reach the bounds are closed
        there by flat caps on the bounds.
    """
    aabb = model.aabb.detach().cpu().numpy()
    bounds = aabb if bounds is None else np.asarray(bounds, float)
    level = default_density_threshold(aabb) if threshold is None else float(threshold)
    volume, spacing = density_grid(model, bounds, resolution, chunk, respect_occupancy, cond)
    volume = np.pad(volume, 1, constant_values=0.0)
    verts, faces = marching_cubes(volume, level, backend)
    if len(faces) == 0:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    # surfaces closed by the padding lie half a cell outside: flatten them onto the bounds
    world = np.clip(bounds[0] + (verts - 1.0) * spacing, bounds[0], bounds[1])
    return trimesh.Trimesh(world, faces, process=True)


def sample_surface(mesh: trimesh.Trimesh, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points (count, 3) uniformly distributed over the area of ``mesh``; (0, 3) for an
    empty mesh."""
    if mesh is None or len(mesh.faces) == 0 or mesh.area <= 0:
        return np.zeros((0, 3))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, float)


def inside_bounds(points: np.ndarray, bounds, margin: float = 1e-6) -> np.ndarray:
    """(N,) bool: points within ``bounds`` (2, 3), widened by ``margin`` metres."""
    lo, hi = np.asarray(bounds, float)
    return np.all((points >= lo - margin) & (points <= hi + margin), axis=1)


def visible_mask(points: np.ndarray, mesh: trimesh.Trimesh, c2w: np.ndarray,
                 intrinsics: np.ndarray, sizes: np.ndarray, tolerance: float = 2e-3) -> np.ndarray:
    """(N,) bool: the point is seen by at least one camera, i.e. it projects inside that
    camera's image and the ray from the camera centre first meets ``mesh`` no nearer than
    ``tolerance`` metres before it. ``points`` should lie on ``mesh``.

    Args:
        c2w: (V, 4, 4) camera-to-world poses (OpenGL convention: the camera looks along -z).
        intrinsics: (V, 4) fx, fy, cx, cy pixels; sizes: (V, 2) width, height pixels.
    """
    points = np.asarray(points, float)
    visible = np.zeros(len(points), bool)
    if len(points) == 0 or len(mesh.faces) == 0:
        return visible
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    for pose, (fx, fy, cx, cy), (w, h) in zip(np.asarray(c2w, float), intrinsics, sizes):
        todo = np.flatnonzero(~visible)
        if len(todo) == 0:
            break
        origin, rot = pose[:3, 3], pose[:3, :3]
        cam = (points[todo] - origin) @ rot  # camera frame: x right, y up, -z forward
        z = -cam[:, 2]
        front = z > 1e-6
        z = np.where(front, z, 1.0)
        u, v = fx * cam[:, 0] / z + cx, cy - fy * cam[:, 1] / z
        todo = todo[front & (u >= 0) & (u < w) & (v >= 0) & (v < h)]
        if len(todo) == 0:
            continue
        offset = points[todo] - origin
        dist = np.linalg.norm(offset, axis=1)
        rays = np.concatenate([np.broadcast_to(origin, offset.shape), offset / dist[:, None]], 1)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        visible[todo[t_hit >= dist - tolerance]] = True
    return visible


def surface_distance(points: np.ndarray, mesh: trimesh.Trimesh) -> np.ndarray:
    """(N,) distance (metres) from each point to the nearest point of ``mesh``'s surface
    (open3d ``RaycastingScene.compute_distance``); inf for an empty mesh."""
    points = np.asarray(points, float).reshape(-1, 3)
    if len(mesh.faces) == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    query = o3d.core.Tensor(points.astype(np.float32))
    return scene.compute_distance(query).numpy().astype(float)


def compare_meshes(pred: trimesh.Trimesh, gt: trimesh.Trimesh, count: int = 100_000,
                   bounds=None, cameras: Optional[tuple] = None, seed: int = 0,
                   fscore_at: float = DEFAULT_FSCORE_DISTANCE) -> dict:
    """Chamfer distance between surfaces ``pred`` and ``gt``, metres -> reported in mm.

    Each surface gets ``count`` area-uniform samples; accuracy is the mean distance from the
    ``pred`` samples to the ``gt`` surface, completeness from the ``gt`` samples to the ``pred``
    surface, and chamfer their mean. Distances go to the other *surface* (exact point-to-
    triangle), not to the other's samples: sample-to-sample nearest neighbours have a floor of
    about half the sample spacing (2.7 mm for the tabletop at 100k samples), as large as the
    errors being measured.

    Args:
        bounds: (2, 3) keep only samples inside these bounds (metres).
        cameras: (c2w, intrinsics, sizes) as in :func:`visible_mask`: keep only samples some
            camera sees (each mesh occludes its own samples), so surfaces no camera observes
            (an object's base on the table, the table's underside) do not count.

        fscore_at: distance (metres) within which a sample counts as matched, for precision
            (pred samples near gt), recall (gt samples near pred) and their F-score.

    Returns:
        chamfer_mm, accuracy_mm (pred -> gt), completeness_mm (gt -> pred), precision, recall
        and fscore (fractions in [0, 1]), pred_points and gt_points (samples kept), pred_faces.
        NaN distances (and 0 scores) when a surface is empty or none of its samples is kept.
    """
    kept = []
    for i, mesh in enumerate((pred, gt)):
        pts = sample_surface(mesh, count, seed + i)
        if bounds is not None and len(pts):
            pts = pts[inside_bounds(pts, bounds)]
        if cameras is not None and len(pts):
            pts = pts[visible_mask(pts, mesh, *cameras)]
        kept.append(pts)
    to_gt = surface_distance(kept[0], gt) if len(gt.faces) else np.zeros(0)
    to_pred = surface_distance(kept[1], pred) if len(pred.faces) else np.zeros(0)
    return {**distance_scores(to_gt, to_pred, fscore_at), "pred_points": len(kept[0]),
            "gt_points": len(kept[1]), "pred_faces": int(len(pred.faces))}


def distance_scores(to_gt: np.ndarray, to_pred: np.ndarray,
                    fscore_at: float = DEFAULT_FSCORE_DISTANCE) -> dict:
    """Chamfer-style scores from the distances (metres) of predicted samples to the true surface
    (``to_gt``) and of true samples to the prediction (``to_pred``): chamfer_mm, accuracy_mm,
    completeness_mm (means; NaN when a side has no samples), and precision, recall, fscore at
    ``fscore_at`` metres (fractions; 0 when a side has no samples)."""
    nan = float("nan")
    acc = float(np.mean(to_gt)) if len(to_gt) else nan
    comp = float(np.mean(to_pred)) if len(to_pred) else nan
    precision = float(np.mean(to_gt <= fscore_at)) if len(to_gt) else 0.0
    recall = float(np.mean(to_pred <= fscore_at)) if len(to_pred) else 0.0
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"chamfer_mm": 1e3 * 0.5 * (acc + comp), "accuracy_mm": 1e3 * acc,
            "completeness_mm": 1e3 * comp, "precision": precision, "recall": recall,
            "fscore": fscore}


def compare_cloud(points: np.ndarray, gt: trimesh.Trimesh, count: int = 100_000, bounds=None,
                  cameras: Optional[tuple] = None, seed: int = 0,
                  fscore_at: float = DEFAULT_FSCORE_DISTANCE) -> dict:
    """Scores of a point cloud (N, 3) against the true surface ``gt``, as
    :func:`compare_meshes`: accuracy from (a random ``count`` of) the cloud's points to the
    ``gt`` surface, completeness from ``count`` visible ``gt`` samples to their nearest point
    of the whole cloud (a cloud has no surface: the distance includes the gaps between its
    points, small for dense clouds).

    Returns:
        :func:`distance_scores`' keys, pred_points (the cloud's points inside ``bounds``) and
        gt_points (kept).
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    if bounds is not None and len(pts):
        pts = pts[inside_bounds(pts, bounds)]
    some = pts if len(pts) <= count else \
        pts[np.random.default_rng(seed).choice(len(pts), count, replace=False)]
    truth = sample_surface(gt, count, seed + 1)
    if bounds is not None and len(truth):
        truth = truth[inside_bounds(truth, bounds)]
    if cameras is not None and len(truth):
        truth = truth[visible_mask(truth, gt, *cameras)]
    to_gt = surface_distance(some, gt) if len(gt.faces) else np.zeros(0)
    to_pred = cKDTree(pts).query(truth)[0] if len(pts) and len(truth) else np.zeros(0)
    return {**distance_scores(to_gt, to_pred, fscore_at), "pred_points": len(pts),
            "gt_points": len(truth)}
