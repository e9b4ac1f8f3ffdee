"""A run's spec (everything that rebuilds its model without the dataset), how a resumed run's
spec may differ from the stored one, and loading a trained run (:func:`load_model`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from nerfbot.data.conditioning import Conditioning, dataset_conditioning
from nerfbot.data.dataset import Dataset
from nerfbot.data.identity import dataset_identity, identity_mismatch
from nerfbot.data.labels import LabelClasses, label_classes
from nerfbot.methods import build_model
from nerfbot.models.base import Model, resize_like_state_dict
from nerfbot.models.labels import attach_label_head
from nerfbot.train import pixelnerf
from nerfbot.train.checkpoints import (CHECKPOINT, CheckpointError,
                                       load_checkpoint, plain)
from nerfbot.train.config import TrainConfig


log = logging.getLogger(__name__)


def model_spec(config: TrainConfig, dataset: Dataset) -> dict:
    """Everything needed to rebuild the model without the dataset (stored in checkpoints), and
    the identity of the dataset it is trained on
    (:func:`nerfbot.data.identity.dataset_identity`)."""
    background = config.background if config.background is not None else dataset.background
    spec = {"method": config.method, "aabb": np.asarray(dataset.aabb, float).tolist(),
            "background": background, "options": dict(config.options), "seed": config.seed,
            "conditioning": dataset_conditioning(dataset).to_dict(),
            "dataset": dataset_identity(dataset)}
    if config.labels:
        if spec["conditioning"]["kind"] != "static":
            raise ValueError(f"{dataset.root}: labels are for static scenes (this capture is "
                             f"conditioned on {spec['conditioning']['kind']})")
        spec["labels"] = label_classes(dataset.manifest, str(dataset.root)).to_dict()
    return spec


def build_from_spec(spec: dict, device="cpu") -> Model:
    """The model of a run's spec, with its label head when the run was trained with labels."""
    if spec["method"] == pixelnerf.METHOD:  # trained across scenes: not a registry method
        return pixelnerf.model_from_spec(spec).to(device)
    model = build_model(spec["method"], spec["aabb"], spec["background"], spec["options"],
                        spec["seed"], Conditioning.from_dict(spec.get("conditioning")))
    if spec.get("labels"):
        attach_label_head(model, LabelClasses.from_dict(spec["labels"]), spec["seed"])
    return model.to(device)


#: Relative tolerance of the bounds comparison on resume (float64 JSON round trips).
AABB_RTOL = 1e-9


def _shown(value) -> str:
    return value if isinstance(value, str) else json.dumps(plain(value))


def canonical_text(value) -> str:
    """JSON text of plain data, for comparisons that ignore list / tuple / numpy types."""
    return json.dumps(plain(value), sort_keys=True)


def _same_numbers(a, b, rtol: float = AABB_RTOL) -> bool:
    """Two numeric arrays of the same shape equal within ``rtol`` of their magnitude."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape:
        return False
    scale = max(1.0, float(np.abs(b).max(initial=0.0)))
    return bool(np.all(np.abs(a - b) <= rtol * scale))


def _same_background(a, b) -> bool:
    if isinstance(a, str) or isinstance(b, str) or a is None or b is None:
        return a == b
    return _same_numbers(a, b)


def _option_differences(requested: dict, stored: dict) -> list[str]:
    out = []
    for key in sorted(set(requested) | set(stored)):
        if key in requested and key in stored:
            if canonical_text(requested[key]) != canonical_text(stored[key]):
                out.append(f"option {key}={_shown(requested[key])}, but the run was made with "
                           f"{_shown(stored[key])}")
        elif key in requested:
            out.append(f"option {key}={_shown(requested[key])}, but the run was made without it "
                       "(the method's default)")
        else:
            out.append(f"no option {key}, but the run was made with {key}="
                       f"{_shown(stored[key])}")
    return out


def spec_differences(stored: dict, requested: dict, dataset: Dataset) -> list[str]:
    """One phrase per field in which the ``requested`` spec of a resume differs from the
    ``stored`` spec of the run: method, options, bounds (within :data:`AABB_RTOL`), background,
    conditioning, seed and the identity of ``dataset`` (skipped for runs that stored none).
    Budgets, evaluation times and checkpoint cadence are not part of a spec."""
    out = []
    if requested["method"] != stored["method"]:
        out.append(f"method {requested['method']!r}, but the run was made with "
                   f"{stored['method']!r}")
        return out  # options and the rest mean other things for another method
    out += _option_differences(requested["options"], stored["options"])
    if not _same_numbers(requested["aabb"], stored["aabb"]):
        shown = [" ".join(f"{v:g}" for v in np.ravel(s["aabb"])) for s in (requested, stored)]
        out.append(f"bounds --aabb {shown[0]}, but the run was made with {shown[1]}")
    if not _same_background(requested["background"], stored["background"]):
        out.append(f"background {_shown(requested['background'])}, but the run was made with "
                   f"{_shown(stored['background'])}")
    now, then = (Conditioning.from_dict(s.get("conditioning")) for s in (requested, stored))
    if canonical_text(now.to_dict()) != canonical_text(then.to_dict()):
        shown = [c.kind + "".join(f" {n}" for n in c.names) for c in (now, then)]
        if shown[0] == shown[1]:
            shown[0] += " (other ranges or joint kinematics)"
        out.append(f"conditioning {shown[0]}, but the run was made with {shown[1]}")
    if bool(requested.get("labels")) != bool(stored.get("labels")):
        out.append(f"labels {'on' if requested.get('labels') else 'off'}, but the run was made "
                   f"with them {'on' if stored.get('labels') else 'off'}")
    elif requested.get("labels") and canonical_text(requested["labels"]) != \
            canonical_text(stored["labels"]):
        out.append("other label classes than the run's")
    if requested["seed"] != stored["seed"]:
        out.append(f"seed {requested['seed']}, but the run was made with {stored['seed']}")
    other = identity_mismatch(stored.get("dataset"), dataset)
    if other is not None:
        out.append(f"another dataset ({dataset.root}: {other})")
    return out


def load_model_state(model: Model, ckpt: dict, path: Path) -> None:
    """Resize ``model``'s tensors to the checkpoint's and load them; CheckpointError naming
    ``path`` when they do not fit the model its spec builds."""
    try:
        resize_like_state_dict(model, ckpt["model"])
        model.load_state_dict(ckpt["model"])
    except (ValueError, RuntimeError, KeyError, AttributeError) as err:
        raise CheckpointError(f"{path}: the model tensors do not fit method "
                              f"{ckpt['spec']['method']!r}: {first_line(err)}") from None


def first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def load_model(run_dir, device="cpu") -> tuple[Model, dict]:
    """Load a trained model from a run folder; returns (model in eval mode, checkpoint info).

    The checkpoint is read as tensors and plain data only (a crafted file is refused, never
    run); a damaged ``checkpoint.pt`` falls back to ``checkpoint.prev.pt``
    (:func:`nerfbot.train.checkpoints.load_checkpoint`). FileNotFoundError when the run has no
    checkpoint, CheckpointError (a ValueError) when it is unusable."""
    path = Path(run_dir) / CHECKPOINT
    found = load_checkpoint(path)
    if found is None:
        raise FileNotFoundError(f"{path}: no checkpoint (is {run_dir} a training run folder?)")
    ckpt, used = found
    try:
        model = build_from_spec(ckpt["spec"], device)
    except (ValueError, KeyError, TypeError) as err:
        raise CheckpointError(f"{used}: cannot build the model of its spec: "
                              f"{first_line(err)}") from None
    load_model_state(model, ckpt, used)
    model.eval()
    info = {k: ckpt[k] for k in ("spec", "step", "train_seconds", "curve", "config")}
    return model, info
