"""The in-memory posed-image dataset every reader produces and every trainer consumes."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from nerfbot.data.errors import DatasetError
from nerfbot.ops.cameras import Cameras


@dataclass
class Dataset:
    """All frames of one capture, loaded and validated, with split lists.

    Images are kept as uint8 to bound memory; :meth:`image_float` converts one frame.
    Poses and intrinsics describe *undistorted* images (readers undistort on load).

    Attributes:
        root: folder the dataset was read from.
        format: "nerfstudio", "blender", "dnerf" or "colmap".
        file_paths: N image paths relative to ``root`` (as written in the JSON).
        images: N arrays (H_i, W_i, 3) uint8 RGB, already composited on ``background`` when the
            source had an alpha channel.
        alphas: N arrays (H_i, W_i) uint8 or None per frame (None when the source had no alpha).
        c2w: (N, 4, 4) float64 poses, OpenGL convention, metres.
        intrinsics: (N, 4) float64 fx, fy, cx, cy in pixels.
        sizes: (N, 2) int64 width, height.
        depths: N arrays (H_i, W_i) float32 z-depth in metres (NaN where unknown) or None.
        masks: N arrays (H_i, W_i) bool (False = invalid: masked out by ``mask_path`` or
            outside the distorted source image) or None (every pixel valid). Invalid pixels are
            never trained on nor scored.
        segmentations: N arrays (H_i, W_i) int32 MuJoCo geom ids (-1 = none) or None.
        times: (N,) float32 in [0, 1], or None for a static capture.
        joints: N dicts joint name -> position, or None.
        splits: split name ("train", "val", "test") -> sorted frame indices.
        aabb: (2, 3) float64 min / max corner of the scene content, metres; for an
            ``unbounded`` scene, the cube around the cameras (the inner cube of a contracted
            model).
        aabb_source: "manifest", "cameras" or "user".
        unbounded: the content reaches far beyond the cameras, and beyond ``aabb``
            (outdoors; :func:`nerfbot.data.bounds.choose_space`): model it with the scene
            contraction.
        manifest: the scene manifest dict written by ``sims``, or None.
        background: "learned" (function of ray direction), or an RGB triple in [0, 1] when the
            images were composited on a fixed colour.
        sensor_depths: N arrays (H_i, W_i) float32 z-depth of a simulated depth sensor (NaN = no
            return) or None per frame; [] when the reader had none to offer.
        keypoints: N arrays (K_i, 4) float32 of sparse depth (structure-from-motion points seen
            in the frame): u, v (pixels, centres at +0.5, undistorted), z-depth and its
            standard deviation (metres); None per frame without; [] when the reader had none.
    """

    root: Path
    format: str
    file_paths: list[str]
    images: list[np.ndarray]
    alphas: list[Optional[np.ndarray]]
    c2w: np.ndarray
    intrinsics: np.ndarray
    sizes: np.ndarray
    depths: list[Optional[np.ndarray]]
    masks: list[Optional[np.ndarray]]
    segmentations: list[Optional[np.ndarray]]
    times: Optional[np.ndarray]
    joints: Optional[list[dict]]
    splits: dict[str, list[int]]
    aabb: np.ndarray
    aabb_source: str
    manifest: Optional[dict] = None
    unbounded: bool = False
    background: object = "learned"
    extras: dict = field(default_factory=dict)
    sensor_depths: list = field(default_factory=list)
    keypoints: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)

    def indices(self, split: str) -> list[int]:
        """Frame indices of ``split`` (possibly empty); :class:`DatasetError` naming the
        available splits when the dataset has no such split."""
        if split not in self.splits:
            raise DatasetError(f"{self.root}: no '{split}' split (available: "
                               f"{', '.join(sorted(self.splits)) or 'none'})")
        return list(self.splits[split])

    def split_sizes(self) -> str:
        """The splits and their frame counts, for messages: "test 4, train 16"."""
        return ", ".join(f"{k} {len(v)}" for k, v in sorted(self.splits.items())) or "none"

    def valid_mask(self, i: int) -> Optional[np.ndarray]:
        """(H, W) bool, the pixels of frame ``i`` that may be trained on and scored; None when
        all of them may."""
        return self.masks[i] if i < len(self.masks) else None

    def cameras(self, indices: Optional[list[int]] = None) -> Cameras:
        """Cameras of the given frames (all frames by default)."""
        idx = np.arange(len(self)) if indices is None else np.asarray(indices, dtype=np.int64)
        return Cameras.from_numpy(self.c2w[idx], self.intrinsics[idx], self.sizes[idx])

    def image_float(self, i: int) -> np.ndarray:
        """Frame ``i`` as (H, W, 3) float32 in [0, 1]."""
        return self.images[i].astype(np.float32) / 255.0
