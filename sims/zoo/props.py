"""Small textured objects ("props") for the ``workspace`` and ``bins`` families.

Kinds, each free (a ``<freejoint>``, so a gripper can lift it) and resting on a surface:

- ``box``: a box lying flat, a printed label (brand name, small print, barcode) on every face;
- ``can``: an upright cylinder wrapped in a label;
- ``marker``: a capsule lying on its side (a pen), one colour;
- ``ball``: an ellipsoid with a two-colour checker;
- ``sphere``: a round ball with a two-colour checker (it rolls where a ``ball`` wobbles);
- ``die``: a cube with a checker and edge marks;
- ``pebble``: a faceted mesh (an icosphere squashed to an ellipsoid), speckled;
- ``book``: a thin box whose top is a printed page.

A family gives each kind a range of its largest dimension (``size_ranges``, metres); the other
dimensions follow from seeded proportions no larger than it. Body and geom share the prop's
name (e.g. ``can_3``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh

from sims.zoo import textures
from sims.zoo.mjcf import Asset, floats

PROP_KINDS = ("box", "can", "marker", "ball", "sphere", "die", "pebble", "book")


@dataclass
class Prop:
    """One prop, before placement.

    Attributes:
        name: body and geom name.
        kind: one of :data:`PROP_KINDS`.
        geom: the ``<geom>`` attributes after name and class (type, size, material, orientation
            in the body frame).
        rest_height: height of the body origin above the surface it rests on, metres.
        footprint: radius of a disc around the body origin covering its x-y extent, metres.
        largest: its largest dimension, metres.
        asset_xml: ``<texture>`` / ``<material>`` / ``<mesh>`` lines for ``<asset>``.
        assets: its texture files, {file name: image}.
    """

    name: str
    kind: str
    geom: str
    rest_height: float
    footprint: float
    largest: float
    asset_xml: list[str] = field(default_factory=list)
    assets: dict[str, Asset] = field(default_factory=dict)

    def body(self, x: float, y: float, surface_z: float, yaw_deg: float) -> str:
        """The ``<body>`` of the prop resting at (x, y) on a surface at height ``surface_z``
        (half a millimetre above it, so it starts free of contact), turned by ``yaw_deg``."""
        z = surface_z + self.rest_height + 0.0005
        return (f'    <body name="{self.name}" pos="{floats([x, y, z])}" '
                f'euler="0 0 {yaw_deg:.2f}">\n'
                f'      <freejoint name="{self.name}"/>\n'
                f'      <geom name="{self.name}" class="object" {self.geom}/>\n'
                f'    </body>')


def make_prop(rng: np.random.Generator, kind: str, name: str,
              size_range: tuple[float, float], texture_px: int = 256) -> Prop:
    """A seeded prop of ``kind`` whose largest dimension is drawn from ``size_range`` (metres);
    its textures are ``texture_px`` pixels square."""
    size = float(rng.uniform(*size_range))
    colour = textures.random_colour(rng)
    mat = f"{name}_mat"
    if kind in ("box", "can"):
        png = {f"{name}.png": textures.label(rng, texture_px)}
        assets_xml = [f'    <texture name="{name}" type="cube" file="{name}.png"/>',
                      f'    <material name="{mat}" texture="{name}" texuniform="true" '
                      f'specular="0.2" shininess="0.3"/>']
        if kind == "box":
            w, h = size * rng.uniform(0.45, 0.8), size * rng.uniform(0.25, 0.6)
            return Prop(name, kind, f'type="box" size="{floats([size / 2, w / 2, h / 2])}" '
                        f'material="{mat}"', h / 2, 0.5 * float(np.hypot(size, w)), size,
                        assets_xml, png)
        r = size * rng.uniform(0.25, 0.4)
        return Prop(name, kind, f'type="cylinder" size="{floats([r, size / 2])}" '
                    f'material="{mat}"', size / 2, r, size, assets_xml, png)
    if kind == "marker":
        r = size * rng.uniform(0.06, 0.1)
        assets_xml = [f'    <material name="{mat}" rgba="{floats(colour, 3)} 1" specular="0.3" '
                      f'shininess="0.5"/>']
        return Prop(name, kind, f'type="capsule" size="{floats([r, size / 2 - r])}" '
                    f'zaxis="1 0 0" material="{mat}"', r, size / 2, size, assets_xml)
    if kind in ("ball", "sphere", "die"):
        other = textures.random_colour(rng, value=(0.2, 0.6))
        mark = ' mark="edge" markrgb="0.05 0.05 0.05"' if kind == "die" else ""
        assets_xml = [f'    <texture name="{name}" type="cube" builtin="checker" '
                      f'rgb1="{floats(colour, 3)}" rgb2="{floats(other, 3)}" width="64" '
                      f'height="64"{mark}/>',
                      f'    <material name="{mat}" texture="{name}" texuniform="true" '
                      f'specular="0.2" shininess="0.4"/>']
        if kind == "die":
            return Prop(name, kind, f'type="box" size="{floats([size / 2] * 3)}" '
                        f'material="{mat}"', size / 2, size / np.sqrt(2.0), size, assets_xml)
        a = size / 2
        if kind == "sphere":
            return Prop(name, kind, f'type="sphere" size="{a:.6g}" material="{mat}"', a, a, size,
                        assets_xml)
        b, c = a * rng.uniform(0.6, 1.0), a * rng.uniform(0.6, 1.0)
        return Prop(name, kind, f'type="ellipsoid" size="{floats([a, b, c])}" '
                    f'material="{mat}"', c, a, size, assets_xml)
    if kind == "pebble":
        a = size / 2
        axes = np.array([a, a * rng.uniform(0.6, 1.0), a * rng.uniform(0.4, 0.8)])
        sphere = trimesh.creation.icosphere(subdivisions=1)
        half = 0.5 * (sphere.vertices.max(axis=0) - sphere.vertices.min(axis=0))
        vertices = sphere.vertices / half * axes          # extents exactly 2 * axes
        png = {f"{name}.png": textures.speckled(rng, max(texture_px // 2, 32), colour, 0.3)}
        assets_xml = [f'    <mesh name="{name}" vertex="{floats(vertices, 5)}" '
                      f'face="{" ".join(str(int(i)) for i in sphere.faces.reshape(-1))}"/>',
                      f'    <texture name="{name}" type="cube" file="{name}.png"/>',
                      f'    <material name="{mat}" texture="{name}" specular="0.1" '
                      f'shininess="0.2"/>']
        return Prop(name, kind, f'type="mesh" mesh="{name}" material="{mat}"',
                    float(axes[2]), float(axes[0]), size, assets_xml, png)
    if kind == "book":
        w, h = size * rng.uniform(0.65, 0.78), rng.uniform(0.015, 0.04)
        page_h = texture_px * 2
        png = {f"{name}.png": textures.printed_page(rng, page_h, int(page_h * w / size))}
        assets_xml = [f'    <texture name="{name}" type="2d" file="{name}.png"/>',
                      f'    <material name="{mat}" texture="{name}" texrepeat="1 1" '
                      f'specular="0.1" shininess="0.1"/>']
        return Prop(name, kind, f'type="box" size="{floats([w / 2, size / 2, h / 2])}" '
                    f'material="{mat}"', h / 2, 0.5 * float(np.hypot(size, w)), size,
                    assets_xml, png)
    raise ValueError(f"unknown prop kind {kind!r} (choose from {PROP_KINDS})")
