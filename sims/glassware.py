"""The ``glassware`` scene family: transparent vessels and opaque look-alikes on a textured table.

Five vessel shapes (wine glass, tumbler, bottle, bowl, Erlenmeyer flask) are built as closed
surfaces of revolution with trimesh (a thin wall: outer profile up, rim, inner profile down, so
the mesh is watertight) and written inline into the MJCF. Each shape appears twice: once as glass
(low alpha, strong specular highlights) and once as an opaque glazed look-alike, the control.
Placement is randomised with a seed: the ten objects take ten of twelve jittered slots of a
4 x 3 grid on the table, far enough apart for a parallel-jaw gripper to reach around each.

Every object is a free body (so a gripper can lift it) whose body and geom share the object's
name, e.g. ``glass_tumbler``; objects stand upright on the table top at z = :data:`TABLE_TOP`.
The MJCF declares them in ``<custom><text name="nerfbot_objects">`` (glass first) and gives the
default capture rig (a hemisphere at 1.3 m around the table centre, 40 degree fov).

Use as a scene name: ``glassware`` (seed 0) or ``glassware:K`` (seed K); see
:func:`sims.scene.resolve_scene`. ``glazed`` / ``glazed:K`` is the same scene without the glass:
specular but nothing transparent, a control for choices that depend on the materials.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

#: Height of the table top surface, metres.
TABLE_TOP = 0.75
#: Table top half-size (x, y), metres.
TABLE_HALF = (0.55, 0.42)
#: Grid of placement slots (columns along x, rows along y) and their spacing, metres.
SLOT_GRID = (4, 3)
SLOT_SPACING = (0.22, 0.22)
#: Uniform jitter of each object around its slot centre, metres (half-width).
SLOT_JITTER = 0.025
#: Segments around the axis of each surface of revolution.
SECTIONS = 48


@dataclass(frozen=True)
class Vessel:
    """One vessel shape.

    Attributes:
        name: short name ("tumbler", ...).
        profile: (K, 2) closed profile (r, z) in metres, starting and ending on the axis (r = 0):
            bottom centre → outer wall up → rim → inner wall down → inner bottom centre.
        mass: kg (glass; the opaque look-alike gets the same mass).
    """

    name: str
    profile: np.ndarray
    mass: float

    @property
    def radius(self) -> float:
        return float(self.profile[:, 0].max())

    @property
    def height(self) -> float:
        return float(self.profile[:, 1].max())


def _walled(outer: list[tuple[float, float]], wall: float, floor: float) -> np.ndarray:
    """Close an outer profile [(r, z), ...] (bottom to rim, r > 0) into a thin-walled vessel:
    axis at z=0 → outer points → rim → the outer curve offset inwards by ``wall`` (down to the
    inner floor at z = ``floor``) → axis at z = ``floor``."""
    outer = np.asarray(outer, dtype=np.float64)
    inner = []
    for r, z in outer[::-1]:
        if z < floor:
            break
        inner.append((max(r - wall, 1e-3), z))
    inner[0] = (outer[-1, 0] - wall, outer[-1, 1])
    pts = [(0.0, 0.0), *map(tuple, outer), *inner, (0.0, floor)]
    return np.asarray(pts, dtype=np.float64)


def _smooth(points: list[tuple[float, float]], n: int = 6) -> list[tuple[float, float]]:
    """Densify a polyline (r, z) by linear interpolation (n points per segment)."""
    out = []
    for (r0, z0), (r1, z1) in zip(points[:-1], points[1:]):
        for t in np.linspace(0.0, 1.0, n, endpoint=False):
            out.append((r0 + t * (r1 - r0), z0 + t * (z1 - z0)))
    out.append(points[-1])
    return out


def vessels() -> list[Vessel]:
    """The five vessel shapes, metres."""
    bowl_curve = [(0.011 + 0.031 * np.sin(np.pi / 2 * t), 0.075 + 0.055 * t)
                  for t in np.linspace(0.0, 1.0, 8)]
    wine_outer = [(0.035, 0.0), (0.035, 0.004), (0.008, 0.008), (0.005, 0.02), (0.005, 0.07),
                  *bowl_curve, (0.040, 0.155), (0.037, 0.175)]
    wine = np.asarray([(0.0, 0.0), *wine_outer,
                       *[(max(r - 0.003, 1e-3), z) for r, z in reversed(wine_outer[-4:])],
                       (0.0, 0.135)], dtype=np.float64)
    tumbler = _walled(_smooth([(0.030, 0.0), (0.037, 0.105)]), 0.003, 0.012)
    bottle = _walled(_smooth([(0.033, 0.0), (0.033, 0.135), (0.026, 0.160), (0.014, 0.180),
                              (0.013, 0.215), (0.015, 0.220)], 4), 0.003, 0.010)
    bowl_pts = [(0.030, 0.0), (0.030, 0.006)] + [
        (0.030 + 0.022 * np.sin(np.pi / 2 * t), 0.006 + 0.062 * t) for t in np.linspace(0.1, 1, 9)]
    bowl = _walled(bowl_pts, 0.004, 0.010)
    flask = _walled(_smooth([(0.044, 0.0), (0.045, 0.008), (0.016, 0.100), (0.015, 0.145),
                             (0.017, 0.150)], 5), 0.003, 0.008)
    return [
        Vessel("wine_glass", wine, 0.17),
        Vessel("tumbler", tumbler, 0.22),
        Vessel("bottle", bottle, 0.30),
        Vessel("bowl", bowl, 0.25),
        Vessel("flask", flask, 0.20),
    ]


def vessel_mesh(vessel: Vessel, sections: int = SECTIONS) -> trimesh.Trimesh:
    """The watertight mesh of ``vessel``: its profile revolved about z (metres, base at z = 0)."""
    mesh = trimesh.creation.revolve(vessel.profile, sections=sections)
    mesh.merge_vertices()
    mesh.fix_normals()
    return mesh


#: Look of the opaque controls, by vessel (glazed ceramics / painted metal).
_OPAQUE_RGBA = {
    "wine_glass": "0.82 0.22 0.25 1",
    "tumbler": "0.95 0.93 0.86 1",
    "bottle": "0.18 0.45 0.25 1",
    "bowl": "0.85 0.55 0.2 1",
    "flask": "0.3 0.4 0.8 1",
}


def _floats(values) -> str:
    return " ".join(f"{v:.6g}" for v in np.asarray(values).reshape(-1))


def placements(seed: int, names: list[str]) -> dict[str, tuple[float, float, float]]:
    """Random (x, y, yaw) per object name: ten jittered slots of the 4 x 3 grid, seeded."""
    rng = np.random.default_rng(seed)
    cols, rows = SLOT_GRID
    xs = (np.arange(cols) - (cols - 1) / 2) * SLOT_SPACING[0]
    ys = (np.arange(rows) - (rows - 1) / 2) * SLOT_SPACING[1]
    slots = [(x, y) for y in ys for x in xs]
    if len(names) > len(slots):
        raise ValueError(f"{len(names)} objects do not fit {len(slots)} slots")
    chosen = rng.permutation(len(slots))[:len(names)]
    out = {}
    for name, slot in zip(names, chosen):
        x, y = slots[slot]
        dx, dy = rng.uniform(-SLOT_JITTER, SLOT_JITTER, size=2)
        out[name] = (float(x + dx), float(y + dy), float(rng.uniform(0.0, 360.0)))
    return out


def glazed_xml(seed: int = 0) -> str:
    """The MJCF text of glazed scene ``seed``: glassware scene ``seed`` without the glass."""
    return glassware_xml(seed, with_glass=False)


def object_names() -> tuple[list[str], list[str]]:
    """(glass object names, opaque control names), in vessel order."""
    shapes = [v.name for v in vessels()]
    return [f"glass_{s}" for s in shapes], [f"opaque_{s}" for s in shapes]


def glassware_xml(seed: int = 0, with_glass: bool = True) -> str:
    """The MJCF text of glassware scene ``seed`` (self-contained: meshes are inline).

    ``with_glass=False`` leaves the glass out: the opaque look-alikes alone, where they stand in
    the full scene (the ``glazed`` family: shiny but nothing transparent)."""
    shapes = vessels()
    glass, opaque = object_names()
    where = placements(seed, glass + opaque)
    if not with_glass:
        glass = []
    meshes, bodies = [], []
    for vessel in shapes:
        mesh = vessel_mesh(vessel)
        meshes.append(f'    <mesh name="{vessel.name}" vertex="{_floats(mesh.vertices)}" '
                      f'face="{" ".join(str(int(i)) for i in mesh.faces.reshape(-1))}"/>')
    for kind, names in (("glass", glass), ("opaque", opaque)):
        for vessel, name in zip(shapes, names):
            x, y, yaw = where[name]
            material = "glass" if kind == "glass" else f"glaze_{vessel.name}"
            inertia = (vessel.mass * (0.5 * vessel.radius ** 2 + vessel.height ** 2 / 3.0) / 2.0,)
            izz = vessel.mass * vessel.radius ** 2 / 2.0
            bodies.append(
                f'    <body name="{name}" pos="{x:.5f} {y:.5f} {TABLE_TOP + 0.0005:.5f}" '
                f'euler="0 0 {yaw:.2f}">\n'
                f'      <freejoint name="{name}"/>\n'
                f'      <inertial pos="0 0 {0.4 * vessel.height:.4f}" mass="{vessel.mass}" '
                f'diaginertia="{inertia[0]:.6g} {inertia[0]:.6g} {izz:.6g}"/>\n'
                f'      <geom name="{name}" type="mesh" mesh="{vessel.name}" '
                f'material="{material}" class="object"/>\n'
                f'    </body>')
    glazes = "\n".join(
        f'    <material name="glaze_{v.name}" rgba="{_OPAQUE_RGBA[v.name]}" specular="0.5" '
        f'shininess="0.6"/>' for v in shapes)
    transparent = (f'    <text name="nerfbot_transparent_objects" data="{" ".join(glass)}"/>\n'
                   if glass else "")
    family, contents = ("glassware", _GLASS_CONTENTS) if glass else ("glazed", _GLAZED_CONTENTS)
    return _TEMPLATE.format(
        seed=seed, family=family, contents=contents.format(seed=seed),
        objects=" ".join(glass + opaque), transparent=transparent, meshes="\n".join(meshes),
        glazes=glazes, bodies="\n".join(bodies),
        top=TABLE_TOP, half_x=TABLE_HALF[0], half_y=TABLE_HALF[1],
        top_centre=TABLE_TOP - 0.02, target_z=TABLE_TOP + 0.06)


_GLASS_CONTENTS = """\
Five transparent vessels (glass_*) and their opaque look-alikes (opaque_*) on a wooden
  table. Glass: alpha 0.18, strong specular highlights from four fixed lights; MuJoCo draws the
  glass into the depth and segmentation buffers, so the capture's ground-truth depth sees it as
  opaque."""
_GLAZED_CONTENTS = """\
The five opaque, glazed look-alikes (opaque_*) of glassware scene {seed} on a wooden table,
  where they stand in that scene, without the glass: shiny surfaces (four fixed lights), nothing
  transparent."""

_TEMPLATE = """<!--
  nerfbot generated scene "{family}", seed {seed} (sims/glassware.py; regenerate, do not edit).

  {contents}
  Units are metres, z up; the table top is at z = {top}. The table is a slab without legs (as in
  tabletop there is no floor), so the content bounds stay tight around what a field must model.
-->
<mujoco model="{family}">
  <compiler angle="degree"/>
  <option timestep="0.002"/>
  <statistic extent="1.2" center="0 0 {top}"/>

  <visual>
    <global offwidth="1024" offheight="1024" fovy="40"/>
    <quality offsamples="8" shadowsize="4096"/>
    <headlight active="1" ambient="0.25 0.25 0.27" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="0.01" zfar="30" haze="0.2" shadowclip="0.6"/>
    <rgba haze="0.55 0.6 0.68 1"/>
  </visual>

  <custom>
    <numeric name="nerfbot_rig_target" data="0 0 {target_z}"/>
    <numeric name="nerfbot_rig_radius" data="1.3"/>
    <numeric name="nerfbot_rig_fovy" data="40"/>
    <text name="nerfbot_objects" data="{objects}"/>
{transparent}  </custom>

  <default>
    <default class="object">
      <geom condim="4" friction="1.0 0.01 0.001" solref="0.004 1" solimp="0.95 0.99 0.001"/>
    </default>
  </default>

  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.3 0.34 0.42"
             rgb2="0.62 0.66 0.72" width="512" height="3072"/>
    <texture name="wood" type="2d" builtin="checker" rgb1="0.62 0.44 0.28"
             rgb2="0.52 0.36 0.22" mark="random" markrgb="0.36 0.24 0.15" random="0.1"
             width="256" height="256"/>
    <material name="wood_top" texture="wood" texrepeat="5 4" specular="0.2" shininess="0.3"/>
    <material name="glass" rgba="0.80 0.90 0.96 0.18" specular="1" shininess="1"/>
{glazes}
{meshes}
  </asset>

  <worldbody>
    <light name="key" pos="1.2 -1.0 2.6" dir="-0.4 0.35 -1" directional="true"
           diffuse="0.55 0.55 0.55" specular="0.8 0.8 0.8" castshadow="true"/>
    <light name="fill" pos="-1.5 -0.8 2.2" dir="0.6 0.3 -1" directional="true"
           diffuse="0.3 0.3 0.32" specular="0.6 0.6 0.6" castshadow="false"/>
    <light name="rim" pos="0 1.8 2.0" dir="0 -0.7 -1" directional="true"
           diffuse="0.25 0.25 0.25" specular="0.7 0.7 0.7" castshadow="false"/>
    <light name="top" pos="0 0 3" dir="0 0 -1" directional="true"
           diffuse="0.2 0.2 0.2" specular="0.5 0.5 0.5" castshadow="false"/>

    <body name="table">
      <geom name="table_top" type="box" size="{half_x} {half_y} 0.02" pos="0 0 {top_centre}"
            material="wood_top" friction="1.0 0.01 0.001"/>
    </body>

{bodies}
  </worldbody>
</mujoco>
"""
