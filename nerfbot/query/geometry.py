"""Geometry a robot can use: point clouds and meshes of a trained run, in world metres.

Training never moves or rescales the scene (fields take world points in the dataset's frame,
metres for every ``sims`` capture), so what these functions return is already where the
dataset's cameras put it; nothing is normalised back.

- :func:`point_cloud`: the run's depth rendered at a set of cameras and back-projected (open3d),
  coloured by the render, normals oriented towards the camera that saw each point, the flying
  pixels at depth discontinuities dropped, cropped to bounds.
- :func:`density_mesh`: marching cubes on the density at a threshold (Dex-NeRF's density
  threshold, for glass), vertex colours from the field looking at each vertex along its normal.
- :func:`tsdf_mesh`: the rendered depth fused in a truncated signed distance volume (open3d's
  sparse :class:`VoxelBlockGrid`), coloured by the renders.
- :func:`colour_by_labels`: any of them coloured by class instead, for runs with labels.

Which depth a point cloud or TSDF takes is a :class:`DepthQuery`: expected, median or threshold
depth (see :mod:`nerfbot.query.render`); ``nerfbot export`` takes a run's own default (threshold
depth for scenes with glass, from ``RUN/auto.json``) unless told otherwise.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np
import open3d as o3d
import open3d.core as o3c
import torch
import trimesh
from tqdm.auto import tqdm

from nerfbot.data.writers import write_bytes_atomic
from nerfbot.ops.cameras import Cameras, opengl_to_opencv
from nerfbot.ops.pointcloud import depth_discontinuities, depth_to_cloud, fuse_clouds
from nerfbot.models.labels import point_labels
from nerfbot.query.density import default_density_threshold
from nerfbot.query.export import label_palette
from nerfbot.query.meshing import field_mesh, inside_bounds
from nerfbot.query.render import DEPTH_MODES, render_image

#: Files :func:`write_point_cloud` and :func:`write_mesh` write, by suffix.
CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz")
MESH_SUFFIXES = (".ply", ".obj", ".glb")

#: A pixel is dropped from a point cloud or TSDF when a 4-neighbour's depth differs by more than
#: this fraction of the nearer one: the blended silhouettes ("flying pixels") of rendered depth.
DEFAULT_EDGE_JUMP = 0.05

#: Expected and median depth count only where the ray is at least this opaque.
MIN_OPACITY = 0.5


@dataclass(frozen=True)
class DepthQuery:
    """Which depth to read from a render: ``mode`` "expected", "median" or "threshold"; the
    last needs ``threshold``, a density in 1/m (Dex-NeRF: where a ray first reaches it)."""

    mode: str = "expected"
    threshold: Optional[float] = None

    def __post_init__(self):
        if self.mode not in DEPTH_MODES:
            raise ValueError(f"unknown depth mode {self.mode!r} (choose from {DEPTH_MODES})")
        if self.mode == "threshold" and not (self.threshold is not None
                                             and np.isfinite(self.threshold)
                                             and self.threshold > 0):
            raise ValueError(f"threshold depth needs a density threshold > 0 (1/m), got "
                             f"{self.threshold}")

    def of(self, img: dict) -> np.ndarray:
        """(H, W) z-depth in metres of a :func:`render_image` result, NaN where this query gives
        none (threshold never reached; expected / median depth on rays under half opaque)."""
        if self.mode == "threshold":
            return np.asarray(img["threshold_z_depth"][0], np.float32)
        z = img["median_z_depth"] if self.mode == "median" else img["z_depth"]
        return np.where(img["opacity"] >= MIN_OPACITY, z, np.nan).astype(np.float32)

    def describe(self) -> str:
        return self.mode + (f" (m = {self.threshold:g} /m)" if self.mode == "threshold" else "")


@dataclass
class RenderedDepth:
    """One camera's render for the exports: rgb (H, W, 3) in [0, 1], z-depth (H, W) metres
    (NaN = none), the camera's (4, 4) c2w and (fx, fy, cx, cy) in pixels."""

    rgb: np.ndarray
    depth: np.ndarray
    c2w: np.ndarray
    intrinsics: tuple[float, float, float, float]


def render_depths(model, cameras: Cameras, query: DepthQuery = DepthQuery(),
                  conds: Optional[Sequence] = None, progress: bool = False,
                  desc: str = "render") -> Iterator[RenderedDepth]:
    """Render every camera once (one ray per pixel centre, as a depth camera measures) and
    yield its colour and ``query``'s depth; ``conds`` gives each camera's condition vector
    (time, joints) for conditioned runs, None for static ones."""
    if conds is not None and len(conds) != len(cameras):
        raise ValueError(f"{len(conds)} conditions for {len(cameras)} cameras")
    thresholds = [query.threshold] if query.mode == "threshold" else []
    for i in tqdm(range(len(cameras)), desc=desc, unit="view", disable=not progress):
        cond = None if conds is None else conds[i]
        img = render_image(model, cameras, i, cond=cond, thresholds=thresholds, supersample=1)
        yield RenderedDepth(img["rgb"], query.of(img), cameras.c2w[i].cpu().numpy().astype(float),
                            tuple(float(getattr(cameras, k)[i]) for k in ("fx", "fy", "cx", "cy")))


def _valid_depth(view: RenderedDepth, max_edge_jump: Optional[float]) -> np.ndarray:
    """The view's depth with flying pixels (and no-depth pixels) set to NaN."""
    z = view.depth.copy()
    if max_edge_jump is not None:
        z[depth_discontinuities(z, max_edge_jump)] = np.nan
    return z


def point_cloud(model, cameras: Cameras, query: DepthQuery = DepthQuery(),
                conds: Optional[Sequence] = None, *, bounds=None, stride: int = 1,
                max_edge_jump: Optional[float] = DEFAULT_EDGE_JUMP,
                voxel: Optional[float] = None, progress: bool = False
                ) -> o3d.geometry.PointCloud:
    """The run's depth at ``cameras`` as one world-frame point cloud (metres).

    Args:
        query: which depth (:class:`DepthQuery`).
        conds: per-camera condition vectors of a conditioned run (None: static).
        bounds: (2, 3) box to keep, metres (None: keep everything rendered).
        stride: every ``stride``-th pixel per axis.
        max_edge_jump: drop pixels at relative depth jumps above this (None keeps them).
        voxel: merge points within voxels of this size, metres (None: keep all).
    Returns:
        open3d PointCloud with colours and normals (oriented towards the cameras).
    """
    clouds = []
    for view in render_depths(model, cameras, query, conds, progress, desc="point cloud"):
        z = _valid_depth(view, max_edge_jump)
        if not np.isfinite(z).any():
            continue
        fx = view.intrinsics[0]
        # normals from neighbours within about three pixels' footprint at the view's depth
        radius = 3.0 * stride * float(np.nanmedian(z)) / fx
        clouds.append(depth_to_cloud(z, *view.intrinsics, view.c2w, rgb=view.rgb,
                                     max_depth=float(np.nanmax(z)) + 1.0, stride=stride,
                                     normal_radius=radius))
    cloud = fuse_clouds(clouds)
    if bounds is not None and len(cloud.points):
        keep = inside_bounds(np.asarray(cloud.points), bounds)
        cloud = cloud.select_by_index(np.flatnonzero(keep).tolist())
    if voxel:
        cloud = cloud.voxel_down_sample(float(voxel))
    return cloud


@torch.no_grad()
def _vertex_colours(model, vertices: np.ndarray, normals: np.ndarray, cond=None,
                    chunk: int = 1 << 16) -> np.ndarray:
    """(V, 3) uint8: the field's colour at each vertex seen from outside along its normal."""
    device = model.aabb.device
    was_training = model.training
    model.eval()
    out = []
    try:
        for i in range(0, len(vertices), chunk):
            x = torch.as_tensor(vertices[i:i + chunk], dtype=torch.float32, device=device)
            d = -torch.as_tensor(np.array(normals[i:i + chunk]), dtype=torch.float32,
                                 device=device)
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            c = None
            if cond is not None:
                c = torch.as_tensor(cond, dtype=torch.float32, device=device).reshape(1, -1)
                c = c.expand(len(x), -1)
            _, feat = model.field.density(x, c)
            out.append(model.field.color(feat, d, c).clamp(0, 1).cpu().numpy())
    finally:
        model.train(was_training)
    rgb = np.concatenate(out) if out else np.zeros((0, 3))
    return (rgb * 255).round().astype(np.uint8)


def point_classes(model, points: np.ndarray) -> np.ndarray:
    """(N,) int class index of the run's label head at world points (N, 3) (static runs;
    ValueError for a run without labels)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    return point_labels(model, np.asarray(points, np.float32)).argmax(-1).cpu().numpy()


def colour_by_labels(model, geometry):
    """Recolour a point cloud (open3d) or mesh (trimesh) of the run by the class its label
    head gives each point or vertex (:func:`~nerfbot.query.export.label_palette`); returns it.
    ValueError for a run trained without labels."""
    if model.label_head is None:
        raise ValueError("this run has no label head (train it with --labels)")
    n = model.label_head.n_classes
    if isinstance(geometry, o3d.geometry.PointCloud):
        classes = point_classes(model, np.asarray(geometry.points))
        geometry.colors = o3d.utility.Vector3dVector(label_palette(n)[classes] / 255.0)
        return geometry
    classes = point_classes(model, np.asarray(geometry.vertices))
    rgb = label_palette(n)[classes]
    geometry.visual.vertex_colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)],
                                                   1)
    return geometry


def density_mesh(model, *, threshold: Optional[float] = None, resolution: int = 256,
                 bounds=None, cond=None, colours: bool = True) -> trimesh.Trimesh:
    """Marching cubes on the run's density over ``bounds`` ((2, 3) metres; None: the model's
    bounds) with ``resolution`` cells along the longest side, at density ``threshold`` (1/m;
    None: where one step of the default marcher is half opaque,
    :func:`~nerfbot.query.density.default_density_threshold`); ``cond``: the condition vector of
    a conditioned run. World metres; vertex colours from the field unless ``colours`` is
    False."""
    aabb = model.aabb.detach().cpu().numpy()
    level = default_density_threshold(aabb) if threshold is None else float(threshold)
    mesh = field_mesh(model, resolution, level, bounds, cond=cond)
    if colours and len(mesh.faces):
        rgb = _vertex_colours(model, np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals),
                              cond)
        mesh.visual.vertex_colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)
    return mesh


def tsdf_mesh(model, cameras: Cameras, query: DepthQuery = DepthQuery(),
              conds: Optional[Sequence] = None, *, voxel: Optional[float] = None, bounds=None,
              trunc_voxels: float = 4.0, max_edge_jump: Optional[float] = DEFAULT_EDGE_JUMP,
              min_views: int = 1, progress: bool = False) -> trimesh.Trimesh:
    """The run's depth at ``cameras`` fused in a TSDF (open3d ``VoxelBlockGrid``) and meshed,
    coloured by the renders.

    Args:
        voxel: TSDF voxel size, metres (None: the longest side of ``bounds`` / 256).
        bounds: (2, 3) box, metres: depth beyond it is not fused and the mesh is cropped to it
            (None: the model's bounds).
        trunc_voxels: truncation distance of the signed distance, in voxels.
        min_views: surfaces seen by fewer views (the voxels' fused weight) are left out.
        Others: as :func:`point_cloud`.
    Returns:
        A world-frame trimesh (metres) with vertex colours; empty when no depth was fused.
    """
    box = np.asarray(model.aabb.detach().cpu().numpy() if bounds is None else bounds, float)
    voxel = float((box[1] - box[0]).max() / 256 if voxel is None else voxel)
    if not (np.isfinite(voxel) and voxel > 0):
        raise ValueError(f"TSDF voxel size must be > 0 metres, got {voxel}")
    device = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
        attr_channels=((1), (1), (3)), voxel_size=voxel, block_resolution=8,
        block_count=50_000, device=device)
    trunc = trunc_voxels * voxel
    fused = 0
    for view in render_depths(model, cameras, query, conds, progress, desc="TSDF"):
        z = _valid_depth(view, max_edge_jump)
        z = np.ascontiguousarray(np.where(np.isfinite(z), z, 0.0), np.float32)
        if not (z > 0).any():
            continue
        fx, fy, cx, cy = view.intrinsics
        # open3d: OpenCV camera, pixel centres at integer coordinates
        k = o3c.Tensor(np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]]), o3c.float64)
        extrinsic = o3c.Tensor(np.linalg.inv(opengl_to_opencv(view.c2w)), o3c.float64)
        depth = o3d.t.geometry.Image(o3c.Tensor(z))
        colour = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(view.rgb, np.float32)))
        far = float(z.max()) + trunc
        # the last argument is the truncation in voxels
        blocks = grid.compute_unique_block_coordinates(depth, k, extrinsic, 1.0, far,
                                                       trunc_voxels)
        grid.integrate(blocks, depth, colour, k, k, extrinsic, 1.0, far, trunc_voxels)
        fused += 1
    if not fused:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    # a voxel's weight counts the views fused into it; open3d keeps weights above the threshold
    tmesh = grid.extract_triangle_mesh(weight_threshold=min_views - 0.5)
    verts = tmesh.vertex.positions.numpy().astype(float)
    faces = tmesh.triangle.indices.numpy().astype(np.int64)
    rgb = (tmesh.vertex.colors.numpy().clip(0, 1) * 255).round().astype(np.uint8) \
        if "colors" in tmesh.vertex else None
    keep_face = inside_bounds(verts, box, margin=voxel)[faces].all(axis=1)
    mesh = trimesh.Trimesh(verts, faces[keep_face], process=False,
                           vertex_colors=None if rgb is None else
                           np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1))
    mesh.remove_unreferenced_vertices()
    return mesh


def _atomic_target(path: Path) -> Path:
    """A hidden temporary beside ``path`` with the same suffix (open3d picks the format from it
    and writes only to paths); the caller renames it over ``path`` once written."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def write_point_cloud(cloud: o3d.geometry.PointCloud, path) -> Path:
    """Write ``cloud`` to ``path`` (.ply, .pcd or .xyz, open3d), atomically."""
    path = Path(path)
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise ValueError(f"{path}: point clouds are written as {', '.join(CLOUD_SUFFIXES)}")
    tmp = _atomic_target(path)
    try:
        if not o3d.io.write_point_cloud(str(tmp), cloud):
            raise OSError(f"{path}: open3d could not write the point cloud")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_mesh(mesh: trimesh.Trimesh, path) -> Path:
    """Write ``mesh`` to ``path`` (.ply, .obj or .glb, trimesh), atomically."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{path}: meshes are written as {', '.join(MESH_SUFFIXES)}")
    data = mesh.export(file_type=path.suffix.lower().lstrip("."))
    return write_bytes_atomic(path, data.encode() if isinstance(data, str) else data)
