"""Training pixels of a dataset: uniform draws among the valid pixels of every training frame,
some optionally drawn by importance weights (:class:`PixelBank`), as rays with their colours,
and which ground-truth depths are usable (:func:`depth_valid_mask`).
"""

from __future__ import annotations

import logging
from typing import Optional

import numpy as np
import torch

from nerfbot.data.dataset import Dataset
from nerfbot.data.error_map import ErrorMap
from nerfbot.data.errors import DatasetError
from nerfbot.ops.cameras import Rays, pixel_rays
from nerfbot.ops.sampling import crosses_top_to_bottom, ray_aabb


log = logging.getLogger(__name__)


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
        self._sorted = None
        """The listed indices (valid or invalid, sorted) as int64, for :meth:`contains`."""
        if invalid.size <= self.count:
            skip = invalid - np.arange(invalid.size)
            self.skip = torch.from_numpy(skip.astype(dtype)).to(device)
        else:
            self.valid = torch.from_numpy(np.flatnonzero(valid).astype(dtype)).to(device)

    def __len__(self) -> int:
        return self.count

    def contains(self, pixels: torch.Tensor) -> torch.Tensor:
        """(n,) bool: which of the flat pixel indices ``pixels`` (n,) are valid."""
        if self._sorted is None:  # built on the first call (error-map sampling's upkeep)
            self._sorted = self.valid.long() if self.valid is not None else \
                self.skip.long() + torch.arange(len(self.skip), device=self.skip.device)
        listed, listed_valid = self._sorted, self.valid is not None
        if not len(listed):
            return torch.full_like(pixels, not listed_valid, dtype=torch.bool)
        at = torch.searchsorted(listed, pixels).clamp_(max=len(listed) - 1)
        return (listed[at] == pixels) == listed_valid

    def count_below(self, pixel: int) -> int:
        """How many valid pixels have a flat index below ``pixel``."""
        if self.valid is not None:
            return int(torch.searchsorted(self.valid.long(), torch.tensor([pixel],
                                          device=self.valid.device)))
        invalid = self.skip.long() + torch.arange(len(self.skip), device=self.skip.device)
        return pixel - int(torch.searchsorted(invalid, torch.tensor([pixel],
                                              device=invalid.device)))

    def pixel(self, rank: torch.Tensor) -> torch.Tensor:
        """(n,) int64 pixel indices of the valid pixels of (n,) ranks in [0, V)."""
        if self.valid is not None:
            return self.valid[rank].long()
        r = rank.to(self.skip.dtype)
        return rank.long() + torch.searchsorted(self.skip, r, right=True)


#: Where depth supervision comes from (:meth:`PixelBank.load_depths`): each frame's field of
#: that name, ``depth_file_path`` or ``sensor_depth_file_path``.
DEPTH_SOURCES = {"depth": "depth_file_path", "sensor_depth": "sensor_depth_file_path"}


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
        self.keypoints: Optional[torch.Tensor] = None
        """(K, 4) float32 sparse depth of the training frames (u, v, z, sigma), loaded by
        :meth:`load_keypoints`; :attr:`keypoint_slots` (K,) their frame slots."""
        self.keypoint_slots: Optional[torch.Tensor] = None
        self.depths: Optional[torch.Tensor] = None
        """(P,) float32 z-depth of every pixel (NaN: unknown, outside the bounds or masked out),
        loaded by :meth:`load_depths` for depth supervision."""
        self.labels: Optional[torch.Tensor] = None
        """(P,) int64 class of every pixel (-1: none), loaded by :meth:`load_labels`."""
        self.clicks: Optional[torch.Tensor] = None
        """(C,) pixel indices of the labelled pixels when labels are sparse (iLabel's clicks),
        else None."""
        self._dataset, self._indices = dataset, list(indices)
        self.last_pixels: Optional[torch.Tensor] = None
        """(n,) pixel indices of the last :meth:`sample`."""
        self._importance: Optional[torch.Tensor] = None
        self._importance_cdf: Optional[torch.Tensor] = None
        self.importance_fraction = 0.0
        """Fraction of each :meth:`sample` drawn by :meth:`set_importance`'s weights."""
        self.importance_debias = 1.0
        """How much of the importance draws' bias :attr:`last_weights` undo (see
        :meth:`set_importance`)."""
        self.last_weights: Optional[torch.Tensor] = None
        """(n,) float32 loss weights of the last :meth:`sample`'s pixels that undo the bias of
        importance draws (None without them): see :meth:`set_importance`."""
        self.last_slots: Optional[torch.Tensor] = None
        """(n,) frame slots of the last :meth:`sample`'s pixels."""
        self.error_map: Optional[ErrorMap] = None
        """The running training error that draws :attr:`importance_fraction` of every batch
        (:meth:`enable_error_map`), or None."""
        self.conds = None if conditions is None else \
            torch.as_tensor(conditions[indices], dtype=torch.float32, device=device)
        """(frames, C) condition vector of each frame (time or joints), None when static."""
        self.time_limit: Optional[float] = None
        """The latest frame time :meth:`sample` draws from (:meth:`set_time_limit`), or None."""
        self._drawable_end: Optional[int] = None
        """With a time limit, the end of the flat pixel range the limit keeps (its frames are
        the first ones), else None."""

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

    def load_depths(self, source: str = "depth") -> None:
        """Keep the depth of every pixel (for depth supervision), NaN where
        :func:`~nerfbot.data.pixels.depth_valid_mask` is False (masked pixels included) or the
        map has no reading. ``source``: "depth" (``Dataset.depths``) or "sensor_depth"
        (``Dataset.sensor_depths``, a simulated sensor's reading). ValueError naming the
        frames without such a map."""
        if source not in DEPTH_SOURCES:
            raise ValueError(f"depth source must be one of {sorted(DEPTH_SOURCES)}, got "
                             f"{source!r}")
        maps_of = self._dataset.depths if source == "depth" else self._dataset.sensor_depths
        field = DEPTH_SOURCES[source]
        missing = [self._dataset.file_paths[i] for i in self._indices
                   if i >= len(maps_of) or maps_of[i] is None]
        if missing:
            raise ValueError(f"{self._dataset.root}: depth supervision needs a depth map "
                             f"(frames[].{field}) for every training frame; {len(missing)} "
                             f"have none (e.g. {missing[0]})")
        maps = []
        for i in self._indices:
            d = np.asarray(maps_of[i], dtype=np.float32).copy()
            d[~depth_valid_mask(self._dataset, i, d)] = np.nan
            maps.append(d.reshape(-1))
        self.depths = torch.from_numpy(np.concatenate(maps)).to(self.device)

    def load_keypoints(self) -> int:
        """Keep the training frames' sparse depth (:attr:`Dataset.keypoints`) for
        :meth:`sample_keypoints`; returns their count. ValueError when no training frame has
        any."""
        rows, slots = [], []
        for slot, i in enumerate(self._indices):
            keys = self._dataset.keypoints[i] if i < len(self._dataset.keypoints) else None
            if keys is not None and len(keys):
                rows.append(np.asarray(keys, dtype=np.float32))
                slots.append(np.full(len(keys), slot, dtype=np.int64))
        if not rows:
            raise ValueError(f"{self._dataset.root}: sparse depth supervision needs keypoints "
                             "(frames[].sparse_depth_file_path, written by nerfbot colmap) in "
                             "the training frames; none has any")
        self.keypoints = torch.from_numpy(np.concatenate(rows)).to(self.device)
        self.keypoint_slots = torch.from_numpy(np.concatenate(slots)).to(self.device)
        return len(self.keypoints)

    def load_labels(self, maps: list[np.ndarray], sparse: bool = False) -> int:
        """Keep the class of every pixel of the training frames, ``maps`` (one (H, W) label
        map per training frame, in order, -1 = unlabelled: :mod:`nerfbot.data.labels`). With
        ``sparse`` (a few clicks) the labelled pixels are also listed for
        :meth:`sample_clicks`. Returns the number of labelled pixels; ValueError when there is
        none."""
        if len(maps) != len(self._indices):
            raise ValueError(f"{len(maps)} label maps for {len(self._indices)} training frames")
        flat = np.concatenate([np.asarray(m).reshape(-1) for m in maps]).astype(np.int64)
        if flat.shape[0] != len(self):
            raise ValueError("label maps do not match the training images' sizes")
        labelled = int((flat >= 0).sum())
        if not labelled:
            raise ValueError(f"{self._dataset.root}: no training pixel has a label")
        self.labels = torch.from_numpy(flat).to(self.device)
        self.clicks = torch.from_numpy(np.flatnonzero(flat >= 0)).to(self.device) \
            if sparse else None
        return labelled

    def add_clicks(self, pixels: torch.Tensor, classes: torch.Tensor) -> None:
        """Label more pixels of sparse labels (:meth:`load_labels` with ``sparse``): pixel
        indices ``pixels`` (n,) get classes ``classes`` (n,) and join :attr:`clicks`."""
        if self.clicks is None:
            raise ValueError("add_clicks needs sparse labels (load_labels(..., sparse=True))")
        pixels = pixels.to(self.device)
        self.labels[pixels] = classes.to(self.device, self.labels.dtype)
        self.clicks = torch.cat([self.clicks, pixels])

    def median_ray_path(self, aabb, rays: int = 1 << 14) -> Optional[float]:
        """Median length, metres, of the training rays' paths through the box ``aabb`` (2, 3):
        over the centre rays of ``rays`` pixels spread evenly through the bank (no random
        draws), those that meet the box; None when none does."""
        r = self._spread_centre_rays(rays)
        box = torch.as_tensor(aabb, dtype=r.origins.dtype, device=r.origins.device)
        t_near, t_far, hit = ray_aabb(r.origins, r.directions, box)
        if not bool(hit.any()):
            return None
        return float((t_far - t_near)[hit].median())

    def top_to_bottom_share(self, aabb, rays: int = 1 << 14) -> float:
        """Share in [0, 1] of the training rays that cross the box ``aabb`` (2, 3) from its
        top face to its bottom face (:func:`~nerfbot.ops.sampling.crosses_top_to_bottom`),
        over the centre rays of ``rays`` pixels spread evenly through the bank: near 1 when
        the cameras look down on a support that fills the box's footprint."""
        r = self._spread_centre_rays(rays)
        box = torch.as_tensor(aabb, dtype=r.origins.dtype, device=r.origins.device)
        t_near, t_far, hit = ray_aabb(r.origins, r.directions, box)
        crossing = crosses_top_to_bottom(r.origins, r.directions, t_near, t_far, hit, box)
        return float(crossing.float().mean())

    def _spread_centre_rays(self, rays: int) -> Rays:
        """The centre rays of ``rays`` pixels spread evenly through the bank (no random draws)."""
        count = len(self) if self.valid is None else len(self.valid)
        rank = torch.linspace(0, count - 1, min(rays, count), device=self.device).long()
        pixels = rank if self.valid is None else self.valid.pixel(rank)
        return self.centre_rays(pixels)

    def centre_rays(self, pixels: torch.Tensor) -> Rays:
        """Rays (n,) through the centres of pixels ``pixels`` (n,) (indices into the bank)."""
        slot = torch.searchsorted(self.offsets[1:], pixels, right=True)
        return self._pixel_rays(pixels, slot, None, 1)[0]

    def sample_clicks(self, n: int, generator: torch.Generator, supersample: int = 1,
                      balanced: bool = False
                      ) -> tuple[Rays, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` random draws (with repetition) among the labelled pixels of sparse labels
        (:meth:`load_labels`): rays (n * S * S,), colours (n, 3), frame slots (n,) and
        classes (n,), as :meth:`sample` gives them. ``balanced``: every class drawn equally
        often, however many clicks it has."""
        if balanced:
            classes = self.labels[self.clicks]
            weights = 1.0 / torch.bincount(classes)[classes].double()
            pick = torch.multinomial(weights.cpu(), n, replacement=True,
                                     generator=generator).to(self.device)
        else:
            pick = torch.randint(len(self.clicks), (n,), generator=generator).to(self.device)
        p = self.clicks[pick]
        slot = torch.searchsorted(self.offsets[1:], p, right=True)
        rays, colours = self._pixel_rays(p, slot, generator, supersample)
        return rays, colours, slot, self.labels[p]

    def sample_keypoints(self, n: int, generator: torch.Generator, supersample: int = 1
                         ) -> tuple[Rays, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``n`` random keypoints (:meth:`load_keypoints` first), as training pixels: the pixel
        holding each keypoint gives its rays (n * S * S, as :meth:`sample`), colour (n, 3) and
        frame slot (n,), and every ray the keypoint's distance along it and that distance's
        standard deviation (n * S * S,) metres (the z-depth over the ray's cosine: the rays of
        one pixel are a fraction of a pixel apart)."""
        pick = torch.randint(len(self.keypoints), (n,), generator=generator).to(self.device)
        keys, slot = self.keypoints[pick], self.keypoint_slots[pick]
        w = self.cameras.width[slot]
        col = keys[:, 0].long().clamp(min=0).minimum(w - 1)
        row = keys[:, 1].long().clamp(min=0).minimum(self.cameras.height[slot] - 1)
        p = self.offsets[slot] + row * w + col
        rays, colours = self._pixel_rays(p, slot, generator, supersample)
        k = supersample * supersample
        z, sigma = keys[:, 2].repeat_interleave(k), keys[:, 3].repeat_interleave(k)
        return rays, colours, slot, z / rays.z_per_t, sigma / rays.z_per_t

    def set_importance(self, weights: np.ndarray, fraction: float, debias: float = 1.0) -> None:
        """Draw ``fraction`` of every :meth:`sample` with probability proportional to
        ``weights`` (P,) >= 0 (e.g. :func:`~nerfbot.data.importance.importance_weights`), the
        rest uniformly. Masked-out pixels weigh 0 whatever ``weights`` says; ValueError when
        nothing is left to weigh.

        A pixel is then drawn with probability q = (1 - f) / V + f w / W (V drawable pixels,
        W the weights' sum, f = ``fraction``) instead of 1 / V, and :attr:`last_weights` holds
        ((1 / V) / q) ** ``debias`` for each drawn pixel. With ``debias`` 1 a loss weighted by
        it has the expectation of a uniform batch's (for f < 1): the static scene is trained
        as much as before and the pixels that change get many more, less noisy, samples of
        the same total weight. With 0 (DyNeRF's) the changing pixels also weigh more in the
        loss; in between, partly."""
        w = torch.as_tensor(np.asarray(weights), dtype=torch.float64).reshape(-1)
        if w.shape[0] != len(self):
            raise ValueError(f"importance weights: expected {len(self)} pixels, got {w.shape[0]}")
        if not bool(torch.isfinite(w).all()) or bool((w < 0).any()):
            raise ValueError("importance weights must be finite and >= 0")
        self._check_draw_settings(fraction, debias)
        if self.error_map is not None:
            raise ValueError("importance weights and an error map both draw rays; use one")
        if self.valid is not None:
            keep = torch.zeros_like(w, dtype=torch.bool)
            rank = torch.arange(len(self.valid))
            for chunk in rank.split(1 << 20):
                keep[self.valid.pixel(chunk)] = True
            w = torch.where(keep, w, torch.zeros_like(w))
        if not float(w.sum()) > 0.0:
            raise ValueError("importance weights are zero on every drawable pixel")
        self._importance = w.float().to(self.device)
        self._importance_cdf = torch.cumsum(w, 0).to(self.device)
        self.importance_fraction = float(fraction)
        self.importance_debias = float(debias)

    def set_time_limit(self, limit: Optional[float]) -> None:
        """Let :meth:`sample` draw only pixels of frames whose time (the conditions' first
        column) is at most ``limit``; None: every frame. The frames must be in order of time
        (build the bank from time-sorted indices) and at least the first must be kept.
        Importance draws keep their weights' proportions within the kept frames; keypoints and
        clicks are drawn from every frame."""
        if limit == self.time_limit:
            return
        if limit is None:
            self.time_limit = self._drawable_end = None
            return
        if self.conds is None or self.conds.shape[1] != 1:
            raise ValueError("a time limit needs a time-conditioned bank (one condition column)")
        if self.error_map is not None:
            raise ValueError("a time limit and an error map cannot both choose the training "
                             "rays; set --error-rays 0")
        times = self.conds[:, 0]
        if bool((times[1:] < times[:-1]).any()):
            raise ValueError("a time limit needs the bank's frames in order of time")
        kept = int(torch.searchsorted(times, torch.tensor([float(limit)], device=times.device),
                                      right=True))
        if kept == 0:
            raise ValueError(f"time limit {limit} keeps no frame (the first is at "
                             f"{float(times[0]):.4g})")
        self.time_limit = float(limit)
        self._drawable_end = None if kept == len(times) else int(self.offsets[kept])

    def _drawable(self) -> int:
        """V, the pixels a uniform draw chooses from (valid ones within the time limit)."""
        end = len(self) if self._drawable_end is None else self._drawable_end
        return end if self.valid is None else (
            len(self.valid) if self._drawable_end is None else self.valid.count_below(end))

    def _importance_total(self) -> torch.Tensor:
        """W, the importance weights' sum over the drawable range."""
        cdf = self._importance_cdf
        return cdf[-1] if self._drawable_end is None else cdf[self._drawable_end - 1]

    @staticmethod
    def _check_draw_settings(fraction: float, debias: float) -> None:
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"importance fraction must be in [0, 1], got {fraction}")
        if not 0.0 <= debias <= 1.0:
            raise ValueError(f"importance debias must be in [0, 1], got {debias}")

    def enable_error_map(self, fraction: float, tile: int = 8, debias: float = 1.0) -> None:
        """Draw ``fraction`` of every :meth:`sample` where the training error is high
        (:class:`~nerfbot.data.error_map.ErrorMap`, tiles of ``tile`` pixels a side), the rest
        uniformly; the trainer reports each batch's errors with :meth:`record_errors`. The loss
        weights undo ``debias`` of the draws' bias, as with :meth:`set_importance`. A draw that
        lands on a masked-out pixel is replaced by a uniform one."""
        self._check_draw_settings(fraction, debias)
        if self._importance is not None:
            raise ValueError("importance weights and an error map both draw rays; use one")
        self.error_map = ErrorMap(self.cameras.width, self.cameras.height, self.offsets, tile,
                                  device=self.device)
        self.importance_fraction = float(fraction)
        self.importance_debias = float(debias)

    def record_errors(self, errors: torch.Tensor) -> None:
        """The squared colour errors (n,) of the last :meth:`sample`'s pixels, in their order,
        for the error map (nothing without one)."""
        if self.error_map is not None:
            self.error_map.update(self.last_pixels, self.last_slots, errors.detach())

    def _error_pixels(self, n: int, generator: torch.Generator) -> torch.Tensor:
        p = self.error_map.draw(n, generator)
        if self.valid is not None:
            bad = ~self.valid.contains(p)
            if bool(bad.any()):
                p[bad] = self._uniform_pixels(int(bad.sum()), generator)
        return p

    def _uniform_pixels(self, n: int, generator: torch.Generator) -> torch.Tensor:
        if self.valid is None:
            return torch.randint(self._drawable(), (n,), generator=generator).to(self.device)
        return self.valid.pixel(torch.randint(self._drawable(), (n,), generator=generator)
                                .to(self.device))

    def _important_pixels(self, n: int, generator: torch.Generator) -> torch.Tensor:
        cdf = self._importance_cdf
        u = torch.rand(n, generator=generator, dtype=torch.float64).to(self.device)
        u = u * self._importance_total()
        end = len(cdf) if self._drawable_end is None else self._drawable_end
        # the first pixel whose cumulative weight exceeds u: never one of weight 0
        return torch.searchsorted(cdf, u, right=True).clamp_(max=end - 1)

    def _loss_weights(self, p: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """(n,) ((1 / V) / q) ** debias of pixels ``p`` in frame slots ``slot`` (see
        :meth:`set_importance`)."""
        f = self.importance_fraction
        drawable = self._drawable()
        if self.error_map is not None:
            share = self.error_map.probability(p, slot) * drawable
        else:
            share = self._importance[p].double() * drawable / self._importance_total()
        return (1.0 / ((1.0 - f) + f * share)).pow(self.importance_debias).float()

    def sample(self, n: int, generator: torch.Generator, supersample: int = 1,
               jitter: bool = False) -> tuple[Rays, torch.Tensor, torch.Tensor]:
        """``n`` random pixels: their rays, colours (n, 3) float32 in [0, 1], frame slots (n,).
        Their pixel indices are kept in :attr:`last_pixels`; masked-out pixels are never drawn.
        After :meth:`set_importance`, the first ``round(n * fraction)`` are drawn by the
        importance weights, the others uniformly.

        With ``supersample`` S = 1 the rays go through the pixel centres, or with ``jitter``
        through a uniformly random point of each pixel: (n,) rays. With S > 1 each pixel gets
        S x S rays, one through a uniformly random point of each cell of an S x S grid over the
        pixel (stratified): (n * S * S,) rays, pixel after pixel."""
        weighted = self.error_map is not None or (  # the kept frames may hold no weight yet
            self._importance_cdf is not None and float(self._importance_total()) > 0.0)
        k = round(n * self.importance_fraction) if weighted else 0
        p = self._uniform_pixels(n - k, generator)
        if k:
            draw = self._important_pixels if self.error_map is None else self._error_pixels
            p = torch.cat([draw(k, generator), p])
        slot = torch.searchsorted(self.offsets[1:], p, right=True)
        self.last_pixels, self.last_slots = p, slot
        self.last_weights = self._loss_weights(p, slot) if weighted else None
        rays, colours = self._pixel_rays(p, slot, generator, supersample, jitter)
        return rays, colours, slot

    def _pixel_rays(self, p: torch.Tensor, slot: torch.Tensor,
                    generator: Optional[torch.Generator],
                    supersample: int, jitter: bool = False) -> tuple[Rays, torch.Tensor]:
        """Rays (n * S * S,) through pixels ``p`` (n,) of frame slots ``slot``, and their
        colours (n, 3) float32 in [0, 1] (see :meth:`sample`; S = 1 without ``jitter``: the
        pixel centres)."""
        n = len(p)
        local = p - self.offsets[slot]
        w = self.cameras.width[slot]
        v, u = local // w, local % w
        cam = self.cameras
        if supersample == 1 and not jitter:
            px, py, ray_slot = u.float() + 0.5, v.float() + 0.5, slot
        else:
            k = supersample * supersample
            cell = torch.arange(k, device=self.device)
            offset = torch.rand((n, k, 2), generator=generator).to(self.device)
            px = (u[:, None] + ((cell % supersample)[None] + offset[..., 0]) / supersample)
            py = (v[:, None] + ((cell // supersample)[None] + offset[..., 1]) / supersample)
            px, py = px.reshape(-1).float(), py.reshape(-1).float()
            ray_slot = slot.repeat_interleave(k)
        rays = pixel_rays(cam.c2w[ray_slot], cam.fx[ray_slot], cam.fy[ray_slot],
                          cam.cx[ray_slot], cam.cy[ray_slot], px, py,
                          1.0 / supersample, 1.0 / supersample)
        return rays, self.pixels[p].float() / 255.0


def depth_valid_mask(dataset: Dataset, i: int, depth: np.ndarray | None = None
                     ) -> np.ndarray | None:
    """(H, W) bool, the pixels of frame ``i`` whose depth (``depth``, (H, W) z-depth in metres;
    default the frame's ground truth) is finite, whose 3D point lies inside the scene bounds,
    and which the frame's mask keeps (:meth:`Dataset.valid_mask`); None when the frame has no
    depth."""
    depth = dataset.depths[i] if depth is None else depth
    if depth is None:
        return None
    cams = dataset.cameras([i])
    rays = cams.rays(0)
    z = torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32)).reshape(-1)
    finite = torch.isfinite(z)
    t = torch.where(finite, z, torch.zeros_like(z)) / rays.z_per_t
    pts = rays.origins + rays.directions * t[:, None]
    lo, hi = torch.as_tensor(dataset.aabb, dtype=torch.float32)
    inside = (((pts >= lo) & (pts <= hi)).all(-1) & finite).reshape(depth.shape).numpy()
    mask = dataset.valid_mask(i)
    return inside if mask is None else inside & mask
