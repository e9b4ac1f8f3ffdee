"""MJCF building blocks shared by the zoo families: the generated-scene container, number
formatting, the ``<custom>`` declarations nerfbot reads, textures from files, and seeded lights.

Lights: captures are statically lit (the headlight keeps only its ambient term, see
:func:`sims.capture.set_lighting`), so every family brings its own lights; :func:`light_colour`
and :func:`light_direction` give them a seeded colour temperature and direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence, Union

import numpy as np

#: An asset file of a generated scene: a uint8 image ((H, W, 3) RGB or (H, W) grey, written as
#: PNG) or the file's bytes.
Asset = Union[np.ndarray, bytes]


@dataclass(frozen=True)
class GeneratedScene:
    """A generated scene: MJCF text and the asset files it names by relative path.

    Attributes:
        xml: the MJCF text; it refers to each asset by its bare file name (e.g.
            ``<texture file="floor_wood.png"/>``): the assets are written beside it.
        assets: {file name: :data:`Asset`}; names are plain file names (no folder).
    """

    xml: str
    assets: dict[str, Asset] = field(default_factory=dict)


def floats(values, digits: int = 6) -> str:
    """Numbers as MJCF attribute text: ``"0.1 0.25 3"`` (``digits`` significant digits)."""
    out = []
    for v in np.asarray(values, dtype=np.float64).reshape(-1):
        text = f"{v:.{digits}g}"
        out.append("0" if text == "-0" else text)
    return " ".join(out)


def custom_block(numerics: Mapping[str, Sequence[float]], texts: Mapping[str, str]) -> str:
    """The ``<custom>`` element: ``<numeric name=... data=.../>`` per entry of ``numerics``, then
    ``<text name=... data=.../>`` per entry of ``texts`` (indented for the top level)."""
    lines = ["  <custom>"]
    lines += [f'    <numeric name="{k}" data="{floats(v)}"/>' for k, v in numerics.items()]
    lines += [f'    <text name="{k}" data="{v}"/>' for k, v in texts.items()]
    lines.append("  </custom>")
    return "\n".join(lines)


def file_texture(name: str, kind: str = "2d") -> str:
    """A ``<texture>`` read from the asset ``NAME.png``: ``kind`` "2d" (planes, and the z-facing
    side of primitives) or "cube" (wrapped around a primitive; the image must be square)."""
    return f'    <texture name="{name}" type="{kind}" file="{name}.png"/>'


def light_colour(rng: np.random.Generator, warmth: tuple[float, float] = (-1.0, 1.0),
                 intensity: tuple[float, float] = (0.5, 0.7)) -> np.ndarray:
    """(3,) RGB of a light: a seeded colour temperature (warmth -1 = cool blue-white, 0 =
    white, 1 = warm tungsten) scaled by a seeded intensity."""
    w = float(rng.uniform(*warmth))
    cool, white, warm = np.array([0.8, 0.9, 1.0]), np.ones(3), np.array([1.0, 0.8, 0.6])
    tint = white + (warm - white) * w if w >= 0 else white + (cool - white) * -w
    return tint * float(rng.uniform(*intensity))


def light_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3,) unit direction a light shines along when it stands at ``azimuth_deg`` (from +x) and
    ``elevation_deg`` (above the horizon) as seen from the scene: towards the scene."""
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return -np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def light(name: str, pos, direction, diffuse, specular: float = 0.3, directional: bool = True,
          castshadow: bool = False, cutoff: float | None = None) -> str:
    """One ``<light>`` element of the world body (directional, or a spot light with
    ``cutoff`` degrees)."""
    extra = f' cutoff="{cutoff:g}" exponent="2" attenuation="1 0 0"' if cutoff else ""
    return (f'    <light name="{name}" pos="{floats(pos)}" dir="{floats(direction)}" '
            f'directional="{str(directional).lower()}" diffuse="{floats(diffuse, 3)}" '
            f'specular="{floats([specular] * 3, 3)}" castshadow="{str(castshadow).lower()}"'
            f'{extra}/>')


def sun_lights(rng: np.random.Generator, centre, distance: float,
               shadow: bool = True) -> list[str]:
    """A key light (seeded azimuth, 35-70 degrees up, casting shadows when ``shadow``) and two
    dimmer fill lights from other sides, all directional, seeded colours; placed ``distance``
    metres from ``centre`` (position matters only for the shadow map)."""
    key_az = float(rng.uniform(0.0, 360.0))
    specs = [("key", key_az, rng.uniform(35.0, 70.0), (0.55, 0.75), shadow),
             ("fill", key_az + rng.uniform(110.0, 160.0), rng.uniform(25.0, 60.0), (0.2, 0.35),
              False),
             ("rim", key_az - rng.uniform(110.0, 160.0), rng.uniform(40.0, 80.0), (0.15, 0.3),
              False)]
    out = []
    for name, az, el, power, casts in specs:
        d = light_direction(az, el)
        pos = np.asarray(centre, dtype=np.float64) - distance * d
        out.append(light(name, pos, d, light_colour(rng, intensity=power), castshadow=casts))
    return out


def header(family: str, seed: int, module: str, description: str) -> str:
    """The comment opening every generated MJCF file."""
    return (f'<!--\n  nerfbot generated scene "{family}", seed {seed} ({module}; regenerate, do '
            f'not edit).\n\n  {description}\n-->')
