"""A dynamic scene as a K-Planes scene plus its moving rigid bodies, each a small field of its
own carried along a track of poses.

    sigma(x, t) = sigma_scene(x, t) + sum_k sigma_k(y_k),   y_k = R_k(t)^T (x - c_k(t)) / s_k
    colour      = the scene's colour MLP of the density-weighted mean of the parts' geometry
                  features, and the view

The scene is the ``kplanes`` field (static ngp field + space-time planes: shadows and whatever
moves without a track), or with ``moving_scene=false`` a static ngp field. Each body k is a
dense multi-level feature grid over the cube [-1, 1]^3 of half-edge s_k around its centre, a
density MLP, and a pose per training time step: a centre c_k and an axis-angle rotation (or,
with ``rotation_increments``, a turn from the step before), both trained. Between steps (a
held-out time) the pose is interpolated, so the body moves there instead of cross-fading; a
point of a body's material goes with the body (:meth:`RigidField.move_points`, scene flow).

Why: space-time planes hold a small object separately at every time step, so each of its
pixels is trained by the few rays of that step (BENCHMARKS.md, section 4, "How many rays the
moving objects get"). A part pools the body's appearance over all steps and views.

The tracks start where the training frames' segmentation puts each body
(:func:`nerfbot.data.tracks.estimate_tracks`, carried in the run's conditioning); rotations
start at zero. Poses then train with the photometric loss through the grids' trilinear
interpolation (which has a gradient with respect to position).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.base import Field, mlp, trunc_exp
from nerfbot.fields.kplanes import KPlanesField, KPlanesFieldConfig
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.ops.lie import so3_exp, so3_log

#: Points per chunk of an occupancy update's nearest-step search over a part's track.
_OCCUPANCY_CHUNK = 1 << 15


@dataclass
class RigidFieldConfig:
    part_levels: int = 3
    """Resolution levels of each part's feature grid (each coarser level halves the cells)."""
    part_resolution: int = 64
    """Cells per axis of a part's finest level, over its cube of half-edge ``extent``."""
    part_features: int = 4
    """Features per level and cell."""
    part_hidden: int = 64
    """Width of a part's density MLP (one hidden layer)."""
    part_initial_transmittance: float = 0.5
    """Transmittance of a ray crossing a part's cube along its diagonal at initialisation."""
    pose_lr_scale: float = 0.1
    """Learning rate of the poses relative to the method's (metres and radians per step, about,
    under Adam); 0 freezes the tracks."""
    rotation_increments: bool = False
    """Train each step's rotation as a turn from the step before it (the first step's as it is),
    so the images of every later step also train an earlier step's turn; False: one rotation
    per step, each trained by its own step's images."""
    rotation_lr_factor: float = 1.0
    """Learning rate of the rotations relative to the poses' (``pose_lr_scale``)."""
    time_curriculum: float = 0.0
    """Learn the scene forward in time: over this fraction of the budget the frames that train
    grow from the first time step's to all of them, and each step's rotation, when its frames
    join, starts from its body's last turn carried on (constant angular velocity from the two
    steps before), so a part sharp at earlier steps follows its body's turns; 0: every frame
    from the start."""
    curriculum_carry: float = 1.0
    """With ``time_curriculum``: the share of its body's last turn a joining step starts from
    (1: a constant angular velocity; 0: the step before's rotation)."""
    moving_scene: bool = True
    """The scene around the parts is ``kplanes`` (static field + space-time planes: shadows,
    bodies without a track, what a part's pose misses); False: a static ngp field, so
    everything that moves must be a part."""

    def __post_init__(self):
        for name in ("part_levels", "part_resolution", "part_features", "part_hidden"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not 0.0 < self.part_initial_transmittance < 1.0:
            raise ValueError(f"part_initial_transmittance must be in (0, 1), got "
                             f"{self.part_initial_transmittance}")
        if not 0.0 <= self.pose_lr_scale < math.inf:
            raise ValueError(f"pose_lr_scale must be >= 0 and finite, got {self.pose_lr_scale}")
        if not 0.0 <= self.rotation_lr_factor < math.inf:
            raise ValueError(f"rotation_lr_factor must be >= 0 and finite, got "
                             f"{self.rotation_lr_factor}")
        if not 0.0 <= self.curriculum_carry <= 1.0:
            raise ValueError(f"curriculum_carry must be in [0, 1], got {self.curriculum_carry}")
        if not 0.0 <= self.time_curriculum <= 1.0:
            raise ValueError(f"time_curriculum must be in [0, 1], got {self.time_curriculum}")


class RigidPart(nn.Module):
    """One rigid body: a feature grid and density MLP in its own frame, and its track.

    ``track`` is one of :func:`nerfbot.data.tracks.estimate_tracks`' dicts (``name``,
    ``times``, ``centres``, ``extent``), optionally with ``rotations`` (J, 3), axis-angle, to
    start the rotations from instead of zero.

    Attributes:
        times: (J,) buffer, the training time steps in [0, 1], sorted.
        centres: (J, 3) parameter, the body's centre at each step, metres.
        rotations: (J, 3) parameter, axis-angle of the body's rotation from its frame to the
            world at each step, radians; with ``rotation_increments`` the first step's, then
            each step's turn from the step before, in that earlier step's body frame.
        extent: half-edge of the part's cube, metres.
    """

    def __init__(self, track: dict, cfg: RigidFieldConfig, geo_feat_dim: int, seed: int):
        super().__init__()
        self.name = str(track["name"])
        self.extent = float(track["extent"])
        self.register_buffer("times", torch.tensor(track["times"], dtype=torch.float32))
        self.centres = nn.Parameter(torch.tensor(track["centres"], dtype=torch.float32))
        rotations = track.get("rotations")
        rotations = (torch.zeros_like(self.centres) if rotations is None
                     else torch.tensor(rotations, dtype=torch.float32))
        self.increments = cfg.rotation_increments
        if self.increments and len(rotations) > 1:
            steps = so3_exp(rotations)
            rotations = torch.cat([rotations[:1],
                                   so3_log(steps[:-1].transpose(1, 2) @ steps[1:])])
        self.rotations = nn.Parameter(rotations)
        gen = torch.Generator().manual_seed(seed)
        self.grids = nn.ParameterList([
            nn.Parameter(1e-4 * (2 * torch.rand(1, cfg.part_features, r, r, r, generator=gen) - 1))
            for r in (max(2, cfg.part_resolution >> (cfg.part_levels - 1 - lvl))
                      for lvl in range(cfg.part_levels))])
        self.mlp = mlp(cfg.part_features * cfg.part_levels, cfg.part_hidden, 1, 1 + geo_feat_dim)
        diagonal = 2.0 * math.sqrt(3.0) * self.extent
        self.density_bias = math.log(-math.log(cfg.part_initial_transmittance) / diagonal)

    def step_rotations(self) -> torch.Tensor:
        """(J, 3, 3) the body -> world rotation at each training step."""
        rot = so3_exp(self.rotations)
        if not self.increments:
            return rot
        shift = 1
        while shift < len(rot):  # prefix products R_0 R_1 ... R_j, in log2(J) batched rounds
            rot = torch.cat([rot[:shift], rot[:-shift] @ rot[shift:]])
            shift *= 2
        return rot

    @torch.no_grad()
    def carry_on_rotation(self, j: int, share: float = 1.0) -> None:
        """Start step ``j``'s rotation (j >= 1) from step j - 1's turned on by ``share`` of the
        turn between steps j - 2 and j - 1 (``R_j = exp(share log(R_{j-1} R_{j-2}^T))
        R_{j-1}``; 1: a constant angular velocity in the world, 0: step j - 1's rotation);
        with increments, step j's turn is ``share`` of step j - 1's."""
        if j < 1:
            return
        if self.increments:
            self.rotations[j] = share * self.rotations[j - 1] if j >= 2 else 0.0
            return
        if j < 2:
            self.rotations[j] = self.rotations[j - 1]
            return
        r = so3_exp(self.rotations[j - 2:j])
        turn = so3_exp(share * so3_log((r[1] @ r[0].T)[None]))[0]
        self.rotations[j] = so3_log((turn @ r[1])[None])[0]

    def pose(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotations (N, 3, 3) body -> world and centres (N, 3) at times t (N,) between the two
        neighbouring steps: the centre linearly, the rotation along the shortest turn from one
        step's to the next (``R_lo exp(w log(R_lo^T R_hi))``); the end steps' poses beyond
        them."""
        times = self.times.to(t.dtype)
        if times.numel() == 1:
            n = t.shape[0]
            return (self.step_rotations().expand(n, 3, 3),
                    self.centres.expand(n, 3))
        # the samples of a ray, and every ray of a rendered image, share one time
        t, which = torch.unique(t, return_inverse=True)
        hi = torch.searchsorted(times, t.contiguous()).clamp(1, times.numel() - 1)
        lo = hi - 1
        w = ((t - times[lo]) / (times[hi] - times[lo])).clamp(0.0, 1.0)[:, None]
        centre = self.centres[lo] + w * (self.centres[hi] - self.centres[lo])
        step_rot = self.step_rotations()  # (J, 3, 3)
        turn = so3_log(step_rot[:-1].transpose(1, 2) @ step_rot[1:])  # (J - 1, 3)
        rot = step_rot[lo] @ so3_exp(w * turn[lo])
        return rot[which], centre[which]

    def local(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """World points x (N, 3) at times t (N,) -> (N, 3) in the part's cube ([-1, 1]^3 holds
        the body)."""
        rot, centre = self.pose(t)
        return torch.einsum("nji,nj->ni", rot, x - centre) / self.extent

    def forward(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """y (M, 3) inside the part's cube -> sigma (M,) 1/m, geometry features (M, C)."""
        coords = y.reshape(1, 1, 1, -1, 3)
        feats = [F.grid_sample(g, coords, mode="bilinear", padding_mode="border",
                               align_corners=True).reshape(g.shape[1], -1).T
                 for g in self.grids]
        h = self.mlp(torch.cat(feats, -1))
        return trunc_exp(h[:, 0] + self.density_bias), h[:, 1:]


class RigidField(Field):
    """``kplanes`` scene + one :class:`RigidPart` per tracked body; ``cond`` (N, 1) time in
    [0, 1] (None: t = 0)."""

    def __init__(self, aabb, conditioning: Conditioning, config: NGPFieldConfig | None = None,
                 kconfig: KPlanesFieldConfig | None = None,
                 rconfig: RigidFieldConfig | None = None, seed: int = 0):
        super().__init__()
        if not conditioning.object_tracks:
            raise ValueError(
                "rigid needs the tracks of the moving bodies, which come from a dynamic "
                "capture's segmentation and its manifest's moving_bodies (`nerfbot capture "
                "--scene dynamic` writes both); this capture gives none")
        self.rconfig = rc = rconfig or RigidFieldConfig()
        if rc.moving_scene:
            self.scene = KPlanesField(aabb, conditioning, config, kconfig, seed=seed)
            self.ngp_config = self.scene.static.config
        else:
            self.scene = NGPField(aabb, config, seed=seed)
            self.ngp_config = self.scene.config
        geo = self.ngp_config.geo_feat_dim
        self.parts = nn.ModuleList(RigidPart(track, rc, geo, seed + 10 + k)
                                   for k, track in enumerate(conditioning.object_tracks))
        if rc.time_curriculum > 0:
            times = torch.cat([part.times for part in self.parts])
            self.time_span = (float(times.min()), float(times.max()))
            # how many of each part's steps have joined training (a checkpoint keeps it)
            self.register_buffer("steps_joined", torch.zeros(len(self.parts), dtype=torch.long))

    def _time(self, cond: Optional[torch.Tensor], x: torch.Tensor) -> torch.Tensor:
        return x.new_zeros(x.shape[0]) if cond is None else cond[:, 0].to(x.dtype)

    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        sigma, geo = self.scene.density(x, cond)
        t = self._time(cond, x)
        total, weighted = sigma, sigma[:, None] * geo
        for part in self.parts:
            y = part.local(x, t)
            idx = (y.abs() < 1.0).all(-1).nonzero().squeeze(1)
            if idx.numel() == 0:
                continue
            s, g = part(y[idx])
            total = total.index_add(0, idx, s)
            weighted = weighted.index_add(0, idx, s[:, None] * g)
        feat = torch.where(total[:, None] > 0, weighted / total.clamp_min(1e-30)[:, None], geo)
        return total, feat

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        return self.scene.color(feat, d, cond)

    def occupancy_density(self, x, generator=None):
        """The scene's, plus each part's density at the step whose centre is nearest to the point
        (a point the body ever covers is covered best then)."""
        sigma = self.scene.occupancy_density(x, generator)
        for part in self.parts:
            reach = math.sqrt(3.0) * part.extent
            centres = part.centres.detach()
            lo, hi = centres.min(0).values - reach, centres.max(0).values + reach
            near = ((x >= lo) & (x <= hi)).all(-1).nonzero().squeeze(1)
            for chunk in near.split(_OCCUPANCY_CHUNK):
                p = x[chunk]
                step = torch.cdist(p, centres).argmin(1)
                y = part.local(p, part.times[step].to(p.dtype))
                inside = (y.abs() < 1.0).all(-1)
                if inside.any():
                    sigma = sigma.index_add(0, chunk[inside], part(y[inside])[0])
        return sigma

    def training_time_limit(self, progress: float) -> Optional[float]:
        """With ``time_curriculum`` c > 0: the first training step's time, moving linearly to
        the last one's over the first c of the budget; then None (every frame)."""
        c = self.rconfig.time_curriculum
        if c <= 0 or progress >= c:
            return None
        first, last = self.time_span
        return first + (last - first) * progress / c

    def before_step(self, step: int, progress: float) -> dict:
        if self.rconfig.time_curriculum > 0:
            limit = self.training_time_limit(progress)
            for k, part in enumerate(self.parts):
                joined = len(part.times) if limit is None else \
                    int((part.times <= limit).sum())
                for j in range(int(self.steps_joined[k]), joined):
                    part.carry_on_rotation(j, self.rconfig.curriculum_carry)
                self.steps_joined[k] = max(joined, int(self.steps_joined[k]))
        return self.scene.before_step(step, progress)

    def prunable(self) -> bool:
        return self.scene.prunable()

    def regularizer(self) -> Optional[torch.Tensor]:
        return self.scene.regularizer()

    def color_head(self):
        return self.scene.color_head()

    def param_groups(self) -> list[dict]:
        grids = [g for part in self.parts for g in part.grids]
        mlps = [p for part in self.parts for p in part.mlp.parameters()]
        rc = self.rconfig
        return self.scene.param_groups() + [
            {"params": grids, "lr_scale": 1.0},
            {"params": mlps, "lr_scale": self.ngp_config.mlp_lr_scale},
            {"params": [part.centres for part in self.parts], "lr_scale": rc.pose_lr_scale},
            {"params": [part.rotations for part in self.parts],
             "lr_scale": rc.pose_lr_scale * rc.rotation_lr_factor}]

    @torch.no_grad()
    def move_points(self, x0: torch.Tensor, t0: float, t1: float
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Where world points x0 (N, 3, metres) of time t0 are at time t1 (both in [0, 1]): a
        point goes with the part whose density there at t0 is the largest and at least the
        scene's (it is that body's material), ``x1 = R1 R0^T (x0 - c0) + c1`` with the part's
        poses at the two times; every other point stays where it is (the scene's space-time
        planes hold what they move as density at each time, not as motion). Returns x1 (N, 3)
        and the residual (N,), zero: the motion is exact, and t1 -> t0 undoes it."""
        x0 = x0.reshape(-1, 3)
        tt0 = x0.new_full((len(x0),), float(t0))
        best = self.scene.density(x0, tt0[:, None])[0]
        owner = torch.full((len(x0),), -1, dtype=torch.long, device=x0.device)
        for k, part in enumerate(self.parts):
            y = part.local(x0, tt0)
            inside = (y.abs() < 1.0).all(-1)
            sigma = torch.zeros_like(best)
            if inside.any():
                sigma[inside] = part(y[inside])[0]
            mine = inside & (sigma > 0) & (sigma >= best)
            owner[mine], best = k, torch.where(mine, sigma, best)
        x1 = x0.clone()
        for k, part in enumerate(self.parts):
            idx = (owner == k).nonzero().squeeze(1)
            if idx.numel() == 0:
                continue
            r0, c0 = part.pose(x0.new_full((1,), float(t0)))
            r1, c1 = part.pose(x0.new_full((1,), float(t1)))
            x1[idx] = (x0[idx] - c0) @ r0[0] @ r1[0].T + c1
        return x1, x0.new_zeros(len(x0))

    def part_centres(self, t: torch.Tensor) -> dict[str, torch.Tensor]:
        """Body name -> (N, 3) its centre at times t (N,), metres (where the field puts it)."""
        with torch.no_grad():
            return {part.name: part.pose(t)[1] for part in self.parts}
