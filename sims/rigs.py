"""Camera rigs: where the capture cameras go, as lists of c2w poses (OpenGL convention, metres).

Three kinds, all described by one :class:`RigConfig`:

- ``hemisphere``: random views on the upper hemisphere around ``target`` (uniform over the sphere
  area between two elevations), seeded; optional random jitter of the look-at point.
- ``orbit``: a ring at one elevation with evenly spaced azimuths.
- ``explicit``: poses read from a JSON file (4x4 matrices or eye/target pairs).

Test views come from the same distribution as training views but never coincide with them:
``hemisphere`` draws them from an independent random stream, ``orbit`` shifts the ring by half a
training step, ``explicit`` takes the file's ``"test"`` list (or the entries after the training
ones). Build them with :func:`make_test_rig`.

Every camera keeps world z up (no roll). A scene may declare its default framing in MJCF
``<custom>`` numerics ``nerfbot_rig_target`` (3), ``nerfbot_rig_radius`` and ``nerfbot_rig_fovy``
(degrees); :func:`scene_rig_defaults` reads them, or derives a framing from the content bounds.
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
from sims.manifest import content_bounds, rendered_geoms
from sims.scene import load_model

RIG_KINDS = ("hemisphere", "orbit", "explicit")

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
        seed: random seed (hemisphere).
        split: "train" or "test"; selects the random stream (hemisphere) or the file's list
            (explicit).
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
        if self.kind != "explicit" and not self.radius > 0.0:
            raise ValueError(f"rig radius must be positive, got {self.radius}")
        lo, hi = self.elevation_range
        if not -90.0 <= lo <= hi <= 90.0:
            raise ValueError(f"elevation range must satisfy -90 <= lo <= hi <= 90, got {lo}, {hi}")
        if self.kind == "explicit" and self.poses_file is None:
            raise ValueError("the explicit rig needs a poses file")
        self.target = tuple(float(v) for v in self.target)
        if len(self.target) != 3:
            raise ValueError(f"target must have 3 coordinates, got {self.target}")

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


def hemisphere_poses(cfg: RigConfig) -> list[np.ndarray]:
    """``cfg.count`` random c2w (4, 4) poses, uniform over the sphere band of ``elevation_range``.

    The random stream is ``numpy.random.default_rng([seed, split_index])``, so train and test
    draws are independent and each is reproducible.
    """
    stream = {"train": 0, "test": 1, "val": 2}.get(cfg.split, 3)
    rng = np.random.default_rng([int(cfg.seed), stream])
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
    return explicit_poses(cfg)


def make_test_rig(train: RigConfig, count: int) -> RigConfig:
    """The rig of ``count`` test views matching ``train``: same distribution, disjoint draws.

    hemisphere: independent random stream; orbit: azimuths shifted by half a training step;
    explicit: the file's "test" list, or the flat list's entries after the training ones.
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


def scene_rig_defaults(model, bounds: Optional[np.ndarray] = None) -> dict:
    """Default ``target``, ``radius`` and ``fov_deg`` for a scene.

    Uses the model's ``<custom>`` numerics ``nerfbot_rig_target`` / ``nerfbot_rig_radius`` /
    ``nerfbot_rig_fovy`` where present. Otherwise: target = centre of ``bounds`` (2, 3), fov
    30 degrees, radius so the bounding sphere fits the vertical fov with 10 % margin.
    """
    found = {}
    for key, name in (("target", "nerfbot_rig_target"), ("radius", "nerfbot_rig_radius"),
                      ("fov_deg", "nerfbot_rig_fovy")):
        nid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, name)
        if nid >= 0:
            adr, size = int(model.numeric_adr[nid]), int(model.numeric_size[nid])
            vals = [float(v) for v in model.numeric_data[adr:adr + size]]
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
    return found


def default_rig(scene: str | Path, **overrides) -> RigConfig:
    """A rig framed for ``scene``: its declared or bounds-derived target/radius/fov + overrides.

    ``overrides`` are :class:`RigConfig` fields; ``None`` values are ignored.
    """
    model = load_model(scene)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ids = sorted({int(g.objid) for g in rendered_geoms(model, data)})
    defaults = scene_rig_defaults(model, content_bounds(model, data, ids) if ids else None)
    defaults.update({k: v for k, v in overrides.items() if v is not None})
    return RigConfig(**defaults)
