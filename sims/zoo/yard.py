"""The ``yard`` scene family: an unbounded outdoor scene, near objects and far content under sky.

Near: 3-6 objects of 0.3-1.2 m (crates, barrels, rocks, bushes, balls, posts; textured) stand
within :data:`NEAR_RADIUS` of the origin on a tiled patio, itself on a ground plane of grass
and soil :data:`GROUND_HALF` metres in every direction. Far, 20-100 m from the origin: trees at
20-50 m, buildings (boxes with window facades) at 25-90 m, hills (ellipsoids, mostly buried) at
70-100 m; above them the sky, which is the capture's background (infinite depth). The near
objects are free bodies whose body and geom share their name, declared in ``<custom><text
name="nerfbot_objects">``; far content is static (``building_K``, ``hill_K``,
``tree_K_trunk`` / ``tree_K_crown``), the patio is ``patio`` and the ground ``ground``.

The default rig is a hemisphere of radius 3.5-4.5 m (seeded) around a point 0.5 m above the
origin, 5-35 degrees up, 60 degree fov: every view sees the near objects against far content,
most also sky. The content bounds span the ground plane and the hills (hundreds of metres)
while the near objects fill a few metres: an unbounded scene, to be modelled with a scene
contraction rather than a box.

The seed sets the objects (kinds, sizes, textures, places), the patio's tiles and the ground's
grass, the far content's places and sizes, the sky's colours and the lighting (a sun casting
shadows near the objects and two fill lights, seeded directions, colours and intensities).

Use as a scene name: ``yard`` (seed 0) or ``yard:K``.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import numpy as np

from sims.zoo import textures
from sims.zoo.layout import scatter_discs
from sims.zoo.mjcf import GeneratedScene, custom_block, file_texture, floats, header, sun_lights

#: Half-size of the square ground plane, metres.
GROUND_HALF = 150.0
#: Half-size range of the square patio under the near objects, metres.
PATIO_HALF = (2.2, 3.0)
#: Near objects stand within this square half-size around the origin, metres.
NEAR_RADIUS = 1.6
#: Number of near objects, inclusive range, and the range of their largest dimension, metres.
NEAR_COUNT = (3, 6)
NEAR_SIZE = (0.3, 1.2)
NEAR_KINDS = ("crate", "barrel", "rock", "bush", "ball", "post")
#: Distances from the origin (metres) of the far content, and how many there are.
TREE_DISTANCE, TREE_COUNT = (20.0, 50.0), (3, 8)
BUILDING_DISTANCE, BUILDING_COUNT = (25.0, 90.0), (4, 8)
HILL_DISTANCE, HILL_COUNT = (70.0, 100.0), (2, 4)
#: Default rig: its target, the range of its seeded radius (metres), fov and elevations
#: (degrees).
RIG_TARGET = (0.0, 0.0, 0.5)
RIG_RADIUS = (3.5, 4.5)
RIG_FOVY = 60.0
RIG_ELEVATION = (5.0, 35.0)


class NearObject(NamedTuple):
    """One near object before placement: its ``<asset>`` lines and texture files, its
    ``<body>`` at (x, y) turned by yaw degrees, its footprint radius and largest dimension
    (metres)."""

    asset_xml: list[str]
    assets: dict
    body: Callable[[float, float, float], str]
    footprint: float
    largest: float


def _near_object(rng: np.random.Generator, kind: str, name: str, patio_top: float) -> NearObject:
    """A seeded near object of ``kind`` standing on the patio (top at ``patio_top``)."""
    size = float(rng.uniform(*NEAR_SIZE))
    colour = textures.random_colour(rng)
    tex = f'    <texture name="{name}" type="cube" file="{name}.png"/>'
    if kind == "crate":
        h = size * rng.uniform(0.5, 1.0)
        w = size * rng.uniform(0.5, 1.0)
        image = textures.wood_planks(rng, 256, 5) if rng.random() < 0.5 else textures.label(rng)
        geom = f'type="box" size="{floats([size / 2, w / 2, h / 2])}"'
        rest, radius = h / 2, 0.5 * math.hypot(size, w)
    elif kind == "barrel":
        r = size * rng.uniform(0.3, 0.45)
        image = textures.speckled(rng, 256, colour, 0.3)
        geom = f'type="cylinder" size="{floats([r, size / 2])}"'
        rest, radius = size / 2, r
    elif kind in ("rock", "bush"):
        a = size / 2
        b, c = a * rng.uniform(0.6, 1.0), a * rng.uniform(0.4, 0.8)
        tone = (np.array([0.5, 0.48, 0.45]) * rng.uniform(0.7, 1.2) if kind == "rock"
                else np.array([0.2, 0.45, 0.15]) * rng.uniform(0.7, 1.2))
        image = textures.speckled(rng, 256, np.clip(tone, 0, 1), 0.5)
        geom = f'type="ellipsoid" size="{floats([a, b, c])}"'
        rest, radius = c, a
    elif kind == "ball":
        r = size / 2
        image = textures.checker(256, 4, colour, textures.random_colour(rng, value=(0.2, 0.5)))
        geom = f'type="sphere" size="{floats([r])}"'
        rest, radius = r, r
    else:  # post
        r = rng.uniform(0.04, 0.08)
        image = textures.checker(256, 2, (0.95, 0.95, 0.95), colour)
        geom = f'type="capsule" size="{floats([r, size / 2 - r])}"'
        rest, radius = size / 2, r
    material = (f'    <material name="{name}" texture="{name}" texuniform="true" '
                f'specular="0.15" shininess="0.3"/>')

    def body(x: float, y: float, yaw: float) -> str:
        return (f'    <body name="{name}" pos="{floats([x, y, patio_top + rest + 0.0005])}" '
                f'euler="0 0 {yaw:.2f}">\n'
                f'      <freejoint name="{name}"/>\n'
                f'      <geom name="{name}" {geom} material="{name}"/>\n'
                f'    </body>')
    return NearObject([tex, material], {f"{name}.png": image}, body, radius, size)


def _far_places(rng: np.random.Generator, count: int, distance: tuple[float, float],
                radius: list[float], taken: list) -> list[tuple[float, float] | None]:
    """Centres (x, y) of ``count`` far footprints of ``radius`` metres, wholly between
    ``distance`` (near, far) metres from the origin (uniform azimuth), clear of the ``taken``
    discs (x, y, r) by 2 m (each placed disc is appended to them); None for a piece that
    finds no place in 200 draws."""
    out: list[tuple[float, float] | None] = []
    for k in range(count):
        lo, hi = distance[0] + radius[k], max(distance[1] - radius[k], distance[0] + radius[k])
        for _ in range(200):
            d, az = rng.uniform(lo, hi), rng.uniform(0.0, 2 * math.pi)
            x, y = d * math.cos(az), d * math.sin(az)
            if all(math.hypot(x - tx, y - ty) > radius[k] + tr + 2.0 for tx, ty, tr in taken):
                taken.append((x, y, radius[k]))
                out.append((x, y))
                break
        else:
            out.append(None)
    return out


def yard_scene(seed: int = 0) -> GeneratedScene:
    """The MJCF text and textures of yard scene ``seed``."""
    rng = np.random.default_rng(seed)
    patio_half = rng.uniform(*PATIO_HALF)
    patio_top = 0.01
    assets = {"ground.png": textures.ground(rng, 512),
              "patio.png": textures.tiles(rng, 512, 4)}
    asset_xml = [file_texture("ground"), file_texture("patio")]

    # Near objects.
    count = int(rng.integers(NEAR_COUNT[0], NEAR_COUNT[1] + 1))
    kinds = [str(k) for k in rng.choice(NEAR_KINDS, count)]
    near = [_near_object(rng, kind, f"{kind}_{i}", patio_top) for i, kind in enumerate(kinds)]
    places = scatter_discs(rng, [n.footprint for n in near],
                           (-NEAR_RADIUS, -NEAR_RADIUS, NEAR_RADIUS, NEAR_RADIUS), 0.25)
    bodies = []
    for thing, (x, y) in zip(near, places):
        asset_xml += thing.asset_xml
        assets.update(thing.assets)
        bodies.append(thing.body(x, y, float(rng.uniform(0.0, 360.0))))
    names = [f"{kind}_{i}" for i, kind in enumerate(kinds)]

    # Far content: trees, buildings, hills.
    taken = [(0.0, 0.0, patio_half * math.sqrt(2.0))]
    far = []
    n_trees = int(rng.integers(TREE_COUNT[0], TREE_COUNT[1] + 1))
    crowns = [float(rng.uniform(1.5, 3.0)) for _ in range(n_trees)]
    assets["foliage.png"] = textures.speckled(rng, 256, np.array([0.18, 0.4, 0.14]), 0.6)
    assets["bark.png"] = textures.speckled(rng, 128, np.array([0.35, 0.25, 0.17]), 0.5)
    asset_xml += [file_texture("foliage", "cube"), file_texture("bark", "cube"),
                  '    <material name="foliage" texture="foliage" specular="0" shininess="0"/>',
                  '    <material name="bark" texture="bark" specular="0" shininess="0"/>']
    for k, place in enumerate(_far_places(rng, n_trees, TREE_DISTANCE, crowns, taken)):
        if place is None:
            continue
        x, y = place
        trunk_r, trunk_h = rng.uniform(0.2, 0.4), rng.uniform(2.0, 4.0)
        crown = crowns[k]
        far.append(f'    <body name="tree_{k}" pos="{floats([x, y, 0])}">\n'
                   f'      <geom name="tree_{k}_trunk" type="cylinder" '
                   f'size="{floats([trunk_r, trunk_h / 2 + 0.3])}" '
                   f'pos="0 0 {trunk_h / 2 - 0.3:.3f}" material="bark"/>\n'
                   f'      <geom name="tree_{k}_crown" type="ellipsoid" '
                   f'size="{floats([crown, crown, crown * rng.uniform(1.0, 1.5)])}" '
                   f'pos="0 0 {trunk_h + crown * 0.8:.3f}" material="foliage"/>\n'
                   f'    </body>')
    n_buildings = int(rng.integers(BUILDING_COUNT[0], BUILDING_COUNT[1] + 1))
    sizes = [(rng.uniform(6, 20), rng.uniform(6, 20), rng.uniform(6, 30))
             for _ in range(n_buildings)]
    footprints = [0.5 * math.hypot(w, d) for w, d, _ in sizes]
    for k, place in enumerate(_far_places(rng, n_buildings, BUILDING_DISTANCE, footprints, taken)):
        if place is None:
            continue
        (x, y), (w, d, h) = place, sizes[k]
        assets[f"building_{k}.png"] = textures.facade(rng, 256)
        asset_xml += [file_texture(f"building_{k}", "cube"),
                      f'    <material name="building_{k}" texture="building_{k}" '
                      f'texuniform="true" specular="0.1" shininess="0.2"/>']
        far.append(f'    <geom name="building_{k}" type="box" '
                   f'size="{floats([w / 2, d / 2, h / 2])}" pos="{floats([x, y, h / 2])}" '
                   f'euler="0 0 {rng.uniform(0, 90):.1f}" material="building_{k}"/>')
    n_hills = int(rng.integers(HILL_COUNT[0], HILL_COUNT[1] + 1))
    axes = [(rng.uniform(20, 35), rng.uniform(20, 35), rng.uniform(10, 22))
            for _ in range(n_hills)]
    assets["hillside.png"] = textures.ground(rng, 256, grassy=0.8)
    asset_xml += [file_texture("hillside", "cube"),
                  '    <material name="hillside" texture="hillside" specular="0" shininess="0"/>']
    for k, place in enumerate(_far_places(rng, n_hills, HILL_DISTANCE,
                                          [0.6 * a for a, _, _ in axes], taken)):
        if place is None:
            continue
        (x, y), (a, b, c) = place, axes[k]
        far.append(f'    <geom name="hill_{k}" type="ellipsoid" size="{floats([a, b, c])}" '
                   f'pos="{floats([x, y, -c * rng.uniform(0.3, 0.6)])}" '
                   f'euler="0 0 {rng.uniform(0, 180):.1f}" material="hillside"/>')

    sky_top = np.clip(np.array([0.3, 0.5, 0.85]) + rng.uniform(-0.1, 0.1, 3), 0.0, 1.0)
    horizon = np.clip(0.75 + 0.2 * rng.random(3), 0, 1)
    radius = float(rng.uniform(*RIG_RADIUS))
    custom = custom_block(
        {"nerfbot_rig_target": list(RIG_TARGET), "nerfbot_rig_radius": [radius],
         "nerfbot_rig_fovy": [RIG_FOVY], "nerfbot_rig_elevation": list(RIG_ELEVATION)},
        {"nerfbot_objects": " ".join(names)})
    description = (f"{count} objects on a patio within {NEAR_RADIUS} m of the origin; trees, "
                   "buildings and hills 20-100 m away;\n  sky. Units are metres, z up; the "
                   "ground is z = 0. Textures are the PNG files beside this file.")
    xml = _TEMPLATE.format(
        header=header("yard", seed, "sims/zoo/yard.py", description), custom=custom,
        ambient=floats([rng.uniform(0.22, 0.32)] * 3, 3), sky_top=floats(sky_top, 3),
        horizon=floats(horizon, 3), assets="\n".join(asset_xml),
        lights="\n".join(sun_lights(rng, (0.0, 0.0, 0.0), 15.0)),
        ground=floats([GROUND_HALF, GROUND_HALF, 5.0]),
        ground_repeat=floats([rng.uniform(0.4, 0.6)] * 2, 3),
        patio_size=floats([patio_half, patio_half, 0.01]),
        near="\n".join(bodies), far="\n".join(far))
    return GeneratedScene(xml, assets)


_TEMPLATE = """{header}
<mujoco model="yard">
  <compiler angle="degree"/>
  <option timestep="0.002"/>
  <statistic extent="20" center="0 0 1"/>

  <visual>
    <global offwidth="1024" offheight="1024" fovy="60"/>
    <quality offsamples="8" shadowsize="2048"/>
    <headlight active="1" ambient="{ambient}" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="0.004" zfar="30" haze="0.3" shadowclip="0.4"/>
    <rgba haze="{horizon} 1"/>
  </visual>

{custom}

  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="{sky_top}" rgb2="{horizon}"
             width="512" height="3072"/>
    <material name="ground" texture="ground" texuniform="true" texrepeat="{ground_repeat}"
              specular="0" shininess="0"/>
    <material name="patio" texture="patio" texuniform="true" texrepeat="0.5 0.5"
              specular="0.1" shininess="0.2"/>
{assets}
  </asset>

  <worldbody>
{lights}

    <geom name="ground" type="plane" size="{ground}" material="ground"/>
    <geom name="patio" type="box" size="{patio_size}" material="patio"/>

{near}

{far}
  </worldbody>
</mujoco>
"""
