"""Camera rigs: where the capture cameras go, as lists of c2w poses (OpenGL convention, metres).

Four kinds, all described by one :class:`RigConfig`:

- ``hemisphere``: random views on the upper hemisphere around ``target`` (uniform over the sphere
  area between two elevations), seeded; optional random jitter of the look-at point.
- ``orbit``: a ring at one elevation with evenly spaced azimuths.
- ``inside``: cameras standing inside a scene (a room) looking around: positions uniform over
  the free part of a floor ``region`` (at least ``clearance`` from its edges and from the
  ``keep_out`` footprints), heights uniform in ``height_range``, random yaw, small random pitch
  in ``pitch_range``; seeded.
- ``explicit``: poses read from a JSON file (4x4 matrices or eye/target pairs).

Test views come from the same distribution as training views but never coincide with them:
``hemisphere`` and ``inside`` draw them from an independent random stream, ``orbit`` shifts the
ring by half a training step, ``explicit`` takes the file's ``"test"`` list (or the entries
after the training ones). Build them with :func:`make_test_rig`.

Every camera keeps world z up (no roll). A scene may declare its default rig in its MJCF
``<custom>`` block; :func:`scene_rig_defaults` reads it, or derives a framing from the content
bounds:

- numerics ``nerfbot_rig_target`` (3), ``nerfbot_rig_radius`` (metres), ``nerfbot_rig_fovy``
  (degrees) and ``nerfbot_rig_elevation`` (LO HI degrees, the hemisphere's band);
- text ``nerfbot_rig_kind``: the default kind (``hemisphere`` when undeclared);
- for ``inside``: numerics ``nerfbot_rig_region`` (xmin ymin xmax ymax, metres; default the
  content bounds), ``nerfbot_rig_heights`` (LO HI metres), ``nerfbot_rig_pitch`` (LO HI
  degrees) and ``nerfbot_rig_clearance`` (metres); the ``keep_out`` footprints are the x-y
  extents of the geoms the scene declares as obstacles (``nerfbot_obstacles``, see
  :func:`sims.manifest.declared_obstacles`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional, Sequence

import mujoco
import numpy as np

from nerfbot.ops.cameras import check_pose, look_at, spherical_eye
from sims.manifest import (content_bounds, custom_numeric, custom_text, declared_obstacles,
                           rendered_geoms)
from sims.scene import load_model

RIG_KINDS = ("hemisphere", "orbit", "inside", "explicit")
#: Random draws per camera of the ``inside`` rig before it gives up (the free floor is too
#: small or missing).
INSIDE_TRIES = 10000

# Defaults of the built-in tabletop scene (also written in its MJCF <custom> block).
TABLETOP_TARGET = (0.0, 0.0, 0.75)
TABLETOP_RADIUS = 4.0
TABLETOP_FOVY = 30.0


@dataclass
class RigConfig:
    """Where the cameras of one split go, and what they see.

    Attributes:
        kind: "hemisphere", "orbit" or "explicit".
        count: number of views (``explicit``: 0 = every available pose of the split).
        width, height: image size in pixels.
        fov_deg: vertical field of view, degrees (MuJoCo's ``fovy``; pixels are square).
        radius: camera distance from the look-at target, metres.
        target: look-at point (x, y, z), world metres.
        elevation_range: (low, high) degrees above the target's horizontal plane (hemisphere).
        elevation: degrees, the ring's elevation (orbit).
        azimuth_offset_deg: azimuth of the first orbit view, degrees from world +x.
        target_jitter: half-width (metres) of a uniform box around ``target`` from which each
            hemisphere view draws its own look-at point; 0 = always look at ``target``.
        region: inside: (xmin, ymin, xmax, ymax), metres, the floor area cameras stand on.
        height_range: inside: (low, high) camera heights, metres (world z).
        pitch_range: inside: (low, high) degrees above the horizontal the cameras look.
        clearance: inside: metres every camera keeps from the region's edges and from the
            ``keep_out`` footprints.
        keep_out: inside: footprints (xmin, ymin, xmax, ymax), metres, no camera stands over.
        seed: random seed (hemisphere, inside).
        split: "train" or "test"; selects the random stream (hemisphere, inside) or the file's
            list (explicit).
        poses_file: JSON file of the explicit rig.
        skip: explicit rig, flat-list files: number of entries before this split's first pose.
    """

    kind: str = "hemisphere"
    count: int = 60
    width: int = 128
    height: int = 128
    fov_deg: float = TABLETOP_FOVY
    radius: float = TABLETOP_RADIUS
    target: tuple[float, float, float] = TABLETOP_TARGET
    elevation_range: tuple[float, float] = (15.0, 70.0)
    elevation: float = 30.0
    azimuth_offset_deg: float = 0.0
    target_jitter: float = 0.0
    region: Optional[tuple[float, float, float, float]] = None
    height_range: tuple[float, float] = (0.4, 1.6)
    pitch_range: tuple[float, float] = (-20.0, 10.0)
    clearance: float = 0.3
    keep_out: tuple[tuple[float, float, float, float], ...] = ()
    seed: int = 0
    split: str = "train"
    poses_file: Optional[Path] = None
    skip: int = 0

    def __post_init__(self) -> None:
        if self.kind not in RIG_KINDS:
            raise ValueError(f"rig kind must be one of {RIG_KINDS}, got '{self.kind}'")
        if self.count < 0 or (self.count == 0 and self.kind != "explicit"):
            raise ValueError(f"rig count must be positive, got {self.count}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if not 0.0 < self.fov_deg < 180.0:
            raise ValueError(f"vertical fov must be in (0, 180) degrees, got {self.fov_deg}")
        if self.kind not in ("explicit", "inside") and not self.radius > 0.0:
            raise ValueError(f"rig radius must be positive, got {self.radius}")
        lo, hi = self.elevation_range
        if not -90.0 <= lo <= hi <= 90.0:
            raise ValueError(f"elevation range must satisfy -90 <= lo <= hi <= 90, got {lo}, {hi}")
        if self.kind == "explicit" and self.poses_file is None:
            raise ValueError("the explicit rig needs a poses file")
        self.target = tuple(float(v) for v in self.target)
        if len(self.target) != 3:
            raise ValueError(f"target must have 3 coordinates, got {self.target}")
        if self.kind == "inside":
            self._check_inside()

    def _check_inside(self) -> None:
        if self.region is None:
            raise ValueError("the inside rig needs a floor region (xmin, ymin, xmax, ymax)")
        self.region = tuple(float(v) for v in self.region)
        if len(self.region) != 4 or not (self.region[0] < self.region[2]
                                         and self.region[1] < self.region[3]):
            raise ValueError(f"inside rig region must be (xmin, ymin, xmax, ymax) with "
                             f"xmin < xmax and ymin < ymax, got {self.region}")
        lo, hi = self.height_range
        if not lo <= hi:
            raise ValueError(f"inside rig heights must satisfy low <= high, got {lo}, {hi}")
        lo, hi = self.pitch_range
        if not -90.0 < lo <= hi < 90.0:
            raise ValueError(f"inside rig pitch must satisfy -90 < low <= high < 90 degrees, "
                             f"got {lo}, {hi}")
        if not self.clearance >= 0.0:
            raise ValueError(f"inside rig clearance must be >= 0, got {self.clearance}")
        self.keep_out = tuple(tuple(float(v) for v in box) for box in self.keep_out)
        if any(len(box) != 4 for box in self.keep_out):
            raise ValueError("inside rig keep_out boxes must be (xmin, ymin, xmax, ymax)")

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height


def parse_size(size: int | Sequence[int]) -> tuple[int, int]:
    """(width, height) from a square size ``n`` or a pair ``(w, h)``."""
    if isinstance(size, (int, np.integer)):
        return int(size), int(size)
    vals = [int(v) for v in size]
    if len(vals) == 1:
        return vals[0], vals[0]
    if len(vals) == 2:
        return vals[0], vals[1]
    raise ValueError(f"size must be N or (W, H), got {size}")


def _split_rng(cfg: RigConfig) -> np.random.Generator:
    """``numpy.random.default_rng([seed, split_index])``: train and test draws are independent
    and each is reproducible."""
    stream = {"train": 0, "test": 1, "val": 2}.get(cfg.split, 3)
    return np.random.default_rng([int(cfg.seed), stream])


def hemisphere_poses(cfg: RigConfig) -> list[np.ndarray]:
    """``cfg.count`` random c2w (4, 4) poses, uniform over the sphere band of ``elevation_range``
    (random stream: :func:`_split_rng`)."""
    rng = _split_rng(cfg)
    lo, hi = (math.radians(v) for v in cfg.elevation_range)
    sin_el = rng.uniform(math.sin(lo), math.sin(hi), cfg.count)  # uniform in area
    az = rng.uniform(0.0, 360.0, cfg.count)
    jitter = rng.uniform(-1.0, 1.0, (cfg.count, 3)) * cfg.target_jitter
    poses = []
    for i in range(cfg.count):
        target = np.asarray(cfg.target) + jitter[i]
        eye = spherical_eye(cfg.target, cfg.radius, az[i], math.degrees(math.asin(sin_el[i])))
        poses.append(look_at(eye, target))
    return poses


def orbit_poses(cfg: RigConfig) -> list[np.ndarray]:
    """``cfg.count`` c2w (4, 4) poses on a ring at ``cfg.elevation``, evenly spaced azimuths."""
    step = 360.0 / cfg.count
    return [look_at(spherical_eye(cfg.target, cfg.radius, cfg.azimuth_offset_deg + i * step,
                                  cfg.elevation), cfg.target)
            for i in range(cfg.count)]


def distance_to_box(box: Sequence[float], x: float, y: float) -> float:
    """Distance (metres) from (x, y) to the box (xmin, ymin, xmax, ymax); 0 inside it."""
    dx = max(box[0] - x, 0.0, x - box[2])
    dy = max(box[1] - y, 0.0, y - box[3])
    return math.hypot(dx, dy)


def inside_poses(cfg: RigConfig) -> list[np.ndarray]:
    """``cfg.count`` c2w (4, 4) poses of cameras standing in ``cfg.region``: (x, y) uniform over
    the region shrunk by ``clearance`` and farther than ``clearance`` from every ``keep_out``
    box (rejection sampling), height uniform in ``height_range``, yaw uniform, pitch uniform in
    ``pitch_range`` (random stream: :func:`_split_rng`).

    Raises:
        ValueError: no free floor found for a camera within :data:`INSIDE_TRIES` draws.
    """
    rng = _split_rng(cfg)
    c = cfg.clearance
    xmin, ymin, xmax, ymax = cfg.region
    xmin, ymin, xmax, ymax = xmin + c, ymin + c, xmax - c, ymax - c
    if not (xmin < xmax and ymin < ymax):
        raise ValueError(f"inside rig: the region {cfg.region} leaves no floor {c:g} m from "
                         "its edges")
    poses = []
    for i in range(cfg.count):
        for _ in range(INSIDE_TRIES):
            x, y = float(rng.uniform(xmin, xmax)), float(rng.uniform(ymin, ymax))
            if all(distance_to_box(box, x, y) >= c for box in cfg.keep_out):
                break
        else:
            raise ValueError(f"inside rig: no free floor for camera {i} in {INSIDE_TRIES} draws "
                             f"(region {cfg.region}, {len(cfg.keep_out)} keep-out boxes, "
                             f"clearance {c:g} m)")
        z = float(rng.uniform(*cfg.height_range))
        yaw = math.radians(float(rng.uniform(0.0, 360.0)))
        pitch = math.radians(float(rng.uniform(*cfg.pitch_range)))
        eye = np.array([x, y, z])
        ahead = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw),
                          math.sin(pitch)])
        poses.append(look_at(eye, eye + ahead))
    return poses


def _pose_from_entry(entry, where: str) -> np.ndarray:
    """One explicit-rig entry -> c2w (4, 4): a 4x4/3x4 matrix, or {eye, target[, up]}."""
    if isinstance(entry, dict):
        if "transform_matrix" in entry:
            return check_pose(entry["transform_matrix"], where)
        if "eye" in entry and "target" in entry:
            try:
                pose = look_at(entry["eye"], entry["target"], entry.get("up", (0.0, 0.0, 1.0)))
            except (ValueError, TypeError) as err:
                raise ValueError(f"{where}: {err}") from err
            return check_pose(pose, where)
        raise ValueError(f"{where}: expected a 4x4 matrix, 'transform_matrix', or 'eye' and "
                         f"'target', got keys {sorted(entry)}")
    try:
        matrix = np.asarray(entry, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: not a numeric matrix: {err}") from err
    return check_pose(matrix, where)


def read_pose_file(path: Path) -> dict[str, list[np.ndarray]] | list[np.ndarray]:
    """Poses of an explicit-rig JSON file, validated.

    Accepted layouts: a list of entries; ``{"poses": [...]}``; ``{"frames": [...]}`` (e.g. a
    nerfstudio ``transforms.json``, its ``transform_matrix`` used); or per split
    ``{"train": [...], "test": [...]}``. An entry is a 4x4 (or 3x4) c2w matrix, an object with
    ``transform_matrix``, or ``{"eye": [x, y, z], "target": [x, y, z], "up": [0, 0, 1]}``.

    Returns a dict split -> poses for per-split files, else a flat list.

    Raises:
        FileNotFoundError, ValueError (naming the file and the entry).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"explicit rig: pose file {path} does not exist")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: not valid JSON: {err}") from err

    def read_list(entries, key: str) -> list[np.ndarray]:
        if not isinstance(entries, list):
            raise ValueError(f"{path}: '{key}' must be a list of poses")
        return [_pose_from_entry(e, f"{path}: {key}[{i}]") for i, e in enumerate(entries)]

    if isinstance(doc, list):
        return read_list(doc, "poses")
    if isinstance(doc, dict):
        for key in ("poses", "frames"):
            if key in doc:
                return read_list(doc[key], key)
        splits = {k: read_list(v, k) for k, v in doc.items() if k in ("train", "val", "test")}
        if splits:
            return splits
    raise ValueError(f"{path}: expected a list of poses or an object with 'poses', 'frames' or "
                     "'train'/'test' lists")


def explicit_poses(cfg: RigConfig) -> list[np.ndarray]:
    """Poses of ``cfg.split`` from ``cfg.poses_file`` (see :func:`read_pose_file`).

    Per-split files give their ``cfg.split`` list; a flat list gives entries
    ``[skip, skip + count)``. ``count == 0`` takes all remaining entries.

    Raises:
        ValueError: fewer poses than requested, naming the file.
    """
    poses = read_pose_file(Path(cfg.poses_file))
    if isinstance(poses, dict):
        available = poses.get(cfg.split, [])
    else:
        available = poses[cfg.skip:]
    if cfg.count == 0:
        return list(available)
    if len(available) < cfg.count:
        raise ValueError(f"{cfg.poses_file}: {cfg.count} '{cfg.split}' poses requested, only "
                         f"{len(available)} available")
    return list(available[:cfg.count])


def rig_poses(cfg: RigConfig) -> list[np.ndarray]:
    """The c2w (4, 4) float64 poses of a rig, OpenGL convention."""
    if cfg.kind == "hemisphere":
        return hemisphere_poses(cfg)
    if cfg.kind == "orbit":
        return orbit_poses(cfg)
    if cfg.kind == "inside":
        return inside_poses(cfg)
    return explicit_poses(cfg)


def make_test_rig(train: RigConfig, count: int) -> RigConfig:
    """The rig of ``count`` test views matching ``train``: same distribution, disjoint draws.

    hemisphere, inside: independent random stream; orbit: azimuths shifted by half a training
    step; explicit: the file's "test" list, or the flat list's entries after the training ones.
    """
    offset = train.azimuth_offset_deg
    if train.kind == "orbit":
        offset += 0.5 * 360.0 / train.count
    skip = train.skip
    if train.kind == "explicit":
        used = train.count
        if used == 0:  # the training split took every pose of a flat list
            poses = read_pose_file(Path(train.poses_file))
            used = 0 if isinstance(poses, dict) else max(len(poses) - train.skip, 0)
        skip += used
    return replace(train, count=count, split="test", azimuth_offset_deg=offset, skip=skip)


def scene_rig_defaults(model, bounds: Optional[np.ndarray] = None,
                       data: Optional[mujoco.MjData] = None) -> dict:
    """Default :class:`RigConfig` fields for a scene: ``target``, ``radius`` and ``fov_deg``,
    plus ``elevation_range``, ``kind`` and the ``inside`` fields where the scene declares them.

    Uses the model's ``<custom>`` declarations (see the module docstring) where present.
    Otherwise: target = centre of ``bounds`` (2, 3), fov 30 degrees, radius so the bounding
    sphere fits the vertical fov with 10 % margin. A scene whose default kind is ``inside``
    also gets ``region``, ``height_range``, ``pitch_range``, ``clearance`` and ``keep_out``
    (:func:`inside_defaults`; ``data``, from ``mj_forward``, places its obstacles, and is made
    when None).

    Raises:
        ValueError: a malformed declaration, naming it.
    """
    found = {}
    for key, name in (("target", "nerfbot_rig_target"), ("radius", "nerfbot_rig_radius"),
                      ("fov_deg", "nerfbot_rig_fovy")):
        vals = custom_numeric(model, name)
        if vals is not None:
            found[key] = tuple(vals) if key == "target" else vals[0]
    fov = found.get("fov_deg", TABLETOP_FOVY)
    if bounds is not None and ("target" not in found or "radius" not in found):
        lo, hi = np.asarray(bounds, dtype=np.float64)
        centre, half_diag = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
        found.setdefault("target", tuple(float(v) for v in centre))
        found.setdefault("radius", 1.1 * max(half_diag, 1e-3) / math.sin(math.radians(fov) / 2))
    found.setdefault("target", TABLETOP_TARGET)
    found.setdefault("radius", TABLETOP_RADIUS)
    found["fov_deg"] = fov
    elevation = _declared_pair(model, "nerfbot_rig_elevation")
    if elevation is not None:
        found["elevation_range"] = elevation
    kind = custom_text(model, "nerfbot_rig_kind")
    if kind is not None:
        if kind not in RIG_KINDS or kind == "explicit":
            raise ValueError(f"<custom> text nerfbot_rig_kind must be one of "
                             f"{', '.join(k for k in RIG_KINDS if k != 'explicit')}, got {kind!r}")
        found["kind"] = kind
        if kind == "inside":
            found.update(inside_defaults(model, bounds, data))
    return found


def _declared_pair(model, name: str) -> Optional[tuple[float, float]]:
    """The two values of ``<custom><numeric name=NAME>`` (None when undeclared)."""
    vals = custom_numeric(model, name)
    if vals is None:
        return None
    if len(vals) != 2:
        raise ValueError(f"<custom> numeric {name} needs 2 values (LO HI), got {vals}")
    return vals[0], vals[1]


def inside_defaults(model, bounds: Optional[np.ndarray] = None,
                    data: Optional[mujoco.MjData] = None) -> dict:
    """The ``inside`` rig's fields for a scene: ``region`` (``nerfbot_rig_region``, else the x-y
    extent of ``bounds``), ``height_range`` / ``pitch_range`` / ``clearance`` where declared,
    and ``keep_out``: the x-y extents of the declared obstacles (``data`` from ``mj_forward``;
    made when None)."""
    out = {}
    region = custom_numeric(model, "nerfbot_rig_region")
    if region is not None:
        if len(region) != 4:
            raise ValueError(f"<custom> numeric nerfbot_rig_region needs 4 values (xmin ymin "
                             f"xmax ymax), got {region}")
        out["region"] = tuple(region)
    elif bounds is not None:
        lo, hi = np.asarray(bounds, dtype=np.float64)
        out["region"] = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    for key, name in (("height_range", "nerfbot_rig_heights"),
                      ("pitch_range", "nerfbot_rig_pitch")):
        pair = _declared_pair(model, name)
        if pair is not None:
            out[key] = pair
    clearance = custom_numeric(model, "nerfbot_rig_clearance")
    if clearance is not None:
        out["clearance"] = clearance[0]
    if data is None:
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
    out["keep_out"] = tuple((float(b[0, 0]), float(b[0, 1]), float(b[1, 0]), float(b[1, 1]))
                            for b in declared_obstacles(model, data).values())
    return out


def default_rig(scene: str | Path, **overrides) -> RigConfig:
    """A rig framed for ``scene``: its declared (or bounds-derived) kind, target, radius, fov and
    the rest of :func:`scene_rig_defaults`, with ``overrides``.

    ``overrides`` are :class:`RigConfig` fields; ``None`` values are ignored. Asking for
    ``kind="inside"`` in a scene that does not declare it takes the region and keep-out boxes
    from the scene (:func:`inside_defaults`); other kinds ignore the inside fields.
    """
    model = load_model(scene)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ids = sorted({int(g.objid) for g in rendered_geoms(model, data)})
    bounds = content_bounds(model, data, ids) if ids else None
    defaults = scene_rig_defaults(model, bounds, data)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    kind = overrides.get("kind", defaults.get("kind", "hemisphere"))
    if kind == "inside" and "region" not in defaults:
        defaults.update(inside_defaults(model, bounds, data))
    defaults.update(overrides)
    return RigConfig(**defaults)
