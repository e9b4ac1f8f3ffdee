"""The scene manifest: what a capture's content is, so nerfbot models only what the scene needs.

The manifest is a JSON-serialisable dict written with every capture (``transforms.json``'s
top-level ``scene``):

- ``name``, ``source``: scene name and where its MJCF came from.
- ``bounds``: [[xmin, ymin, zmin], [xmax, ymax, zmax]] world AABB of all rendered geoms, metres.
- ``transparent_geoms``: names of rendered geoms whose effective alpha is below 1.
- ``moving_joints``: names of joints that move across frames ([] for static captures).
- ``time_varying``: whether the scene changes with time (false for static captures).
- ``specular``: whether any rendered geom is shiny (material specular > 0.3 or reflectance > 0).
- ``shiny_geoms``: names of rendered geoms whose look changes strongly with the viewpoint
  (material specular or reflectance above 0.3: bright highlights or clear mirror images).
- ``shiny_pixel_fraction``: share of the training images' pixels that show ``shiny_geoms``
  (added by the capture, which sees the segmentation; absent from manifests of other origins).
- ``geoms``: {geom id (as a string): name} for reading segmentation images; unnamed geoms are
  called ``geom_<id>``.
- ``objects``: the geoms the MJCF declares as objects (:func:`declared_objects`).
- ``obstacles`` (only for scenes that declare them, e.g. the ``room`` family):
  {geom name: [[xmin, ymin, zmin], [xmax, ymax, zmax]]}, the world AABBs, metres, of the geoms a
  mobile robot must not drive into (:func:`declared_obstacles`); a planner reads footprints from
  the x-y extent and clearance from zmin (a low robot may pass under a table top).

"Rendered" is decided by MuJoCo itself: the geoms ``mjv_updateScene`` emits with the capture's
visualisation options (:func:`sims.camera.capture_scene_option`), which applies geom groups,
alpha = 0 and the material / geom rgba precedence exactly as the images do.
"""

from __future__ import annotations

from typing import Iterable, Optional

import mujoco
import numpy as np

from sims.camera import capture_scene_option

#: Material specular above which a geom counts as shiny.
SPECULAR_THRESHOLD = 0.3
#: Material reflectance above which a geom's mirror images count as a strong view dependence
#: (weak reflectance, e.g. 0.06 on the tabletop's wood, only makes the ``specular`` flag true).
SHINY_REFLECTANCE = 0.3

# Sign patterns of the 8 corners of a box.
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                    dtype=np.float64)


def geom_name(model: mujoco.MjModel, gid: int) -> str:
    """Name of geom ``gid``, or ``geom_<gid>`` when unnamed."""
    return model.geom(gid).name or f"geom_{gid}"


def rendered_geoms(model: mujoco.MjModel, data: mujoco.MjData,
                   option: mujoco.MjvOption | None = None) -> list[mujoco.MjvGeom]:
    """The model geoms MuJoCo draws with ``option`` (default: the capture options)."""
    option = option or capture_scene_option()
    scene = mujoco.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom + 100))
    camera = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(model, camera)
    mujoco.mjv_updateScene(model, data, option, None, camera,
                           mujoco.mjtCatBit.mjCAT_ALL.value, scene)
    geom_type = int(mujoco.mjtObj.mjOBJ_GEOM)
    return [scene.geoms[i] for i in range(scene.ngeom)
            if scene.geoms[i].objtype == geom_type and scene.geoms[i].objid >= 0]


def transparent_geom_ids(drawn: list[mujoco.MjvGeom]) -> list[int]:
    """Sorted ids of the ``drawn`` geoms (:func:`rendered_geoms`) whose effective alpha is
    below 1."""
    return sorted({int(g.objid) for g in drawn if g.rgba[3] < 1.0})


def is_infinite_plane(model: mujoco.MjModel, gid: int) -> bool:
    """True for plane geoms with a zero half-size (rendered as infinite)."""
    return (model.geom_type[gid] == mujoco.mjtGeom.mjGEOM_PLANE
            and (model.geom_size[gid, 0] <= 0.0 or model.geom_size[gid, 1] <= 0.0))


def geom_world_aabb(model: mujoco.MjModel, data: mujoco.MjData, gid: int) -> np.ndarray:
    """(2, 3) world AABB of geom ``gid``: all 8 corners of its local ``geom_aabb`` box.

    A finite plane is bounded by its rectangle: MuJoCo's ``geom_aabb`` gives planes an infinite
    depth below their surface.
    """
    local = model.geom_aabb[gid].copy()
    if model.geom_type[gid] == mujoco.mjtGeom.mjGEOM_PLANE:
        local[:] = (0.0, 0.0, 0.0, model.geom_size[gid, 0], model.geom_size[gid, 1], 0.0)
    corners = local[:3] + _CORNERS * local[3:]
    world = corners @ data.geom_xmat[gid].reshape(3, 3).T + data.geom_xpos[gid]
    return np.stack([world.min(axis=0), world.max(axis=0)])


def content_bounds(model: mujoco.MjModel, data: mujoco.MjData, geom_ids: Iterable[int]) -> np.ndarray:
    """(2, 3) union AABB of the given geoms, skipping infinite planes; metres.

    Raises:
        ValueError: no finite geom to bound.
    """
    boxes = [geom_world_aabb(model, data, g) for g in geom_ids if not is_infinite_plane(model, g)]
    if not boxes:
        raise ValueError("scene has no rendered geom of finite size to bound")
    boxes = np.stack(boxes)
    return np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)])


def scene_manifest(model: mujoco.MjModel, data: mujoco.MjData, name: str, source: str,
                   moving_joints: Iterable[str] = (), time_varying: bool = False) -> dict:
    """The manifest dict of the scene in its current state (``mj_forward`` must have run)."""
    drawn = rendered_geoms(model, data)
    ids = sorted({int(g.objid) for g in drawn})
    try:
        bounds = content_bounds(model, data, ids)
    except ValueError as err:
        raise ValueError(f"{source.removeprefix('builtin:')}: {err}") from None
    transparent = transparent_geom_ids(drawn)
    specular = any(g.specular > SPECULAR_THRESHOLD or g.reflectance > 0.0 for g in drawn)
    shiny = sorted({int(g.objid) for g in drawn
                    if g.specular > SPECULAR_THRESHOLD or g.reflectance > SHINY_REFLECTANCE})
    manifest = {
        "name": str(name),
        "source": str(source),
        "bounds": bounds.tolist(),
        "transparent_geoms": [geom_name(model, g) for g in transparent],
        "moving_joints": [str(j) for j in moving_joints],
        "time_varying": bool(time_varying),
        "specular": bool(specular),
        "shiny_geoms": [geom_name(model, g) for g in shiny],
        "geoms": {str(g): geom_name(model, g) for g in range(model.ngeom)},
        "objects": declared_objects(model),
    }
    obstacles = declared_obstacles(model, data)
    if obstacles:
        manifest["obstacles"] = {name: box.tolist() for name, box in obstacles.items()}
    return manifest


def custom_text(model: mujoco.MjModel, name: str) -> Optional[str]:
    """The ``<custom><text name=NAME data=.../>`` string of the model, or None."""
    tid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, name)
    if tid < 0:
        return None
    adr, size = int(model.text_adr[tid]), int(model.text_size[tid])
    return bytes(model.text_data[adr:adr + size]).decode().rstrip("\x00").strip()


def custom_numeric(model: mujoco.MjModel, name: str) -> Optional[list[float]]:
    """The ``<custom><numeric name=NAME data=.../>`` values of the model, or None."""
    nid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if nid < 0:
        return None
    adr, size = int(model.numeric_adr[nid]), int(model.numeric_size[nid])
    return [float(v) for v in model.numeric_data[adr:adr + size]]


def _declared_geoms(model: mujoco.MjModel, text_name: str) -> list[str]:
    """Geom names listed in ``<custom><text name=TEXT_NAME>`` (in order; [] when absent).
    ValueError naming the unknown geom if the list names a geom the model lacks."""
    names = (custom_text(model, text_name) or "").split()
    for name in names:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) < 0:
            raise ValueError(f"<custom> text {text_name} names geom {name!r}, "
                             "which the model does not have")
    return names


def declared_objects(model: mujoco.MjModel) -> list[str]:
    """Geom names the MJCF declares as objects (``<custom><text name="nerfbot_objects"
    data="geom names separated by spaces"/>``), in order; [] when it declares none.

    Raises ValueError naming the unknown geom if the list names a geom the model lacks.
    """
    return _declared_geoms(model, "nerfbot_objects")


def declared_obstacles(model: mujoco.MjModel, data: mujoco.MjData) -> dict[str, np.ndarray]:
    """{geom name: (2, 3) world AABB, metres} of the geoms the MJCF declares as obstacles to a
    mobile robot (``<custom><text name="nerfbot_obstacles" data="geom names"/>``), in declared
    order; {} when it declares none. ``mj_forward`` must have run on ``data``.

    Raises ValueError naming the unknown geom if the list names a geom the model lacks.
    """
    return {name: geom_world_aabb(model, data, model.geom(name).id)
            for name in _declared_geoms(model, "nerfbot_obstacles")}
