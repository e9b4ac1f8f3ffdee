"""Cameras for captures over time steps or joint configurations, and the MJCF declarations
that make a scene such a capture.

A scene says how it is captured in its MJCF ``<custom>`` block:

- ``<text name="nerfbot_capture" data="dynamic"/>`` (a physics rollout over time, see
  :mod:`sims.dynamic`) or ``data="articulated"`` (joint configurations, see
  :mod:`sims.articulated`); scenes without it are ``static`` (:mod:`sims.capture`).
- ``<numeric name="nerfbot_rig_azimuth" data="LO HI"/>``: the azimuths (degrees from world +x)
  cameras may take; default the full circle. E.g. a cabinet facing -y uses ``-170 -10``.
- ``nerfbot_rig_target`` / ``nerfbot_rig_radius`` / ``nerfbot_rig_fovy`` frame the cameras, as
  for static scenes (:func:`sims.rigs.scene_rig_defaults`).

Camera placements (c2w 4x4, OpenGL convention, world z up, no roll), per step (a time step or a
joint configuration):

- :func:`spiral_path`: one camera per step on a smooth path around the target (monocular, the
  camera moves between steps): azimuth sweeps ``turns`` revolutions (or back and forth across a
  restricted azimuth range) while elevation oscillates across the elevation band.
- :func:`fixed_ring`: the same K cameras at every step (a multi-camera rig): evenly spaced
  azimuths, elevations spread across the band.
- :func:`stratified_views`: K fresh cameras per step: evenly spaced azimuths rotated by a random
  offset per step, random elevations (uniform in sphere area); K = 1 is a random view per step,
  the "teleporting" monocular camera of the D-NeRF synthetic scenes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import mujoco
import numpy as np

from nerfbot.ops.cameras import look_at, spherical_eye
from sims.joints import body_name
from sims.manifest import content_bounds, custom_numeric, custom_text, rendered_geoms
from sims.rigs import parse_size, scene_rig_defaults
from sims.scene import load_capture_model, load_model, resolve_scene

CAPTURE_KINDS = ("static", "dynamic", "articulated")
#: Rigs of captures over time / configurations: one camera per step, or several.
SEQUENCE_RIGS = ("monocular", "multiview")
#: How the monocular camera of a dynamic capture moves.
CAMERA_PATHS = ("spiral", "random")
#: What a :class:`SequenceRig` takes of a scene's declared or derived rig defaults
#: (:func:`sims.rigs.scene_rig_defaults`).
_FRAMING_FIELDS = ("target", "radius", "fov_deg", "elevation_range")


def capture_kind(model: mujoco.MjModel) -> str:
    """"static", "dynamic" or "articulated": the model's ``nerfbot_capture`` declaration
    (static when undeclared). ValueError for an unknown declaration."""
    kind = custom_text(model, "nerfbot_capture") or "static"
    if kind not in CAPTURE_KINDS:
        raise ValueError(f"<custom> text nerfbot_capture must be one of {CAPTURE_KINDS}, "
                         f"got {kind!r}")
    return kind


def load_sequence_scene(scene: str | Path, kind: str):
    """(model, data, scene name) of a ``kind`` ("dynamic" or "articulated") scene, compiled with
    the capture camera; ValueError if the scene declares another kind."""
    model, data = load_capture_model(scene)
    actual = capture_kind(model)
    if actual != kind:
        raise ValueError(f"scene '{scene}' is {actual}, not {kind} (such a scene declares "
                         f"<custom><text name=\"nerfbot_capture\" data=\"{kind}\"/>)")
    return model, data, resolve_scene(scene).stem


def scene_capture_kind(scene: str | Path) -> str:
    """:func:`capture_kind` of a scene name or MJCF path."""
    return capture_kind(load_model(scene))


@dataclass
class SequenceRig:
    """Where the cameras of a capture over steps go, and what they see.

    Attributes:
        kind: "monocular" (one camera per step) or "multiview" (``views_per_step`` per step).
        views_per_step: cameras per step (1 for monocular).
        width, height: image size in pixels.
        fov_deg: vertical field of view, degrees.
        radius: camera distance from ``target``, metres.
        target: look-at point (x, y, z), world metres.
        elevation_range: (low, high) degrees above the target's horizontal plane.
        azimuth_range: (low, high) degrees from world +x; ``high - low >= 360`` is the full
            circle.
        camera_path: monocular dynamic captures: "spiral" (smooth path) or "random" (a random
            view per step, as in D-NeRF's synthetic scenes).
        turns: spiral: revolutions over the capture (or sweeps across a restricted azimuth
            range).
        seed: random seed of random / stratified placements.
    """

    kind: str = "monocular"
    views_per_step: int = 1
    width: int = 128
    height: int = 128
    fov_deg: float = 30.0
    radius: float = 3.2
    target: tuple[float, float, float] = (0.0, 0.0, 0.85)
    elevation_range: tuple[float, float] = (15.0, 70.0)
    azimuth_range: tuple[float, float] = (0.0, 360.0)
    camera_path: str = "spiral"
    turns: float = 2.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.kind not in SEQUENCE_RIGS:
            raise ValueError(f"rig must be one of {SEQUENCE_RIGS}, got '{self.kind}'")
        if self.kind == "monocular" and self.views_per_step != 1:
            raise ValueError(f"a monocular rig has one view per step, got {self.views_per_step}")
        if self.views_per_step < 1:
            raise ValueError(f"views per step must be positive, got {self.views_per_step}")
        if self.camera_path not in CAMERA_PATHS:
            raise ValueError(f"camera path must be one of {CAMERA_PATHS}, got "
                             f"'{self.camera_path}'")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"vertical fov must be in (0, 180) degrees, got {self.fov_deg}")
        if not self.radius > 0.0:
            raise ValueError(f"rig radius must be positive, got {self.radius}")
        lo, hi = self.elevation_range
        if not -90.0 <= lo <= hi <= 90.0:
            raise ValueError(f"elevation range must satisfy -90 <= lo <= hi <= 90, got {lo}, {hi}")
        a_lo, a_hi = self.azimuth_range
        if not a_lo < a_hi:
            raise ValueError(f"azimuth range must satisfy lo < hi, got {a_lo}, {a_hi}")
        self.target = tuple(float(v) for v in self.target)
        if len(self.target) != 3:
            raise ValueError(f"target must have 3 coordinates, got {self.target}")

    @property
    def full_circle(self) -> bool:
        return self.azimuth_range[1] - self.azimuth_range[0] >= 360.0

    def pose(self, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
        """c2w (4, 4) of a camera at (azimuth, elevation) on the rig's sphere, looking at the
        target."""
        return look_at(spherical_eye(self.target, self.radius, azimuth_deg, elevation_deg),
                       self.target)


def sequence_rig(scene: str | Path, kind: str = "monocular", views_per_step: int = 1,
                 size: int | Sequence[int] = 128, **overrides) -> SequenceRig:
    """A :class:`SequenceRig` framed for ``scene``: its declared (or bounds-derived) target,
    radius and fov and its declared azimuth range, with ``overrides`` (SequenceRig fields;
    None values are ignored)."""
    model = load_model(scene)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ids = sorted({int(g.objid) for g in rendered_geoms(model, data)})
    framing = scene_rig_defaults(model, content_bounds(model, data, ids) if ids else None, data)
    framing = {k: v for k, v in framing.items() if k in _FRAMING_FIELDS}
    azimuth = custom_numeric(model, "nerfbot_rig_azimuth")
    if azimuth is not None:
        if len(azimuth) != 2:
            raise ValueError(f"<custom> numeric nerfbot_rig_azimuth needs 2 values (LO HI "
                             f"degrees), got {azimuth}")
        framing["azimuth_range"] = tuple(azimuth)
    width, height = parse_size(size)
    framing.update(kind=kind, views_per_step=views_per_step, width=width, height=height)
    framing.update({k: v for k, v in overrides.items() if v is not None})
    return SequenceRig(**framing)


def _area_uniform_elevation(rng: np.random.Generator, rig: SequenceRig, n: int) -> np.ndarray:
    lo, hi = (math.radians(v) for v in rig.elevation_range)
    return np.degrees(np.arcsin(rng.uniform(math.sin(lo), math.sin(hi), n)))


def spiral_path(rig: SequenceRig, n_steps: int) -> list[np.ndarray]:
    """One c2w (4, 4) per step on a smooth path, step ``i`` at path parameter u = i / (n - 1).

    Azimuth: ``lo + 360 * turns * u`` on the full circle, else ``turns`` back-and-forth sweeps
    (cosine-eased) across the azimuth range. Elevation: from the band's low edge up and down
    ``1.5 * turns`` times (cosine), so the path does not retrace itself.
    """
    u = np.linspace(0.0, 1.0, n_steps) if n_steps > 1 else np.zeros(1)
    a_lo, a_hi = rig.azimuth_range
    if rig.full_circle:
        az = a_lo + 360.0 * rig.turns * u
    else:
        az = a_lo + (a_hi - a_lo) * (0.5 - 0.5 * np.cos(2.0 * math.pi * rig.turns * u))
    e_lo, e_hi = rig.elevation_range
    el = e_lo + (e_hi - e_lo) * (0.5 - 0.5 * np.cos(2.0 * math.pi * 1.5 * rig.turns * u))
    return [rig.pose(a, e) for a, e in zip(az, el)]


def fixed_ring(rig: SequenceRig) -> list[np.ndarray]:
    """The ``views_per_step`` c2w (4, 4) poses of a fixed multi-camera rig: evenly spaced
    azimuths across the azimuth range, elevations spread over the band (golden-ratio steps)."""
    k = rig.views_per_step
    a_lo, a_hi = rig.azimuth_range
    span = 360.0 if rig.full_circle else a_hi - a_lo
    e_lo, e_hi = rig.elevation_range
    poses = []
    for j in range(k):
        frac = (0.5 + j * 0.6180339887498949) % 1.0
        poses.append(rig.pose(a_lo + span * (j + 0.5) / k, e_lo + (e_hi - e_lo) * frac))
    return poses


def stratified_views(rig: SequenceRig, n_steps: int, stream: int = 0) -> list[list[np.ndarray]]:
    """``n_steps`` lists of ``views_per_step`` c2w (4, 4) poses, fresh at every step.

    Step ``s``'s azimuths are evenly spaced across the azimuth range and rotated by a random
    fraction of a spacing; elevations are random, uniform in sphere area. The random stream is
    ``numpy.random.default_rng([seed, stream])``: use different ``stream`` values for train and
    test steps so their views never coincide.
    """
    rng = np.random.default_rng([int(rig.seed), int(stream)])
    k = rig.views_per_step
    a_lo, a_hi = rig.azimuth_range
    span = 360.0 if rig.full_circle else a_hi - a_lo
    out = []
    for _ in range(n_steps):
        offset = rng.uniform(0.0, 1.0)
        elevations = _area_uniform_elevation(rng, rig, k)
        out.append([rig.pose(a_lo + span * (j + offset) / k, elevations[j]) for j in range(k)])
    return out


def union_bounds(model: mujoco.MjModel, data: mujoco.MjData, qpos_list) -> np.ndarray:
    """(2, 3) AABB of the rendered geoms over all states ``qpos_list`` (each (nq,)), metres.

    ``data`` is left in the last state (positions only: ``mj_kinematics``).
    """
    mujoco.mj_forward(model, data)
    ids = sorted({int(g.objid) for g in rendered_geoms(model, data)})
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for qpos in qpos_list:
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        box = content_bounds(model, data, ids)
        lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
    return np.stack([lo, hi])


def state_arrays(model: mujoco.MjModel, data: mujoco.MjData, qpos_list) -> dict[str, np.ndarray]:
    """World poses of every body in each state: ``body_names`` (nbody,), ``body_pos``
    (S, nbody, 3) metres, ``body_quat`` (S, nbody, 4) w-x-y-z, and ``qpos`` (S, nq)."""
    qpos = np.asarray(qpos_list, dtype=np.float64)
    pos = np.empty((len(qpos), model.nbody, 3))
    quat = np.empty((len(qpos), model.nbody, 4))
    for s, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        pos[s], quat[s] = data.xpos, data.xquat
    names = np.array([body_name(model, b) for b in range(model.nbody)])
    return {"qpos": qpos, "body_names": names, "body_pos": pos, "body_quat": quat}
