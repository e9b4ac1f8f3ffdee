"""The training loop: batches of random pixels, Adam, a decaying learning rate, budgets in
steps or seconds, atomic checkpoints and exact resume."""

from __future__ import annotations

import copy
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from tqdm.auto import tqdm

from nerfbot.cameras import Rays, pixel_rays
from nerfbot.checkpoints import (CHECKPOINT, RESUME_REQUIRED, CheckpointError, load_checkpoint,
                                 plain, remove_stale_temporaries, save_checkpoint)
from nerfbot.conditioning import Conditioning, dataset_conditioning, frame_conditions
from nerfbot.data.dataset import Dataset
from nerfbot.data.errors import DatasetError
from nerfbot.data.identity import dataset_identity, identity_mismatch
from nerfbot.data.run_dataset import run_data_fields
from nerfbot.data.writers import write_json_atomic
from nerfbot.methods import build_model, get_method
from nerfbot.models import Model, pixel_mean, resize_like_state_dict
from nerfbot.rendering import RenderOutput

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    method: str = "ngp"
    """Method name from :data:`nerfbot.methods.METHODS`."""
    max_steps: Optional[int] = None
    """Stop after this many optimisation steps (None: no step limit)."""
    max_seconds: Optional[float] = None
    """Stop when the training loop has run this long (wall clock; loading, compilation,
    checkpointing and evaluation excluded). At least one of the two budgets must be set."""
    seed: int = 0
    """Seeds parameters, batches and jitter. Runs with a step budget are deterministic on CPU."""
    lr: Optional[float] = None
    """Adam learning rate (None: the method's default)."""
    options: dict = field(default_factory=dict)
    """Method options (field / model config fields), e.g. {"log2_hashmap_size": 19}."""
    background: Optional[object] = None
    """"learned", "white", "black" or an RGB triple; None: what the dataset says."""
    checkpoint_every_seconds: float = 60.0
    """Write a checkpoint at least this often (training time; inf: only at the end)."""
    checkpoint_every_steps: Optional[int] = None
    """Also write a checkpoint after every step that is a multiple of this (None: no step
    cadence). Checkpoints at fixed steps make interrupted runs reproducible."""
    eval_at_seconds: tuple = ()
    """Training times (s) at which to pause the clock and record test PSNR (a learning curve)."""
    eval_at_steps: tuple = ()
    """Steps at which to record test PSNR."""
    depth_weight: float = 0.0
    """Depth supervision (as DS-NeRF, for RGB-D captures): weight of the L1 error of the rendered
    expected z-depth against the dataset's depth maps, in units of the scene cube's diagonal,
    on training pixels whose depth is finite and inside the bounds. 0 = RGB only."""
    device: str = "cpu"
    """torch device; the fast kernels are CPU kernels, other devices use the torch twins
    (``NERFBOT_KERNELS=torch`` forces the twins on the CPU too: :mod:`nerfbot.kernels`)."""
    progress: bool = True
    """Show a progress bar."""

    def validate(self) -> None:
        recipe = get_method(self.method).baked_from
        if recipe is not None:
            raise ValueError(f"method {self.method!r} is baked, not trained: train "
                             f"--method {recipe.source}, then run `nerfbot bake` on that run")
        if self.max_steps is None and self.max_seconds is None:
            raise ValueError("set a training budget: max_steps and/or max_seconds")
        if self.max_steps is not None and self.max_steps < 0:
            raise ValueError(f"max_steps must be >= 0, got {self.max_steps}")
        if self.max_seconds is not None and not self.max_seconds >= 0:
            raise ValueError(f"max_seconds must be >= 0, got {self.max_seconds}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.lr is not None and not 0.0 < self.lr < math.inf:
            raise ValueError(f"lr must be positive and finite, got {self.lr}")
        if not 0.0 <= self.depth_weight < math.inf:
            raise ValueError(f"depth_weight must be >= 0 and finite, got {self.depth_weight}")
        if not self.checkpoint_every_seconds >= 0:
            raise ValueError(f"checkpoint_every_seconds must be >= 0, got "
                             f"{self.checkpoint_every_seconds}")
        if self.checkpoint_every_steps is not None and self.checkpoint_every_steps < 1:
            raise ValueError(f"checkpoint_every_steps must be >= 1, got "
                             f"{self.checkpoint_every_steps}")


class ValidPixels:
    """Uniform draws among the valid pixels of a flat (P,) validity mask, stored compactly.

    Holds whichever is shorter: the valid pixel indices (a draw is a lookup), or the invalid
    ones as ``skip[j] = invalid[j] - j``, the count of valid pixels before the j-th invalid one
    (the r-th valid pixel is then ``r + #{j : skip[j] <= r}``). Either costs 4 bytes per entry
    (8 beyond 2^31 pixels), so an undistortion border of a few percent costs almost nothing.
    """

    def __init__(self, valid: np.ndarray, device="cpu"):
        valid = np.asarray(valid, dtype=bool).reshape(-1)
        self.count = int(valid.sum())
        """V, the number of valid pixels."""
        dtype = np.int32 if valid.size < 2**31 else np.int64
        invalid = np.flatnonzero(~valid)
        self.valid = self.skip = None
        if invalid.size <= self.count:
            skip = invalid - np.arange(invalid.size)
            self.skip = torch.from_numpy(skip.astype(dtype)).to(device)
        else:
            self.valid = torch.from_numpy(np.flatnonzero(valid).astype(dtype)).to(device)

    def __len__(self) -> int:
        return self.count

    def pixel(self, rank: torch.Tensor) -> torch.Tensor:
        """(n,) int64 pixel indices of the valid pixels of (n,) ranks in [0, V)."""
        if self.valid is not None:
            return self.valid[rank].long()
        r = rank.to(self.skip.dtype)
        return rank.long() + torch.searchsorted(self.skip, r, right=True)


class PixelBank:
    """All pixels of a set of frames, for drawing random training rays.

    Colours are stored flat as uint8 (P, 3); a pixel index maps to (frame, row, column) through
    per-frame offsets, so mixed image sizes work and rays are built only for drawn pixels.
    Pixels the dataset's masks mark invalid (``Dataset.masks``: ``mask_path`` or outside an
    undistorted image) are never drawn; without masks, draws are exactly those of an unmasked
    bank (one ``torch.randint`` over all pixels).
    """

    def __init__(self, dataset: Dataset, indices: list[int], device="cpu",
                 conditions: Optional[np.ndarray] = None):
        if not indices:
            raise DatasetError(f"{dataset.root}: the training split is empty; training needs "
                               f"at least one frame in 'train' (splits: {dataset.split_sizes()})")
        self.device = torch.device(device)
        self.frames = torch.as_tensor(indices, dtype=torch.long)
        self.cameras = dataset.cameras(indices).to(device)
        self.pixels = torch.from_numpy(
            np.concatenate([dataset.images[i].reshape(-1, 3) for i in indices])).to(device)
        counts = torch.as_tensor([dataset.images[i].shape[0] * dataset.images[i].shape[1]
                                  for i in indices], dtype=torch.long)
        self.offsets = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(counts, 0)]).to(device)
        self.valid = self._valid_pixels(dataset, indices)
        """The drawable pixels when some frame has a mask, else None (every pixel)."""
        self.depths: Optional[torch.Tensor] = None
        """(P,) float32 z-depth of every pixel (NaN: unknown, outside the bounds or masked out),
        loaded by :meth:`load_depths` for depth supervision."""
        self._dataset, self._indices = dataset, list(indices)
        self.last_pixels: Optional[torch.Tensor] = None
        """(n,) pixel indices of the last :meth:`sample`."""
        self.conds = None if conditions is None else \
            torch.as_tensor(conditions[indices], dtype=torch.float32, device=device)
        """(frames, C) condition vector of each frame (time or joints), None when static."""

    def _valid_pixels(self, dataset: Dataset, indices: list[int]) -> Optional[ValidPixels]:
        masks = [dataset.valid_mask(i) for i in indices]
        if all(m is None for m in masks):
            return None
        flat = np.concatenate([np.ones(dataset.images[i].shape[:2], bool).reshape(-1) if m is None
                               else np.asarray(m, bool).reshape(-1)
                               for i, m in zip(indices, masks)])
        valid = ValidPixels(flat, self.device)
        if not len(valid):
            raise DatasetError(f"{dataset.root}: every pixel of the {len(indices)} training "
                               "frame(s) is masked out (mask_path, or outside the undistorted "
                               "image); nothing to train on")
        return valid

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def mean_color(self) -> torch.Tensor:
        """(3,) mean colour of all valid pixels, in [0, 1]."""
        if self.valid is None:
            return self.pixels.float().mean(0) / 255.0
        rank = torch.arange(len(self.valid), device=self.device)
        total = torch.zeros(3, dtype=torch.float64, device=self.device)
        for chunk in rank.split(1 << 20):
            total += self.pixels[self.valid.pixel(chunk)].double().sum(0)
        return (total / len(self.valid) / 255.0).float()

    def load_depths(self) -> None:
        """Keep the depth of every pixel (for depth supervision), NaN where
        :func:`~nerfbot.evaluation.depth_valid_mask` is False (masked pixels included);
        ValueError naming the frames without depth."""
        from nerfbot.evaluation import depth_valid_mask

        missing = [self._dataset.file_paths[i] for i in self._indices
                   if self._dataset.depths[i] is None]
        if missing:
            raise ValueError(f"{self._dataset.root}: depth supervision needs a depth map for every "
                             f"training frame; {len(missing)} have none (e.g. {missing[0]})")
        maps = []
        for i in self._indices:
            d = np.asarray(self._dataset.depths[i], dtype=np.float32).copy()
            d[~depth_valid_mask(self._dataset, i)] = np.nan
            maps.append(d.reshape(-1))
        self.depths = torch.from_numpy(np.concatenate(maps)).to(self.device)

    def sample(self, n: int, generator: torch.Generator, supersample: int = 1
               ) -> tuple[Rays, torch.Tensor, torch.Tensor]:
        """``n`` random pixels: their rays, colours (n, 3) float32 in [0, 1], frame slots (n,).
        Their pixel indices are kept in :attr:`last_pixels`; masked-out pixels are never drawn.

        With ``supersample`` S = 1 the rays go through the pixel centres: (n,) rays. With S > 1
        each pixel gets S x S rays, one through a uniformly random point of each cell of an
        S x S grid over the pixel (stratified): (n * S * S,) rays, pixel after pixel."""
        if self.valid is None:
            p = torch.randint(len(self), (n,), generator=generator).to(self.device)
        else:
            p = self.valid.pixel(torch.randint(len(self.valid), (n,), generator=generator)
                                 .to(self.device))
        self.last_pixels = p
        slot = torch.searchsorted(self.offsets[1:], p, right=True)
        local = p - self.offsets[slot]
        w = self.cameras.width[slot]
        v, u = local // w, local % w
        cam = self.cameras
        if supersample == 1:
            px, py, ray_slot = u.float() + 0.5, v.float() + 0.5, slot
        else:
            k = supersample * supersample
            cell = torch.arange(k, device=self.device)
            jitter = torch.rand((n, k, 2), generator=generator).to(self.device)
            px = (u[:, None] + ((cell % supersample)[None] + jitter[..., 0]) / supersample)
            py = (v[:, None] + ((cell // supersample)[None] + jitter[..., 1]) / supersample)
            px, py = px.reshape(-1).float(), py.reshape(-1).float()
            ray_slot = slot.repeat_interleave(k)
        rays = pixel_rays(cam.c2w[ray_slot], cam.fx[ray_slot], cam.fy[ray_slot],
                          cam.cx[ray_slot], cam.cy[ray_slot], px, py,
                          1.0 / supersample, 1.0 / supersample)
        return rays, self.pixels[p].float() / 255.0, slot


def learning_rate(base: float, final_factor: float, progress: float) -> float:
    """Exponential decay from ``base`` to ``base * final_factor`` as progress goes 0 -> 1."""
    return base * final_factor ** min(max(progress, 0.0), 1.0)


def model_spec(config: TrainConfig, dataset: Dataset) -> dict:
    """Everything needed to rebuild the model without the dataset (stored in checkpoints), and
    the identity of the dataset it is trained on
    (:func:`nerfbot.data.identity.dataset_identity`)."""
    background = config.background if config.background is not None else dataset.background
    return {"method": config.method, "aabb": np.asarray(dataset.aabb, float).tolist(),
            "background": background, "options": dict(config.options), "seed": config.seed,
            "conditioning": dataset_conditioning(dataset).to_dict(),
            "dataset": dataset_identity(dataset)}


def build_from_spec(spec: dict, device="cpu") -> Model:
    return build_model(spec["method"], spec["aabb"], spec["background"], spec["options"],
                       spec["seed"], Conditioning.from_dict(spec.get("conditioning"))).to(device)


#: Relative tolerance of the bounds comparison on resume (float64 JSON round trips).
AABB_RTOL = 1e-9


def _shown(value) -> str:
    return value if isinstance(value, str) else json.dumps(plain(value))


def _canonical(value) -> str:
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
            if _canonical(requested[key]) != _canonical(stored[key]):
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
    if _canonical(now.to_dict()) != _canonical(then.to_dict()):
        shown = [c.kind + "".join(f" {n}" for n in c.names) for c in (now, then)]
        if shown[0] == shown[1]:
            shown[0] += " (other ranges or joint kinematics)"
        out.append(f"conditioning {shown[0]}, but the run was made with {shown[1]}")
    if requested["seed"] != stored["seed"]:
        out.append(f"seed {requested['seed']}, but the run was made with {stored['seed']}")
    other = identity_mismatch(stored.get("dataset"), dataset)
    if other is not None:
        out.append(f"another dataset ({dataset.root}: {other})")
    return out


def _load_model_state(model: Model, ckpt: dict, path: Path) -> None:
    """Resize ``model``'s tensors to the checkpoint's and load them; CheckpointError naming
    ``path`` when they do not fit the model its spec builds."""
    try:
        resize_like_state_dict(model, ckpt["model"])
        model.load_state_dict(ckpt["model"])
    except (ValueError, RuntimeError, KeyError, AttributeError) as err:
        raise CheckpointError(f"{path}: the model tensors do not fit method "
                              f"{ckpt['spec']['method']!r}: {_first_line(err)}") from None


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


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


def batch_loss(model: Model, bank: "PixelBank", n_rays: int, generator: torch.Generator,
               progress: float) -> tuple[torch.Tensor, RenderOutput, int]:
    """The loss of a batch of about ``n_rays`` random training rays at ``progress`` of the
    budget: S x S rays per pixel (S = ``model.training_supersample(progress)``), whose
    colours the model averages before comparing them with the pixel's (a pixel's colour is the
    mean over its area, as a renderer's anti-aliasing or a camera's sensor makes it).
    Returns the loss, the rays' render output and S."""
    s = model.training_supersample(progress)
    k = s * s
    rays, target, slot = bank.sample(max(1, n_rays // k), generator, s)
    cond = None if bank.conds is None else bank.conds[slot].repeat_interleave(k, 0)
    return (*model.loss(rays, target, generator, cond, rays_per_pixel=k), s)


class Trainer:
    """Trains one model on one dataset into a run folder.

    The run folder holds ``config.json``, ``checkpoint.pt`` (model, optimiser, random state,
    step and training time; written durably, the one before kept as ``checkpoint.prev.pt``:
    :mod:`nerfbot.checkpoints`) and ``curve.json`` (test PSNR over time).
    """

    def __init__(self, dataset: Dataset, out_dir, config: TrainConfig,
                 evaluate_fn: Optional[Callable[[Model], dict]] = None):
        config.validate()
        self.dataset, self.config = dataset, config
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.method = get_method(config.method)
        self.spec = model_spec(config, dataset)
        self.device = torch.device(config.device)
        torch.manual_seed(config.seed)
        self.model = build_from_spec(self.spec, self.device)
        self.lr = config.lr if config.lr is not None else self.method.lr
        self.optimizer = self._make_optimizer()
        conditioning = Conditioning.from_dict(self.spec["conditioning"])
        self.bank = PixelBank(dataset, dataset.indices("train"), self.device,
                              frame_conditions(dataset, conditioning))
        self.model.init_mean_color(self.bank.mean_color())
        if config.depth_weight > 0:
            self.bank.load_depths()
        aabb = self.model.aabb
        self.depth_scale = float((aabb[1] - aabb[0]).max()) * math.sqrt(3.0)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.step = 0
        self.train_seconds = 0.0
        self.n_rays = self.model.rays_for_next_batch(None, 0)
        self.last_samples: Optional[int] = None
        self.curve: list[dict] = []
        self.evaluate_fn = evaluate_fn

    def _make_optimizer(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.model.param_groups(), lr=self.lr, betas=(0.9, 0.99),
                                eps=self.method.adam_eps)

    # -- state -------------------------------------------------------------------------------
    def state(self) -> dict:
        return {"spec": self.spec, "model": self.model.state_dict(),
                "optimizer": self.optimizer.state_dict(), "step": self.step,
                "train_seconds": self.train_seconds, "n_rays": self.n_rays,
                "last_samples": self.last_samples,
                "generator": self.generator.get_state(), "curve": self.curve,
                "config": asdict(self.config)}

    def save(self) -> Path:
        """Write the run's checkpoint durably (:func:`nerfbot.checkpoints.save_checkpoint`;
        the one before is kept as ``checkpoint.prev.pt``) and ``curve.json``."""
        path = save_checkpoint(self.state(), self.out / CHECKPOINT)
        write_json_atomic(self.out / "curve.json", self.curve, allow_nan=True)
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
        if _canonical(spec) != _canonical(self.spec):  # equal within tolerances: the run's wins
            self._rebuild_model(spec)
        _load_model_state(self.model, ckpt, used)
        try:
            self.optimizer = self._make_optimizer()  # over the (possibly resized) parameters
            self.optimizer.load_state_dict(ckpt["optimizer"])
            self.generator.set_state(ckpt["generator"])
        except (ValueError, RuntimeError, KeyError, TypeError) as err:
            raise CheckpointError(f"{used}: optimiser or random state does not fit the model: "
                                  f"{_first_line(err)}") from None
        self.step, self.train_seconds = ckpt["step"], ckpt["train_seconds"]
        self.n_rays, self.curve = ckpt["n_rays"], ckpt["curve"]
        self.last_samples = ckpt["last_samples"]
        remove_stale_temporaries(path)
        return True

    def _rebuild_model(self, spec: dict) -> None:
        """Build the model from ``spec`` as :meth:`__init__` does (the optimiser is left to
        the caller)."""
        self.spec = spec
        torch.manual_seed(spec["seed"])
        self.model = build_from_spec(spec, self.device)
        self.model.init_mean_color(self.bank.mean_color())
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
        z = pixel_mean(out.z_depth, supersample ** 2)
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
            "spec": self.spec}, allow_nan=True)
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
                if upkeep.pop("params_changed", False):
                    self.optimizer = self._make_optimizer()
                lr = learning_rate(self.lr, self.method.lr_final_factor, progress)
                for group in self.optimizer.param_groups:
                    group["lr"] = lr * group["lr_scale"]
                self.n_rays = self.model.rays_for_next_batch(self.last_samples, self.n_rays)
                loss, out, supersample = batch_loss(
                    self.model, self.bank, self.n_rays, self.generator, progress)
                if c.depth_weight > 0:
                    loss = loss + c.depth_weight * self._depth_loss(out, supersample)
                self.optimizer.zero_grad(set_to_none=True)
                if not torch.isfinite(loss):
                    raise FloatingPointError(
                        f"non-finite training loss at step {self.step}; lower the learning rate "
                        f"(now {self.optimizer.param_groups[0]['lr']:.2e})")
                loss.backward()
                self.optimizer.step()
                self.step += 1
                self.last_samples = out.num_samples
                self.train_seconds += time.perf_counter() - t0
                loss_v = loss.detach().item()
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
        return {"steps": self.step, "train_seconds": self.train_seconds,
                "steps_per_second": self.step / max(self.train_seconds, 1e-9)}


def load_model(run_dir, device="cpu") -> tuple[Model, dict]:
    """Load a trained model from a run folder; returns (model in eval mode, checkpoint info).

    The checkpoint is read as tensors and plain data only (a crafted file is refused, never
    run); a damaged ``checkpoint.pt`` falls back to ``checkpoint.prev.pt``
    (:func:`nerfbot.checkpoints.load_checkpoint`). FileNotFoundError when the run has no
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
                              f"{_first_line(err)}") from None
    _load_model_state(model, ckpt, used)
    model.eval()
    info = {k: ckpt[k] for k in ("spec", "step", "train_seconds", "curve", "config")}
    return model, info
