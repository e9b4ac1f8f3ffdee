"""The true geometry of a MuJoCo scene as triangle meshes (trimesh), in world coordinates.

Each geom becomes a mesh in its local frame (boxes, spheres, capsules, cylinders, ellipsoids,
finite planes, meshes from ``model.mesh_vert`` / ``model.mesh_face``), placed by
``data.geom_xpos`` / ``data.geom_xmat`` (``mj_forward`` must have run). Infinite planes, height
fields and SDF geoms have no finite surface here and are skipped with a warning.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable, Optional

import mujoco
import numpy as np
import trimesh

from sims.manifest import is_infinite_plane, rendered_geoms
from sims.scene import load_model

log = logging.getLogger(__name__)

#: Icosphere subdivisions of spheres and ellipsoids (4: 5120 faces, area within 0.2 %).
SPHERE_SUBDIVISIONS = 4
#: Segments around the axis of cylinders and capsules.
SECTIONS = 64

_T = mujoco.mjtGeom


def _geom_id(model: mujoco.MjModel, geom) -> int:
    if isinstance(geom, (int, np.integer)):
        gid = int(geom)
        if not 0 <= gid < model.ngeom:
            raise ValueError(f"geom id {gid} out of range (model has {model.ngeom} geoms)")
        return gid
    gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, str(geom))
    if gid < 0:
        raise ValueError(f"the model has no geom named {geom!r}")
    return gid


def geom_local_mesh(model: mujoco.MjModel, gid: int) -> Optional[trimesh.Trimesh]:
    """Mesh of geom ``gid`` in its own frame (metres), or None when it has no finite surface."""
    kind, size = int(model.geom_type[gid]), np.asarray(model.geom_size[gid], float)
    if kind == _T.mjGEOM_BOX:
        return trimesh.creation.box(extents=2.0 * size)
    if kind == _T.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(SPHERE_SUBDIVISIONS, radius=size[0])
    if kind == _T.mjGEOM_ELLIPSOID:
        mesh = trimesh.creation.icosphere(SPHERE_SUBDIVISIONS, radius=1.0)
        mesh.vertices = mesh.vertices * size
        return mesh
    if kind == _T.mjGEOM_CAPSULE:  # radius, half-length of the cylinder part; axis = local z
        return trimesh.creation.capsule(height=2.0 * size[1], radius=size[0], count=[SECTIONS, SECTIONS])
    if kind == _T.mjGEOM_CYLINDER:  # radius, half-height
        return trimesh.creation.cylinder(radius=size[0], height=2.0 * size[1], sections=SECTIONS)
    if kind == _T.mjGEOM_PLANE:
        if size[0] <= 0 or size[1] <= 0:
            return None  # infinite plane
        x, y = size[0], size[1]
        verts = np.array([[-x, -y, 0], [x, -y, 0], [x, y, 0], [-x, y, 0]], float)
        return trimesh.Trimesh(verts, [[0, 1, 2], [0, 2, 3]], process=False)
    if kind == _T.mjGEOM_MESH:
        mid = int(model.geom_dataid[gid])
        va, vn = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
        fa, fn = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
        verts = np.asarray(model.mesh_vert[va:va + vn], float)
        faces = np.asarray(model.mesh_face[fa:fa + fn], np.int64)
        return trimesh.Trimesh(verts, faces, process=False)
    return None  # height field, SDF: not supported


def geom_mesh(model: mujoco.MjModel, data: mujoco.MjData, geom) -> Optional[trimesh.Trimesh]:
    """World-frame mesh of one geom (id or name), or None when it has no finite surface."""
    gid = _geom_id(model, geom)
    mesh = geom_local_mesh(model, gid)
    if mesh is None:
        return None
    rot = np.asarray(data.geom_xmat[gid], float).reshape(3, 3)
    verts = np.asarray(mesh.vertices, float) @ rot.T + np.asarray(data.geom_xpos[gid], float)
    return trimesh.Trimesh(verts, np.asarray(mesh.faces), process=False)


def scene_meshes(model: mujoco.MjModel, data: mujoco.MjData,
                 geoms: Optional[Iterable] = None) -> trimesh.Trimesh:
    """One world-frame mesh of the given geoms (ids or names; default: every geom).

    Geoms without a finite surface (infinite planes, height fields, SDFs) are skipped with a
    warning. The meshes are concatenated, not merged: touching geoms keep their hidden faces
    (the bottom of an object resting on the table); see
    :func:`nerfbot.query.meshing.visible_mask` to keep only what cameras see.

    Raises:
        ValueError: an unknown geom name or id, or no geom with a finite surface.
    """
    ids = range(model.ngeom) if geoms is None else [_geom_id(model, g) for g in geoms]
    parts = []
    for gid in ids:
        mesh = geom_mesh(model, data, gid)
        if mesh is None:
            if not (int(model.geom_type[gid]) == _T.mjGEOM_PLANE and geoms is None):
                log.warning("geom %r (type %d) has no finite surface; skipped",
                            model.geom(gid).name or gid, int(model.geom_type[gid]))
            continue
        parts.append(mesh)
    if not parts:
        raise ValueError("no geom with a finite surface to mesh")
    return trimesh.util.concatenate(parts)


def capture_geometry(manifest: Optional[dict]) -> Optional[tuple[trimesh.Trimesh, np.ndarray]]:
    """(world mesh of every rendered geom, content bounds (2, 3)) of the scene a capture's
    manifest names, in the state the capture rendered (``qpos0``); None when that cannot be
    known: no manifest, a source that is neither ``builtin:NAME`` nor an existing MJCF file, or
    a scene that moves across frames (joints or time)."""
    if not manifest or manifest.get("time_varying") or manifest.get("moving_joints"):
        return None
    source = str(manifest.get("source") or "")
    if source.startswith("builtin:"):
        scene = source[len("builtin:"):]
    elif source.endswith(".xml") and Path(source).is_file():
        scene = source
    else:
        return None
    model = load_model(scene)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ids = sorted({int(g.objid) for g in rendered_geoms(model, data)
                  if not is_infinite_plane(model, int(g.objid))})
    if not ids:
        return None
    bounds = np.asarray(manifest.get("bounds"), float) if manifest.get("bounds") else None
    mesh = scene_meshes(model, data, ids)
    return mesh, (bounds if bounds is not None else np.asarray(mesh.bounds, float))
