"""What a ray sees when it leaves the scene bounds: a fixed colour or a learned sky."""

from __future__ import annotations

import itertools

import numpy as np
import torch
from torch import nn

from nerfbot.fields.base import mlp
from nerfbot.kernels import octahedral as _oct
from nerfbot.ops.encodings import SHEncoding
from nerfbot.ops.octahedral import direction_grid

#: Vertices per side of the octahedral map a baked renderer reads its background from: about
#: 0.7 degrees apart, finer than the learned sky's SH(4) varies (the test bounds the error).
BAKED_BACKGROUND_RESOLUTION = 256


class FixedBackground(nn.Module):
    """A constant colour: (R, 3) directions -> (R, 3) rgb."""

    def __init__(self, rgb=(1.0, 1.0, 1.0)):
        super().__init__()
        self.register_buffer("rgb", torch.as_tensor(rgb, dtype=torch.float32).reshape(3))

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        return self.rgb.expand(directions.shape[0], 3)

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """A fixed colour stays fixed."""


class LearnedBackground(nn.Module):
    """Colour as a smooth function of ray direction (sky, distant walls): SH(d) -> MLP -> rgb."""

    def __init__(self, sh_degree: int = 4, hidden: int = 32):
        super().__init__()
        self.encoding = SHEncoding(sh_degree)
        self.net = mlp(self.encoding.out_dim, hidden, 1, 3)

    def forward(self, directions: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(self.encoding(directions)))

    def init_mean_color(self, rgb: torch.Tensor) -> None:
        """Start as the uniform colour ``rgb`` (3,) in (0, 1)."""
        with torch.no_grad():
            self.net[-1].bias.copy_(torch.logit(rgb.clamp(0.02, 0.98)).to(self.net[-1].bias))


def make_background(spec) -> nn.Module:
    """``"learned"`` -> :class:`LearnedBackground`; an RGB triple -> :class:`FixedBackground`."""
    if isinstance(spec, str):
        named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
        if spec == "learned":
            return LearnedBackground()
        if spec in named:
            return FixedBackground(named[spec])
        raise ValueError(f"background must be 'learned', 'white', 'black' or an RGB triple, got {spec!r}")
    return FixedBackground(tuple(float(c) for c in spec))


class BakedBackground:
    """A background module tabulated on an octahedral map of directions and read back with
    bilinear interpolation in one numba pass: what the baked renderers (FastNeRF cache,
    PlenOctree, KiloNeRF) use, as they bake everything else a ray reads. The table is rebuilt
    when the module's parameters or buffers change (fine-tuning), so it never goes stale.

    Not an ``nn.Module``: it holds no state of its own and is not saved; the module is.
    """

    def __init__(self, module: nn.Module, resolution: int = BAKED_BACKGROUND_RESOLUTION):
        if resolution < 2:
            raise ValueError(f"background map resolution must be >= 2, got {resolution}")
        self.module = module
        self.resolution = int(resolution)
        self._key = None
        self._table = np.zeros((2, 2, 3), np.float32)

    def _state_key(self) -> tuple:
        return tuple((t.data_ptr(), t._version) for t in
                     itertools.chain(self.module.parameters(), self.module.buffers()))

    def table(self) -> np.ndarray:
        """(ND, ND, 3) float32: the module's colour at the map's vertex directions."""
        key = self._state_key()
        if key != self._key:
            grid = direction_grid(self.resolution).reshape(-1, 3)
            with torch.no_grad():
                rgb = self.module(grid).float().expand(grid.shape[0], 3)
            self._table = rgb.reshape(self.resolution, self.resolution, 3).contiguous().numpy()
            self._key = key
        return self._table

    def __call__(self, directions: torch.Tensor) -> np.ndarray:
        """(R, 3) unit directions (CPU) -> (R, 3) float32 numpy colours."""
        d = directions.detach().float().contiguous().numpy()
        out = np.empty((d.shape[0], 3), np.float32)
        _oct.lookup(d, self.table(), out)
        return out
