"""Labels for a run that was trained without them: a label head trained on the frozen field
(``nerfbot label RUN --out LABELLED``), written as a run of its own.

The label head reads the field's geometry features detached and composites with detached
weights (:mod:`nerfbot.models.labels`), so training it jointly (``nerfbot train --labels``) never
changes the field either: here the field is simply finished first. Each step renders a batch of
labelled pixels in eval mode (no gradients through the field) and takes one AdamW step of the
head on their cross-entropy.

With a few clicks per class, where they fall matters more than how many there are. iLabel
(Zhi et al. 2021) asks the user for the next clicks where the head is least sure; the
``uncertain`` click choice does that with the capture's label maps answering for the user
(:func:`uncertain_pixels` is the question, usable by an interactive tool as it is). The most
uncertain pixels tend to lie in one large ambiguous region (a wall, a table) that one class
answers, so the question takes each predicted class in turn and training draws each clicked
class equally often.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch.nn.functional import one_hot
from tqdm.auto import tqdm

from nerfbot.data.conditioning import dataset_conditioning
from nerfbot.data.dataset import Dataset
from nerfbot.data.labels import LabelClasses, click_maps, label_classes, label_maps
from nerfbot.data.outputs import check_output_folder
from nerfbot.data.pixels import PixelBank
from nerfbot.data.run_dataset import run_data_fields
from nerfbot.data.writers import write_json_atomic
from nerfbot.models.base import Model
from nerfbot.models.labels import attach_label_head, label_loss, render_labels
from nerfbot.train.checkpoints import CHECKPOINT, save_checkpoint

log = logging.getLogger(__name__)

#: Where clicks fall (:attr:`LabelTrainConfig.click_choice`).
CLICK_CHOICES = ("random", "uncertain")


@dataclass
class LabelTrainConfig:
    steps: int = 1000
    """AdamW steps of the head."""
    rays: int = 4096
    """Labelled pixels per step (with clicks: at most as many as there are clicks)."""
    lr: float = 5e-3
    """AdamW learning rate of the head."""
    weight_decay: float = 1.0
    """AdamW's decoupled weight decay on the head: keeps it smooth where no pixel is labelled,
    which matters with a few clicks."""
    clicks: Optional[int] = None
    """iLabel's setting: on average this many labelled pixels per class over the training
    frames (``clicks`` times the number of classes in all); None: full label maps."""
    click_choice: str = "uncertain"
    """Where the clicks fall. ``random``: ``clicks`` per class, drawn uniformly over each
    class's pixels (:func:`~nerfbot.data.labels.click_maps`). ``uncertain`` (iLabel's active
    choice): one random click per class, the rest asked in :attr:`click_rounds` rounds over
    the first half of the steps, at the pixels of highest class entropy among
    :attr:`candidates` random training pixels, taken in turn from each class the head
    predicts (:func:`uncertain_pixels`); the capture's label maps answer for the user. Either
    way the head trains on its clicks class-balanced: each class drawn equally often."""
    click_rounds: int = 8
    """Rounds of questions of the ``uncertain`` choice."""
    candidates: int = 4096
    """Random training pixels the head renders per round of questions."""
    seed: int = 0
    """Seeds the head, the clicks and the batches."""

    def validate(self) -> None:
        for name in ("steps", "rays"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not 0.0 < self.lr < float("inf"):
            raise ValueError(f"lr must be positive and finite, got {self.lr}")
        if not 0.0 <= self.weight_decay < float("inf"):
            raise ValueError(f"weight_decay must be >= 0 and finite, got {self.weight_decay}")
        if self.clicks is not None and (isinstance(self.clicks, bool) or self.clicks < 1):
            raise ValueError(f"clicks must be an integer >= 1, got {self.clicks!r}")
        if self.click_choice not in CLICK_CHOICES:
            raise ValueError(f"click_choice must be one of {CLICK_CHOICES}, got "
                             f"{self.click_choice!r}")
        for name in ("click_rounds", "candidates"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")


def train_label_head(model: Model, dataset: Dataset, config: LabelTrainConfig = LabelTrainConfig(),
                     classes: Optional[LabelClasses] = None, progress: bool = False) -> dict:
    """Attach a label head to ``model`` (a static run; its field stays as it is) and train it
    on the training frames' segmentation (classes from the dataset's manifest unless given).
    Returns {"steps", "seconds", "loss" (mean of the last 50 steps), "labelled_pixels"}."""
    config.validate()
    if model.label_head is not None:
        raise ValueError("this run already has a label head")
    if not dataset_conditioning(dataset, tracks=False).is_static:
        raise ValueError(f"{dataset.root}: labels are for static scenes (this capture has time "
                         "or joints)")
    classes = classes or label_classes(dataset.manifest, str(dataset.root))
    attach_label_head(model, classes, config.seed)
    head = model.label_head
    train = dataset.indices("train")
    bank = PixelBank(dataset, train, model.aabb.device)
    maps = label_maps(dataset, classes, train)
    questions: dict[int, int] = {}  # head step -> clicks asked for before it
    if config.clicks is not None:
        answers = torch.from_numpy(np.concatenate([m.reshape(-1) for m in maps]))
        first = 1 if config.click_choice == "uncertain" else config.clicks
        maps = click_maps(maps, first, config.seed)
        if config.click_choice == "uncertain":
            questions = question_schedule(config, len(classes) * config.clicks
                                          - sum(int((m >= 0).sum()) for m in maps))
    count = bank.load_labels(maps, sparse=config.clicks is not None)
    optimizer = torch.optim.AdamW(head.parameters(), lr=config.lr,
                                  weight_decay=config.weight_decay)
    generator = torch.Generator().manual_seed(config.seed)
    model.eval()
    losses, t0 = [], time.perf_counter()
    for step in tqdm(range(config.steps), desc="label head", unit="step", disable=not progress):
        if step in questions:
            asked = uncertain_pixels(model, bank, answers, questions[step], config.candidates,
                                     generator)
            bank.add_clicks(asked, answers[asked])
            count += len(asked)
        if bank.clicks is not None:
            rays, _, _, target = bank.sample_clicks(min(config.rays, len(bank.clicks)), generator,
                                                    balanced=True)
        else:
            rays, _, _ = bank.sample(config.rays, generator)
            target = bank.labels[bank.last_pixels]
        out = model.render_rays(rays)  # eval mode: no gradients into the field
        loss = label_loss(render_labels(head, out), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    seconds = time.perf_counter() - t0
    tail = losses[-50:]
    return {"steps": config.steps, "seconds": seconds, "loss": sum(tail) / len(tail),
            "labelled_pixels": count}


def question_schedule(config: LabelTrainConfig, extra: int) -> dict[int, int]:
    """{head step: clicks to ask for before it}: ``extra`` clicks spread over
    ``config.click_rounds`` rounds at even steps over the first half of the training."""
    if extra <= 0:
        return {}
    rounds = max(1, min(config.click_rounds, extra, config.steps // 2))
    schedule: dict[int, int] = {}
    for r in range(rounds):
        step = min(max(1, ((r + 1) * config.steps) // (2 * rounds)), config.steps - 1)
        schedule[step] = schedule.get(step, 0) + (extra * (r + 1)) // rounds - (extra * r) // rounds
    return schedule


@torch.no_grad()
def uncertain_pixels(model: Model, bank: PixelBank, answerable: torch.Tensor, n: int,
                     candidates: int, generator: torch.Generator, chunk: int = 4096
                     ) -> torch.Tensor:
    """iLabel's question: ``n`` pixels (indices into ``bank``, (n,) int64) of high class
    entropy among ``candidates`` pixels drawn at random from those not yet labelled and whose
    entry of ``answerable`` (P,) is >= 0 (a class the user can give). Taken in turn from each
    class the head predicts, most uncertain first, so that a large ambiguous region (a wall, a
    table) does not take every question. Fewer when fewer remain."""
    head = model.label_head
    free = (answerable.to(bank.device) >= 0) & (bank.labels < 0)
    pool = torch.nonzero(free).squeeze(1)
    if len(pool) == 0 or n <= 0:
        return pool[:0]
    pick = torch.randperm(len(pool), generator=generator)[:candidates].to(pool.device)
    pool = pool[pick]
    entropy, predicted = [], []
    for part in pool.split(chunk):
        probs = render_labels(head, model.render_rays(bank.centre_rays(part))).clamp_min(1e-12)
        entropy.append(-(probs * probs.log()).sum(-1))
        predicted.append(probs.argmax(-1))
    order = torch.cat(entropy).argsort(descending=True, stable=True)
    predicted = torch.cat(predicted)[order]
    # each candidate's place among those of its predicted class, most uncertain first
    rank = one_hot(predicted, head.n_classes).cumsum(0).gather(1, predicted[:, None])[:, 0] - 1
    turn = (rank * len(order) + torch.arange(len(order), device=rank.device)).argsort()
    return pool[order[turn[:n]]]


def write_labelled_run(model: Model, spec: dict, source_info: dict, out: Path, data: Path,
                       report: dict, overwrite: bool = False) -> Path:
    """Write ``model`` (a run with its new label head; ``spec`` the source run's with
    ``labels``) as a run folder ``out``: ``checkpoint.pt`` (durable), ``config.json`` (linking
    the dataset folder ``data``) and ``labels.json`` (``report``). The step and training time
    are the source run's. ``out`` must be new, empty or (``overwrite``) an earlier run."""
    folder = check_output_folder(out, "run", overwrite=overwrite)
    ckpt = {"spec": spec, "model": model.state_dict(), "step": source_info.get("step", 0),
            "train_seconds": source_info.get("train_seconds", 0.0),
            "curve": source_info.get("curve", []), "config": source_info.get("config", {})}
    path = folder.path / CHECKPOINT
    with folder.writing():
        save_checkpoint(ckpt, path)
        write_json_atomic(folder.path / "config.json", {"spec": spec, "train": ckpt["config"],
                                                        **run_data_fields(data, folder.path)},
                          allow_nan=True)
        write_json_atomic(folder.path / "labels.json", report, allow_nan=True)
    return path


def label_run(model: Model, info: dict, dataset: Dataset, data: Path, out: Path,
              config: LabelTrainConfig = LabelTrainConfig(), overwrite: bool = False,
              progress: bool = False) -> dict:
    """Train a label head on a loaded run (``model``, ``info`` from
    :func:`~nerfbot.train.runs.load_model`) and write the labelled run to ``out``; returns
    the report (classes, training summary, config)."""
    check_output_folder(out, "run", overwrite=overwrite)  # before training
    summary = train_label_head(model, dataset, config, progress=progress)
    classes = model.label_head.classes
    spec = {**info["spec"], "labels": classes.to_dict()}
    report = {"classes": list(classes.names), **summary, "config": asdict(config)}
    write_labelled_run(model, spec, info, out, data, report, overwrite=overwrite)
    log.info("label head: %d steps in %.1f s, loss %.3f", summary["steps"], summary["seconds"],
             summary["loss"])
    return report
