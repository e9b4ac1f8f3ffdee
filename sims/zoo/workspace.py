"""The ``workspace`` scene family: a frame-filling, finely textured work table seen from close by.

A large table top (1.6-1.9 m x 1.2-1.4 m, wood grain from :func:`sims.zoo.textures.wood_grain`)
carries a cutting mat (a printed grid with numbers) and 6-12 props (:mod:`sims.zoo.props`) whose
largest dimension is 3-30 cm: labelled boxes and cans (brand names, small print, barcodes),
books with printed pages, markers, checkered balls and dice, faceted pebbles. The props stand
in the middle 0.96 m x 0.68 m, at least :data:`GAP` apart; each is a free body whose body and
geom share its name, declared in ``<custom><text name="nerfbot_objects">``.

The default rig is a hemisphere 0.8 m around a point 4 cm above the table centre, 45-80 degrees
up, 40 degree fov: from there the table top fills (nearly) the whole frame, so there is little
or no sky. The seed sets the table's size and grain, the props (kinds, sizes, textures, places,
turns), the cutting mat's colour and place, and the lighting (three directional lights of
seeded directions, colours and intensities; the key light casts shadows).

Use as a scene name: ``workspace`` (seed 0) or ``workspace:K``.
"""

from __future__ import annotations

import numpy as np

from sims.zoo import textures
from sims.zoo.layout import scatter_discs
from sims.zoo.mjcf import GeneratedScene, custom_block, file_texture, floats, header, sun_lights
from sims.zoo.props import Prop, make_prop

#: Height of the table top surface, metres.
TABLE_TOP = 0.75
#: Ranges of the table top's half-size along x and y, metres.
TABLE_HALF_X = (0.8, 0.95)
TABLE_HALF_Y = (0.6, 0.7)
#: Half-size (x, y) of the middle of the table where props stand, metres.
PROP_REGION_HALF = (0.48, 0.34)
#: Smallest gap between two props' footprint discs, metres.
GAP = 0.015
#: Number of props, inclusive range.
PROP_COUNT = (6, 12)
#: Range of the largest dimension of any prop, metres.
PROP_SIZE = (0.03, 0.30)
#: Largest dimension of each prop kind, metres (within :data:`PROP_SIZE`).
SIZE_RANGES = {"box": (0.06, 0.22), "can": (0.07, 0.16), "marker": (0.10, 0.18),
               "ball": (0.04, 0.10), "die": (0.03, 0.07), "pebble": (0.04, 0.10),
               "book": (0.15, 0.26)}
#: Props with a large footprint; at most :data:`MAX_LARGE` of them per scene.
LARGE_KINDS = ("box", "book")
MAX_LARGE = 3
#: Share of the prop region the props' footprint discs (with gaps) may cover.
MAX_COVERAGE = 0.4
#: Default rig: distance to the target (metres), fov and elevations (degrees).
RIG_RADIUS = 0.8
RIG_FOVY = 40.0
RIG_ELEVATION = (45.0, 80.0)
#: The rig's target: this far above the table centre, metres.
TARGET_HEIGHT = 0.04


def choose_props(rng: np.random.Generator) -> list[Prop]:
    """The scene's props: a labelled box and a can always, then random kinds (at most
    :data:`MAX_LARGE` boxes and books), fewer when their footprints would crowd the region."""
    count = int(rng.integers(PROP_COUNT[0], PROP_COUNT[1] + 1))
    kinds = ["box", "can"]
    while len(kinds) < count:
        kind = str(rng.choice(list(SIZE_RANGES)))
        if kind in LARGE_KINDS and sum(k in LARGE_KINDS for k in kinds) >= MAX_LARGE:
            continue
        kinds.append(kind)
    props = [make_prop(rng, kind, f"{kind}_{i}", SIZE_RANGES[kind]) for i, kind in enumerate(kinds)]
    area = 4.0 * PROP_REGION_HALF[0] * PROP_REGION_HALF[1]
    while len(props) > PROP_COUNT[0] and sum(
            np.pi * (p.footprint + GAP) ** 2 for p in props) > MAX_COVERAGE * area:
        props.pop()
    return props


def workspace_scene(seed: int = 0) -> GeneratedScene:
    """The MJCF text and textures of workspace scene ``seed``."""
    rng = np.random.default_rng(seed)
    half_x, half_y = rng.uniform(*TABLE_HALF_X), rng.uniform(*TABLE_HALF_Y)
    props = choose_props(rng)
    hx, hy = PROP_REGION_HALF
    places = scatter_discs(rng, [p.footprint for p in props], (-hx, -hy, hx, hy), GAP)
    bodies = [p.body(x, y, TABLE_TOP, float(rng.uniform(0.0, 360.0)))
              for p, (x, y) in zip(props, places)]

    assets = {"table_wood.png": textures.wood_grain(rng, 512, 512),
              "cutting_mat.png": textures.cutting_mat(rng, 512)}
    mat_half = (rng.uniform(0.28, 0.34), rng.uniform(0.2, 0.24))
    mat_xy = (rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2))
    asset_xml = [file_texture("table_wood"), file_texture("cutting_mat")]
    for p in props:
        asset_xml += p.asset_xml
        assets.update(p.assets)
    sky_top = textures.random_colour(rng, (0.2, 0.5), (0.5, 0.8))
    ambient = rng.uniform(0.18, 0.3)
    custom = custom_block(
        {"nerfbot_rig_target": [0.0, 0.0, TABLE_TOP + TARGET_HEIGHT],
         "nerfbot_rig_radius": [RIG_RADIUS], "nerfbot_rig_fovy": [RIG_FOVY],
         "nerfbot_rig_elevation": list(RIG_ELEVATION)},
        {"nerfbot_objects": " ".join(p.name for p in props)})
    description = (f"{len(props)} props (labelled boxes and cans, books, markers, balls, dice, "
                   "pebbles; 3-30 cm) on a\n  wooden work table with a cutting mat, seen from "
                   f"{RIG_RADIUS} m: the table fills the frame. Units are metres, z up;\n  the "
                   f"table top is at z = {TABLE_TOP}. Textures are the PNG files beside this "
                   "file.")
    return GeneratedScene(_TEMPLATE.format(
        header=header("workspace", seed, "sims/zoo/workspace.py", description),
        custom=custom, top=TABLE_TOP, ambient=floats([ambient] * 3, 3),
        sky_top=floats(sky_top, 3), assets="\n".join(asset_xml),
        lights="\n".join(sun_lights(rng, (0.0, 0.0, TABLE_TOP), 3.0)),
        table_size=floats([half_x, half_y, 0.02]), table_z=TABLE_TOP - 0.02,
        mat_size=floats([*mat_half, 0.0015]), mat_pos=floats([*mat_xy, TABLE_TOP - 0.001]),
        bodies="\n".join(bodies)), assets)


_TEMPLATE = """{header}
<mujoco model="workspace">
  <compiler angle="degree"/>
  <option timestep="0.002"/>
  <statistic extent="1.5" center="0 0 {top}"/>

  <visual>
    <global offwidth="1024" offheight="1024" fovy="40"/>
    <quality offsamples="8" shadowsize="2048"/>
    <headlight active="1" ambient="{ambient}" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="0.005" zfar="30" haze="0.2" shadowclip="0.8"/>
    <rgba haze="0.7 0.72 0.75 1"/>
  </visual>

{custom}

  <default>
    <default class="object">
      <geom condim="4" friction="1.0 0.01 0.001" solref="0.004 1" solimp="0.95 0.99 0.001"/>
    </default>
  </default>

  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="{sky_top}"
             rgb2="0.85 0.86 0.88" width="512" height="3072"/>
    <material name="table_wood" texture="table_wood" texrepeat="1 1" specular="0.15"
              shininess="0.3"/>
    <material name="cutting_mat" texture="cutting_mat" texrepeat="1 1" specular="0.1"
              shininess="0.2"/>
{assets}
  </asset>

  <worldbody>
{lights}

    <body name="table">
      <geom name="table_top" type="box" size="{table_size}" pos="0 0 {table_z}"
            material="table_wood" friction="1.0 0.01 0.001"/>
      <geom name="cutting_mat" type="box" size="{mat_size}" pos="{mat_pos}"
            material="cutting_mat" friction="1.0 0.01 0.001"/>
    </body>

{bodies}
  </worldbody>
</mujoco>
"""
