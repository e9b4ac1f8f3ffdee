"""Where a capture over time changes: per-pixel weights for drawing training rays there
(DyNeRF's importance sampling).

A camera that films several time steps sees the same static pixels again and again; the pixels
where something moves are few (the moving objects of the built-in ``dynamic`` scene cover about
2 % of each image) and get few of a uniform batch's rays. :func:`temporal_weights` weighs pixel
``p`` of frame ``f`` by its squared deviation from the pixel's mean colour over the frames of
the same camera,

    w[f, p] = mean over RGB of (C_f(p) - mean_g C_g(p))^2,

so a pixel that never changes weighs 0, and the mean of ``w[:, p]`` over the frames is the
pixel's temporal variance: the frames in which the pixel differs most (the ones showing the
moving object) get most of its weight. :func:`importance_weights` assembles the weights of a
set of frames in the pixel order of :class:`~nerfbot.data.pixels.PixelBank`; frames whose
camera films a single time step (a moving monocular camera) weigh 0, as nothing tells what
changed there.
"""

from __future__ import annotations

import numpy as np
import torch

from nerfbot.data.dataset import Dataset

#: Cameras are the same when their poses (metres and rotation-matrix entries) and intrinsics
#: (pixels) round to the same multiples of this.
POSE_TOLERANCE = 1e-5

#: Colour values per chunk of :func:`temporal_weights` (frames x pixels x channels): about
#: 130 MB of float64, whatever the number of frames.
_CHUNK_VALUES = 1 << 24


def camera_groups(dataset: Dataset, indices: list[int]) -> list[list[int]]:
    """Positions in ``indices`` grouped by camera: frames with the same image size,
    intrinsics and pose (rounded to :data:`POSE_TOLERANCE`), in order of first appearance."""
    cams = dataset.cameras(indices)
    keys = np.concatenate([
        cams.c2w.reshape(len(indices), -1).double().numpy(),
        torch.stack([cams.fx, cams.fy, cams.cx, cams.cy], -1).double().numpy(),
        torch.stack([cams.width, cams.height], -1).double().numpy()], axis=1)
    groups: dict[bytes, list[int]] = {}
    for pos, key in enumerate(np.round(keys / POSE_TOLERANCE).astype(np.int64)):
        groups.setdefault(key.tobytes(), []).append(pos)
    return list(groups.values())


def temporal_weights(images: list[np.ndarray]) -> np.ndarray:
    """(F, H * W) float32 weights of the pixels of F frames (H, W, 3) uint8 (or float in
    [0, 1]) of one camera: each pixel's squared deviation from its mean colour over the F
    frames, averaged over the channels (colours in [0, 1]); all zero for F = 1."""
    if not images:
        return np.zeros((0, 0), np.float32)
    shape = images[0].shape
    if any(im.shape != shape for im in images):
        raise ValueError(f"temporal_weights: frames of one camera differ in size "
                         f"({sorted({im.shape for im in images})})")
    scale = 1.0 / 255.0 if images[0].dtype == np.uint8 else 1.0
    flat = [im.reshape(-1, shape[-1]) for im in images]
    n_pix = flat[0].shape[0]
    out = np.empty((len(images), n_pix), np.float32)
    chunk = max(1, _CHUNK_VALUES // (len(images) * shape[-1]))
    for start in range(0, n_pix, chunk):
        stop = min(start + chunk, n_pix)
        # float64: the mean of equal colours is exactly that colour, so a pixel that never
        # changes weighs exactly 0
        x = np.stack([f[start:stop] for f in flat]).astype(np.float64)
        out[:, start:stop] = np.square(x - x.mean(0, keepdims=True)).mean(-1) * scale ** 2
    return out


def importance_weights(dataset: Dataset, indices: list[int]) -> tuple[np.ndarray, int]:
    """((P,) float32 weights of every pixel of frames ``indices`` in their order, row-major
    within a frame; the number of frames whose camera films more than one of them).

    Frames of a camera that appears once weigh 0."""
    per_frame: list[np.ndarray] = [np.zeros(0, np.float32)] * len(indices)
    repeated = 0
    for group in camera_groups(dataset, indices):
        images = [dataset.images[indices[pos]] for pos in group]
        if len(group) == 1:
            per_frame[group[0]] = np.zeros(images[0].shape[0] * images[0].shape[1], np.float32)
            continue
        repeated += len(group)
        for pos, w in zip(group, temporal_weights(images)):
            per_frame[pos] = w
    return np.concatenate(per_frame), repeated
