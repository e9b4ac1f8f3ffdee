"""The settings of one training run (:class:`TrainConfig`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Optional

from nerfbot.data.pixels import DEPTH_SOURCES
from nerfbot.methods import get_method


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
    """Dense depth supervision (for RGB-D captures): weight of the L1 error of the rendered
    expected z-depth against the dataset's depth maps, in units of the scene cube's diagonal,
    on training pixels whose depth is finite and inside the bounds. 0 = RGB only."""
    depth_from: str = "depth"
    """The depth maps ``depth_weight`` trains on: "depth" (the frames' ``depth_file_path``: a
    simulator's true depth, or an RGB-D camera's) or "sensor_depth" (``sensor_depth_file_path``:
    a simulated depth sensor's reading, :mod:`sims.sensor`)."""
    sparse_depth_weight: float = 0.0
    """DS-NeRF's sparse depth supervision: weight of
    :func:`~nerfbot.ops.losses.keypoint_depth_loss` on the training frames' keypoints
    (``Dataset.keypoints``, from structure from motion). 0 = off."""
    sparse_depth_robust: float = 0.0
    """Robust keypoint weights, c > 0: from a quarter of the budget on, each keypoint's depth
    loss is weighed by ``1 / (1 + (r / (c sigma))^2)``, r the distance from the ray's rendered
    expected distance to the keypoint's and sigma its width (a wrong match, which the images'
    colours contradict, stops pulling the surface toward it); 0: every keypoint at full
    weight, as DS-NeRF trains."""
    sparse_depth_until: float = 1.0
    """Fraction of the budget after which keypoints leave the batch (0 < f <= 1): the depth
    prior shapes the geometry early, and the last 1 - f of the budget trains colour on every
    pixel of the batch. 1 = to the end, as DS-NeRF trains."""
    sparse_depth_rays: int = 256
    """Keypoint pixels per step for the sparse depth loss (at most a quarter of the batch's
    pixels); they replace as many random pixels of the batch, and only their depth is trained."""
    labels: bool = False
    """Train Semantic-NeRF's label branch (:mod:`nerfbot.models.labels`) on the capture's
    segmentation, classes from its manifest (:func:`nerfbot.data.labels.label_classes`)."""
    label_weight: float = 0.04
    """Weight of the labels' cross-entropy against the photometric MSE (Semantic-NeRF's 0.04)."""
    label_clicks: Optional[int] = None
    """iLabel's setting: train labels from this many labelled pixels per class over all the
    training frames, drawn at random (:func:`nerfbot.data.labels.click_maps`), instead of full
    label maps. Clicks asked where the head is unsure need a head that already predicts
    something: :func:`nerfbot.train.labelling.train_label_head` on the finished field."""
    label_rays: int = 1024
    """Pixels per step whose labels are trained: the first of the batch's random pixels with
    full label maps; with ``label_clicks``, pixels drawn from the clicks, which replace as
    many random pixels of the batch (their colour is trained too)."""
    dynamic_rays: float = 0.5
    """Captures over time: the fraction of each batch's pixels drawn in proportion to how much
    they change over time (:mod:`nerfbot.data.importance`, DyNeRF's importance sampling), the
    rest uniformly. Only frames whose camera films several time steps have such weights (a
    multi-camera rig); 0 = uniform."""
    dynamic_rays_debias: float = 0.5
    """How much of the bias of those draws the loss undoes (each pixel's loss weight is
    (uniform probability / its probability) ** this, :meth:`PixelBank.set_importance`): 1 =
    unbiased, the changing pixels get more samples of the same total weight; 0 = DyNeRF's, they
    also weigh more. On the dynamic scene (BENCHMARKS.md, section 4) 1 kept the whole image but
    lost the moving objects, 0 showed them with floaters over the static scene, 0.5 kept the
    one and most of the other."""
    error_rays: float = 0.0
    """The fraction of each batch's pixels drawn where the training error is high
    (:mod:`nerfbot.data.error_map`, Instant-NGP's error-map sampling), the rest uniformly;
    0 = uniform. Not with ``dynamic_rays`` on a capture over time (choose one)."""
    error_rays_debias: float = 1.0
    """How much of the bias of those draws the loss undoes, as ``dynamic_rays_debias``: 1 =
    unbiased (more, less noisy samples where the error is, the same optimum); 0 = the pixels
    drawn there also weigh more."""
    error_tile: int = 8
    """Side of the error map's tiles, pixels."""
    device: str = "cpu"
    """torch device; the fast kernels are CPU kernels, other devices use the torch twins
    (``NERFBOT_KERNELS=torch`` forces the twins on the CPU too: :mod:`nerfbot.kernels`)."""
    progress: bool = True
    """Show a progress bar."""

    def keypoint_pixels(self, progress: float) -> int:
        """Keypoint pixels a step at ``progress`` (0-1) of the budget asks for: 0 without
        sparse depth supervision and from ``sparse_depth_until`` on."""
        if self.sparse_depth_weight > 0 and progress < self.sparse_depth_until:
            return self.sparse_depth_rays
        return 0

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
        if self.depth_from not in DEPTH_SOURCES:
            raise ValueError(f"depth_from must be one of {sorted(DEPTH_SOURCES)}, got "
                             f"{self.depth_from!r}")
        if not 0.0 <= self.sparse_depth_weight < math.inf:
            raise ValueError(f"sparse_depth_weight must be >= 0 and finite, got "
                             f"{self.sparse_depth_weight}")
        if not 0.0 <= self.sparse_depth_robust < math.inf:
            raise ValueError(f"sparse_depth_robust must be >= 0 and finite, got "
                             f"{self.sparse_depth_robust}")
        if not 0.0 < self.sparse_depth_until <= 1.0:
            raise ValueError(f"sparse_depth_until must be in (0, 1], got "
                             f"{self.sparse_depth_until}")
        if isinstance(self.sparse_depth_rays, bool) or not isinstance(self.sparse_depth_rays, int) \
                or self.sparse_depth_rays < 1:
            raise ValueError(f"sparse_depth_rays must be an integer >= 1, got "
                             f"{self.sparse_depth_rays!r}")
        if not 0.0 <= self.label_weight < math.inf:
            raise ValueError(f"label_weight must be >= 0 and finite, got {self.label_weight}")
        for name in ("label_clicks", "label_rays"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int)
                                      or value < 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if self.label_clicks is not None and not self.labels:
            raise ValueError("label_clicks needs labels")
        if isinstance(self.dynamic_rays, bool) or not isinstance(self.dynamic_rays, (int, float)) \
                or not 0.0 <= self.dynamic_rays <= 1.0:
            raise ValueError(f"dynamic_rays must be in [0, 1], got {self.dynamic_rays!r}")
        if isinstance(self.dynamic_rays_debias, bool) \
                or not isinstance(self.dynamic_rays_debias, (int, float)) \
                or not 0.0 <= self.dynamic_rays_debias <= 1.0:
            raise ValueError(f"dynamic_rays_debias must be in [0, 1], got "
                             f"{self.dynamic_rays_debias!r}")
        for name in ("error_rays", "error_rays_debias"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value!r}")
        if isinstance(self.error_tile, bool) or not isinstance(self.error_tile, int) \
                or self.error_tile < 1:
            raise ValueError(f"error_tile must be an integer >= 1 pixels, got {self.error_tile!r}")
        if not self.checkpoint_every_seconds >= 0:
            raise ValueError(f"checkpoint_every_seconds must be >= 0, got "
                             f"{self.checkpoint_every_seconds}")
        if self.checkpoint_every_steps is not None and self.checkpoint_every_steps < 1:
            raise ValueError(f"checkpoint_every_steps must be >= 1, got "
                             f"{self.checkpoint_every_steps}")
