"""Training pixelNeRF across the scenes of a family, saving and loading it, conditioning it on
a scene's source views and fine-tuning it on them.

Each step takes one scene at random, 1-3 of its training views at random as the sources, and
random pixels of its training views as the targets (pixelNeRF's recipe); the loss is the coarse
and the fine passes' colour MSE. The trained model is a run folder like any other:
``checkpoint.pt`` (tensors only, written atomically, :mod:`nerfbot.train.checkpoints`) and
``config.json``; its spec names the method ``pixelnerf`` and the scenes it was trained on, and
:func:`nerfbot.train.runs.load_model` loads it like any run.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from nerfbot.data.dataset import Dataset
from nerfbot.fields.background import make_background
from nerfbot.fields.pixelnerf import PixelNeRFField, PixelNeRFFieldConfig, SourceViews
from nerfbot.models.pixelnerf import PixelNeRFModel, PixelNeRFModelConfig
from nerfbot.ops.cameras import pixel_rays
from nerfbot.train.checkpoints import CHECKPOINT, save_checkpoint

METHOD = "pixelnerf"


@dataclass
class PixelTrainConfig:
    """How a pixelNeRF model is trained across scenes.

    Attributes:
        steps: training steps (the budget, with ``max_seconds``).
        max_seconds: stop after this many seconds of training (None: steps only).
        sources: (fewest, most) source views per step, drawn uniformly.
        lr: Adam learning rate, decayed exponentially to ``lr * lr_final_factor`` over the
            budget (steps or seconds, whichever runs out first).
        lr_final_factor: see ``lr``.
        seed: seeds the initialisation and every draw.
        progress: show a progress bar.
    """

    steps: int = 20000
    max_seconds: Optional[float] = None
    sources: tuple = (1, 3)
    lr: float = 5e-4
    lr_final_factor: float = 0.1
    seed: int = 0
    progress: bool = True

    def validate(self) -> None:
        lo, hi = self.sources
        if not 1 <= lo <= hi:
            raise ValueError(f"sources must be (fewest, most) with 1 <= fewest <= most, got "
                             f"{self.sources}")
        if self.steps < 1:
            raise ValueError(f"steps must be at least 1, got {self.steps}")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise ValueError(f"max_seconds must be positive, got {self.max_seconds}")
        if not (self.lr > 0 and 0 < self.lr_final_factor <= 1):
            raise ValueError("lr must be positive and lr_final_factor in (0, 1]")


class SceneViews:
    """One scene's frames as tensors, for drawing sources and target pixels.

    Attributes:
        images: (N, H, W, 3) float RGB in [0, 1]; c2w: (N, 4, 4) float32 (OpenGL);
        intrinsics: (N, 4) float32; train: (T,) int64 training frame indices; aabb: (2, 3).
    """

    def __init__(self, dataset: Dataset, device="cpu"):
        sizes = {tuple(int(v) for v in s) for s in dataset.sizes}
        if len(sizes) != 1:
            raise ValueError(f"{dataset.root}: pixelNeRF needs frames of one size, got "
                             f"{sorted(sizes)}")
        self.name = str(dataset.root)
        self.images = torch.from_numpy(np.stack(dataset.images)).to(device).float() / 255.0
        self.c2w = torch.as_tensor(dataset.c2w, dtype=torch.float32, device=device)
        self.intrinsics = torch.as_tensor(dataset.intrinsics, dtype=torch.float32, device=device)
        self.train = torch.as_tensor(dataset.indices("train"), dtype=torch.int64)
        if len(self.train) == 0:
            raise ValueError(f"{dataset.root}: no training frames")
        self.aabb = np.asarray(dataset.aabb, dtype=np.float64)

    def sources(self, indices: Sequence[int]) -> SourceViews:
        idx = torch.as_tensor(list(indices), dtype=torch.int64)
        return SourceViews(self.images[idx].permute(0, 3, 1, 2).contiguous(),
                           torch.linalg.inv(self.c2w[idx].double()).float(),
                           self.intrinsics[idx])

    def random_pixels(self, n: int, generator: torch.Generator):
        """n random pixels of the training views: (rays, (n, 3) colours)."""
        h, w = self.images.shape[1:3]
        view = self.train[torch.randint(len(self.train), (n,), generator=generator)]
        px = torch.randint(w, (n,), generator=generator)
        py = torch.randint(h, (n,), generator=generator)
        k = self.intrinsics[view]
        rays = pixel_rays(self.c2w[view], k[:, 0], k[:, 1], k[:, 2], k[:, 3],
                          px.float() + 0.5, py.float() + 0.5)
        return rays, self.images[view, py, px]


def build_pixelnerf(aabb, field_config: PixelNeRFFieldConfig | None = None,
                    model_config: PixelNeRFModelConfig | None = None, seed: int = 0
                    ) -> PixelNeRFModel:
    """An untrained pixelNeRF model (learned background, a function of the ray direction)."""
    torch.manual_seed(seed)
    return PixelNeRFModel(PixelNeRFField(aabb, field_config), make_background("learned"), aabb,
                          model_config)


def condition_on(model: PixelNeRFModel, dataset: Dataset, source_indices: Sequence[int]
                 ) -> PixelNeRFModel:
    """Set ``model`` to render ``dataset``'s scene from its frames ``source_indices``, within
    the dataset's bounds; returns the model."""
    if not len(source_indices):
        raise ValueError("pixelNeRF needs at least one source view")
    bad = [i for i in source_indices if not 0 <= int(i) < len(dataset)]
    if bad:
        raise ValueError(f"{dataset.root}: no frame {bad[0]} (it has {len(dataset)})")
    idx = [int(i) for i in source_indices]
    sources = SourceViews.from_frames([dataset.images[i] for i in idx], dataset.c2w[idx],
                                      dataset.intrinsics[idx], model.aabb.device)
    model.set_scene(sources, dataset.aabb)
    return model


def _fit(model: PixelNeRFModel, draw, steps: Optional[int], max_seconds: Optional[float], lr: float,
         lr_final_factor: float, seed: int, progress: bool, desc: str) -> dict:
    """Adam on the colour loss of the batches ``draw(generator)`` gives: (sources, aabb, rays,
    target colours). The budget is ``steps`` and ``max_seconds``, whichever runs out first
    (either may be None, not both); the lr decays exponentially to ``lr * lr_final_factor``
    over it. Leaves the model in eval mode; returns
    {"steps", "train_seconds", "loss" (mean of the last 100 steps), "curve" (step, seconds,
    loss every 50 steps)}."""
    device = model.aabb.device
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    model.train()
    losses, curve = [], []
    t0 = time.perf_counter()
    step = 0
    bar = tqdm(total=steps, disable=not progress, unit="step", desc=desc)
    while steps is None or step < steps:
        elapsed = time.perf_counter() - t0
        if max_seconds is not None and elapsed >= max_seconds:
            break
        frac = min(1.0, max(step / max(steps - 1, 1) if steps else 0.0,
                            elapsed / max_seconds if max_seconds else 0.0))
        for group in optimizer.param_groups:
            group["lr"] = lr * lr_final_factor ** frac
        sources, aabb, rays, target = draw(gen)
        model.set_scene(sources, aabb)
        loss, _ = model.loss(rays.to(device), target, gen)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
        step += 1
        if step % 50 == 0 or step == steps:
            recent = float(np.mean(losses[-50:]))
            curve.append({"step": step, "seconds": time.perf_counter() - t0, "loss": recent})
            bar.set_postfix(loss=f"{recent:.4f}")
        bar.update(1)
    bar.close()
    model.eval()
    return {"steps": step, "train_seconds": time.perf_counter() - t0,
            "loss": float(np.mean(losses[-100:])) if losses else math.nan, "curve": curve}


def train_pixelnerf(model: PixelNeRFModel, datasets: Sequence[Dataset], config: PixelTrainConfig,
                    out_dir: Optional[Path] = None) -> dict:
    """Train ``model`` across ``datasets`` (scenes of one family); when ``out_dir`` is given,
    save the run there at the end. Returns {"steps", "train_seconds", "loss" (mean of the last
    100 steps), "curve" (step, seconds, loss every 50 steps)}."""
    config.validate()
    if not datasets:
        raise ValueError("pixelNeRF trains across scenes: give at least one dataset")
    scenes = [SceneViews(ds, model.aabb.device) for ds in datasets]
    lo, hi = config.sources

    def draw(gen):
        scene = scenes[int(torch.randint(len(scenes), (1,), generator=gen))]
        k = min(int(torch.randint(lo, hi + 1, (1,), generator=gen)), len(scene.train))
        chosen = scene.train[torch.randperm(len(scene.train), generator=gen)[:k]]
        rays, target = scene.random_pixels(model.config.rays_per_batch, gen)
        return scene.sources(chosen.tolist()), scene.aabb, rays, target

    summary = _fit(model, draw, config.steps, config.max_seconds, config.lr,
                   config.lr_final_factor, config.seed, config.progress, "pixelNeRF")
    if out_dir is not None:
        save_pixelnerf(model, out_dir, config, [s.name for s in scenes], summary)
    return summary


@dataclass
class FinetuneConfig:
    """Fine-tuning a trained pixelNeRF on one scene (pixelNeRF's optional per-scene step).

    The model, conditioned on the scene's source views, learns those views' own pixels: they
    are all a new scene gives. Every weight is trained, the encoder included.

    Attributes:
        steps: fine-tuning steps (None: ``max_seconds`` only).
        max_seconds: stop after this many seconds (None: ``steps`` only).
        lr: Adam learning rate (default: training's), decayed exponentially to a tenth over
            the budget.
        seed: seeds the pixel draws.
        progress: show a progress bar.
    """

    steps: Optional[int] = 200
    max_seconds: Optional[float] = None
    lr: float = 5e-4
    seed: int = 0
    progress: bool = True

    def validate(self) -> None:
        if self.steps is None and self.max_seconds is None:
            raise ValueError("fine-tuning needs a budget: steps or max_seconds")
        if self.steps is not None and self.steps < 1:
            raise ValueError(f"fine-tuning steps must be at least 1, got {self.steps}")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise ValueError(f"fine-tuning seconds must be positive, got {self.max_seconds}")
        if not self.lr > 0:
            raise ValueError(f"fine-tuning lr must be positive, got {self.lr}")


def finetune_on(model: PixelNeRFModel, dataset: Dataset, source_indices: Sequence[int],
                config: FinetuneConfig | None = None) -> dict:
    """Condition ``model`` on ``dataset``'s frames ``source_indices`` and fine-tune it on their
    pixels; the model stays conditioned on them, in eval mode. Returns :func:`_fit`'s summary."""
    config = config or FinetuneConfig()
    config.validate()
    condition_on(model, dataset, source_indices)
    scene = SceneViews(dataset, model.aabb.device)
    scene.train = torch.as_tensor([int(i) for i in source_indices], dtype=torch.int64)
    sources = model.field.sources

    def draw(gen):
        rays, target = scene.random_pixels(model.config.rays_per_batch, gen)
        return sources, None, rays, target

    return _fit(model, draw, config.steps, config.max_seconds, config.lr, 0.1, config.seed,
                config.progress, "pixelNeRF fine-tuning")


def pixelnerf_spec(model: PixelNeRFModel, config: PixelTrainConfig, scenes: list[str]) -> dict:
    """The run spec: what :func:`load_pixelnerf` rebuilds the model from."""
    return {"method": METHOD, "aabb": model.aabb.tolist(), "background": "learned",
            "options": {"field": asdict(model.field.config), "model": asdict(model.config)},
            "seed": config.seed, "scenes": scenes}


def save_pixelnerf(model: PixelNeRFModel, out_dir, config: PixelTrainConfig, scenes: list[str],
                   summary: dict) -> Path:
    """Write the run folder ``out_dir``: checkpoint and config.json."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    spec = pixelnerf_spec(model, config, scenes)
    train_config = {k: v for k, v in asdict(config).items() if k != "progress"}
    save_checkpoint({"spec": spec, "model": model.state_dict(), "step": summary["steps"],
                     "train_seconds": summary["train_seconds"], "curve": summary["curve"],
                     "config": train_config}, out / CHECKPOINT)
    (out / "config.json").write_text(json.dumps({"spec": spec, "train": train_config}, indent=2))
    return out


def model_from_spec(spec: dict) -> PixelNeRFModel:
    """The (untrained) model of a pixelNeRF run's spec (:func:`pixelnerf_spec`)."""
    options = spec["options"]
    field_cfg = PixelNeRFFieldConfig(**{k: tuple(v) if isinstance(v, list) else v
                                        for k, v in options["field"].items()})
    return build_pixelnerf(spec["aabb"], field_cfg, PixelNeRFModelConfig(**options["model"]),
                           spec["seed"])
