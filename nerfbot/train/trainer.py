"""The training loop: batches of random pixels, Adam, a decaying learning rate, budgets in
steps or seconds, durable checkpoints and exact resume (:class:`Trainer`)."""

from __future__ import annotations

import copy
import logging
import math
import platform
import time
from dataclasses import asdict
from importlib import metadata
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from torch.autograd.graph import increment_version
from tqdm.auto import tqdm

from nerfbot.data.conditioning import Conditioning, frame_conditions
from nerfbot.data.dataset import Dataset
from nerfbot.data.importance import importance_weights
from nerfbot.data.labels import LabelClasses, click_maps, label_maps
from nerfbot.data.pixels import PixelBank
from nerfbot.data.run_dataset import run_data_fields
from nerfbot.data.writers import write_json_atomic
from nerfbot.methods import get_method
from nerfbot.models.base import Model, pixel_mean
from nerfbot.models.labels import label_loss, render_labels
from nerfbot.ops.cameras import Rays
from nerfbot.ops.losses import keypoint_depth_loss
from nerfbot.ops.rendering import RenderOutput
from nerfbot.ops.schedules import learning_rate
from nerfbot.train.checkpoints import (CHECKPOINT, RESUME_REQUIRED, CheckpointError,
                                       load_checkpoint, remove_stale_temporaries,
                                       save_checkpoint)
from nerfbot.train.config import TrainConfig
from nerfbot.train.runs import (build_from_spec, canonical_text, first_line, load_model,
                                load_model_state, model_spec, spec_differences)
from nerfbot.train.scalars import SCALARS, plot_scalars, read_scalars, step_row, write_scalars


log = logging.getLogger(__name__)


#: Rays of the throwaway step that compiles a method's kernels before the training clock starts.
WARM_UP_RAYS = 64


def warm_up_step(model: Model, bank: "PixelBank", step: int, progress: float) -> None:
    """One training step's forward and backward pass on a throwaway copy of ``model``, on
    :data:`WARM_UP_RAYS` rays drawn with a private generator.

    It compiles (or loads from numba's cache) every kernel a step of this method calls and
    builds torch's first-call state, so none of it counts as training time: on a fresh install,
    kernels once compiled several seconds into a 30 s budget. The model, its optimiser and the
    run's random state are untouched, so runs stay deterministic for a seed.
    """
    twin = copy.deepcopy(model)
    generator = torch.Generator().manual_seed(0)
    twin.before_step(step, generator, progress)
    loss, _, _ = batch_loss(twin, bank, WARM_UP_RAYS, generator, progress)
    loss.backward()


#: Packages whose versions a run's config.json records.
RECORDED_PACKAGES = ("nerfbot", "torch", "numpy", "numba", "mujoco", "open3d", "pycolmap",
                     "trimesh", "opencv-contrib-python-headless")


def package_versions() -> dict:
    """{"python": version, package: version or None (not installed)} of
    :data:`RECORDED_PACKAGES`."""
    versions = {"python": platform.python_version()}
    for name in RECORDED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def sample_span(out: RenderOutput, first_ray: int, stop_ray: int) -> slice:
    """The packed samples of rays ``first_ray`` up to ``stop_ray`` (exclusive) of a render
    output (its samples are sorted by ray)."""
    index = out.ray_indices
    bounds = torch.tensor([first_ray, stop_ray], dtype=index.dtype, device=index.device)
    lo, hi = (int(v) for v in torch.searchsorted(index, bounds))
    return slice(lo, hi)


def batch_loss(model: Model, bank: "PixelBank", n_rays: int, generator: torch.Generator,
               progress: float, keypoints: int = 0, sparse_depth_weight: float = 0.0,
               label_weight: float = 0.0, label_pixels: int = 0,
               sparse_depth_robust: float = 0.0) -> tuple[torch.Tensor, RenderOutput, int]:
    """The loss of a batch of about ``n_rays`` random training rays at ``progress`` of the
    budget: S x S rays per pixel (S = ``model.training_supersample(progress)``), whose
    colours the model averages before comparing them with the pixel's (a pixel's colour is the
    mean over its area, as a renderer's anti-aliasing or a camera's sensor makes it).

    With ``keypoints`` > 0, that many pixels holding sparse-depth keypoints
    (:meth:`PixelBank.sample_keypoints`; no more than a quarter of the batch's pixels) join the
    batch, as DS-NeRF trains: their rays add ``sparse_depth_weight`` x
    :func:`~nerfbot.ops.losses.keypoint_depth_loss` (robust with ``sparse_depth_robust`` from
    a quarter of the budget on), and their colours are left out of the
    colour loss, which stays the mean over the random pixels (a few keypoints drawn again and
    again are not a sample of the images).

    With ``label_weight`` > 0 (a model with a label head, a bank with labels:
    :meth:`PixelBank.load_labels`) the batch adds ``label_weight`` x the cross-entropy of the
    rendered class probabilities (:func:`~nerfbot.models.labels.render_labels`) of
    ``label_pixels`` pixels: the first random ones when every pixel is labelled, else pixels
    drawn from the clicks (:meth:`PixelBank.sample_clicks`; no more than there are clicks,
    nor than a quarter of the batch's pixels), which join the batch like keypoints.

    The random pixels drawn are in ``bank.last_pixels`` (keypoint and click pixels are not, so
    dense depth supervision sees only those). Returns the loss, the rays' render output (the
    random pixels' rays first, then keypoints', then clicks') and S."""
    s = model.training_supersample(progress)
    k = s * s
    clicks = 0
    if bank.clicks is not None and label_weight > 0:  # at most a quarter of the pixels
        clicks = max(1, min(label_pixels, len(bank.clicks), n_rays // k // 4))
    if keypoints:
        keypoints = max(1, min(keypoints, n_rays // k // 4))
    n_pixels = max(1, n_rays // k - keypoints - clicks)
    rays, target, slot = bank.sample(n_pixels, generator, s, jitter=model.pixel_jitter)
    parts = [(rays, target, slot)]
    depth = click_labels = None
    if keypoints:
        krays, kcolour, kslot, kt, ksigma = bank.sample_keypoints(keypoints, generator, s)
        parts.append((krays, kcolour, kslot))
        depth = kt, ksigma
    if clicks:
        crays, ccolour, cslot, click_labels = bank.sample_clicks(clicks, generator, s)
        parts.append((crays, ccolour, cslot))
    if len(parts) > 1:
        rays = Rays.cat([p[0] for p in parts])
        target, slot = torch.cat([p[1] for p in parts]), torch.cat([p[2] for p in parts])
    cond = None if bank.conds is None else bank.conds[slot].repeat_interleave(k, 0)
    weights = bank.last_weights
    if keypoints:  # keypoint pixels weigh 0, the random ones make up for them
        random = weights if weights is not None else target.new_ones(n_pixels)
        weights = torch.cat([random * ((n_pixels + keypoints) / n_pixels),
                             target.new_zeros(keypoints)])
    if weights is not None and len(weights) < len(target):  # click pixels weigh 1
        weights = torch.cat([weights, weights.new_ones(len(target) - len(weights))])
    loss, out = model.loss(rays, target, generator, cond, rays_per_pixel=k,
                           pixel_weights=weights)
    if bank.error_map is not None:
        with torch.no_grad():
            rgb = out.rgb[:n_pixels * k].reshape(n_pixels, k, 3).mean(1)
            bank.record_errors(((rgb - target[:n_pixels]) ** 2).mean(-1))
    if depth is not None:
        first = n_pixels * k
        span = sample_span(out, first, first + keypoints * k)
        loss = loss + sparse_depth_weight * keypoint_depth_loss(
            out.weights[span], out.t_starts[span], out.t_ends[span],
            out.ray_indices[span] - first, *depth,
            robust=sparse_depth_robust if progress >= 0.25 else 0.0)
    if label_weight > 0:
        if click_labels is None:
            m = min(n_pixels, label_pixels)
            labelled, classes = slice(0, m * k), bank.labels[bank.last_pixels[:m]]
        else:
            first = (n_pixels + keypoints) * k
            labelled, classes = slice(first, first + clicks * k), click_labels
        probs = pixel_mean(render_labels(model.label_head, out, labelled), k)
        loss = loss + label_weight * label_loss(probs, classes)
    return loss, out, s


class Trainer:
    """Trains one model on one dataset into a run folder.

    The run folder holds ``config.json``, ``checkpoint.pt`` (model, optimiser, random state,
    step and training time; written durably, the one before kept as ``checkpoint.prev.pt``:
    :mod:`nerfbot.train.checkpoints`) and ``curve.json`` (test PSNR over time).
    """

    def __init__(self, dataset: Dataset, out_dir, config: TrainConfig,
                 evaluate_fn: Optional[Callable[[Model], dict]] = None,
                 command: Optional[list[str]] = None):
        config.validate()
        self.dataset, self.config = dataset, config
        self.command = command
        """The command line of this training session (``nerfbot`` and its arguments; a resume's
        replaces the first), kept in config.json beside the package versions."""
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.method = get_method(config.method)
        self.spec = model_spec(config, dataset)
        self.device = torch.device(config.device)
        torch.manual_seed(config.seed)
        self.model = build_from_spec(self.spec, self.device)
        self.model.use_run_loader(load_model)
        self.lr = config.lr if config.lr is not None else self.method.lr
        self.optimizer = self._make_optimizer()
        conditioning = Conditioning.from_dict(self.spec["conditioning"])
        conditions = frame_conditions(dataset, conditioning)
        train = dataset.indices("train")
        if self.model.training_time_limit(0.0) is not None:  # a time window: frames by time
            train = sorted(train, key=lambda i: float(conditions[i, 0]))
        self.bank = PixelBank(dataset, train, self.device, conditions)
        self.model.init_mean_color(self.bank.mean_color())
        self.model.init_ray_length(self.bank.median_ray_path(self.model.aabb))
        self.model.init_floor_share(self.bank.top_to_bottom_share(self.model.aabb))
        if conditioning.kind == "time" and config.dynamic_rays > 0:
            self._load_importance()
        if config.error_rays > 0:
            if self.bank.importance_fraction > 0:
                raise ValueError("error_rays and dynamic_rays both choose where rays go; set "
                                 "one of them to 0 (--error-rays / --dynamic-rays)")
            self.bank.enable_error_map(config.error_rays, config.error_tile,
                                       config.error_rays_debias)
            log.info("error rays: %.0f%% of each batch where the training error is high "
                     "(%d tiles of %d px)", 100 * config.error_rays, len(self.bank.error_map),
                     config.error_tile)
        if config.depth_weight > 0:
            self.bank.load_depths(config.depth_from)
        if config.labels:
            self._load_labels()
        if config.sparse_depth_weight > 0:
            count = self.bank.load_keypoints()
            log.info("sparse depth supervision: %d keypoints, %d keypoint pixels per step",
                     count, config.sparse_depth_rays)
        aabb = self.model.aabb
        self.depth_scale = float((aabb[1] - aabb[0]).max()) * math.sqrt(3.0)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.train_seconds = 0.0
        self.n_rays = self.model.rays_for_next_batch(None, 0)
        self.last_samples: Optional[int] = None
        self.curve: list[dict] = []
        self.scalars: list[dict] = []
        """Per-step scalars (:mod:`nerfbot.train.scalars`), written to ``scalars.csv``."""
        self._occupied: Optional[float] = None
        self.evaluate_fn = evaluate_fn

    def _load_importance(self) -> None:
        """Draw ``dynamic_rays`` of every batch where the training frames change over time
        (:func:`~nerfbot.data.importance.importance_weights`), when some camera films several
        of them."""
        weights, repeated = importance_weights(self.dataset, self.bank.frames.tolist())
        if not repeated or not float(weights.sum()) > 0.0:
            log.info("dynamic rays: no camera films several time steps with a change between "
                     "them; rays are drawn uniformly")
            return
        self.bank.set_importance(weights, self.config.dynamic_rays,
                                 self.config.dynamic_rays_debias)
        k = max(1, len(weights) // 20)
        top = np.partition(weights, len(weights) - k)[-k:]
        log.info("dynamic rays: %.0f%% of each batch where the images change over %d frames of "
                 "repeated cameras (the 5%% of pixels that change most hold %.0f%% of the "
                 "weight)", 100 * self.config.dynamic_rays, repeated,
                 100 * float(top.sum()) / float(weights.sum()))

    def _load_labels(self) -> None:
        """Give the pixel bank the training frames' label maps (full, or ``label_clicks``
        per class)."""
        c = self.config
        classes = LabelClasses.from_dict(self.spec["labels"])
        maps = label_maps(self.dataset, classes, self.bank.frames.tolist())
        if c.label_clicks is not None:
            maps = click_maps(maps, c.label_clicks, c.seed)
        count = self.bank.load_labels(maps, sparse=c.label_clicks is not None)
        log.info("labels: %d classes, %d labelled pixels%s", len(classes), count,
                 f" ({c.label_clicks} clicks per class)" if c.label_clicks else "")

    def _fused_adam(self) -> bool:
        """Whether torch's fused Adam kernel can update every parameter (floating point, on
        CPU or CUDA)."""
        return all(p.is_floating_point() and p.device.type in ("cpu", "cuda")
                   for p in self.model.parameters())

    def _make_optimizer(self) -> torch.optim.Optimizer:
        # the fused kernel updates each parameter in one pass over its four arrays; torch's
        # default (foreach) makes several, 8x slower on the 3.2 M parameters of ngp's tables
        return torch.optim.Adam(self.model.param_groups(), lr=self.lr, betas=(0.9, 0.99),
                                eps=self.method.adam_eps, fused=self._fused_adam())

    def optimizer_step(self) -> None:
        """One Adam step. The fused kernel writes the parameters without bumping their version
        counters, which caches of derived tensors (cast weights, packed links) key on: bump
        them here."""
        self.optimizer.step()
        if any(group.get("fused") for group in self.optimizer.param_groups):
            increment_version([p for group in self.optimizer.param_groups
                               for p in group["params"]])

    # -- state -------------------------------------------------------------------------------
    def state(self) -> dict:
        return {"spec": self.spec, "model": self.model.state_dict(),
                "optimizer": self.optimizer.state_dict(), "step": self.step,
                "train_seconds": self.train_seconds, "n_rays": self.n_rays,
                "last_samples": self.last_samples,
                "generator": self.generator.get_state(), "curve": self.curve,
                "config": asdict(self.config)}

    def save(self) -> Path:
        """Write the run's checkpoint durably (:func:`nerfbot.train.checkpoints.save_checkpoint`;
        the one before is kept as ``checkpoint.prev.pt``), ``curve.json`` and
        ``scalars.csv``."""
        path = save_checkpoint(self.state(), self.out / CHECKPOINT)
        write_json_atomic(self.out / "curve.json", self.curve, allow_nan=True)
        write_scalars(self.out / SCALARS, self.scalars)
        return path

    def load(self, path: Optional[Path] = None) -> bool:
        """Resume from ``path`` (default: the run's checkpoint; its previous checkpoint when it
        is missing or damaged); False if there is none.

        The checkpoint's spec is compared with this trainer's first (:func:`spec_differences`):
        any difference is a ValueError naming the run folder and each field, and nothing is
        changed, in memory or on disk. Then the model is built from the run's spec, takes the
        checkpoint's tensors, and stale temporary files of interrupted writes are removed."""
        path = Path(path) if path else self.out / CHECKPOINT
        found = load_checkpoint(path, RESUME_REQUIRED)
        if found is None:
            return False
        ckpt, used = found
        differences = spec_differences(ckpt["spec"], self.spec, self.dataset)
        if differences:
            raise ValueError(f"{self.out}: --resume with {'; '.join(differences)}; resume with "
                             "the run's options or train into a new --out")
        spec = {**self.spec, **ckpt["spec"], "dataset": self.spec["dataset"]}
        # equal within tolerances: the run's spec wins
        if canonical_text(spec) != canonical_text(self.spec):
            self._rebuild_model(spec)
        load_model_state(self.model, ckpt, used)
        try:
            self.optimizer = self._make_optimizer()  # over the (possibly resized) parameters
            self.optimizer.load_state_dict(ckpt["optimizer"])
            self.generator.set_state(ckpt["generator"])
        except (ValueError, RuntimeError, KeyError, TypeError) as err:
            raise CheckpointError(f"{used}: optimiser or random state does not fit the model: "
                                  f"{first_line(err)}") from None
        self.step, self.train_seconds = ckpt["step"], ckpt["train_seconds"]
        self.n_rays, self.curve = ckpt["n_rays"], ckpt["curve"]
        self.last_samples = ckpt["last_samples"]
        try:  # the steps up to the checkpoint's; a damaged table is started afresh
            self.scalars = read_scalars(self.out / SCALARS, up_to_step=self.step)
        except (ValueError, OSError, UnicodeDecodeError) as err:
            log.warning("%s; its per-step scalars start again at step %d", first_line(err),
                        self.step)
            self.scalars = []
        remove_stale_temporaries(path)
        return True

    def _rebuild_model(self, spec: dict) -> None:
        """Build the model from ``spec`` as :meth:`__init__` does (the optimiser is left to
        the caller)."""
        self.spec = spec
        torch.manual_seed(spec["seed"])
        self.model = build_from_spec(spec, self.device)
        self.model.use_run_loader(load_model)
        self.model.init_mean_color(self.bank.mean_color())
        self.model.init_ray_length(self.bank.median_ray_path(self.model.aabb))
        self.model.init_floor_share(self.bank.top_to_bottom_share(self.model.aabb))
        aabb = self.model.aabb
        self.depth_scale = float((aabb[1] - aabb[0]).max()) * math.sqrt(3.0)

    # -- loop --------------------------------------------------------------------------------
    def progress(self) -> float:
        c = self.config
        p = 0.0
        if c.max_steps:
            p = max(p, self.step / c.max_steps)
        if c.max_seconds:
            p = max(p, self.train_seconds / c.max_seconds)
        return p

    def done(self) -> bool:
        c = self.config
        return ((c.max_steps is not None and self.step >= c.max_steps)
                or (c.max_seconds is not None and self.train_seconds >= c.max_seconds))

    def _record(self) -> None:
        if self.evaluate_fn is None:
            return
        self.model.eval()
        metrics = self.evaluate_fn(self.model)
        self.model.train()
        entry = {"step": self.step, "train_seconds": round(self.train_seconds, 3), **metrics}
        self.curve.append(entry)
        log.info("eval at %.1fs / step %d: %s", self.train_seconds, self.step, metrics)

    def _check_finite_parameters(self) -> None:
        """Raise FloatingPointError if any parameter is NaN or inf. The loss check of every step
        catches a diverged model one step late; this catches the last step, before saving."""
        bad = [name for name, p in self.model.named_parameters() if not torch.isfinite(p).all()]
        if bad:
            raise FloatingPointError(
                f"non-finite parameters after step {self.step} ({', '.join(bad[:3])}); lower the "
                f"learning rate (now {self.optimizer.param_groups[0]['lr']:.2e})")

    def _depth_loss(self, out, supersample: int) -> torch.Tensor:
        """Mean L1 error of the expected z-depth of the last batch (with ``supersample`` squared
        rays per pixel, their mean), on its pixels with a valid depth, in cube diagonals (0 when
        none has one)."""
        gt = self.bank.depths[self.bank.last_pixels]
        z = pixel_mean(out.z_depth, supersample ** 2)[:len(gt)]  # keypoint pixels come last
        valid = torch.isfinite(gt)
        if not bool(valid.any()):
            return z.sum() * 0.0
        return (z[valid] - gt[valid]).abs().mean() / self.depth_scale

    def train(self, on_step: Optional[Callable[["Trainer"], None]] = None) -> dict:
        """Run until a budget is spent. ``on_step(trainer)`` is called after every step (tests
        use it to simulate interruptions). On KeyboardInterrupt a checkpoint is written first."""
        c = self.config
        remove_stale_temporaries(self.out / CHECKPOINT)
        warm_up_step(self.model, self.bank, self.step, self.progress())
        write_json_atomic(self.out / "config.json", {
            "train": asdict(c), **run_data_fields(self.dataset.root, self.out),
            "spec": self.spec, "command": self.command, "versions": package_versions()},
            allow_nan=True)
        pending_t = sorted(s for s in c.eval_at_seconds if s > self.train_seconds)
        pending_s = sorted(s for s in c.eval_at_steps if s > self.step)
        total = c.max_steps if c.max_steps is not None else None
        bar = tqdm(total=total, initial=self.step, disable=not c.progress, unit="step",
                   desc=f"train {c.method}", dynamic_ncols=True)
        last_ckpt = self.train_seconds
        loss_ema = None
        self.model.train()
        try:
            while not self.done():
                t0 = time.perf_counter()
                progress = self.progress()
                upkeep = self.model.before_step(self.step, self.generator, progress)
                self.bank.set_time_limit(self.model.training_time_limit(progress))
                if upkeep.pop("params_changed", False):
                    self.optimizer = self._make_optimizer()
                lr = learning_rate(self.lr, self.method.lr_final_factor, progress)
                for group in self.optimizer.param_groups:
                    group["lr"] = lr * group["lr_scale"]
                self.n_rays = self.model.rays_for_next_batch(self.last_samples, self.n_rays)
                loss, out, supersample = batch_loss(
                    self.model, self.bank, self.n_rays, self.generator, progress,
                    c.keypoint_pixels(progress), c.sparse_depth_weight,
                    c.label_weight if c.labels else 0.0, c.label_rays, c.sparse_depth_robust)
                if c.depth_weight > 0:
                    loss = loss + c.depth_weight * self._depth_loss(out, supersample)
                self.optimizer.zero_grad(set_to_none=True)
                if not torch.isfinite(loss):
                    raise FloatingPointError(
                        f"non-finite training loss at step {self.step}; lower the learning rate "
                        f"(now {self.optimizer.param_groups[0]['lr']:.2e})")
                loss.backward()
                self.optimizer_step()
                self.step += 1
                self.last_samples = out.num_samples
                step_seconds = time.perf_counter() - t0
                self.train_seconds += step_seconds
                loss_v = loss.detach().item()
                self._occupied = upkeep.get("occupied", self._occupied)
                self.scalars.append(step_row(self.step, self.train_seconds, loss_v, self.n_rays,
                                             out.num_samples, self._occupied, lr, step_seconds))
                loss_ema = loss_v if loss_ema is None else 0.9 * loss_ema + 0.1 * loss_v
                bar.update(1)
                if self.step % 10 == 0 or self.done():
                    post = {"loss": f"{loss_ema:.4f}",
                            "psnr": f"{-10 * math.log10(max(loss_ema, 1e-10)):.2f}",
                            "rays": self.n_rays,
                            "spr": f"{out.num_samples / max(self.n_rays, 1):.1f}",
                            "t": f"{self.train_seconds:.0f}s"}
                    if "occupied" in upkeep:
                        post["occ"] = f"{upkeep['occupied']:.3f}"
                    bar.set_postfix(post, refresh=False)
                if on_step is not None:
                    on_step(self)
                due = bool(pending_t and self.train_seconds >= pending_t[0]) or \
                    bool(pending_s and self.step >= pending_s[0])
                pending_t = [s for s in pending_t if s > self.train_seconds]
                pending_s = [s for s in pending_s if s > self.step]
                if due:  # one record even when a slow step passed several requested times
                    self._record()
                every = c.checkpoint_every_steps
                if not self.done() and (self.train_seconds - last_ckpt >= c.checkpoint_every_seconds
                                        or (every is not None and self.step % every == 0)):
                    self.save()  # the last one is written after the loop
                    last_ckpt = self.train_seconds
        except KeyboardInterrupt:
            bar.close()
            path = self.save()
            log.warning("interrupted at step %d; checkpoint %s (resume with --resume)", self.step, path)
            raise
        bar.close()
        self._check_finite_parameters()
        self.save()
        plot_scalars(self.out / "curve.png", self.scalars, self.curve,
                     title=f"{c.method}: {self.step} steps in {self.train_seconds:.0f} s")
        return {"steps": self.step, "train_seconds": self.train_seconds,
                "steps_per_second": self.step / max(self.train_seconds, 1e-9)}
