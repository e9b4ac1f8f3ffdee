"""pixelNeRF (Yu et al. 2021): a radiance field conditioned on a few posed source images.

A small convolutional encoder, trained from scratch (no pretrained weights can be fetched),
turns each source image into a feature map. A world point is projected into every source view;
the feature under its projection (bilinear) is added into the first blocks of a residual MLP
whose input is the point's position in that view's camera frame; the views' hidden states are
averaged after those blocks, and the remaining blocks give density and a colour feature. One
trained field renders any scene of the family it was trained on from that scene's source views,
without per-scene training.

Differences from the paper, for 2 CPU cores: a 4-stage encoder of 160 channels instead of
ResNet34's 512, an MLP of 4 blocks of width 64 (pooled after 2) instead of 5 of 512 (pooled
after 3), and the view direction entering the colour branch after the views are pooled (in the
world frame) rather than each view's input. Source views are set with
:meth:`PixelNeRFField.set_sources` before rendering; their features are recomputed at every
training step (the encoder trains) and cached while the field is in eval mode.

The layers that add a feature into the MLP are linear, and so is bilinear sampling (with zero
padding): instead of sampling the C-channel feature maps and applying each layer at every
sample, the layers are applied once to the maps (a 1 x 1 convolution) and their
``pooled_after x width`` channels are sampled. The result is the same; a sample-view costs a
third of the multiply-adds at the default sizes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn

from nerfbot.fields.base import BoxNormalizer, Field
from nerfbot.ops.encodings import FrequencyEncoding


@dataclass
class PixelNeRFFieldConfig:
    encoder_channels: tuple = (16, 32, 48, 64)
    """Channels of the encoder's stem (stride 2) and of its stages (strides 4, 8, 16); every
    stage's output is upsampled to the stem's resolution and concatenated."""
    width: int = 64
    """Width of the residual MLP."""
    blocks: int = 4
    """Residual blocks of the MLP."""
    pooled_after: int = 2
    """Source features are added before each of the first this many blocks; the source views'
    hidden states are averaged after them."""
    pos_freqs: int = 6
    """L of the positional encoding of the point in each source camera's frame."""
    dir_freqs: int = 4
    """L of the positional encoding of the view direction (colour branch)."""
    position_scale: float = 1.0
    """Metres that map to 1 before the positional encoding (about the cameras' distance)."""


class ImageEncoder(nn.Module):
    """(V, 3, H, W) images in [0, 1] -> (V, C, ceil(H / 2), ceil(W / 2)) features: a stem at
    stride 2 and three stages at strides 4, 8 and 16, each upsampled bilinearly to the stem's
    resolution and concatenated (pixelNeRF's multi-scale features)."""

    def __init__(self, channels: tuple = (32, 48, 64, 96)):
        super().__init__()
        self.channels = tuple(int(c) for c in channels)
        stages, c_in = [], 3
        for c in self.channels:
            stages.append(nn.Sequential(
                nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.ReLU(inplace=True),
                nn.Conv2d(c, c, 3, padding=1), nn.ReLU(inplace=True)))
            c_in = c
        self.stages = nn.ModuleList(stages)

    @property
    def out_channels(self) -> int:
        return sum(self.channels)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        h = images * 2.0 - 1.0
        maps = []
        for stage in self.stages:
            h = stage(h)
            maps.append(h)
        size = maps[0].shape[-2:]
        return torch.cat([maps[0]] + [F.interpolate(m, size=size, mode="bilinear",
                                                    align_corners=False) for m in maps[1:]], 1)


class ResBlock(nn.Module):
    """h + W2 relu(W1 relu(h)), width preserved."""

    def __init__(self, width: int):
        super().__init__()
        self.fc0, self.fc1 = nn.Linear(width, width), nn.Linear(width, width)
        nn.init.zeros_(self.fc1.weight)  # starts as the identity, as in pixelNeRF
        nn.init.zeros_(self.fc1.bias)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return h + self.fc1(F.relu(self.fc0(F.relu(h))))


@dataclass
class SourceViews:
    """The views a pixelNeRF field is conditioned on.

    Attributes:
        images: (V, 3, H, W) float RGB in [0, 1].
        w2c: (V, 4, 4) world-to-camera, OpenGL camera frame (x right, y up, looking along -z).
        intrinsics: (V, 4) fx, fy, cx, cy in pixels of ``images``.
    """

    images: torch.Tensor
    w2c: torch.Tensor
    intrinsics: torch.Tensor

    @staticmethod
    def from_frames(images, c2w, intrinsics, device="cpu") -> "SourceViews":
        """Source views from V images (H, W, 3) (uint8, or float in [0, 1]) of one size, their
        (V, 4, 4) camera-to-world poses (OpenGL) and (V, 4) intrinsics."""
        imgs = [torch.as_tensor(i) for i in images]
        if not imgs:
            raise ValueError("pixelNeRF needs at least one source view")
        if len({tuple(i.shape) for i in imgs}) != 1 or imgs[0].dim() != 3 or imgs[0].shape[-1] < 3:
            raise ValueError("pixelNeRF's source images must share one (H, W, 3) size, got "
                             f"{sorted({tuple(i.shape) for i in imgs})}")
        stack = torch.stack([i[..., :3] for i in imgs]).to(device)
        stack = stack.float() / 255.0 if stack.dtype == torch.uint8 else stack.float()
        c2w = torch.as_tensor(c2w, dtype=torch.float64).reshape(-1, 4, 4)
        k = torch.as_tensor(intrinsics, dtype=torch.float32).reshape(-1, 4)
        if len(c2w) != len(imgs) or len(k) != len(imgs):
            raise ValueError(f"{len(imgs)} source images need as many poses and intrinsics, "
                             f"got {len(c2w)} and {len(k)}")
        return SourceViews(stack.permute(0, 3, 1, 2).contiguous(),
                           torch.linalg.inv(c2w).float().to(device), k.to(device))

    def __len__(self) -> int:
        return self.images.shape[0]


def project(points: torch.Tensor, sources: SourceViews) -> tuple[torch.Tensor, torch.Tensor,
                                                                   torch.Tensor]:
    """Project world points into every source view.

    Args:
        points: (N, 3) world points, metres.
    Returns:
        camera-frame points (V, N, 3) (OpenGL: in front of the camera when z < 0), image points
        (V, N, 2) in pixels (x right, y down; pixel centres at +0.5) and (V, N) bool: in front
        of the camera.
    """
    xh = torch.cat([points, torch.ones_like(points[:, :1])], -1)
    xc = torch.einsum("vij,nj->vni", sources.w2c[:, :3], xh)
    depth = -xc[..., 2]
    front = depth > 1e-6
    z = depth.clamp_min(1e-6)
    fx, fy, cx, cy = (sources.intrinsics[:, i, None] for i in range(4))
    u = fx * xc[..., 0] / z + cx
    v = cy - fy * xc[..., 1] / z
    return xc, torch.stack([u, v], -1), front


class PixelNeRFField(Field):
    """sigma, colour at world points from the features of :meth:`set_sources`' views.

    Points outside the scene bounds have zero density; a point behind a source camera or
    projecting outside its image reads a zero feature from it.
    """

    def __init__(self, aabb, config: PixelNeRFFieldConfig | None = None):
        super().__init__()
        self.config = cfg = config or PixelNeRFFieldConfig()
        if not 0 < cfg.pooled_after <= cfg.blocks:
            raise ValueError(f"pooled_after must be in 1..blocks ({cfg.blocks}), got "
                             f"{cfg.pooled_after}")
        self.normalize = BoxNormalizer(aabb)
        self.encoder = ImageEncoder(cfg.encoder_channels)
        self.pos_enc = FrequencyEncoding(3, cfg.pos_freqs)
        self.dir_enc = FrequencyEncoding(3, cfg.dir_freqs)
        self.lin_in = nn.Linear(self.pos_enc.out_dim, cfg.width)
        self.feature_in = nn.ModuleList(nn.Linear(self.encoder.out_channels, cfg.width)
                                        for _ in range(cfg.pooled_after))
        self.blocks = nn.ModuleList(ResBlock(cfg.width) for _ in range(cfg.blocks))
        self.sigma_head = nn.Linear(cfg.width, 1)
        self.branch = nn.Linear(cfg.width + self.dir_enc.out_dim, cfg.width // 2)
        self.rgb_head = nn.Linear(cfg.width // 2, 3)
        self.sources: Optional[SourceViews] = None
        self._features: Optional[torch.Tensor] = None
        self._terms: Optional[torch.Tensor] = None

    # -- conditioning --------------------------------------------------------------------------
    def set_sources(self, sources: SourceViews) -> None:
        """Condition the field on ``sources`` (replacing any earlier ones)."""
        self.sources, self._features, self._terms = sources, None, None

    def features(self) -> torch.Tensor:
        """(V, C, h, w) encoder features of the source views (cached in eval mode)."""
        if self.sources is None:
            raise RuntimeError("pixelNeRF: set the source views (set_sources) before rendering")
        if self._features is not None and not self.training:
            return self._features
        feats = self.encoder(self.sources.images)
        self._features = None if self.training else feats
        return feats

    def _feature_terms(self) -> torch.Tensor:
        """(V, pooled_after * width, h, w): every feature layer's weights applied to the
        feature maps (no bias), stacked (cached in eval mode, like the features)."""
        if self._terms is not None and not self.training:
            return self._terms
        weight = torch.cat([layer.weight for layer in self.feature_in])  # (K * W, C)
        terms = torch.einsum("oc,vchw->vohw", weight, self.features())
        self._terms = None if self.training else terms
        return terms

    def train(self, mode: bool = True):
        self._features = self._terms = None
        return super().train(mode)

    def sample_features(self, points: torch.Tensor, maps: Optional[torch.Tensor] = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) world points -> the source feature maps' values under their projections
        (V, N, C') and the points in each source camera's frame (V, N, 3). ``maps`` (V, C', h,
        w): what to sample (default the encoder's features, C' = C)."""
        feats = self.features() if maps is None else maps
        xc, uv, front = project(points, self.sources)
        h, w = self.sources.images.shape[-2:]
        grid = torch.stack([2.0 * uv[..., 0] / w - 1.0, 2.0 * uv[..., 1] / h - 1.0], -1)
        grid = torch.where(front[..., None], grid, torch.full_like(grid, -2.0))  # reads zero
        sampled = F.grid_sample(feats, grid[:, None], mode="bilinear", padding_mode="zeros",
                                align_corners=False)  # (V, C, 1, N)
        return sampled[:, :, 0].transpose(1, 2), xc

    # -- Field ---------------------------------------------------------------------------------
    def density(self, x: torch.Tensor, cond: Optional[torch.Tensor] = None):
        cfg = self.config
        terms, xc = self.sample_features(x, self._feature_terms())  # (V, N, K * W)
        h = self.lin_in(self.pos_enc(xc / cfg.position_scale))
        for k, block in enumerate(self.blocks):
            if k < cfg.pooled_after:
                h = h + terms[..., k * cfg.width:(k + 1) * cfg.width] + self.feature_in[k].bias
            if k == cfg.pooled_after:
                h = h.mean(0)
            h = block(h)
        if cfg.pooled_after == cfg.blocks:
            h = h.mean(0)
        sigma = F.softplus(self.sigma_head(F.relu(h))[:, 0] - 1.0)
        sigma = torch.where(self.normalize.inside(x), sigma, torch.zeros_like(sigma))
        return sigma, h

    def color_head(self):
        return self.rgb_head

    def color(self, feat: torch.Tensor, d: torch.Tensor, cond: Optional[torch.Tensor] = None):
        h = F.relu(self.branch(torch.cat([F.relu(feat), self.dir_enc(d)], -1)))
        return torch.sigmoid(self.rgb_head(h))
