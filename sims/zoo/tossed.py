"""The ``tossed`` scene family: props thrown onto a textured table, and sometimes a pendulum;
a dynamic scene (captured over time by :mod:`sims.dynamic`).

A table top (1.0-1.2 m x 0.7-0.84 m, wood grain from :func:`sims.zoo.textures.wood_grain`)
with a low rim receives 3-5 props (:mod:`sims.zoo.props`: a checkered sphere always, then
checkered balls and dice, labelled boxes and cans, faceted pebbles; largest dimension 6-14 cm),
each starting 5-35 cm above the table at a seeded place and orientation, thrown with a seeded
velocity (0.2-0.7 m/s across the table) and spin (up to 8 rad/s about a random axis): they
fall, bounce, tumble and slide, and the round ones roll on, off the rim, for the whole capture.
Half the seeds add a pendulum (a 20-32 cm rod with a sphere, on a gantry at one end of the
table) released 35-70 degrees from vertical. Everything beyond the table is sky, as in the
built-in ``dynamic`` scene.

The seed sets the table's size and grain, the props (kinds, sizes, textures, start poses and
velocities), the pendulum and the lighting (three directional lights of seeded directions,
colours and intensities; the key light casts shadows). Throws are drawn again (from the same
seeded stream, so a seed always gives the same scene) until a physics rollout of the scene's
duration keeps every prop on the table top and something still moves in its last quarter
(:func:`throw_is_kept`).

The default rig circles :data:`RIG_RADIUS` m around a point above the table centre at 25-65
degrees of elevation with a 30 degree fov: the table fills most of the frame and a prop of
10 cm covers about 14 pixels of a 128-pixel image.

Use as a scene name: ``tossed`` (seed 0) or ``tossed:K``.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from nerfbot.data.writers import encode_png
from sims.zoo import textures
from sims.zoo.layout import scatter_discs
from sims.zoo.mjcf import GeneratedScene, custom_block, file_texture, floats, header, sun_lights
from sims.zoo.props import Prop, make_prop

#: Height of the table top surface, metres.
TABLE_TOP = 0.75
#: Ranges of the table top's half-size along x and y, metres.
TABLE_HALF_X = (0.5, 0.6)
TABLE_HALF_Y = (0.35, 0.42)
#: Half-size (x, y) of the middle of the table above which props start, metres.
START_REGION_HALF = (0.28, 0.2)
#: Smallest gap between two props' start footprints, metres.
GAP = 0.03
#: Number of props, inclusive range.
PROP_COUNT = (3, 5)
#: Largest dimension of each prop kind, metres.
SIZE_RANGES = {"sphere": (0.08, 0.12), "ball": (0.08, 0.12), "die": (0.06, 0.10),
               "box": (0.08, 0.14), "can": (0.08, 0.14), "pebble": (0.06, 0.10)}
#: The rim around the table top: height above the top and thickness, metres.
RIM_HEIGHT = 0.03
RIM_WIDTH = 0.02
#: Height of a prop's lowest point above the table at the start, metres.
DROP_HEIGHT = (0.05, 0.35)
#: Horizontal throw speed (m/s), upward speed (m/s) and spin (rad/s) ranges.
THROW_SPEED = (0.2, 0.7)
THROW_UP = (-0.2, 0.6)
SPIN = (0.0, 8.0)
#: A prop stays on the table while its centre is above the top and inside the rim.
#: Something moves late when a prop's centre or the bob moves faster than this (m/s) at some
#: recorded state of the rollout's last :data:`LATE_SHARE`.
LATE_SPEED = 0.05
LATE_SHARE = 0.25
#: Throws drawn before the generator gives up.
THROW_TRIES = 40
#: Chance of a pendulum, its rod length (m), bob radius (m) and release angle (degrees).
PENDULUM_CHANCE = 0.5
PENDULUM_LENGTH = (0.2, 0.32)
PENDULUM_BOB = (0.035, 0.05)
PENDULUM_ANGLE = (35.0, 70.0)
#: The pendulum's gantry stands this far inside the table's x edge, metres.
GANTRY_INSET = 0.1
#: Simulated seconds of a capture (``nerfbot_duration``).
DURATION_S = 2.5
#: Default rig: distance to the target (metres), fov and elevations (degrees).
RIG_RADIUS = 1.7
RIG_FOVY = 30.0
RIG_ELEVATION = (25.0, 65.0)
#: The rig's target: this far above the table centre, metres.
TARGET_HEIGHT = 0.1


@dataclass
class Pendulum:
    """A pendulum on a gantry along y at ``x`` (metres): pivot height, rod length and bob radius
    (metres), release angle (radians, about +x)."""

    x: float
    pivot_z: float
    length: float
    bob: float
    angle: float

    def geoms(self) -> str:
        """The gantry's two posts and bar (static geoms of the world body); the posts stand
        beyond the bob's reach."""
        post_half = (self.pivot_z - TABLE_TOP) / 2
        post_y = self.length + self.bob + 0.04
        return "\n".join([
            f'    <geom name="gantry_post_a" type="box" size="0.015 0.015 {post_half:.4f}" '
            f'pos="{floats([self.x, -post_y, TABLE_TOP + post_half])}" material="gantry"/>',
            f'    <geom name="gantry_post_b" type="box" size="0.015 0.015 {post_half:.4f}" '
            f'pos="{floats([self.x, post_y, TABLE_TOP + post_half])}" material="gantry"/>',
            f'    <geom name="gantry_bar" type="cylinder" size="0.012 {post_y + 0.015:.4f}" '
            f'pos="{floats([self.x, 0.0, self.pivot_z])}" zaxis="0 1 0" material="gantry"/>'])

    def body(self) -> str:
        """The swinging body: a hinge about +x, the rod (no contacts) and the bob, which knocks a
        prop that strays under its arc."""
        half = self.length / 2
        return (f'    <body name="pendulum" pos="{floats([self.x, 0.0, self.pivot_z])}">\n'
                f'      <joint name="pendulum_hinge" type="hinge" axis="1 0 0" '
                f'damping="0.002"/>\n'
                f'      <geom name="pendulum_rod" type="cylinder" size="0.006 {half:.4f}" '
                f'pos="0 0 {-half:.4f}" material="rod" contype="0" conaffinity="0"/>\n'
                f'      <geom name="pendulum_bob" type="sphere" size="{self.bob:.4f}" '
                f'pos="0 0 {-self.length:.4f}" material="bob" density="3000"/>\n'
                f'    </body>')


def _pendulum(rng: np.random.Generator, half_x: float) -> Pendulum | None:
    """A seeded pendulum at one x end of the table, or None (:data:`PENDULUM_CHANCE`)."""
    if rng.uniform() >= PENDULUM_CHANCE:
        return None
    side = 1.0 if rng.uniform() < 0.5 else -1.0
    length = float(rng.uniform(*PENDULUM_LENGTH))
    bob = float(rng.uniform(*PENDULUM_BOB))
    # The bob swings 4 cm above the rim at the bottom of its arc.
    pivot_z = TABLE_TOP + RIM_HEIGHT + length + bob + 0.04
    angle = np.radians(rng.uniform(*PENDULUM_ANGLE)) * (1.0 if rng.uniform() < 0.5 else -1.0)
    return Pendulum(side * (half_x - GANTRY_INSET), pivot_z, length, bob, float(angle))


def _random_quaternion(rng: np.random.Generator) -> np.ndarray:
    """(4,) w-x-y-z unit quaternion, uniform over rotations."""
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def _throws(rng: np.random.Generator, props: list[Prop]) -> tuple[np.ndarray, np.ndarray]:
    """Start state of each prop: qpos (P, 7) (centre, w-x-y-z quaternion) and qvel (P, 6)
    (linear velocity in the world, angular velocity in the body frame)."""
    hx, hy = START_REGION_HALF
    places = scatter_discs(rng, [p.largest / 2 for p in props], (-hx, -hy, hx, hy), GAP)
    qpos, qvel = [], []
    for p, (x, y) in zip(props, places):
        # The largest half-dimension bounds the centre's height above the lowest point in any
        # orientation, so no prop starts inside the table.
        z = TABLE_TOP + p.largest / 2 + rng.uniform(*DROP_HEIGHT)
        heading = rng.uniform(0.0, 2 * np.pi)
        speed = rng.uniform(*THROW_SPEED)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        qpos.append([x, y, z, *_random_quaternion(rng)])
        qvel.append([speed * np.cos(heading), speed * np.sin(heading), rng.uniform(*THROW_UP),
                     *(axis * rng.uniform(*SPIN))])
    return np.asarray(qpos), np.asarray(qvel)


def throw_is_kept(model: mujoco.MjModel, prop_names: list[str],
                  duration_s: float = DURATION_S) -> bool:
    """Whether a rollout of ``model`` from its ``init`` keyframe over ``duration_s`` seconds,
    looked at every 10th physics step, stays finite, keeps the centre of every prop above the
    table top (``table_top``) and inside its rim, and has a prop (or the pendulum's bob) moving
    faster than :data:`LATE_SPEED` at some look in its last :data:`LATE_SHARE`."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("init").id)
    ids = [model.body(n).id for n in prop_names]
    pendulum = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "pendulum")
    if pendulum >= 0:
        ids.append(pendulum)
    total = int(round(duration_s / model.opt.timestep))
    inner_x, inner_y = model.geom("table_top").size[:2] - RIM_WIDTH
    moving_late, before = False, None
    for step in range(1, total + 1):
        mujoco.mj_step(model, data)
        if step % 10:
            continue
        # Centres of mass: the pendulum body's origin is its pivot, its centre of mass lies
        # near the bob.
        pos = np.array(data.xipos[ids])
        if not np.isfinite(pos).all():
            return False
        props = pos[:len(prop_names)]
        if ((np.abs(props[:, 0]) > inner_x).any() or (np.abs(props[:, 1]) > inner_y).any()
                or (props[:, 2] < TABLE_TOP).any()):
            return False
        if before is not None and step >= (1.0 - LATE_SHARE) * total:
            speed = np.linalg.norm(pos - before, axis=1) / (10 * model.opt.timestep)
            moving_late |= bool((speed > LATE_SPEED).any())
        before = pos
    return moving_late


def _rim(half_x: float, half_y: float) -> str:
    """Four boxes around the table top's edge, :data:`RIM_HEIGHT` above it, that keep the
    rolling props on the table."""
    h, w = RIM_HEIGHT / 2, RIM_WIDTH / 2
    z = TABLE_TOP + h
    sides = [("x_pos", [half_x - w, 0.0], [w, half_y, h]),
             ("x_neg", [-half_x + w, 0.0], [w, half_y, h]),
             ("y_pos", [0.0, half_y - w], [half_x, w, h]),
             ("y_neg", [0.0, -half_y + w], [half_x, w, h])]
    return "\n".join(
        f'    <geom name="table_rim_{name}" type="box" size="{floats(size)}" '
        f'pos="{floats([*xy, z])}" material="table_wood" friction="0.5 0.01 0.001"/>'
        for name, xy, size in sides)


def _legs(half_x: float, half_y: float) -> str:
    """Four metal legs under the table top's corners."""
    half = (TABLE_TOP - 0.04) / 2
    return "\n".join(
        f'    <geom name="table_leg_{i}" type="box" size="0.025 0.025 {half:.4f}" '
        f'pos="{floats([sx * (half_x - 0.05), sy * (half_y - 0.05), half])}" material="gantry"/>'
        for i, (sx, sy) in enumerate([(1, 1), (1, -1), (-1, 1), (-1, -1)]))


def _keyframe(pendulum: Pendulum | None, qpos: np.ndarray, qvel: np.ndarray) -> str:
    """The ``init`` keyframe: the pendulum's angle first (its body comes first), then the
    props' free joints."""
    pos = ([pendulum.angle] if pendulum else []) + qpos.reshape(-1).tolist()
    vel = ([0.0] if pendulum else []) + qvel.reshape(-1).tolist()
    return (f'  <keyframe>\n    <key name="init" qpos="{floats(pos)}"\n'
            f'         qvel="{floats(vel)}"/>\n  </keyframe>')


def tossed_scene(seed: int = 0) -> GeneratedScene:
    """The MJCF text and textures of tossed scene ``seed``.

    Raises:
        RuntimeError: none of :data:`THROW_TRIES` throws passed :func:`throw_is_kept`.
    """
    rng = np.random.default_rng(seed)
    half_x, half_y = rng.uniform(*TABLE_HALF_X), rng.uniform(*TABLE_HALF_Y)
    count = int(rng.integers(PROP_COUNT[0], PROP_COUNT[1] + 1))
    kinds = ["sphere"] + [str(rng.choice(list(SIZE_RANGES))) for _ in range(count - 1)]
    props = [make_prop(rng, kind, f"{kind}_{i}", SIZE_RANGES[kind]) for i, kind in enumerate(kinds)]
    pendulum = _pendulum(rng, half_x)

    assets = {"table_wood.png": textures.wood_grain(rng, 512, 512)}
    asset_xml = [file_texture("table_wood")]
    for p in props:
        asset_xml += p.asset_xml
        assets.update(p.assets)
    sky_top = textures.random_colour(rng, (0.2, 0.5), (0.5, 0.8))
    ambient = rng.uniform(0.2, 0.3)
    bob_colour = textures.random_colour(rng)
    objects = [p.name for p in props] + (["pendulum_bob"] if pendulum else [])
    custom = custom_block(
        {"nerfbot_rig_target": [0.0, 0.0, TABLE_TOP + TARGET_HEIGHT],
         "nerfbot_rig_radius": [RIG_RADIUS], "nerfbot_rig_fovy": [RIG_FOVY],
         "nerfbot_rig_elevation": list(RIG_ELEVATION), "nerfbot_duration": [DURATION_S]},
        {"nerfbot_capture": "dynamic", "nerfbot_objects": " ".join(objects)})
    description = (f"{len(props)} props thrown onto a wooden table"
                   f"{' beside a swinging pendulum' if pendulum else ''}, seen from "
                   f"{RIG_RADIUS} m over\n  {DURATION_S} s of physics. Units are metres, z up; "
                   f"the table top is at z = {TABLE_TOP}. Textures are\n  the PNG files beside "
                   "this file.")
    lights = "\n".join(sun_lights(rng, (0.0, 0.0, TABLE_TOP), 3.0))
    # The bodies' own poses do not matter: the keyframe places and throws them.
    bodies = [pendulum.body()] if pendulum else []
    bodies += [f'    <body name="{p.name}" pos="0 0 {TABLE_TOP + 1.0}">\n'
               f'      <freejoint name="{p.name}"/>\n'
               f'      <geom name="{p.name}" class="object" {p.geom}/>\n'
               f'    </body>' for p in props]
    files = {name: encode_png(image) if isinstance(image, np.ndarray) else image
             for name, image in assets.items()}

    for _ in range(THROW_TRIES):
        qpos, qvel = _throws(rng, props)
        xml = _TEMPLATE.format(
            header=header("tossed", seed, "sims/zoo/tossed.py", description),
            custom=custom, top=TABLE_TOP, ambient=floats([ambient] * 3, 3),
            sky_top=floats(sky_top, 3), bob=floats(bob_colour, 3), assets="\n".join(asset_xml),
            lights=lights, table_size=floats([half_x, half_y, 0.02]), table_z=TABLE_TOP - 0.02,
            rim=_rim(half_x, half_y), legs=_legs(half_x, half_y),
            gantry=pendulum.geoms() if pendulum else "", bodies="\n".join(bodies),
            keyframe=_keyframe(pendulum, qpos, qvel))
        model = mujoco.MjModel.from_xml_string(xml, files)
        if throw_is_kept(model, [p.name for p in props]):
            return GeneratedScene(xml, assets)
    raise RuntimeError(f"tossed:{seed}: none of {THROW_TRIES} throws kept every prop on the "
                       "table and something moving to the end")


_TEMPLATE = """{header}
<mujoco model="tossed">
  <compiler angle="degree"/>
  <option timestep="0.002" integrator="implicitfast"/>
  <statistic extent="1.3" center="0 0 {top}"/>

  <visual>
    <global offwidth="1024" offheight="1024" fovy="30"/>
    <quality offsamples="8" shadowsize="4096"/>
    <headlight active="1" ambient="{ambient}" diffuse="0 0 0" specular="0 0 0"/>
    <map znear="0.02" zfar="40" haze="0.25" shadowclip="0.8"/>
    <rgba haze="0.78 0.84 0.92 1"/>
  </visual>

{custom}

  <default>
    <!-- Slightly bouncy contacts; a little rolling friction slows balls and cans down. -->
    <default class="object">
      <geom condim="6" friction="0.5 0.01 0.001" solref="0.01 0.4"/>
    </default>
  </default>

  <asset>
    <texture name="sky" type="skybox" builtin="gradient" rgb1="{sky_top}"
             rgb2="0.86 0.9 0.95" width="512" height="3072"/>
    <material name="table_wood" texture="table_wood" texrepeat="1 1" specular="0.2"
              shininess="0.3"/>
    <material name="gantry" rgba="0.3 0.3 0.34 1" specular="0.25" shininess="0.4"/>
    <material name="rod" rgba="0.75 0.75 0.7 1" specular="0.25" shininess="0.5"/>
    <material name="bob" rgba="{bob} 1" specular="0.25" shininess="0.5"/>
{assets}
  </asset>

  <worldbody>
{lights}

    <geom name="table_top" type="box" size="{table_size}" pos="0 0 {table_z}"
          material="table_wood" friction="0.5 0.01 0.001"/>
{rim}
{legs}
{gantry}

{bodies}
  </worldbody>

{keyframe}
</mujoco>
"""
