"""The ``room`` scene family: a closed, furnished room seen from cameras inside it.

The room is W x D metres (each 4-8 m, seeded) and 2.4-3.0 m high, centred on the origin with
its floor at z = 0. Floor (wooden planks or tiles), four walls (wallpaper; one accent wall) and
the ceiling (plaster) are finite planes facing inwards, so no sky is visible from inside and the
content bounds are the room. A partition (1.2-2.0 m high panels) crosses the room from wall to
wall with a narrow doorway (:data:`DOORWAY_WIDTH`, 0.55-0.68 m): at least one narrow passage
between obstacles, and the only way from one part of the room to the other. Furniture stands in
the rest of the room, at least :data:`FURNITURE_GAP` (0.7 m) from other furniture and the
partition, and clear of the doorway's approach:

- tables on four legs: desks and dining tables (tops at 0.70-0.78 m, a low robot may pass
  under them) and coffee tables (0.40-0.45 m);
- open shelves against a wall (side panels, boards, a back covered in book spines);
- crates (boxes of wood or printed cardboard) and barrels (cylinders).

Every furniture geom is named after its piece (``table_0_top``, ``table_0_leg_2``,
``shelf_1_board_1``, ``crate_2``, ``partition_a_0``, ...) and declared twice in ``<custom>``: as
``nerfbot_obstacles`` (a mobile robot's planner reads their footprints; the capture manifest
lists their world AABBs under ``obstacles``) and as ``nerfbot_objects``. Further declarations:
``nerfbot_room_size`` (W D H, metres) and ``nerfbot_passage`` (x0 y0 x1 y1: the doorway's two
jambs, so its width is their distance).

The default rig is ``inside`` (:mod:`sims.rigs`): cameras uniform over the free floor, at least
:data:`CAMERA_CLEARANCE` m from walls and obstacle footprints, 0.4-1.6 m high, random yaw, pitch
-20 to +10 degrees, 70 degree fov. Lighting: a ceiling spot light casting shadows (a second one
in large rooms), a soft directional fill from above and a weak bounce light from below for the
ceiling, with seeded colours, intensities and directions.

Use as a scene name: ``room`` (seed 0) or ``room:K``.

``room_glass`` / ``room_glass:K`` is room ``K`` (the same layout, textures and lights) with a
glass partition: its panels are clear glass (alpha :data:`GLASS_ALPHA`, strong specular
highlights, as in ``glassware``) held by opaque posts at the doorway's jambs, named
``partition_a_0``, ... and ``post_a`` / ``post_b``. The panels are listed as transparent in
the capture manifest, so the simulated depth sensor sees through them while the ground-truth
depth, segmentation and obstacle footprints keep them: a map made from the sensor alone
shows open floor where the glass stands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sims.zoo import textures
from sims.zoo.layout import box_gap
from sims.zoo.mjcf import (GeneratedScene, custom_block, file_texture, floats, header, light,
                           light_colour, light_direction)

#: Ranges of the room's width (x), depth (y) and height, metres.
ROOM_WIDTH = (4.0, 8.0)
ROOM_DEPTH = (4.0, 8.0)
ROOM_HEIGHT = (2.4, 3.0)
#: Width of the partition's doorway, metres: the narrow passage.
DOORWAY_WIDTH = (0.55, 0.68)
#: Thickness of the partition, metres, and the range of its height.
PARTITION_THICKNESS = 0.1
PARTITION_HEIGHT = (1.2, 2.0)
#: The partition stands at least this far from the walls it runs along, metres.
PARTITION_WALL_DISTANCE = 1.5
#: The partition's panels are at most this long, metres.
PANEL_LENGTH = 1.0
#: Furniture keeps :data:`FURNITURE_GAP` from a box this far (metres) on both sides of the
#: partition's centre line across the doorway, so the passage can be reached.
DOORWAY_APPROACH = 0.5
#: Smallest gap between two pieces of furniture, and between furniture and the partition,
#: metres: wide enough for cameras and a small robot to pass.
FURNITURE_GAP = 0.7
#: Random draws per piece of furniture before it is left out.
PLACEMENT_TRIES = 300
#: Opacity of a ``room_glass`` partition's panels (the ``glassware`` family's glass).
GLASS_ALPHA = 0.18
#: Width of the opaque posts at the doorway's jambs in ``room_glass``, metres; a post is
#: 2 cm thicker than the panels, which end inside it.
POST_WIDTH = 0.05
#: Cameras of the default rig keep this far from walls and obstacle footprints, metres.
CAMERA_CLEARANCE = 0.3
#: Camera heights (metres) and pitch (degrees) of the default rig.
CAMERA_HEIGHTS = (0.4, 1.6)
CAMERA_PITCH = (-20.0, 10.0)
CAMERA_FOVY = 70.0


@dataclass
class Piece:
    """One piece of furniture, before placement: its geoms in its own frame (origin at the
    centre of its footprint on the floor) and its footprint's half-size (x, y), metres."""

    name: str
    half: tuple[float, float]
    geoms: list[tuple[str, str, list[float], list[float], str]]  # (name, type, size, pos, mat)

    def body(self, x: float, y: float, yaw_deg: float) -> str:
        """The piece's static ``<body>`` with its footprint centred on (x, y), turned by
        ``yaw_deg`` about z (a multiple of 90 degrees keeps the footprint axis-aligned)."""
        lines = [f'    <body name="{self.name}" pos="{floats([x, y, 0.0])}" '
                 f'euler="0 0 {yaw_deg:g}">']
        for name, kind, size, pos, mat in self.geoms:
            lines.append(f'      <geom name="{name}" type="{kind}" size="{floats(size)}" '
                         f'pos="{floats(pos)}" material="{mat}"/>')
        lines.append("    </body>")
        return "\n".join(lines)


def table(rng: np.random.Generator, name: str, max_length: float) -> Piece:
    """A table on four square legs: a desk or dining table (top 0.70-0.78 m up, room beneath
    for a low robot) or, one time in three, a coffee table (0.40-0.45 m)."""
    low = rng.random() < 1 / 3
    length = rng.uniform(0.8, max(min(1.6, max_length), 0.9))
    width = rng.uniform(0.55, 0.9) if not low else rng.uniform(0.45, 0.6)
    height = rng.uniform(0.40, 0.45) if low else rng.uniform(0.70, 0.78)
    top, leg = 0.035, 0.05
    geoms = [(f"{name}_top", "box", [length / 2, width / 2, top / 2], [0, 0, height - top / 2],
              f"{name}_top")]
    lx, ly = length / 2 - leg, width / 2 - leg
    for k, (sx, sy) in enumerate([(1, 1), (-1, 1), (-1, -1), (1, -1)]):
        geoms.append((f"{name}_leg_{k}", "box", [leg / 2, leg / 2, (height - top) / 2],
                      [sx * lx, sy * ly, (height - top) / 2], "furniture_frame"))
    return Piece(name, (length / 2, width / 2), geoms)


def shelf(rng: np.random.Generator, name: str) -> Piece:
    """Open shelves, back to the wall along the piece's +y side: two side panels, a bottom, a
    top and 2-3 boards between, and a back covered in book spines."""
    width, depth = rng.uniform(0.8, 1.4), rng.uniform(0.3, 0.4)
    height = rng.uniform(1.4, 2.0)
    t = 0.025
    geoms = [(f"{name}_side_l", "box", [t / 2, depth / 2, height / 2],
              [-width / 2 + t / 2, 0, height / 2], f"{name}_wood"),
             (f"{name}_side_r", "box", [t / 2, depth / 2, height / 2],
              [width / 2 - t / 2, 0, height / 2], f"{name}_wood"),
             (f"{name}_back", "box", [width / 2 - t, t / 2, height / 2 - t],
              [0, depth / 2 - t / 2, height / 2], f"{name}_books")]
    boards = int(rng.integers(2, 4))
    levels = np.linspace(0.06, height - t / 2, boards + 2)
    for k, z in enumerate(levels):
        geoms.append((f"{name}_board_{k}", "box", [width / 2 - t, depth / 2 - t / 2, t / 2],
                      [0, -t / 2, z], f"{name}_wood"))
    return Piece(name, (width / 2, depth / 2), geoms)


def crate(rng: np.random.Generator, name: str) -> Piece:
    """A crate or cabinet: a box 0.4-0.9 m wide and deep, 0.4-1.2 m high."""
    w, d, h = rng.uniform(0.4, 0.9), rng.uniform(0.4, 0.9), rng.uniform(0.4, 1.2)
    return Piece(name, (w / 2, d / 2), [(name, "box", [w / 2, d / 2, h / 2], [0, 0, h / 2], name)])


def barrel(rng: np.random.Generator, name: str) -> Piece:
    """A barrel or pillar: a cylinder of radius 0.2-0.35 m, 0.6-1.2 m high."""
    r, h = rng.uniform(0.2, 0.35), rng.uniform(0.6, 1.2)
    return Piece(name, (r, r), [(name, "cylinder", [r, h / 2], [0, 0, h / 2], name)])


def _walls(width: float, depth: float, height: float, accent: int) -> list[str]:
    """Floor, ceiling and the four walls: finite planes facing into the room (``xyaxes`` keeps
    each wall's texture upright), slightly oversized so the corners have no cracks."""
    w, d, h, e = width / 2, depth / 2, height / 2, 0.02
    planes = [("floor", [w + e, d + e, 0.2], [0, 0, 0], "1 0 0 0 1 0", "floor"),
              ("ceiling", [w + e, d + e, 0.2], [0, 0, height], "1 0 0 0 -1 0", "ceiling"),
              ("wall_east", [d + e, h + e, 0.2], [w, 0, h], "0 -1 0 0 0 1", "wall"),
              ("wall_west", [d + e, h + e, 0.2], [-w, 0, h], "0 1 0 0 0 1", "wall"),
              ("wall_north", [w + e, h + e, 0.2], [0, d, h], "1 0 0 0 0 1", "wall"),
              ("wall_south", [w + e, h + e, 0.2], [0, -d, h], "-1 0 0 0 0 1", "wall")]
    out = []
    for k, (name, size, pos, axes, mat) in enumerate(planes):
        if k - 2 == accent:
            mat = "wall_accent"
        out.append(f'    <geom name="{name}" type="plane" size="{floats(size)}" '
                   f'pos="{floats(pos)}" xyaxes="{axes}" material="{mat}"/>')
    return out


def _against_wall(rng: np.random.Generator, piece: Piece, width: float, depth: float,
                  placed: list) -> tuple[float, float, float] | None:
    """(x, y, yaw degrees) of ``piece`` (a shelf, its back along its +y side) against a random
    wall, :data:`FURNITURE_GAP` from the boxes ``placed`` (its own box is appended); None when
    no place is found."""
    hw, hd = piece.half
    for _ in range(PLACEMENT_TRIES):
        wall = int(rng.integers(4))      # north, south, east, west; yaw turns the back to it
        if wall < 2:
            x = rng.uniform(-width / 2 + hw, width / 2 - hw)
            y = depth / 2 - hd if wall == 0 else -depth / 2 + hd
            yaw, box = (0.0 if wall == 0 else 180.0), (x - hw, y - hd, x + hw, y + hd)
        else:
            x = width / 2 - hd if wall == 2 else -width / 2 + hd
            y = rng.uniform(-depth / 2 + hw, depth / 2 - hw)
            yaw, box = (-90.0 if wall == 2 else 90.0), (x - hd, y - hw, x + hd, y + hw)
        if all(box_gap(box, other) >= FURNITURE_GAP for other in placed):
            placed.append(box)
            return float(x), float(y), yaw
    return None


def _free_standing(rng: np.random.Generator, piece: Piece, region, placed: list
                   ) -> tuple[float, float, float] | None:
    """(x, y, yaw degrees: 0 or 90) of ``piece`` inside ``region`` (xmin, ymin, xmax, ymax),
    :data:`FURNITURE_GAP` from the boxes ``placed`` (its own box is appended); None when no
    place is found."""
    for _ in range(PLACEMENT_TRIES):
        turned = bool(rng.random() < 0.5)
        hx, hy = (piece.half[1], piece.half[0]) if turned else piece.half
        if region[2] - region[0] <= 2 * hx or region[3] - region[1] <= 2 * hy:
            continue
        x = rng.uniform(region[0] + hx, region[2] - hx)
        y = rng.uniform(region[1] + hy, region[3] - hy)
        box = (x - hx, y - hy, x + hx, y + hy)
        if all(box_gap(box, other) >= FURNITURE_GAP for other in placed):
            placed.append(box)
            return float(x), float(y), 90.0 if turned else 0.0
    return None


def _partition(width: float, depth: float, at: float, door: float, door_at: float,
               height: float, glass: bool = False
               ) -> tuple[list[str], list[tuple[float, float, float, float]]]:
    """(geom lines, footprints) of the partition: wall-to-wall panels (each at most
    :data:`PANEL_LENGTH` long) with the doorway between ``door_at`` -/+ ``door`` / 2 along it.
    It runs along y at x = ``at`` when the room is wider than deep, else along x at y = ``at``.
    With ``glass`` the panels are glass and an opaque post stands at each jamb, inside the
    panels' span (the doorway keeps its width)."""
    along_y = width >= depth
    span = depth if along_y else width
    t = PARTITION_THICKNESS

    def box(name: str, centre: float, half: float, thickness: float, material: str) -> str:
        pos = [at, centre, height / 2] if along_y else [centre, at, height / 2]
        size = [thickness / 2, half, height / 2] if along_y else [half, thickness / 2, height / 2]
        return (f'      <geom name="{name}" type="box" size="{floats(size)}" '
                f'pos="{floats(pos)}" material="{material}"/>')

    geoms, boxes = [], []
    for label, (s0, s1) in zip("ab", [(-span / 2, door_at - door / 2),
                                      (door_at + door / 2, span / 2)]):
        panels = int(np.ceil((s1 - s0) / PANEL_LENGTH - 1e-9))
        edges = np.linspace(s0, s1, panels + 1)
        for k, (e0, e1) in enumerate(zip(edges[:-1], edges[1:])):
            geoms.append(box(f"partition_{label}_{k}", 0.5 * (e0 + e1), 0.5 * (e1 - e0), t,
                             "glass" if glass else "partition"))
        if glass:  # the post at this side's jamb
            jamb = s1 if label == "a" else s0
            inward = -1.0 if label == "a" else 1.0
            geoms.append(box(f"post_{label}", jamb + inward * POST_WIDTH / 2, POST_WIDTH / 2,
                             t + 0.02, "furniture_frame"))
        lo, hi = (s0, s1)
        boxes.append((at - t / 2, lo, at + t / 2, hi) if along_y
                     else (lo, at - t / 2, hi, at + t / 2))
    return geoms, boxes


def room_scene(seed: int = 0) -> GeneratedScene:
    """The MJCF text and textures of room scene ``seed``."""
    return _room(seed, glass=False)


def room_glass_scene(seed: int = 0) -> GeneratedScene:
    """Room scene ``seed`` with a glass partition (module docstring)."""
    return _room(seed, glass=True)


def _room(seed: int, glass: bool) -> GeneratedScene:
    """Room ``seed``; with ``glass`` its partition is glass. The glass takes no random draw,
    so both share every other choice."""
    rng = np.random.default_rng(seed)
    width, depth = rng.uniform(*ROOM_WIDTH), rng.uniform(*ROOM_DEPTH)
    height = rng.uniform(*ROOM_HEIGHT)
    area = width * depth

    # The partition crosses the longer side, so both parts keep room to move.
    along_y = width >= depth
    span, across = (depth, width) if along_y else (width, depth)
    at = rng.uniform(-across / 2 + PARTITION_WALL_DISTANCE, across / 2 - PARTITION_WALL_DISTANCE)
    door = rng.uniform(*DOORWAY_WIDTH)
    door_at = rng.uniform(-span / 2 + 0.9, span / 2 - 0.9)
    partition_geoms, placed = _partition(width, depth, at, door, door_at,
                                         rng.uniform(*PARTITION_HEIGHT), glass)
    bodies = ['    <body name="partition">', *partition_geoms, "    </body>"]
    obstacles = [line.split('"')[1] for line in partition_geoms]
    jamb_a, jamb_b = door_at - door / 2, door_at + door / 2
    passage = [at, jamb_a, at, jamb_b] if along_y else [jamb_a, at, jamb_b, at]
    reach = DOORWAY_APPROACH
    placed.append((at - reach, jamb_a, at + reach, jamb_b) if along_y
                  else (jamb_a, at - reach, jamb_b, at + reach))

    # Furniture: shelves against walls first, then free-standing pieces; textures per piece.
    assets, asset_xml = {}, []
    pieces = [shelf(rng, f"shelf_{k}") for k in range(1 + int(area > 36.0))]
    pieces += [table(rng, f"table_{k}", 0.35 * min(width, depth))
               for k in range(1 + int(area > 30.0))]
    pieces += [crate(rng, f"crate_{k}") for k in range(int(rng.integers(1, 3)) + int(area > 40.0))]
    pieces += [barrel(rng, f"barrel_{k}") for k in range(int(rng.integers(1, 3)))]
    margin = 0.1
    region = (-width / 2 + margin, -depth / 2 + margin, width / 2 - margin, depth / 2 - margin)
    for piece in pieces:
        name = piece.name
        if name.startswith("shelf"):
            where = _against_wall(rng, piece, width, depth, placed)
        else:
            where = _free_standing(rng, piece, region, placed)
        if where is None:
            continue
        bodies.append(piece.body(*where))
        obstacles += [g[0] for g in piece.geoms]
        if name.startswith("shelf"):
            assets[f"{name}_wood.png"] = textures.wood_grain(rng, 256, 256)
            assets[f"{name}_books.png"] = textures.books(rng, 256, len(piece.geoms) - 4)
            asset_xml += [file_texture(f"{name}_wood", "cube"),
                          f'    <material name="{name}_wood" texture="{name}_wood" '
                          f'specular="0.15" shininess="0.3"/>',
                          file_texture(f"{name}_books", "cube"),
                          f'    <material name="{name}_books" texture="{name}_books" '
                          f'texuniform="true" specular="0.1" shininess="0.2"/>']
        elif name.startswith("table"):
            assets[f"{name}_top.png"] = textures.wood_grain(rng, 256, 512)
            asset_xml += [file_texture(f"{name}_top"),
                          f'    <material name="{name}_top" texture="{name}_top" '
                          f'texrepeat="1 1" specular="0.25" shininess="0.4"/>']
        elif name.startswith("crate"):
            cardboard = rng.random() < 0.5
            assets[f"{name}.png"] = (textures.label(rng, 256) if cardboard
                                     else textures.wood_planks(rng, 256, 4))
            asset_xml += [file_texture(name, "cube"),
                          f'    <material name="{name}" texture="{name}" texuniform="true" '
                          f'specular="0.1" shininess="0.2"/>']
        else:
            assets[f"{name}.png"] = textures.speckled(rng, 256, amount=0.25)
            asset_xml += [file_texture(name, "cube"),
                          f'    <material name="{name}" texture="{name}" specular="0.3" '
                          f'shininess="0.5"/>']

    # Surfaces.
    if rng.random() < 0.6:
        assets["floor.png"] = textures.wood_planks(rng, 512, 6)
        floor_repeat = rng.uniform(0.7, 0.9)      # images per metre: planks 18-24 cm wide
    else:
        assets["floor.png"] = textures.tiles(rng, 512, 6)
        floor_repeat = rng.uniform(0.4, 0.6)      # tiles 28-42 cm
    assets["wall.png"] = textures.wallpaper(rng, 256)
    assets["wall_accent.png"] = textures.wallpaper(rng, 256)
    assets["partition.png"] = textures.speckled(rng, 256, amount=0.2)
    asset_xml = [file_texture("floor"), file_texture("wall"), file_texture("wall_accent"),
                 file_texture("partition", "cube")] + asset_xml
    plaster = textures.random_colour(rng, (0.0, 0.15), (0.8, 0.95))

    # Lights: ceiling spots (the first casts shadows), a fill from above, a bounce from below.
    lights = []
    lamps = [(0.0, 0.0)] if area <= 30.0 else [(-width / 4, 0.0), (width / 4, 0.0)]
    for k, (x, y) in enumerate(lamps):
        lights.append(light(f"ceiling_{k}", [x, y, height - 0.05], [0, 0, -1],
                            light_colour(rng, (-0.3, 1.0), (0.5, 0.7)), specular=0.3,
                            directional=False, castshadow=k == 0, cutoff=70))
    fill = light_direction(rng.uniform(0, 360), rng.uniform(40, 75))
    lights.append(light("fill", -3.0 * fill + [0, 0, height], fill,
                        light_colour(rng, (-1.0, 0.5), (0.2, 0.35))))
    lights.append(light("bounce", [0, 0, 0.1], [0, 0, 1],
                        light_colour(rng, (-0.2, 0.6), (0.12, 0.2)), specular=0.0))

    custom = custom_block(
        {"nerfbot_rig_target": [0.0, 0.0, 1.0], "nerfbot_rig_radius": [1.0],
         "nerfbot_rig_fovy": [CAMERA_FOVY],
         "nerfbot_rig_region": [-width / 2, -depth / 2, width / 2, depth / 2],
         "nerfbot_rig_heights": list(CAMERA_HEIGHTS),
         "nerfbot_rig_pitch": list(CAMERA_PITCH),
         "nerfbot_rig_clearance": [CAMERA_CLEARANCE],
         "nerfbot_room_size": [width, depth, height],
         "nerfbot_passage": passage},
        {"nerfbot_rig_kind": "inside",
         "nerfbot_obstacles": " ".join(obstacles),
         "nerfbot_objects": " ".join(obstacles)})
    kind = "a glass partition (clear panels, opaque posts at the doorway)" if glass \
        else "a partition"
    description = (f"A {width:.2f} m x {depth:.2f} m room, {height:.2f} m high, seen from inside:"
                   f" {kind} with a\n  doorway {door:.2f} m wide, shelves, tables, crates "
                   "and barrels. Units are metres, z up; the floor\n  is at z = 0, the room "
                   "centred on the origin. Textures are the PNG files beside this file.")
    family = "room_glass" if glass else "room"
    xml = _TEMPLATE.format(
        header=header(family, seed, "sims/zoo/room.py", description), family=family,
        custom=custom, glass=_GLASS.format(alpha=GLASS_ALPHA) if glass else "",
        extent=floats([max(width, depth)], 3), centre=floats([0, 0, height / 2], 3),
        ambient=floats([rng.uniform(0.2, 0.3)] * 3, 3), assets="\n".join(asset_xml),
        floor_repeat=floats([floor_repeat] * 2, 3), plaster=floats(plaster, 3),
        plaster_mark=floats(plaster * 0.85, 3), lights="\n".join(lights),
        frame=floats(textures.random_colour(rng, (0.0, 0.3), (0.15, 0.5)), 3),
        surfaces="\n".join(_walls(width, depth, height, int(rng.integers(4)))),
        bodies="\n".join(bodies))
    return GeneratedScene(xml, assets)


#: The glass material of ``room_glass`` (the ``glassware`` family's).
_GLASS = '\n    <material name="glass" rgba="0.80 0.90 0.96 {alpha:.2f}" specular="1" shininess="1"/>'

_TEMPLATE = """{header}
<mujoco model="{family}">
  <compiler angle="degree"/>
  <option timestep="0.002"/>
  <statistic extent="{extent}" center="{centre}"/>

  <visual>
    <global offwidth="1024" offheight="1024" fovy="70"/>
    <quality offsamples="8" shadowsize="2048"/>
    <headlight active="1" ambient="{ambient}" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="0.005" zfar="10" haze="0" shadowclip="1"/>
  </visual>

{custom}

  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="0.4 0.5 0.6" rgb2="0 0 0"
             width="64" height="384"/>
    <texture name="ceiling" type="2d" builtin="flat" rgb1="{plaster}" mark="random"
             markrgb="{plaster_mark}" random="0.08" width="256" height="256"/>
    <material name="ceiling" texture="ceiling" texuniform="true" texrepeat="1 1"
              specular="0" shininess="0"/>
    <material name="floor" texture="floor" texuniform="true" texrepeat="{floor_repeat}"
              specular="0.2" shininess="0.3"/>
    <material name="wall" texture="wall" texuniform="true" texrepeat="2 2" specular="0.05"
              shininess="0.1"/>
    <material name="wall_accent" texture="wall_accent" texuniform="true" texrepeat="2 2"
              specular="0.05" shininess="0.1"/>
    <material name="partition" texture="partition" texuniform="true" specular="0.1"
              shininess="0.2"/>
    <material name="furniture_frame" rgba="{frame} 1" specular="0.3" shininess="0.5"/>{glass}
{assets}
  </asset>

  <worldbody>
{lights}

{surfaces}

{bodies}
  </worldbody>
</mujoco>
"""
