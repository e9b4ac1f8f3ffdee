"""The occupancy-grid renderer (Instant-NGP's): samples marched along each ray only through
occupied cells of a grid that follows the field's density, packed per ray, composited with early
termination. Every grid-like field renders through it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import nn

from nerfbot.fields.base import Field
from nerfbot.models.base import ADAPTIVE_TOLERANCE, Model, photometric_loss
from nerfbot.ops.cameras import Rays
from nerfbot.ops.contraction import disparity_distance
from nerfbot.ops.losses import distortion_loss, opacity_entropy_loss
from nerfbot.ops.rendering import RenderOutput, composite, render_weights
from nerfbot.ops.sampling import OccupancyGrid, crosses_top_to_bottom, ray_aabb

log = logging.getLogger(__name__)


@dataclass
class OccupancyModelConfig:
    grid_resolution: int = 64
    """G: occupancy cells per axis of the cube enclosing the bounds."""
    grid_update_every: int = 16
    """Steps between occupancy-grid updates."""
    grid_warmup_steps: int = 32
    """Updates before this step track densities but keep every cell occupied: pruning on an
    untrained field removes cells at random, and a pruned cell gets no samples to recover."""
    grid_threshold: float = 0.01
    """A cell is occupied when one marching step through it is at least this opaque."""
    render_steps: int = 256
    """Marching steps along the cube's diagonal: sets the smallest step dt_min. 256 measured
    better than 512 within a CPU time budget (fewer samples per ray, more steps)."""
    cone_angle: float = 0.0
    """Steps grow as t * cone_angle (0: constant steps), clamped to [dt_min, 8 dt_min]."""
    early_stop_transmittance: float = 1e-3
    """Rendering stops along a ray once its transmittance falls below this."""
    train_early_termination: bool = True
    """In training, march and evaluate colours and gradients only up to where the ray
    saturates (rounds of marching with a density-only pass find it)."""
    full_march_kept_fraction: float = 0.7
    """With ``train_early_termination``: while more than this fraction of a full march's
    samples lie before their ray saturates (a field not yet opaque), training skips the
    density-only pass and trains every marched sample; the choice is re-made after each step
    from that step's samples. In the step profiles of BENCHMARKS.md (section 7) a sample costs
    about 0.7 us in the density-only pass and 2.5 us trained, so the pass pays for itself only
    when it drops over about a fifth of the samples; 0.7 leans towards the rounds and was
    measured against always marching in rounds (1)."""
    samples_per_batch: int = 1 << 17
    """Target number of samples per training batch; the ray count adapts to it."""
    shade_min_weight: float = 1e-4
    """Rendering evaluates the colour of a sample only if it weighs at least this much in its
    pixel; lighter ones are black (on the trained tabletop 60 % of the samples, together under
    7e-4 of any pixel). 0: every colour."""
    inference_round_samples: int = 16
    """Most samples marched per ray in one round, in rendering and (with
    ``train_early_termination``) in training: after each round, rays that are already opaque
    stop."""
    first_round_samples: int = 4
    """Samples per ray of the first round of an eval-mode render (images, depth, geometry);
    each later round takes twice as many, up to ``inference_round_samples``. A ray that meets
    a surface saturates within a few samples of it: small first rounds stop such rays before
    they evaluate samples hidden behind it, while rays through fog still reach long rounds
    (fewer passes). The samples kept are the same whatever the rounds, up to float32 rounding
    where a round resumes. The differentiable render (pose estimation) marches in rounds of
    ``inference_round_samples``: the closed-loop drive of the navigation tutorial changes its
    outcome with float-level changes of the field, and keeps its numerics."""
    train_first_round_samples: int = 4
    """The same for training's density-only pass (with ``train_early_termination``), which
    finds where each training ray saturates; 0: rounds of ``inference_round_samples``. From 4
    instead of 16, that pass evaluates a third fewer samples on a trained bins scene and a
    step late in a budget takes 5-9 % less time (BENCHMARKS.md, section 7)."""
    distortion_weight: float = 0.01
    """Weight of the distortion loss (mip-NeRF 360), which discourages fog spread along rays;
    distances are measured in cube diagonals. 0.01 gained 0.2-0.6 dB test PSNR on the tabletop
    within 180 s and brought object depth from 2.97 to 2.80 cm (BENCHMARKS.md); 0 turns it
    off."""
    opacity_entropy_weight: float = 0.0
    """Weight of the mean binary entropy of the training rays' opacities
    (:func:`~nerfbot.ops.losses.opacity_entropy_loss`): pushes every ray toward opaque or
    empty, so a surface inside the bounds does not turn half transparent to mix the learned
    background into its colour. 0 turns it off."""
    density_noise: float = 0.0
    """Standard deviation s of the noise on each training sample's log-density: its density is
    multiplied by exp(N(0, s^2)) (the original NeRF's noise on raw density, for exponential
    activations); 0 turns it off. A veil (a surface a few samples thick, 80 % opaque, whose
    colour compensates for what shows through it) fits the images as well as an opaque
    surface, and nothing else in the loss tells them apart: on uniformly coloured objects the
    field settles for veils and the expected depth falls behind them. Under the noise a veil's
    opacity, and so its pixel, flickers from step to step while a saturated surface's does not,
    so training prefers surfaces. Rendering never adds noise."""
    density_noise_centre: str = "median"
    """What the noise leaves unchanged: "median", factor exp(s N) (median 1, mean exp(s^2 / 2),
    1.65 at s = 1); "mean", factor exp(s N - s^2 / 2) (mean 1). Under the median-one factor a
    translucent field is trained to be denser on average than it renders without noise."""
    near_gradient_distance: float = 0.0
    """d0, metres: the gradients a training sample at distance t from its camera sends to the
    field are scaled by min(1, (t / d0)^2) (Philip and Deschaintre, "Floaters No More", 2023);
    the forward pass is unchanged. Space next to a camera fills a large part of its image and
    little of any other's, so a floater there can fit one view's pixels at little cost to the
    rest; the scaling balances how much each region's density is pulled by how large it looks.
    Matters for cameras that stand inside the scene (rooms); 0 turns it off."""
    supersample: int = 1
    """S: rays per pixel axis for colour. Training compares the mean colour of S x S rays,
    one through a random point of each cell of an S x S grid over the pixel, with the pixel's
    colour; rendering averages S x S rays through the cells' centres (depth still comes from
    the pixel centre). Rendered images are anti-aliased (a renderer's multisampling, a
    camera's sensor): one central ray can match a pixel that an edge crosses only by making
    the edge semi-transparent, and an object a few pixels wide then becomes a veil whose
    depth lies behind it. Costs S^2 rays per training pixel and S^2 + 1 per rendered pixel."""
    pixel_jitter: bool = False
    """With S = 1 (and before ``supersample_from``), training rays go through a uniformly
    random point of their pixel instead of its centre, as Instant-NGP trains: the field fits
    each pixel's mean over its area instead of asking one central ray to match it. Renders
    still cast rays through the pixel centres."""
    supersample_tolerance: float = 0.0
    """Rendering casts the S x S rays only through pixels whose 3 x 3 neighbourhood of
    centre-ray colours spans more than this (max - min in some channel, colours in [0, 1]);
    elsewhere the centre ray's colour stands for the pixel's mean, which in a smooth region it
    matches to second order. 0: S x S rays through every pixel. Training is unaffected."""
    supersample_pattern: str = "adaptive"
    """Where a render with S > 1 casts its rays over a pixel: "grid", S x S rays through the
    centres of an S x S grid of cells (as training spreads them) plus the centre ray for
    depth; "corners", the centre ray and the pixel's four corner rays, each shared by the
    four pixels that meet there, weighted 2/3 and 1/12 each (the mean over the pixel square
    to second order along each axis): about 2 rays per pixel instead of S^2 + 1;
    "adaptive", the corners, and the grid instead where the centre and corner colours span
    more than ``adaptive_tolerance`` (:func:`nerfbot.query.render.render_image`). The
    default: on seven zoo scenes it renders in 0.4-0.6x the grid's time within 0.02 dB of
    its PSNR (BENCHMARKS.md, section 7). Training is unaffected."""
    adaptive_tolerance: float = ADAPTIVE_TOLERANCE
    """The "adaptive" pattern's test: a pixel gets the S x S grid when its centre and four
    corner colours span more than this (max - min in some channel, colours in [0, 1])."""
    supersample_from: float = 0.0
    """Fraction of the training budget before which training rays go through the pixel
    centres, S x S per pixel after it. With a fixed number of samples per batch, S x S rays
    per pixel mean S^2 times fewer pixels per step, which slows the early, coarse phase."""
    carving_weight: float = 0.0
    """Weight of a sparsity prior (Plenoxels' Cauchy loss): the mean of log(1 + tau^2) over
    ``carving_points`` random points of the occupied cells, tau = density x the marching
    step (the optical thickness of one step). Density hidden behind a surface gets no
    photometric gradient at all, so without a prior a uniformly coloured surface is learnt as
    its visual hull (from cameras at one range of heights, a flat partition becomes a
    lens-shaped solid many times its thickness); the prior carves what no image needs
    (BENCHMARKS.md, sections 9 and 10). 0 turns it off; ``ngp`` trains with 1e-4."""
    carving_points: int = 4096
    """Random points per step for ``carving_weight``."""
    floor_background: str = "learned"
    """What the learned background does on training rays that cross the bounds from their top
    face to their bottom face. Such a ray, from a camera above the bounds, passes through all
    their height, and in scenes whose content stands on a support filling the bounds'
    footprint (a table, a bench) it must meet a surface before it leaves; the background, a
    smooth function of direction that every view shares, can otherwise learn the colour of a
    plain surface seen from above (a cutting mat, a bench top) in place of the field, which
    then leaves that surface empty and loses its print. ``"learned"``: these rays train the
    background like any other. ``"detached"``: they show it but send it no gradient.
    ``"random"``: they see a uniformly random colour per ray and step instead, which only an
    opaque field can match, so they end inside the bounds (Instant-NGP's random backgrounds,
    on these rays only; renders still show the learned background). The colour moves from
    the learned background's (without its gradient) to the random one over the first
    ``floor_random_ramp`` of the budget: random from the first step, a young field saturates
    where the rays enter the bounds and paints the views on that face. Rays that enter through
    a side (the sky under a table) and cameras inside the bounds (rooms) are unaffected.
    ``"auto"``: ``"random"`` when at least :data:`FLOOR_SUPPORT_SHARE` of the training rays
    cross the bounds so (the cameras look down on a support that fills the bounds'
    footprint: the frame-filling workspaces and bins), else ``"learned"`` (the tabletop,
    whose crossing rays pass beside the table to the sky, and rooms). ``"learned"`` is the
    default: ``"auto"`` gains on the workspaces and loses where a plain, faintly textured
    surface (the bins' bench top) is pushed to be opaque at a height no view settles
    (BENCHMARKS.md, section 10, "Random colours where a support fills the view"). Ignored
    under the contraction, which has no faces."""
    floor_random_ramp: float = 0.25
    """Share of the budget over which ``floor_background="random"`` fades in; 0: from the
    first step."""
    contraction: bool = False
    """Model all of space, not only the bounds: the scene contraction
    (:mod:`nerfbot.ops.contraction`) keeps the bounds' enclosing cube as it is and maps
    everything beyond it into a shell as thick again; the occupancy grid covers the contracted
    cube and rays march from the camera to :data:`CONTRACTED_FAR` half-sizes, with steps that
    grow as the square of the distance. For scenes seen from inside (rooms) and scenes with
    far content (outdoors); the field must take contracted coordinates (``ngp``)."""

    def __post_init__(self):
        for name in ("grid_resolution", "grid_update_every", "render_steps", "samples_per_batch",
                     "inference_round_samples", "first_round_samples", "supersample",
                     "carving_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"option {name}: must be >= 1, got {getattr(self, name)}")
        for name in ("grid_warmup_steps", "grid_threshold", "cone_angle", "distortion_weight",
                     "opacity_entropy_weight", "density_noise", "shade_min_weight",
                     "near_gradient_distance", "supersample_tolerance", "carving_weight",
                     "adaptive_tolerance", "train_first_round_samples"):
            if getattr(self, name) < 0:
                raise ValueError(f"option {name}: must be >= 0, got {getattr(self, name)}")
        if self.density_noise_centre not in ("median", "mean"):
            raise ValueError(f"option density_noise_centre: must be 'median' or 'mean', got "
                             f"{self.density_noise_centre!r}")
        if self.floor_background not in FLOOR_BACKGROUNDS:
            raise ValueError(f"option floor_background: must be one of "
                             f"{', '.join(FLOOR_BACKGROUNDS)}, got {self.floor_background!r}")
        if self.supersample_pattern not in ("grid", "corners", "adaptive"):
            raise ValueError(f"option supersample_pattern: must be 'grid', 'corners' or "
                             f"'adaptive', got {self.supersample_pattern!r}")
        for name in ("early_stop_transmittance", "supersample_from", "full_march_kept_fraction",
                     "floor_random_ramp"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"option {name}: must be in [0, 1], got {getattr(self, name)}")


#: The values of ``OccupancyModelConfig.floor_background``.
FLOOR_BACKGROUNDS = ("auto", "learned", "detached", "random")

#: ``floor_background="auto"`` gives the rays that cross the bounds from top to bottom random
#: colours when at least this share of the training rays do: 99.7-99.9 % on the zoo's
#: workspaces and bins, 2.9 % on the tabletop, none in a room (BENCHMARKS.md, section 10).
FLOOR_SUPPORT_SHARE = 0.9

#: Training keeps the samples before a ray's transmittance falls below this (1e-4: a sample
#: behind it weighs less than 1e-4 in the pixel).
TRAIN_STOP_TRANSMITTANCE = 1e-4

#: Under the contraction rays stop this many inner half-sizes from the camera (contracted
#: radius 1.999): beyond, the learned background takes over.
CONTRACTED_FAR = 1000.0


class OccupancyModel(Model):
    """Occupancy-grid ray marching over packed samples (Instant-NGP's renderer)."""

    supports_labels = True

    def __init__(self, field: Field, background: nn.Module, aabb,
                 config: OccupancyModelConfig | None = None):
        super().__init__()
        self.config = cfg = config or OccupancyModelConfig()
        if isinstance(cfg.supersample, bool) or not isinstance(cfg.supersample, int) \
                or cfg.supersample < 1:
            raise ValueError(f"supersample must be an integer >= 1, got {cfg.supersample!r}")
        if not 0.0 <= cfg.supersample_from <= 1.0:
            raise ValueError(f"supersample_from must be in [0, 1], got {cfg.supersample_from}")
        if not 0.0 <= cfg.density_noise < math.inf:
            raise ValueError(f"density_noise must be finite and >= 0, got {cfg.density_noise}")
        self.field = field
        self.background = background
        self.register_buffer("aabb", torch.as_tensor(aabb, dtype=torch.float32).clone())
        self.grid = OccupancyGrid(self.aabb, cfg.grid_resolution, cfg.grid_threshold,
                                  contract=cfg.contraction)
        if cfg.contraction and not getattr(getattr(field, "normalize", None), "contracted",
                                           False):
            raise ValueError(f"option contraction: {type(field).__name__} does not take "
                             "contracted coordinates (ngp does)")
        self.dt_min = self.grid.inner_size * math.sqrt(3.0) / cfg.render_steps
        self.dt_max = 8.0 * self.dt_min if cfg.cone_angle > 0 else self.dt_min
        # whether the next training step marches fully, without the density-only pass; saved
        # with the model so that a resumed run makes the same choices
        self.register_buffer("train_full_march", torch.zeros((), dtype=torch.bool))
        #: what ``floor_background`` does in this run; "auto" is settled by
        #: :meth:`init_floor_share` from the training rays, and trains as "learned" until then
        self.floor_mode = "learned" if cfg.floor_background == "auto" else cfg.floor_background
        self._progress = 0.0  # share of the budget done, from before_step

    def init_floor_share(self, share: float) -> None:
        """Settle ``floor_background="auto"`` from the share of training rays that cross the
        bounds from top to bottom: "random" at :data:`FLOOR_SUPPORT_SHARE` or more."""
        if self.config.floor_background != "auto" or self.config.contraction:
            return
        self.floor_mode = "random" if share >= FLOOR_SUPPORT_SHARE else "learned"
        log.info("%.1f %% of the training rays cross the bounds from top to bottom: "
                 "floor_background %s", 100.0 * share, self.floor_mode)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # checkpoints written before the buffer existed resume marching in rounds
        state_dict.setdefault(prefix + "train_full_march", torch.zeros((), dtype=torch.bool))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def supersample(self) -> int:
        return self.config.supersample

    @property
    def pixel_jitter(self) -> bool:
        return self.config.pixel_jitter

    @property
    def supersample_pattern(self) -> str:
        return self.config.supersample_pattern

    @property
    def supersample_tolerance(self) -> float:
        return self.config.supersample_tolerance

    @property
    def adaptive_tolerance(self) -> float:
        return self.config.adaptive_tolerance

    def training_supersample(self, progress: float) -> int:
        return self.supersample if progress >= self.config.supersample_from else 1

    # -- sampling ----------------------------------------------------------------------------
    def ray_range(self, rays: Rays) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(t_near, t_far, hit), each (R,): where rays enter and leave the modelled space (the
        bounds, or under the contraction from the camera to :data:`CONTRACTED_FAR`)."""
        if not self.config.contraction:
            return ray_aabb(rays.origins, rays.directions, self.aabb)
        n, device = len(rays), self.aabb.device
        far = CONTRACTED_FAR * self.grid.half
        return (torch.zeros(n, device=device), torch.full((n,), far, device=device),
                torch.ones(n, dtype=torch.bool, device=device))

    def _march(self, rays: Rays, t_begin, t_far, max_per_ray: int = 1 << 30):
        return self.grid.march(rays.origins, rays.directions, t_begin, t_far, self.dt_min,
                               self.dt_max, self.config.cone_angle, max_per_ray)

    def _points(self, rays: Rays, s) -> tuple[torch.Tensor, torch.Tensor]:
        t_mid = 0.5 * (s.t_starts + s.t_ends)
        o, d = rays.origins[s.ray_indices], rays.directions[s.ray_indices]
        return o + d * t_mid[:, None], d

    def _density(self, x: torch.Tensor, rays: Rays, ray_idx: torch.Tensor, t: torch.Tensor,
                 cond, cond_idx: Optional[torch.Tensor] = None):
        """The field's (sigma, features) at samples x (S, 3) at distances t (S,) along rays
        ``ray_idx`` (S,) of ``rays``, with the pixel's cone radius there when the field uses
        it (:meth:`~nerfbot.fields.base.Field.density_at_scale`); the samples' conditions are
        rows ``cond_idx`` (default ``ray_idx``) of ``cond``."""
        c = gather_rows(cond, ray_idx if cond_idx is None else cond_idx)
        if not self.field.uses_footprint or rays.radii is None:
            return self.field.density(x, c)
        return self.field.density_at_scale(x, rays.radii[ray_idx] * t, c)

    def render_rays(self, rays: Rays, generator=None, cond=None) -> RenderOutput:
        """Training mode: samples from jittered starts up to where each ray saturates
        (:meth:`_march_until_opaque`) or, while the field is mostly translucent, all of them
        (``full_march_kept_fraction``); gradients through all of them. Eval mode: marching in
        rounds from the ray's entry, colours of the samples that show, no gradients."""
        if not self.training:
            return self._render_inference(rays, cond)
        t_near, t_far, hit = self.ray_range(rays)
        jitter = torch.rand(t_near.shape, generator=generator, device=t_near.device)
        t_begin = t_near + jitter * self.dt_min
        n = len(rays)
        rounds = self.config.train_early_termination and not bool(self.train_full_march)
        if rounds:
            with torch.no_grad():
                ray_idx, ts, te, _, _, _ = self._march_until_opaque(
                    rays, t_begin, t_far, cond, TRAIN_STOP_TRANSMITTANCE,
                    first_round=self.config.train_first_round_samples)
                full = self._march(rays, t_begin, t_far).ray_indices.numel()
                self._choose_train_march(ray_idx.numel(), full)
        else:
            s = self._march(rays, t_begin, t_far)
            ray_idx, ts, te = s.ray_indices, s.t_starts, s.t_ends
        o, d = rays.origins[ray_idx], rays.directions[ray_idx]
        t_mid = 0.5 * (ts + te)
        x = o + d * t_mid[:, None]
        sigma, feat = self._density(x, rays, ray_idx, t_mid, cond)
        if self.config.train_early_termination and not rounds:
            with torch.no_grad():
                _, trans = render_weights(sigma.detach().double(), ts, te, ray_idx, n)
                self._choose_train_march(int((trans > TRAIN_STOP_TRANSMITTANCE).sum()),
                                         ray_idx.numel())
        noise_std = self.config.density_noise
        if noise_std > 0:
            noise = torch.randn(sigma.shape, generator=generator, device=sigma.device)
            if self.config.density_noise_centre == "mean":
                noise = noise - 0.5 * noise_std
            sigma = sigma * torch.exp(noise_std * noise)
        rgb = self.field.color(feat, d, gather_rows(cond, ray_idx))
        if self.config.near_gradient_distance > 0:
            scale = (0.5 * (ts + te) / self.config.near_gradient_distance).square().clamp_max(1.0)
            sigma = scale_gradient(sigma, scale)
            rgb = scale_gradient(rgb, scale[:, None])
        background = self._training_background(rays, t_near, t_far, hit, generator)
        out = composite(sigma, rgb, ts, te, ray_idx, n, background,
                        t_far, rays.z_per_t, with_median=False)
        if self.label_head is not None:
            out.positions, out.features = x, feat
        return out

    def _training_background(self, rays: Rays, t_near, t_far, hit, generator) -> torch.Tensor:
        """(R, 3) the colour each training ray sees beyond the bounds, with
        ``floor_background`` applied to the rays that cross them from top to bottom."""
        background = self.background(rays.directions)
        mode = self.floor_mode
        if mode == "learned" or self.config.contraction:
            return background
        floor = crosses_top_to_bottom(rays.origins, rays.directions, t_near, t_far, hit,
                                      self.aabb)[:, None]
        if mode == "detached":
            return torch.where(floor, background.detach(), background)
        noise = torch.rand(background.shape, generator=generator, device=background.device)
        ramp = self.config.floor_random_ramp
        weight = 1.0 if ramp <= 0 else min(1.0, self._progress / ramp)
        return torch.where(floor, torch.lerp(background.detach(), noise, weight), background)

    def render_rays_differentiable(self, rays: Rays, cond=None) -> RenderOutput:
        """Eval-mode samples (marched in rounds from each ray's entry until it saturates, no
        jitter or noise), evaluated with gradients flowing to the rays through the sample
        positions and view directions."""
        n = len(rays)
        t_near, t_far, _ = self.ray_range(rays)
        with torch.no_grad():
            ray_idx, ts, te, _, _, _ = self._march_until_opaque(
                rays, t_near.detach(), t_far.detach(), cond,
                self.config.early_stop_transmittance)
        o, d = rays.origins[ray_idx], rays.directions[ray_idx]
        t_mid = 0.5 * (ts + te)
        x = o + d * t_mid[:, None]
        sigma, feat = self._density(x, rays, ray_idx, t_mid, cond)
        rgb = self.field.color(feat, d, gather_rows(cond, ray_idx))
        return composite(sigma, rgb, ts, te, ray_idx, n, self.background(rays.directions),
                         t_far, rays.z_per_t, with_median=False)

    def _choose_train_march(self, kept: int, marched: int) -> None:
        """Set how the next training step marches from this one's counts: ``kept`` of the
        ``marched`` samples of a full march lie before their ray saturates."""
        self.train_full_march.fill_(kept > self.config.full_march_kept_fraction * marched)

    def _march_until_opaque(self, rays: Rays, t_begin: torch.Tensor, t_far: torch.Tensor, cond,
                            stop_transmittance: float, with_color: bool = False,
                            drop_hidden: bool = True, first_round: int = 0):
        """March in rounds of ``inference_round_samples`` samples per ray (with ``first_round``
        > 0: that many first, doubling each round up to it), evaluating density after each
        round and dropping rays whose transmittance fell below ``stop_transmittance``: later
        rounds are never marched.

        Returns packed (ray_indices, t_starts, t_ends) of the kept samples (sorted by ray, in t
        order), their densities and (``with_color``) colours and (points, geometry features),
        else None and (None, None): colours are evaluated only for samples weighing at least
        ``shade_min_weight``. With ``drop_hidden``
        a sample is kept only when the transmittance before it is above
        ``stop_transmittance``; otherwise the last round's samples are all kept.
        """
        n = len(rays)
        t_cur = t_begin.clone()
        log_trans = torch.zeros(n, dtype=torch.float64, device=t_begin.device)
        alive = t_cur < t_far
        pieces = []
        stop = math.log(stop_transmittance)
        round_samples = self.config.inference_round_samples
        if first_round > 0:
            round_samples = min(first_round, round_samples)
        while bool(alive.any()):
            ids = torch.nonzero(alive).squeeze(-1)
            sub = rays[ids]
            s = self._march(sub, t_cur[ids], t_far[ids], round_samples)
            round_samples = min(2 * round_samples, self.config.inference_round_samples)
            t_cur[ids] = s.t_stop
            if s.ray_indices.numel():
                gidx = ids[s.ray_indices]
                x, d = self._points(sub, s)
                sigma, feat = self._density(x, sub, s.ray_indices,
                                            0.5 * (s.t_starts + s.t_ends), cond, gidx)
                if drop_hidden:
                    _, trans = render_weights(sigma.double(), s.t_starts, s.t_ends,
                                              s.ray_indices, len(ids))
                    keep = torch.log(trans.clamp_min(1e-300)) + log_trans[gidx] > stop
                else:
                    keep = torch.ones_like(gidx, dtype=torch.bool)
                tau = (sigma * (s.t_ends - s.t_starts)).double().clamp_max(1e4)
                log_trans.index_add_(0, gidx, -tau)
                pieces.append((gidx[keep], s.t_starts[keep], s.t_ends[keep], sigma[keep],
                               feat[keep] if with_color else None,
                               x[keep] if with_color else None))
            alive = alive & (t_cur < t_far) & (log_trans > stop)
        if not pieces:
            empty = torch.zeros(0, device=t_begin.device)
            rgb = torch.zeros(0, 3, device=t_begin.device) if with_color else None
            return (torch.zeros(0, dtype=torch.long, device=t_begin.device), empty, empty,
                    empty, rgb, (None, None))
        gidx = torch.cat([p[0] for p in pieces])
        order = torch.sort(gidx, stable=True).indices  # rounds are in t order per ray
        gidx = gidx[order]
        ts, te, sigma = (torch.cat([p[k] for p in pieces])[order] for k in (1, 2, 3))
        rgb = feat = x = None
        if with_color:
            feat = torch.cat([p[4] for p in pieces])[order]
            x = torch.cat([p[5] for p in pieces])[order]
            weights, _ = render_weights(sigma, ts, te, gidx, n)
            shown = torch.nonzero(weights >= self.config.shade_min_weight).squeeze(-1)
            rgb = torch.zeros(len(gidx), 3, device=t_begin.device)
            if shown.numel():
                rgb[shown] = self.field.color(feat[shown], rays.directions[gidx[shown]],
                                              gather_rows(cond, gidx[shown])).to(rgb.dtype)
        return gidx, ts, te, sigma, rgb, (x, feat)

    def render_geometry(self, rays: Rays, cond=None) -> RenderOutput:
        """The eval-mode samples of :meth:`render_rays` without colours or background
        (``rgb`` is black)."""
        return self._render_inference(rays, cond, with_color=False)

    @torch.no_grad()
    def _render_inference(self, rays: Rays, cond=None, with_color: bool = True) -> RenderOutput:
        """Samples from each ray's entry until its transmittance falls below
        ``early_stop_transmittance`` (:meth:`_march_until_opaque`), composited at once; without
        ``with_color`` neither colours nor the background are evaluated (``rgb`` is black)."""
        n = len(rays)
        t_near, t_far, _ = self.ray_range(rays)
        gidx, ts, te, sigma, rgb, (x, feat) = self._march_until_opaque(
            rays, t_near, t_far, cond, self.config.early_stop_transmittance,
            with_color=with_color, drop_hidden=False,
            first_round=self.config.first_round_samples)
        if with_color:
            background = self.background(rays.directions)
        else:
            rgb = torch.zeros(len(gidx), 3, device=sigma.device, dtype=sigma.dtype)
            background = rgb.new_zeros(3)
        out = composite(sigma, rgb, ts, te, gidx, n, background, t_far, rays.z_per_t)
        if with_color and self.label_head is not None:
            out.positions, out.features = x, feat
        return out

    def loss(self, rays, target_rgb, generator=None, cond=None, rays_per_pixel=1,
             pixel_weights=None):
        out = self.render_rays(rays, generator, cond)
        loss = photometric_loss(out.rgb, target_rgb, rays_per_pixel, pixel_weights)
        if self.config.distortion_weight > 0:
            diagonal = self.grid.inner_size * math.sqrt(3.0)
            ts, te = out.t_starts, out.t_ends
            if self.config.contraction:
                ts, te = disparity_distance(ts, diagonal), disparity_distance(te, diagonal)
            loss = loss + self.config.distortion_weight * distortion_loss(
                out.weights, ts, te, out.ray_indices, len(rays), diagonal)
        if self.config.opacity_entropy_weight > 0:
            loss = loss + self.config.opacity_entropy_weight * opacity_entropy_loss(out.opacity)
        if self.config.carving_weight > 0:
            loss = loss + self.config.carving_weight * self.carving_loss(generator)
        reg = self.field.regularizer()
        if reg is not None:
            loss = loss + reg
        return loss, out

    def carving_loss(self, generator=None) -> torch.Tensor:
        """Scalar: mean log(1 + tau^2) at ``carving_points`` uniform random points of the
        occupied cells, tau = density x ``dt_min`` (conditioned fields at random conditions,
        :meth:`~nerfbot.fields.base.Field.occupancy_density`); 0 when no cell is occupied."""
        x = self.grid.random_occupied_points(self.config.carving_points, generator)
        if len(x) == 0:
            return torch.zeros((), device=self.grid.cube_min.device)
        tau = self.field.occupancy_density(x, generator) * self.dt_min
        return torch.log1p(tau.square()).mean()

    # -- upkeep ------------------------------------------------------------------------------
    def before_step(self, step: int, generator=None, progress: float = 0.0) -> dict:
        self._progress = float(progress)
        out = dict(self.field.before_step(step, progress))
        if step == 0 or step % self.config.grid_update_every:
            return out
        frac = self.grid.update(lambda x: self.field.occupancy_density(x, generator), self.dt_min,
                                generator,
                                prune=step >= self.config.grid_warmup_steps
                                and self.field.prunable())
        return {**out, "occupied": frac}

    def rays_for_next_batch(self, last_samples: Optional[int], n_rays: int) -> int:
        """Rays that make ``samples_per_batch`` samples at the last batch's samples per ray.

        Before any batch, assume rays cross half the marching steps (the grid starts full)."""
        target = self.config.samples_per_batch
        if last_samples is None:
            return max(64, min(1 << 16, 2 * target // self.config.render_steps))
        per_ray = max(last_samples, 1) / max(n_rays, 1)
        return int(max(64, min(1 << 16, target / per_ray)))


def scale_gradient(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``x`` unchanged in the forward pass; its gradient multiplied by ``scale`` (broadcast to
    ``x``'s shape, no gradient of its own)."""
    scale = scale.detach().to(x.dtype)
    return x * scale + (x * (1.0 - scale)).detach()


def gather_rows(cond: Optional[torch.Tensor], idx: torch.Tensor) -> Optional[torch.Tensor]:
    """Per-sample conditioning from per-ray conditioning (None stays None)."""
    return None if cond is None else cond[idx]
