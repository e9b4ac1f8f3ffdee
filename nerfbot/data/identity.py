"""What makes two loaded datasets the same dataset, wherever their folders are.

A run stores its dataset's identity; resume, eval and render compare it with the dataset they
are given, so a moved dataset is found again and another dataset is never taken for it.
"""

from __future__ import annotations

import hashlib
import json
from typing import Optional

import numpy as np

from nerfbot.data.dataset import Dataset

#: Poses and intrinsics are rounded to this many decimals before hashing (float round trips
#: through JSON must not change the identity).
_DECIMALS = 6


def _digest(*parts) -> str:
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True).encode())
    return h.hexdigest()[:16]


def dataset_identity(dataset: Dataset) -> dict:
    """A small JSON-able fingerprint of ``dataset``: its format, frame count, and digests of
    the frames' file paths and sizes, their poses and intrinsics (rounded to 1e-6), and the
    split lists. Image pixels are not read. Two folders holding the same files give the same
    identity; a dataset with other frames, poses or splits gives another."""
    frames = _digest([str(p) for p in dataset.file_paths], dataset.sizes.astype(np.int64))
    geometry = _digest(np.round(dataset.c2w, _DECIMALS).astype(np.float64),
                       np.round(dataset.intrinsics, _DECIMALS - 3).astype(np.float64))
    splits = _digest({k: [int(i) for i in v] for k, v in dataset.splits.items()})
    return {"format": dataset.format, "num_frames": len(dataset), "frames": frames,
            "geometry": geometry, "splits": splits}


def identity_mismatch(stored: Optional[dict], dataset: Dataset) -> Optional[str]:
    """None when ``dataset`` matches the ``stored`` identity (or none was stored), else a short
    phrase saying what differs (e.g. "60 frames, not 70")."""
    if not stored:
        return None
    now = dataset_identity(dataset)
    if stored.get("num_frames") != now["num_frames"]:
        return f"{now['num_frames']} frames, not {stored.get('num_frames')}"
    for key, what in (("frames", "frame files or image sizes"), ("geometry", "camera poses or "
                      "intrinsics"), ("splits", "train / test splits"), ("format", "format")):
        if stored.get(key) != now[key]:
            return f"other {what}"
    return None
