"""What a frame is conditioned on besides its camera: nothing (static), time, or joint positions.

A dataset's :class:`Conditioning` is decided once, from its frames and scene manifest, stored in
the model spec of every checkpoint, and handed to the method's builder. Fields receive the
per-ray condition vector ``cond`` (R, C) in *scene units* (time in [0, 1]; joints in radians /
metres, in :attr:`Conditioning.names` order) and use :meth:`Conditioning.normalize` when they want
[0, 1] inputs. Static fields ignore ``cond``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Optional

import numpy as np
import torch

from nerfbot.data.errors import DatasetError
from nerfbot.data.spec import joint_range
from nerfbot.data.tracks import estimate_tracks

KINDS = ("static", "time", "joints")


@dataclass(frozen=True)
class Conditioning:
    """The conditioning of a scene.

    Attributes:
        kind: "static", "time" or "joints".
        names: the C condition names: () static, ("time",), or joint names.
        ranges: C (lo, hi) pairs: (0, 1) for time; a joint's limits (radians / metres) from the
            manifest, else the span of the values seen in the frames.
        joint_info: joint name -> kinematics from the manifest (:func:`sims.joints.joint_info`:
            type, axis, anchor, qpos0, range, bodies, ...); {} when unknown.
        part_bounds: list of rigid parts moved by joints, each {"joints": [outer .. inner],
            "bodies": [...], "bounds": [[min], [max]]} in the rest (``qpos0``) world frame; []
            when the manifest has none.
        object_tracks: the moving rigid bodies of a time-conditioned capture and where its
            training frames' segmentation puts them at each training time step
            (:func:`nerfbot.data.tracks.estimate_tracks`); [] when it has none.
    """

    kind: str = "static"
    names: tuple = ()
    ranges: tuple = ()
    joint_info: dict = field(default_factory=dict)
    part_bounds: list = field(default_factory=list)
    object_tracks: list = field(default_factory=list)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"conditioning kind must be one of {KINDS}, got {self.kind!r}")
        if len(self.names) != len(self.ranges):
            raise ValueError("conditioning: one (lo, hi) range per name is needed")

    @property
    def dim(self) -> int:
        """C, the length of a condition vector (0 for static scenes)."""
        return len(self.names)

    @property
    def is_static(self) -> bool:
        return self.kind == "static"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["names"], d["ranges"] = list(self.names), [list(r) for r in self.ranges]
        return d

    @classmethod
    def from_dict(cls, d: Optional[dict]) -> "Conditioning":
        if not d:
            return cls()
        return cls(kind=d["kind"], names=tuple(d["names"]),
                   ranges=tuple(tuple(float(v) for v in r) for r in d["ranges"]),
                   joint_info=dict(d.get("joint_info") or {}),
                   part_bounds=list(d.get("part_bounds") or []),
                   object_tracks=list(d.get("object_tracks") or []))

    def _lo_span(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        r = torch.as_tensor(self.ranges, dtype=like.dtype, device=like.device).reshape(-1, 2)
        return r[:, 0], (r[:, 1] - r[:, 0]).clamp_min(1e-9)

    def normalize(self, cond: torch.Tensor) -> torch.Tensor:
        """(N, C) scene units -> (N, C), 0 at each range's low end and 1 at its high end (values
        beyond the range, e.g. extrapolated joint positions, fall outside [0, 1])."""
        lo, span = self._lo_span(cond)
        return (cond - lo) / span

    def sample(self, n: int, generator: Optional[torch.Generator] = None,
               device="cpu") -> torch.Tensor:
        """(n, C) conditions drawn uniformly over the ranges (for occupancy updates)."""
        u = torch.rand(n, self.dim, generator=generator).to(device)
        lo, span = self._lo_span(u)
        return lo + u * span

    def vector(self, time: Optional[float] = None, joints: Optional[dict] = None) -> Optional[list]:
        """The condition vector (C,) of a frame given its ``time`` or ``joints`` {name: value};
        None for a static scene. Joints not given stay at the middle of their range."""
        if self.kind == "static":
            return None
        if self.kind == "time":
            if time is None:
                raise ValueError("this scene is time-conditioned: give a time in [0, 1]")
            return [float(time)]
        joints = dict(joints or {})
        unknown = set(joints) - set(self.names)
        if unknown:
            raise ValueError(f"unknown joint(s) {sorted(unknown)}; this scene's joints: "
                             f"{', '.join(self.names)}")
        return [float(joints.get(n, 0.5 * (lo + hi))) for n, (lo, hi) in zip(self.names, self.ranges)]


def _source(dataset) -> str:
    """The dataset's (first) transforms file, for messages; its folder when unknown."""
    files = (getattr(dataset, "extras", None) or {}).get("json_files") or []
    return str(files[0]) if files else str(dataset.root)


def dataset_conditioning(dataset, tracks: bool = True) -> Conditioning:
    """The conditioning of a :class:`~nerfbot.data.dataset.Dataset`: time when its frames carry
    ``time``, joints when they carry ``joints``, static otherwise. ``tracks``: estimate the
    moving bodies' tracks of a time-conditioned capture (what a model is built from); callers
    that only read the frames' condition vectors skip it.

    Raises:
        DatasetError: naming the transforms file and manifest field, when a joint range is not
            ``[lo, hi]`` with finite lo <= hi, or ``moving_joints`` names a joint the frames do
            not give.
    """
    manifest = dataset.manifest or {}
    if dataset.times is not None:
        return Conditioning("time", ("time",), ((0.0, 1.0),),
                            object_tracks=estimate_tracks(dataset) if tracks else [])
    if dataset.joints is None:
        return Conditioning()
    where = f"{_source(dataset)}: scene"
    info = manifest.get("joint_info") or {}
    carried = dataset.joints[0]
    names = list(manifest.get("moving_joints") or []) or sorted(carried)
    missing = [n for n in names if n not in carried]
    if missing:
        raise DatasetError(f"{where}.moving_joints: {', '.join(map(repr, missing))} not given by "
                           f"the frames (their joints: {', '.join(sorted(carried))})")
    ranges = []
    for n in names:
        limits = joint_range((info.get(n) or {}).get("range"), f"{where}.joint_info.{n}.range")
        if limits is None:
            values = [float(j[n]) for j in dataset.joints]
            limits = (min(values), max(values))
        ranges.append(limits)
    return Conditioning("joints", tuple(names), tuple(ranges),
                        {n: info[n] for n in names if n in info},
                        list(manifest.get("part_bounds") or []))


def frame_conditions(dataset, conditioning: Conditioning) -> Optional[np.ndarray]:
    """(N, C) float32 condition vectors of every frame, or None for a static conditioning."""
    if conditioning.is_static:
        return None
    if conditioning.kind == "time":
        return np.asarray(dataset.times, dtype=np.float32).reshape(-1, 1)
    missing = [(i, n) for i, j in enumerate(dataset.joints) for n in conditioning.names if n not in j]
    if missing:
        i, n = missing[0]
        raise DatasetError(f"{_source(dataset)}: frame {dataset.file_paths[i]}: joints: no "
                           f"'{n}' (every frame must give every moving joint)")
    return np.array([[float(j[n]) for n in conditioning.names] for j in dataset.joints],
                    dtype=np.float32)
