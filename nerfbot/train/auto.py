"""``--method auto``: model only what a scene requires, and pick the cheapest budget that works.

Two decisions, each explained in :attr:`AutoChoice.reasons`:

1. **What to model**, from the scene manifest (:func:`choose_from_manifest`):

   - conditioning: a static capture gets none; time-varying captures need a time-conditioned
     field, captures with moving joints a joint-conditioned one (methods of those kinds are
     chosen when the registry has them, otherwise a clear error says what is missing);
   - no specular material, or shiny surfaces on under :data:`MIN_SHINY_PIXEL_FRACTION` of the
     training pixels and no glass → view-independent colour (spherical-harmonics degree 0):
     modelling view dependence costs more steps than it returns when little of the image has it;
   - transparent geoms → keep low-density structure (a 10x lower occupancy threshold, so faint
     glass is never pruned), the distortion loss against floaters, and threshold depth as the
     run's default depth query (Dex-NeRF);
   - bounds and occupancy come from the manifest (the dataset reader already uses its bounds);
   - an unbounded scene (the reader's :func:`~nerfbot.data.bounds.choose_space`: content far
     beyond the cameras) gets the scene contraction around the cameras' region
     (:func:`choose_for_dataset`).

2. **How much to train** (:func:`choose_budget`), for ``--target-psnr P`` or ``--time-budget S``:
   the rows of a ``nerfbot bench`` table for this scene and method (``bench.json``), or, with
   none given, a short sweep of the same configuration at a few budgets run first
   (:mod:`nerfbot.bench.auto_sweep`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

from nerfbot.methods import METHODS, option_names


log = logging.getLogger(__name__)


#: Occupancy threshold (opacity of one marching step) kept for scenes with transparent geoms:
#: 10x below the default 0.01, so density of faint glass stays occupied.
TRANSPARENT_GRID_THRESHOLD = 0.001


#: Distortion-loss weight for scenes with transparent geoms (fewer floaters at low thresholds).
TRANSPARENT_DISTORTION = 0.01


#: Log-density noise for scenes with transparent geoms: none. Glass is a real veil, faint density
#: a threshold finds (Dex-NeRF); the noise that turns ngp's veils into surfaces (its default)
#: would push glass to opaque or empty, and the glass figures were measured without it.
TRANSPARENT_DENSITY_NOISE = 0.0


#: Dex-NeRF density threshold (1/m) of the default depth query for scenes with transparent
#: geoms: the best threshold on the transparent pixels of the held-out glassware scene
#: (glassware:1000, 1.38 cm MAE there; BENCHMARKS.md, section 3), as the grasp task calibrates it.
TRANSPARENT_DEPTH_THRESHOLD = 5.0


#: Share of the training pixels on shiny surfaces (manifest ``shiny_pixel_fraction``) below
#: which a scene without glass gets view-independent colour. Measured with step budgets (ngp's
#: renderer defaults of the time): on the tabletop (2.4 % shiny pixels) SH degree 0 led degree 4 by
#: 0.2-0.35 dB at 120-240 steps and trailed by 0.1 dB at 568; on the glazed scene (5.5 %) it
#: trailed by 1.3-2.2 dB. A two-scene estimate, set nearer the tabletop because guessing wrong
#: costs more on the shiny side.
MIN_SHINY_PIXEL_FRACTION = 0.03


@dataclass
class AutoChoice:
    """What ``--method auto`` decided, and why.

    Attributes:
        method: registry name of the method to train.
        options: method options (field / model config fields).
        conditioning: "static", "time" or "joints".
        query_defaults: defaults for queries of the trained run, e.g. {"depth_mode":
            "threshold"} for scenes with glass.
        reasons: one line per decision, for logs and ``RUN/auto.json``.
        budget_seconds: training budget chosen by :func:`choose_budget` (None: not chosen).
    """

    method: str
    options: dict = field(default_factory=dict)
    conditioning: str = "static"
    query_defaults: dict = field(default_factory=dict)
    reasons: list = field(default_factory=list)
    budget_seconds: Optional[float] = None

    def to_dict(self) -> dict:
        return asdict(self)


#: Conditioning -> candidate methods, most capable first (the first registered one is used).
_CONDITIONED = {"time": ("kplanes", "dnerf", "tnerf"), "joints": ("articulated",)}


def choose_from_manifest(manifest: Optional[dict]) -> AutoChoice:
    """The method and options a scene needs, from its manifest (None: no manifest).

    Raises:
        ValueError: the scene needs a kind of field the registry does not have yet.
    """
    choice = AutoChoice(method="ngp")
    if not manifest:
        choice.reasons.append("no scene manifest: static ngp with view-dependent colour "
                              "(nothing known to leave out)")
        return choice
    if manifest.get("time_varying"):
        choice.conditioning = "time"
    elif manifest.get("moving_joints"):
        choice.conditioning = "joints"
    if choice.conditioning != "static":
        candidates = [m for m in _CONDITIONED[choice.conditioning] if m in METHODS]
        if not candidates:
            raise ValueError(
                f"scene '{manifest.get('name')}' is {'time-varying' if choice.conditioning == 'time' else 'articulated'} "
                f"(manifest: time_varying={manifest.get('time_varying')}, moving_joints="
                f"{manifest.get('moving_joints')}) and needs one of "
                f"{list(_CONDITIONED[choice.conditioning])}, which this nerfbot does not have yet")
        choice.method = candidates[0]
        choice.reasons.append(f"{choice.conditioning}-conditioned field ({choice.method}): the "
                              "manifest says the scene changes across frames")
    else:
        choice.reasons.append("static field (ngp): no time variation or moving joints")
    transparent = manifest.get("transparent_geoms") or []
    shiny = manifest.get("shiny_pixel_fraction")
    if not manifest.get("specular", True):
        choice.options["sh_degree"] = 0
        choice.reasons.append("view-independent colour (SH degree 0): no specular material")
    elif not transparent and shiny is not None and shiny < MIN_SHINY_PIXEL_FRACTION:
        choice.options["sh_degree"] = 0
        choice.reasons.append(
            f"view-independent colour (SH degree 0): shiny surfaces cover {100 * shiny:.1f} % of "
            f"the training pixels (< {100 * MIN_SHINY_PIXEL_FRACTION:g} %) and nothing is "
            "transparent, so view dependence costs more steps than it returns")
    else:
        share = "" if shiny is None else f" on {100 * shiny:.1f} % of the training pixels"
        choice.reasons.append("view-dependent colour (SH degree 4): specular materials "
                              f"present{share}" + (" and glass" if transparent else ""))
    if transparent:
        choice.options["grid_threshold"] = TRANSPARENT_GRID_THRESHOLD
        choice.options["distortion_weight"] = TRANSPARENT_DISTORTION
        choice.options["density_noise"] = TRANSPARENT_DENSITY_NOISE
        choice.query_defaults.update(depth_mode="threshold", threshold=TRANSPARENT_DEPTH_THRESHOLD)
        choice.reasons.append(
            f"{len(transparent)} transparent geom(s): occupancy threshold "
            f"{TRANSPARENT_GRID_THRESHOLD} (faint density kept), distortion loss "
            f"{TRANSPARENT_DISTORTION}, no density noise (glass is a real veil), threshold depth "
            f"(Dex-NeRF, m = {TRANSPARENT_DEPTH_THRESHOLD:g} /m) as the default depth query of "
            "`nerfbot render`")

    known = set(option_names(choice.method))
    dropped = sorted(set(choice.options) - known)
    for k in dropped:  # a conditioned method may lack an option the static one has
        choice.options.pop(k)
    if dropped:
        choice.reasons.append(f"{choice.method} has no option(s) {dropped}: left at defaults")
    return choice


def choose_for_dataset(ds) -> AutoChoice:
    """:func:`choose_from_manifest` for a loaded dataset, plus how to model its space: the
    scene contraction when the reader found the scene unbounded (``ds.unbounded``)."""
    choice = choose_from_manifest(ds.manifest)
    reason = ds.extras.get("space") or f"bounds from {ds.aabb_source}"
    if ds.unbounded and "contraction" in option_names(choice.method):
        choice.options["contraction"] = True
        choice.reasons.append(reason)
    elif ds.unbounded:
        choice.reasons.append(f"{reason}; {choice.method} has no contraction: the box around "
                              "the cameras")
    else:
        choice.reasons.append(reason)
    return choice


def bench_rows(table: Path, scene: Optional[str] = None, method: Optional[str] = None,
               options: Optional[dict] = None) -> list[dict]:
    """Configurations (medians) of a ``nerfbot bench`` output (``bench.json`` or its folder),
    filtered by scene label (a built-in name or the dataset folder's name), method and option
    values (rows must have swept exactly these values); budgets in seconds only."""
    path = Path(table)
    if path.is_dir():
        path = path / "bench.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no bench table (run `nerfbot bench ... --out DIR`)")
    doc = json.loads(path.read_text())
    rows = doc.get("summary") or []
    out = []
    for r in rows:
        if r.get("budget_kind", "seconds") != "seconds":
            continue
        if scene is not None and r.get("scene") != scene:
            continue
        if method is not None and r.get("method") != method:
            continue
        if options and any(r.get(f"option_{k}") != v for k, v in options.items()):
            continue
        out.append(r)
    return out


def choose_budget(rows: Sequence[dict], target_psnr: Optional[float] = None,
                  time_budget: Optional[float] = None) -> dict:
    """The row to train like: with ``target_psnr``, the cheapest (train seconds) that reaches
    it, else the best PSNR; with ``time_budget``, the best PSNR among rows trained within it.

    Raises:
        ValueError: no rows, both or neither target given, or no row within the time budget.
    """
    if (target_psnr is None) == (time_budget is None):
        raise ValueError("give exactly one of target_psnr and time_budget")
    rows = [r for r in rows if r.get("psnr") is not None and r.get("train_seconds") is not None]
    if not rows:
        raise ValueError("no bench rows with PSNR and train time to choose from")
    if target_psnr is not None:
        reaching = [r for r in rows if r["psnr"] >= target_psnr]
        if reaching:
            return min(reaching, key=lambda r: (r["train_seconds"], -r["psnr"]))
        log.warning("no configuration reaches %.2f dB; taking the best (%.2f dB)", target_psnr,
                    max(r["psnr"] for r in rows))
        return max(rows, key=lambda r: r["psnr"])
    within = [r for r in rows if r["train_seconds"] <= time_budget * 1.05]
    if not within:
        raise ValueError(f"no configuration trains within {time_budget:g} s "
                         f"(fastest: {min(r['train_seconds'] for r in rows):.0f} s)")
    return max(within, key=lambda r: (r["psnr"], -r["train_seconds"]))
