"""Articulated field: one radiance field per rigid part, placed by forward kinematics.

The scene manifest of an articulated capture lists its rigid parts (the bodies each chain of
joints moves, with their bounds at the rest configuration; :func:`sims.joints.rigid_parts`). Each
part gets its own Instant-NGP field in its *rest frame*; everything no joint moves is the static
part, a field over the whole scene bounds. At joint values q, a world sample x is moved into each
part's rest frame (x_k = T_k(q)^-1 x, directions rotated alike) and the parts composite as
a mixture of densities:

    sigma(x, q) = sum_k sigma_k(x_k),    rgb(x, d, q) = sum_k sigma_k rgb_k(x_k, d_k) / sigma

So a configuration never seen in training (a door opened further than in any training image)
renders from the same part fields, just placed differently. A part's field is evaluated only at
samples inside its (padded) rest bounds.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
import torch

from nerfbot.data.conditioning import Conditioning
from nerfbot.fields.base import Field
from nerfbot.fields.ngp import NGPField, NGPFieldConfig
from nerfbot.ops.kinematics import JointChain


@dataclass
class ArticulatedFieldConfig:
    part_log2_hashmap_size: int = 15
    """log2 hash-table rows per level of each moving part's field (parts are small)."""
    part_padding: float = 0.02
    """Metres added on every side of a part's rest bounds."""
    occupancy_configs: int = 2
    """Random joint configurations (over the full joint limits) per occupancy-grid update; the
    grid keeps the maximum, so it covers every configuration, not only the training ones."""


def parts_from_conditioning(conditioning: Conditioning) -> list[dict]:
    """The moving parts: [{"joints": [...], "bounds": [[min], [max]]}] from the manifest's
    ``part_bounds``. Raises ValueError naming what is missing."""
    if conditioning.kind != "joints":
        raise ValueError("the articulated field needs a joint-conditioned capture (frames with "
                         "'joints', e.g. `nerfbot capture --scene articulated`)")
    missing = [n for n in conditioning.names if n not in conditioning.joint_info]
    if missing:
        raise ValueError(f"the scene manifest has no 'joint_info' for joint(s) {missing}: the "
                         "articulated field needs each joint's axis, anchor and rest value")
    if not conditioning.part_bounds:
        raise ValueError("the scene manifest has no 'part_bounds' (which bodies each joint moves "
                         "and where they are at rest); capture with sims to get it")
    return [p for p in conditioning.part_bounds
            if all(j in conditioning.names for j in p["joints"])]


class ArticulatedField(Field):
    """Static part + one field per moving rigid part (see the module docstring).

    ``cond`` (N, C): joint values in radians / metres in the conditioning's order; None means
    every joint at rest (``qpos0``).
    """

    def __init__(self, aabb, conditioning: Conditioning, config: NGPFieldConfig | None = None,
                 aconfig: ArticulatedFieldConfig | None = None, seed: int = 0):
        super().__init__()
        self.conditioning = conditioning
        self.aconfig = ac = aconfig or ArticulatedFieldConfig()
        cfg = config or NGPFieldConfig()
        parts = parts_from_conditioning(conditioning)
        col = {n: i for i, n in enumerate(conditioning.names)}
        self.static = NGPField(aabb, cfg, seed=seed)
        self.part_names = [",".join(p["joints"]) for p in parts]
        self.chains = torch.nn.ModuleList(
            JointChain([conditioning.joint_info[j] for j in p["joints"]], [col[j] for j in p["joints"]])
            for p in parts)
        part_cfg = replace(cfg, log2_hashmap_size=min(cfg.log2_hashmap_size, ac.part_log2_hashmap_size))
        self.parts = torch.nn.ModuleList()
        for k, p in enumerate(parts):
            box = np.asarray(p["bounds"], dtype=np.float64)
            box = np.stack([box[0] - ac.part_padding, box[1] + ac.part_padding]).astype(np.float32)
            self.parts.append(NGPField(box, part_cfg, seed=seed + 1 + k))
        q_rest = [float(conditioning.joint_info[n].get("qpos0", 0.0)) for n in conditioning.names]
        self.register_buffer("q_rest", torch.tensor(q_rest, dtype=torch.float32))

    # -- helpers -------------------------------------------------------------------------------
    def _q(self, cond: Optional[torch.Tensor], n: int, like: torch.Tensor) -> torch.Tensor:
        if cond is None:
            return self.q_rest.to(like).expand(n, -1)
        return cond.to(like.dtype)

    def _fields(self):
        yield self.static, None
        yield from zip(self.parts, self.chains)

    def part_points(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None) -> list[torch.Tensor]:
        """World points x (N, 3) in each part's rest frame: [static (N, 3), part 1, ...]."""
        q = self._q(cond, x.shape[0], x)
        return [x if chain is None else chain.to_rest(x, q) for _, chain in self._fields()]

    # -- Field interface -------------------------------------------------------------------------
    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        """-> sigma (N,), features (N, K * (1 + 1 + G)): per part its density, an 'inside' flag
        and its geometry features (what :meth:`color` needs to mix the parts)."""
        n = x.shape[0]
        q = self._q(cond, n, x)
        sigmas, feats = [], []
        for field, chain in self._fields():
            xk = x if chain is None else chain.to_rest(x, q)
            inside = field.normalize.inside(xk)
            idx = torch.nonzero(inside).squeeze(-1)
            sk = x.new_zeros(n)
            fk = x.new_zeros(n, field.config.geo_feat_dim)
            if idx.numel():
                s, f = field.density(xk[idx])
                sk = sk.index_put((idx,), s)
                fk = fk.index_put((idx,), f)
            sigmas.append(sk)
            feats += [sk[:, None], inside[:, None].to(x.dtype), fk]
        return torch.stack(sigmas).sum(0), torch.cat(feats, -1)

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        n = d.shape[0]
        q = self._q(cond, n, d)
        num = d.new_zeros(n, 3)
        den = d.new_zeros(n)
        col = 0
        for field, chain in self._fields():
            g = field.config.geo_feat_dim
            sk, inside, fk = feat[:, col], feat[:, col + 1] > 0.5, feat[:, col + 2:col + 2 + g]
            col += 2 + g
            idx = torch.nonzero(inside).squeeze(-1)
            if not idx.numel():
                continue
            dk = d[idx] if chain is None else chain.dirs_to_rest(d[idx], q[idx])
            rgb = field.color(fk[idx], dk)
            num = num.index_add(0, idx, sk[idx, None] * rgb)
            den = den.index_add(0, idx, sk[idx])
        return num / den.clamp_min(1e-12)[:, None]

    def before_step(self, step: int, progress: float) -> dict:
        out: dict = {}
        for field, _ in self._fields():
            out.update(field.before_step(step, progress))
        return out

    def occupancy_density(self, x, generator=None):
        best = None
        for _ in range(self.aconfig.occupancy_configs):
            q = self.conditioning.sample(x.shape[0], generator, x.device)
            s = self.density(x, q)[0]
            best = s if best is None else torch.maximum(best, s)
        return best

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        for field, _ in self._fields():
            field.init_mean_color(rgb)

    def param_groups(self) -> list[dict]:
        return [g for field, _ in self._fields() for g in field.param_groups()]
