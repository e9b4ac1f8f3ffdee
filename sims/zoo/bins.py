"""The ``bins`` scene family: bin picking, small parts in a tray seen from 0.3-0.6 m.

A plastic tray (inner 26-34 cm x 18-24 cm, walls 5-7 cm high, a checkered floor, speckled
walls) stands on a textured bench top; inside lie 8-15 props (:mod:`sims.zoo.props`) whose
largest dimension is 1-5 cm: labelled boxes and cans, checkered balls and dice, faceted pebbles,
pen caps (small capsules). They rest on the tray floor side by side (not piled), at least
:data:`GAP` apart; each is a free body whose body and geom share its name, declared in
``<custom><text name="nerfbot_objects">``. The tray is a static body of five boxes
(``bin_floor``, ``bin_wall_*``).

The default rig is a hemisphere :data:`RIG_RADIUS` m around a point just above the tray floor's
centre, 40-80 degrees up (lower views would see little but the walls), 40 degree fov. The seed
sets the tray's size and colours, the bench's texture, the props (kinds, sizes, textures, places,
turns) and the lighting (three directional lights of seeded directions, colours and intensities;
the key light casts shadows).

Use as a scene name: ``bins`` (seed 0) or ``bins:K``.
"""

from __future__ import annotations

import numpy as np

from sims.zoo import textures
from sims.zoo.layout import scatter_discs
from sims.zoo.mjcf import GeneratedScene, custom_block, file_texture, floats, header, sun_lights
from sims.zoo.props import Prop, make_prop

#: Height of the bench top surface, metres.
BENCH_TOP = 0.75
#: Half-size (x, y) of the bench top, metres.
BENCH_HALF = (0.6, 0.45)
#: Ranges of the tray's inner half-size along x and y and of its wall height, metres.
BIN_HALF_X = (0.13, 0.17)
BIN_HALF_Y = (0.09, 0.12)
BIN_WALL_HEIGHT = (0.05, 0.07)
#: Thickness of the tray's walls and floor, metres.
BIN_WALL = 0.008
BIN_FLOOR = 0.006
#: Props keep this far from the inside of the walls, and :data:`GAP` from each other, metres.
WALL_MARGIN = 0.004
GAP = 0.004
#: Number of props, inclusive range.
PROP_COUNT = (8, 15)
#: Range of the largest dimension of any prop, metres.
PROP_SIZE = (0.01, 0.05)
#: Largest dimension of each prop kind, metres (within :data:`PROP_SIZE`).
SIZE_RANGES = {"box": (0.02, 0.05), "can": (0.02, 0.05), "marker": (0.025, 0.05),
               "ball": (0.012, 0.04), "die": (0.01, 0.025), "pebble": (0.015, 0.04)}
#: Share of the tray floor the props' footprint discs (with gaps) may cover.
MAX_COVERAGE = 0.4
#: Default rig: distance to the target (metres), fov and elevations (degrees).
RIG_RADIUS = 0.45
RIG_FOVY = 40.0
RIG_ELEVATION = (40.0, 80.0)


def choose_props(rng: np.random.Generator, floor_area: float) -> list[Prop]:
    """The tray's props: random kinds, fewer (down to the minimum count) when their
    footprints would crowd the floor."""
    count = int(rng.integers(PROP_COUNT[0], PROP_COUNT[1] + 1))
    kinds = [str(k) for k in rng.choice(list(SIZE_RANGES), count)]
    props = [make_prop(rng, kind, f"{kind}_{i}", SIZE_RANGES[kind], texture_px=128)
             for i, kind in enumerate(kinds)]
    while len(props) > PROP_COUNT[0] and sum(
            np.pi * (p.footprint + GAP) ** 2 for p in props) > MAX_COVERAGE * floor_area:
        props.pop()
    return props


def _tray(half_x: float, half_y: float, height: float) -> list[str]:
    """The geoms of the tray standing on the bench: a floor and four walls (boxes)."""
    t, f = BIN_WALL, BIN_FLOOR
    ox, oy = half_x + t, half_y + t                       # outer half-size
    zf, zw = BENCH_TOP + f / 2, BENCH_TOP + height / 2
    geoms = [("bin_floor", [ox, oy, f / 2], [0, 0, zf], "bin_floor"),
             ("bin_wall_px", [t / 2, oy, height / 2], [half_x + t / 2, 0, zw], "bin_wall"),
             ("bin_wall_nx", [t / 2, oy, height / 2], [-half_x - t / 2, 0, zw], "bin_wall"),
             ("bin_wall_py", [half_x, t / 2, height / 2], [0, half_y + t / 2, zw], "bin_wall"),
             ("bin_wall_ny", [half_x, t / 2, height / 2], [0, -half_y - t / 2, zw], "bin_wall")]
    return [f'      <geom name="{name}" type="box" size="{floats(size)}" pos="{floats(pos)}" '
            f'material="{mat}"/>' for name, size, pos, mat in geoms]


def _bench_texture(rng: np.random.Generator) -> np.ndarray:
    """The bench top: wood, a mottled mat or a checker, by the seed."""
    style = int(rng.integers(3))
    if style == 0:
        return textures.wood_grain(rng, 512, 512)
    if style == 1:
        return textures.speckled(rng, 256, textures.random_colour(rng, (0.05, 0.3)), 0.25)
    return textures.checker(256, 8, textures.random_colour(rng, value=(0.7, 0.95)),
                            textures.random_colour(rng, value=(0.2, 0.5)))


def bins_scene(seed: int = 0) -> GeneratedScene:
    """The MJCF text and textures of bins scene ``seed``."""
    rng = np.random.default_rng(seed)
    half_x, half_y = rng.uniform(*BIN_HALF_X), rng.uniform(*BIN_HALF_Y)
    height = rng.uniform(*BIN_WALL_HEIGHT)
    props = choose_props(rng, 4.0 * half_x * half_y)
    floor_z = BENCH_TOP + BIN_FLOOR
    hx, hy = half_x - WALL_MARGIN, half_y - WALL_MARGIN
    places = scatter_discs(rng, [p.footprint for p in props], (-hx, -hy, hx, hy), GAP)
    bodies = [p.body(x, y, floor_z, float(rng.uniform(0.0, 360.0)))
              for p, (x, y) in zip(props, places)]

    plastic = textures.random_colour(rng, (0.4, 0.9), (0.35, 0.85))
    assets = {"bench_top.png": _bench_texture(rng),
              "bin_floor.png": textures.checker(
                  128, 4, np.clip(plastic * 1.25, 0, 1), plastic * 0.7),
              "bin_wall.png": textures.speckled(rng, 128, plastic, 0.2)}
    asset_xml = [file_texture("bench_top"), file_texture("bin_floor"),
                 file_texture("bin_wall", "cube")]
    for p in props:
        asset_xml += p.asset_xml
        assets.update(p.assets)
    ambient = rng.uniform(0.2, 0.3)
    custom = custom_block(
        {"nerfbot_rig_target": [0.0, 0.0, floor_z + 0.02],
         "nerfbot_rig_radius": [RIG_RADIUS], "nerfbot_rig_fovy": [RIG_FOVY],
         "nerfbot_rig_elevation": list(RIG_ELEVATION)},
        {"nerfbot_objects": " ".join(p.name for p in props)})
    description = (f"{len(props)} small parts (1-5 cm) in a tray of inner size "
                   f"{2 * half_x:.2f} m x {2 * half_y:.2f} m on a bench,\n  seen from "
                   f"{RIG_RADIUS} m. Units are metres, z up; the bench top is at z = "
                   f"{BENCH_TOP}, the tray floor at\n  z = {floor_z:.3f}. Textures are the PNG "
                   "files beside this file.")
    return GeneratedScene(_TEMPLATE.format(
        header=header("bins", seed, "sims/zoo/bins.py", description),
        custom=custom, top=BENCH_TOP, ambient=floats([ambient] * 3, 3),
        assets="\n".join(asset_xml),
        lights="\n".join(sun_lights(rng, (0.0, 0.0, BENCH_TOP), 2.0)),
        bench_size=floats([*BENCH_HALF, 0.02]), bench_z=BENCH_TOP - 0.02,
        tray="\n".join(_tray(half_x, half_y, height)), bodies="\n".join(bodies)), assets)


_TEMPLATE = """{header}
<mujoco model="bins">
  <compiler angle="degree"/>
  <option timestep="0.002"/>
  <statistic extent="0.6" center="0 0 {top}"/>

  <visual>
    <global offwidth="1024" offheight="1024" fovy="40"/>
    <quality offsamples="8" shadowsize="2048"/>
    <headlight active="1" ambient="{ambient}" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="0.005" zfar="50" haze="0.2" shadowclip="1.0"/>
    <rgba haze="0.7 0.72 0.75 1"/>
  </visual>

{custom}

  <default>
    <default class="object">
      <geom condim="4" friction="1.0 0.01 0.001" solref="0.004 1" solimp="0.95 0.99 0.001"/>
    </default>
  </default>

  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.45 0.5 0.58"
             rgb2="0.85 0.86 0.88" width="512" height="3072"/>
    <material name="bench_top" texture="bench_top" texrepeat="2 2" specular="0.15"
              shininess="0.3"/>
    <material name="bin_floor" texture="bin_floor" texuniform="true" texrepeat="25 25"
              specular="0.2" shininess="0.3"/>
    <material name="bin_wall" texture="bin_wall" texuniform="true" specular="0.2"
              shininess="0.3"/>
{assets}
  </asset>

  <worldbody>
{lights}

    <body name="bench">
      <geom name="bench_top" type="box" size="{bench_size}" pos="0 0 {bench_z}"
            material="bench_top" friction="1.0 0.01 0.001"/>
    </body>
    <body name="bin">
{tray}
    </body>

{bodies}
  </worldbody>
</mujoco>
"""
