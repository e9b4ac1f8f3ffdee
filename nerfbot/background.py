"""What a ray sees when it leaves the scene bounds: a fixed colour or a learned sky."""

from __future__ import annotations

import torch
from torch import nn

from nerfbot.encodings import SHEncoding
from nerfbot.fields.base import mlp


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
