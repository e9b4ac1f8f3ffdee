"""Semantic classes of a capture, from its segmentation: which class each pixel shows, the full
label maps Semantic-NeRF trains on, and iLabel's few labelled pixels ("clicks").

Classes come from the scene manifest (:func:`label_classes`): ``background`` (pixels that show
no geom: sky), one class per object the scene declares (``objects``; rooms without objects:
their ``obstacles``), and ``structure`` for every other rendered geom (table, floor, walls).
Segmentation images hold MuJoCo geom ids; :func:`label_maps` turns them into class indices,
:data:`IGNORE` where a pixel has no usable label (a geom the manifest does not list, a masked
pixel, or no segmentation at all).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from nerfbot.data.dataset import Dataset

#: Class of the pixels that show no geom (segmentation -1).
BACKGROUND = "background"
#: Class of every rendered geom that is neither an object nor an obstacle.
STRUCTURE = "structure"
#: Label index of a pixel without a usable label; never trained on nor scored.
IGNORE = -1


@dataclass(frozen=True)
class LabelClasses:
    """Class names and how geom ids map to them.

    Attributes:
        names: K class names; index 0 is :data:`BACKGROUND`.
        geom_class: {geom id: class index} for every geom the manifest lists.
    """

    names: tuple[str, ...]
    geom_class: dict[int, int]

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Class index of ``name``; ValueError naming the classes when there is none."""
        if name not in self.names:
            raise ValueError(f"no class {name!r}; the classes are {list(self.names)}")
        return self.names.index(name)

    def to_dict(self) -> dict:
        return {"names": list(self.names),
                "geom_class": {str(g): c for g, c in sorted(self.geom_class.items())}}

    @classmethod
    def from_dict(cls, d: dict) -> "LabelClasses":
        return cls(tuple(d["names"]), {int(g): int(c) for g, c in d["geom_class"].items()})


def label_classes(manifest: Optional[dict], where: str = "dataset") -> LabelClasses:
    """The classes of a scene from its manifest (see the module docstring); ValueError naming
    ``where`` when there is no manifest with geoms (labels come from ``sims`` captures)."""
    if not manifest or not manifest.get("geoms"):
        raise ValueError(f"{where}: labels need the scene manifest's geoms (transforms.json "
                         "'scene', written by nerfbot capture) to map segmentation to classes")
    geoms = {int(g): name for g, name in manifest["geoms"].items()}
    things = list(manifest.get("objects") or []) or list(manifest.get("obstacles") or {})
    names = [BACKGROUND] + [n for n in things if n in geoms.values()] + [STRUCTURE]
    index = {n: k for k, n in enumerate(names)}
    geom_class = {g: index.get(name, index[STRUCTURE]) for g, name in geoms.items()}
    return LabelClasses(tuple(names), geom_class)


def label_map(segmentation: np.ndarray, classes: LabelClasses,
              mask: Optional[np.ndarray] = None) -> np.ndarray:
    """(H, W) int16 class indices of a segmentation image (geom ids, -1 = none):
    :data:`IGNORE` for geoms the classes do not know and where ``mask`` (H, W) is False."""
    seg = np.asarray(segmentation)
    lut_size = max(max(classes.geom_class, default=0), int(seg.max(initial=-1))) + 2
    lut = np.full(lut_size, IGNORE, dtype=np.int16)
    lut[0] = classes.index(BACKGROUND)  # geom id -1 sits at 0
    for g, c in classes.geom_class.items():
        lut[g + 1] = c
    out = lut[np.clip(seg, -1, None) + 1]
    if mask is not None:
        out[~np.asarray(mask, bool)] = IGNORE
    return out


def label_maps(dataset: Dataset, classes: LabelClasses, indices: Sequence[int]
               ) -> list[np.ndarray]:
    """Label maps (:func:`label_map`) of frames ``indices``; ValueError naming the frames
    without segmentation."""
    missing = [dataset.file_paths[i] for i in indices if dataset.segmentations[i] is None]
    if missing:
        raise ValueError(f"{dataset.root}: labels need a segmentation image for every frame "
                         f"used; {len(missing)} have none (e.g. {missing[0]})")
    return [label_map(dataset.segmentations[i], classes, dataset.valid_mask(i)) for i in indices]


def click_maps(maps: Sequence[np.ndarray], clicks: int, seed: int = 0) -> list[np.ndarray]:
    """iLabel's sparse supervision: of the labelled pixels of ``maps`` (label maps of the
    training frames), keep ``clicks`` per class, drawn uniformly at random over all the
    frames' pixels of that class (seeded); every other pixel becomes :data:`IGNORE`. A class
    with fewer pixels keeps them all."""
    if clicks < 1:
        raise ValueError(f"clicks must be >= 1 per class, got {clicks}")
    flat = np.concatenate([m.reshape(-1) for m in maps])
    rng = np.random.default_rng(seed)
    keep = np.full(flat.shape, IGNORE, dtype=np.int16)
    for c in np.unique(flat[flat != IGNORE]):
        where = np.flatnonzero(flat == c)
        pick = rng.choice(where, size=min(clicks, len(where)), replace=False)
        keep[pick] = c
    out, start = [], 0
    for m in maps:
        out.append(keep[start:start + m.size].reshape(m.shape))
        start += m.size
    return out


def mean_iou(pred: np.ndarray, target: np.ndarray, n_classes: int
             ) -> tuple[float, np.ndarray]:
    """Mean intersection over union of class maps ``pred`` and ``target`` (same shape,
    :data:`IGNORE` in ``target`` not scored), over the classes present in the target or the
    prediction (on scored pixels). Returns (mIoU, (K,) per-class IoU, NaN where absent)."""
    scored = target != IGNORE
    p, t = pred[scored].astype(np.int64), target[scored].astype(np.int64)
    inter = np.bincount(t[p == t], minlength=n_classes)[:n_classes].astype(float)
    union = (np.bincount(p, minlength=n_classes)[:n_classes]
             + np.bincount(t, minlength=n_classes)[:n_classes] - inter).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(union > 0, inter / union, np.nan)
    return (float(np.nanmean(iou)) if np.isfinite(iou).any() else float("nan")), iou
