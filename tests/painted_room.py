"""An analytic stand-in for a trained field, for the pose estimators' tests."""

from __future__ import annotations

from types import SimpleNamespace

import torch

from nerfbot.ops.cameras import Cameras


class PaintedRoom(torch.nn.Module):
    """An analytic stand-in for a trained field: the inside of a 4 x 3 x 2.5 m box whose walls,
    floor and ceiling are painted with smooth stripes of a few wavelengths; a ray's colour is
    the paint where it leaves the box, differentiable w.r.t. the ray; its depth is that exit
    point's, its opacity one."""

    lo = torch.tensor([-2.0, -1.5, 0.0])
    hi = torch.tensor([2.0, 1.5, 2.5])

    def __init__(self):
        super().__init__()
        self.register_buffer("aabb", torch.stack([self.lo, self.hi]))

    def render_rays_differentiable(self, rays):
        o, d = rays.origins, rays.directions
        wall = torch.where(d > 0, self.hi, self.lo)
        t = ((wall - o) / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)).amin(-1)
        p = o + d * t[:, None]
        x, y, z = p.unbind(-1)
        rgb = torch.stack([0.5 + 0.25 * torch.sin(3 * x + 2 * z) + 0.2 * torch.sin(7 * y),
                           0.5 + 0.25 * torch.sin(4 * y - 3 * z) + 0.2 * torch.cos(9 * x),
                           0.5 + 0.3 * torch.sin(2.5 * (x + y) + 5 * z)], -1)
        return SimpleNamespace(rgb=rgb, z_depth=t * rays.z_per_t, opacity=torch.ones_like(t))


def painted_room_view(model, c2w, size=64):
    cams = Cameras.pinhole(c2w, 70.0, size, size)
    with torch.no_grad():
        rgb = model.render_rays_differentiable(cams.rays(0)).rgb
    intr = tuple(float(getattr(cams, k)[0]) for k in ("fx", "fy", "cx", "cy"))
    return rgb.reshape(size, size, 3).clamp(0, 1).numpy(), intr
