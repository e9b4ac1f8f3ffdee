"""Speed/accuracy sweeps: methods x budgets x knobs x scenes, medians, baselines, Pareto fronts.

A sweep point is (scene, image size, method, option values, budget, repeat). Every point trains
a model from scratch in a process of its own (:mod:`nerfbot.bench.point`) and reports train
seconds, steps/s, peak RSS, render ms per image and FPS, PSNR, SSIM, depth MAE / RMSE and the
Chamfer distance (mm) between a marching-cubes mesh of the field and the scene's true MuJoCo
geometry. Points run strictly one at a time locally (:mod:`nerfbot.bench.executors`), or one per
node on a Ray cluster.

Outputs in the ``out`` folder: ``bench.json`` (settings, every run, failures, summary),
``bench.csv`` (one row per configuration: medians over the repeats), ``bench_runs.csv`` (every
repeat), ``bench.md`` (Markdown tables per scene), ``psnr_vs_train_time.png`` and
``psnr_vs_render_fps.png`` (Pareto fronts marked), ``data/`` (captures of built-in scenes) and
``runs/`` (one folder per point: point.json, result.json, log.txt).

Rerunning resumes: points whose key is already in ``bench.json`` are not run again unless
``force``. Ratios use a baseline measured in the same sweep: per scene, the first
configuration in sweep order (first size, method, option values and budget) that has results.
A resumed sweep mixes runs of several invocations; every run records ``measured_at``.
``out`` must be new, empty or a bench folder; a folder holding anything else is refused
(:mod:`nerfbot.data.outputs`).
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import logging
import math
import re
from dataclasses import asdict, dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from tqdm.auto import tqdm

from nerfbot.bench.executors import EXECUTORS, BenchError, make_executor
from nerfbot.bench.plots import markdown_table, plot_tradeoffs
from nerfbot.bench.point import capture_builtin
from nerfbot.data import DatasetError, load_dataset
from nerfbot.data.outputs import check_output_folder
from nerfbot.data.writers import write_json_atomic
from nerfbot.methods import METHODS, sweep_option_names
from sims.scene import builtin_scenes, parse_generated

log = logging.getLogger(__name__)

__all__ = ["BenchConfig", "BenchError", "EXECUTORS", "pareto_front", "run_bench",
           "parse_option_sweep", "summarize"]

BUILTIN_SIZE = 128
#: The pseudo-method whose points train what ``--method auto`` picks from each scene's manifest.
AUTO = "auto"
#: Metrics of a run that are medians in the summary, in table order.
METRICS = ("psnr", "psnr_non_sky", "psnr_objects", "ssim", "depth_mae_m", "depth_rmse_m",
           "depth_mae_objects_m", "chamfer_mm", "chamfer_accuracy_mm",
           "chamfer_completeness_mm", "train_seconds", "steps", "steps_per_second",
           "render_ms_per_image", "render_fps", "peak_rss_mb", "num_params", "size_mb",
           "mesh_faces", "source_psnr", "source_render_ms_per_image", "render_speedup_vs_source",
           "psnr_change_vs_source", "bake_seconds")
#: Counts among METRICS (medians rounded to integers).
COUNT_METRICS = ("steps", "num_params", "mesh_faces")


@dataclass
class BenchConfig:
    """What to sweep and how to measure it (``nerfbot bench`` options)."""

    data: list
    """Dataset folders and/or built-in scene names (``tabletop``, ``builtin:glassware:3``)."""
    methods: list
    budgets: list
    """Training budgets, seconds (``budget_kind="seconds"``) or steps."""
    out: Path
    budget_kind: str = "seconds"
    sizes: list = field(default_factory=lambda: [None])
    """Image sizes (longer side, pixels): captures of built-in scenes are made at that size,
    datasets are downscaled to it. None: built-ins at 128, datasets as they are."""
    options: dict = field(default_factory=dict)
    """Method option -> values to sweep, e.g. {"log2_hashmap_size": [15, 17, 19]}. A method
    sweeps only the options it accepts."""
    repeats: int = 1
    seed: int = 0
    """Repeat r trains with seed ``seed + r``; captures of built-in scenes use rig seed ``seed``."""
    views: int = 60
    test_views: int = 10
    eval_images: Optional[int] = None
    """Evaluate on the first N test images (default all)."""
    chamfer: bool = True
    mesh_resolution: int = 128
    mesh_threshold: Optional[float] = None
    """Surface density (1/m); None: :func:`nerfbot.query.meshing.default_density_threshold`."""
    chamfer_points: int = 100_000
    visible_only: bool = True
    """Chamfer over the surface parts the training cameras see (see
    :mod:`nerfbot.query.meshing`)."""
    executor: str = "local"
    address: Optional[str] = None
    ray_num_cpus: Optional[int] = None
    force: bool = False
    keep_checkpoints: bool = False
    progress: bool = True

    def measurement_settings(self) -> dict:
        """Settings that change a run's numbers without being part of its key; a resumed sweep
        must use the same."""
        return {"eval_images": self.eval_images, "chamfer": self.chamfer_settings()}

    def chamfer_settings(self) -> Optional[dict]:
        if not self.chamfer:
            return None
        return {"mesh_resolution": self.mesh_resolution, "mesh_threshold": self.mesh_threshold,
                "chamfer_points": self.chamfer_points, "visible_only": self.visible_only}


# -- parsing helpers ---------------------------------------------------------------------------
def _json_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text.strip()


def parse_option_sweep(text: str) -> tuple[str, list]:
    """``key=v1,v2,...`` -> (key, [v1, v2, ...]), each value parsed as JSON when it is JSON."""
    if "=" not in text:
        raise ValueError(f"--option expects key=v1,v2,..., got {text!r}")
    key, values = text.split("=", 1)
    parsed = [_json_value(v) for v in values.split(",") if v.strip()]
    if not key.strip() or not parsed:
        raise ValueError(f"--option expects key=v1,v2,..., got {text!r}")
    return key.strip(), parsed


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "x"


# -- scenes ------------------------------------------------------------------------------------
@dataclass
class Source:
    """One ``--data`` entry: a built-in scene to capture, or a dataset folder."""

    label: str
    builtin: Optional[str] = None
    path: Optional[Path] = None


def classify_data(entries: Sequence[str]) -> list[Source]:
    """Sources of the ``--data`` entries; BenchError naming an entry that is neither an existing
    dataset nor a built-in scene. Datasets are loaded once to validate them."""
    sources = []
    for entry in entries:
        text = str(entry).strip()
        name = text[len("builtin:"):] if text.startswith("builtin:") else text
        path = Path(text).expanduser()
        try:
            is_builtin = "/" not in name and (name in builtin_scenes()
                                              or parse_generated(name) is not None)
        except ValueError as err:
            raise BenchError(f"--data {text!r}: {err}") from None
        if path.exists() and not text.startswith("builtin:"):
            try:
                ds = load_dataset(path)
            except (DatasetError, ValueError, OSError) as err:
                raise BenchError(f"--data {text!r}: not a readable dataset: {err}") from None
            if not ds.splits.get("test"):
                raise BenchError(f"--data {text!r}: the dataset has no test frames to evaluate")
            label = (path if path.is_dir() else path.parent).resolve().name
            sources.append(Source(label, path=path.resolve()))
        elif is_builtin:
            sources.append(Source(name, builtin=name))
        else:
            raise BenchError(f"--data {text!r}: no such dataset folder and not a built-in scene "
                             f"(built-in: {', '.join(builtin_scenes())})")
    labels = [s.label for s in sources]
    for s in sources:  # two datasets in folders of the same name: add the parent's name
        if labels.count(s.label) > 1 and s.path is not None:
            s.label = f"{s.path.parent.name}/{s.label}"
    if len({s.label for s in sources}) != len(sources):
        raise BenchError(f"--data lists the same scene twice: {', '.join(labels)}")
    return sources


def capture_spec(cfg: BenchConfig, scene: str, size: Optional[int]) -> dict:
    return {"scene": scene, "size": int(size or BUILTIN_SIZE), "views": cfg.views,
            "test_views": cfg.test_views, "seed": cfg.seed}


def capture_folder(cfg: BenchConfig, spec: dict) -> Path:
    return Path(cfg.out) / "data" / _slug(
        f"{spec['scene']}-{spec['size']}px-{spec['views']}v{spec['test_views']}t-seed{spec['seed']}")


# -- the sweep ---------------------------------------------------------------------------------
def validate(cfg: BenchConfig) -> None:
    """BenchError for anything wrong before work starts (methods, options, budgets, executor)."""
    if not cfg.methods:
        raise BenchError("no methods given")
    for m in cfg.methods:
        if m not in METHODS and m != AUTO:
            raise BenchError(f"unknown method {m!r}; available: {', '.join(sorted(METHODS))}, "
                             f"{AUTO}")
    if len(set(cfg.methods)) != len(cfg.methods):
        raise BenchError(f"a method is listed twice: {','.join(cfg.methods)}")
    named = [m for m in cfg.methods if m != AUTO]
    for key in cfg.options:
        if not any(key in sweep_option_names(m) for m in named):
            known = "; ".join(f"{m}: {', '.join(sweep_option_names(m))}" for m in named)
            raise BenchError(f"--option {key}: none of the methods ({', '.join(cfg.methods)}) "
                             f"has this option (known: {known})")
    if cfg.budget_kind not in ("seconds", "steps"):
        raise BenchError(f"budget kind must be 'seconds' or 'steps', got {cfg.budget_kind!r}")
    if not cfg.budgets or any(not (b > 0 and math.isfinite(b)) for b in cfg.budgets):
        raise BenchError(f"budgets must be positive numbers, got {cfg.budgets}")
    if cfg.budget_kind == "steps" and any(b != int(b) for b in cfg.budgets):
        raise BenchError(f"step budgets must be whole numbers, got {cfg.budgets}")
    if any(s is not None and s < 8 for s in cfg.sizes):
        raise BenchError(f"image sizes must be >= 8 pixels, got {cfg.sizes}")
    if cfg.repeats < 1:
        raise BenchError(f"repeats must be >= 1, got {cfg.repeats}")
    if not cfg.data:
        raise BenchError("no --data given")
    if cfg.executor not in EXECUTORS:
        raise BenchError(f"unknown executor {cfg.executor!r}; available: {', '.join(EXECUTORS)}")


def _budget_value(cfg: BenchConfig, b: float):
    return int(b) if cfg.budget_kind == "steps" else float(b)


def config_key(point: dict) -> str:
    """Key of a point's configuration (everything but the repeat)."""
    return json.dumps({k: point[k] for k in ("scene", "capture_id", "size", "method",
                                             "budget_kind", "budget", "options")},
                      sort_keys=True)


def expand_points(cfg: BenchConfig, sources: list[Source]) -> list[dict]:
    """Every point of the sweep, repeat by repeat, each repeat in sweep order: scene, size,
    method, option values, budget. The machine's speed drifts over a sweep (2x within minutes
    here): running one repeat of every configuration before the next spreads the drift over
    the configurations, where running each configuration's repeats back to back biased the
    ones that happened to run in a slow spell. A point is a JSON-able dict (see
    :func:`nerfbot.bench.point.run_point`)."""
    points = []
    sizes, budgets = list(dict.fromkeys(cfg.sizes)), list(dict.fromkeys(cfg.budgets))
    for src, size, method in itertools.product(sources, sizes, cfg.methods):
        spec = capture_spec(cfg, src.builtin, size) if src.builtin else None
        data_path = capture_folder(cfg, spec) if spec else src.path
        capture_id = None if spec is None else f"{spec['views']}v{spec['test_views']}t-seed{spec['seed']}"
        # auto decides its own options from the scene manifest: it takes the fixed settings
        # (options given one value) but is never swept
        keys = [k for k in cfg.options if len(cfg.options[k]) == 1] if method == AUTO else \
            [k for k in cfg.options if k in sweep_option_names(method)]
        values = [list({json.dumps(v): v for v in cfg.options[k]}.values()) for k in keys]
        for combo in itertools.product(*values):
            options = dict(zip(keys, combo))
            for budget, repeat in itertools.product(budgets, range(cfg.repeats)):
                p = {"scene": src.label, "capture_id": capture_id,
                     "size": None if size is None else int(size), "method": method,
                     "budget_kind": cfg.budget_kind, "budget": _budget_value(cfg, budget),
                     "options": options, "repeat": repeat}
                p["config_key"] = config_key(p)
                p["key"] = json.dumps({"config": p["config_key"], "repeat": repeat,
                                       "seed": cfg.seed}, sort_keys=True)
                digest = hashlib.sha1(p["key"].encode()).hexdigest()[:8]
                opts = "-".join(f"{k}{v}" for k, v in options.items())
                p["run_name"] = _slug(f"{src.label}-{size or 'native'}-{method}-{opts}-"
                                      f"{p['budget']}{cfg.budget_kind[:2]}-r{repeat}-{digest}")
                p.update(seed=cfg.seed + repeat, data_path=str(data_path), capture=spec,
                         eval_images=cfg.eval_images, chamfer=cfg.chamfer_settings(),
                         keep_checkpoint=cfg.keep_checkpoints)
                points.append(p)
    points.sort(key=lambda p: p["repeat"])  # stable: sweep order within a repeat
    return points


def prepare_captures(cfg: BenchConfig, points: list[dict]) -> None:
    """Capture every built-in scene the points need (once per spec; kept for resumes)."""
    done = set()
    for p in points:
        spec, path = p["capture"], Path(p["data_path"])
        if spec is None or p["data_path"] in done:
            continue
        done.add(p["data_path"])
        if not (path / "transforms.json").exists():
            log.info("capturing %s at %d px (%d + %d views) into %s", spec["scene"], spec["size"],
                     spec["views"], spec["test_views"], path)
            capture_builtin(spec, path, progress=cfg.progress)


# -- aggregation -------------------------------------------------------------------------------
def pareto_front(x: Sequence[float], y: Sequence[float], x_lower_is_better: bool = True) -> list[bool]:
    """Which points are non-dominated when higher ``y`` is better and ``x`` is better lower
    (``x_lower_is_better``) or higher. A point is dominated if another is at least as good in
    both and strictly better in one; points with a missing / NaN coordinate are never on the
    front. Ties (identical points) are all on the front."""
    xs = np.array([np.nan if v is None else float(v) for v in x], float)
    ys = np.array([np.nan if v is None else float(v) for v in y], float)
    if not x_lower_is_better:
        xs = -xs
    ok = np.isfinite(xs) & np.isfinite(ys)
    front = []
    for i in range(len(xs)):
        if not ok[i]:
            front.append(False)
            continue
        better_eq = ok & (xs <= xs[i]) & (ys >= ys[i])
        strictly = (xs < xs[i]) | (ys > ys[i])
        front.append(not bool(np.any(better_eq & strictly)))
    return front


def _median(values: list):
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.median(v)) if v else None


def summarize(points: list[dict], runs: dict) -> list[dict]:
    """One row per configuration of ``points`` that has successful runs: medians over repeats,
    ratios to each scene's baseline, Pareto flags. Rows are in sweep order."""
    groups: dict[str, list[dict]] = {}
    first: dict[str, dict] = {}
    for p in points:
        first.setdefault(p["config_key"], p)
        if p["key"] in runs:
            groups.setdefault(p["config_key"], []).append(runs[p["key"]])
    option_keys = sorted({k for p in points for k in p["options"]})
    rows = []
    for ck, p in first.items():
        results = groups.get(ck)
        if not results:
            continue
        row = {"scene": p["scene"], "size": p["size"], "image_size": results[0].get("image_size"),
               "method": p["method"], "budget_kind": p["budget_kind"], "budget": p["budget"],
               "options": ";".join(f"{k}={v}" for k, v in p["options"].items()),
               **{f"option_{k}": p["options"].get(k) for k in option_keys},
               "repeats": len(results)}
        if p["method"] == AUTO:  # show what auto picked
            row["method"] = f"{AUTO}:{results[0].get('auto_method')}"
            row["options"] = results[0].get("auto_options", "")
        if results[0].get("source_method"):
            row["source_method"] = results[0]["source_method"]
        for m in METRICS:
            row[m] = _median([r.get(m) for r in results])
            if m in COUNT_METRICS and row[m] is not None:
                row[m] = int(round(row[m]))
        rows.append(row)
    for scene in dict.fromkeys(r["scene"] for r in rows):
        mine = [r for r in rows if r["scene"] == scene]
        base = mine[0]
        for r in mine:
            r["baseline"] = r is base
            r["speedup_vs_baseline"] = _ratio(r["render_fps"], base["render_fps"])
            r["train_time_ratio"] = _ratio(r["train_seconds"], base["train_seconds"])
        psnr = [r["psnr"] for r in mine]
        for r, a, b in zip(mine, pareto_front([r["train_seconds"] for r in mine], psnr, True),
                           pareto_front([r["render_fps"] for r in mine], psnr, False)):
            r["pareto_train_time"], r["pareto_render_fps"] = a, b
        for r in mine:
            # --method auto against the best other configuration of the sweep at the same
            # budget and image size
            others = [o for o in mine if not o["method"].startswith(AUTO) and o["psnr"] is not None
                      and (o["budget"], o["size"]) == (r["budget"], r["size"])]
            best = max(others, key=lambda o: o["psnr"], default=None)
            if r["method"].startswith(AUTO) and best is not None and r["psnr"] is not None:
                r["psnr_gap_to_best"] = best["psnr"] - r["psnr"]
                r["best_config"] = f"{best['method']} {best['options']}".strip()
                r["best_train_seconds"] = best["train_seconds"]
    return rows


def _ratio(a, b):
    return None if a is None or not b else a / b


# -- outputs -----------------------------------------------------------------------------------
def _write_csv(path: Path, rows: list[dict]) -> None:
    columns = list(dict.fromkeys(k for r in rows for k in r))
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, columns, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: "" if r.get(k) is None else r.get(k) for k in columns})
    tmp.replace(path)


def _run_row(point: dict, result: dict) -> dict:
    cfg = {k: point[k] for k in ("scene", "size", "method", "budget_kind", "budget", "repeat",
                                 "seed")}
    cfg["options"] = ";".join(f"{k}={v}" for k, v in point["options"].items())
    return {**cfg, **{k: v for k, v in result.items() if k != "key"}}


def write_outputs(out: Path, cfg: BenchConfig, points: list[dict], runs: dict, failures: dict,
                  plots: bool = False) -> list[dict]:
    """(Re)write bench.json / .csv / .md (and the plots); returns the summary rows."""
    rows = summarize(points, runs)
    doc = {"version": 1, "settings": cfg.measurement_settings(),
           "sweep": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()},
           "runs": list(runs.values()), "failures": list(failures.values()), "summary": rows}
    write_json_atomic(out / "bench.json", doc, allow_nan=True)
    _write_csv(out / "bench.csv", rows)
    by_key = {p["key"]: p for p in points}
    _write_csv(out / "bench_runs.csv", [_run_row(by_key[k], r) for k, r in runs.items()
                                        if k in by_key])
    md = markdown_table(rows, cfg)
    tmp = out / ".bench.md.tmp"
    tmp.write_text(md)
    tmp.replace(out / "bench.md")
    if plots:
        plot_tradeoffs(rows, out)
    return rows


def _load_previous(cfg: BenchConfig) -> tuple[dict, dict]:
    """(runs by key, failures by key) of an earlier sweep in ``cfg.out``."""
    path = Path(cfg.out) / "bench.json"
    if not path.exists():
        return {}, {}
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise BenchError(f"{path}: not readable JSON ({err}); move it away to start over") from None
    runs = {r["key"]: r for r in doc.get("runs", [])}
    if doc.get("settings") != json.loads(json.dumps(cfg.measurement_settings())):
        if not cfg.force:
            raise BenchError(f"{path} was measured with other settings ({doc.get('settings')}, "
                             f"now {cfg.measurement_settings()}); pass --force to measure again "
                             "or choose another --out")
        runs = {}
    return runs, {f["key"]: f for f in doc.get("failures", [])}


@dataclass
class BenchResult:
    rows: list
    """Summary rows (medians) of this sweep's configurations."""
    ran: int
    skipped: int
    failures: list
    out: Path


def run_bench(cfg: BenchConfig) -> BenchResult:
    """Run (or resume) the sweep ``cfg`` and write its outputs; see the module docstring.

    Raises:
        BenchError: an unknown method, option, executor or dataset (named in the message), or
            an ``out`` that is neither new, empty nor a bench folder (see
            :mod:`nerfbot.data.outputs`), before any point runs.
    """
    validate(cfg)
    executor = make_executor(cfg.executor, address=cfg.address, num_cpus=cfg.ray_num_cpus)
    out = Path(cfg.out)
    sources = classify_data(cfg.data)
    try:
        folder = check_output_folder(out, "bench")
    except FileExistsError as err:
        raise BenchError(str(err)) from None
    runs, failures = _load_previous(cfg)
    folder.prepare()
    (out / "runs").mkdir(parents=True, exist_ok=True)
    points = expand_points(cfg, sources)
    todo = [p for p in points if cfg.force or p["key"] not in runs]
    prepare_captures(cfg, todo)
    if len(todo) < len(points):
        log.info("resuming: %d of %d points already measured in %s", len(points) - len(todo),
                 len(points), out / "bench.json")
    write_outputs(out, cfg, points, runs, failures)
    bar = tqdm(total=len(points), initial=len(points) - len(todo), unit="point", desc="bench",
               disable=not cfg.progress, dynamic_ncols=True)
    try:
        for point, result in (executor.run(todo, out / "runs") if todo else ()):
            result["measured_at"] = datetime.now().astimezone().isoformat(timespec="seconds")
            if result.get("status") == "ok":
                runs[point["key"]] = result
                failures.pop(point["key"], None)
            else:  # (with --force, an earlier run of this point is dropped too)
                runs.pop(point["key"], None)
                failures[point["key"]] = result
                log.error("point %s failed: %s", point["run_name"], result.get("error"))
            write_outputs(out, cfg, points, runs, failures)
            bar.set_postfix_str(f"{point['scene']} {point['method']} {point['budget']}", refresh=False)
            bar.update(1)
    finally:
        bar.close()
    rows = write_outputs(out, cfg, points, runs, failures, plots=True)
    mine = {p["key"] for p in points}
    return BenchResult(rows, len(todo), len(points) - len(todo),
                       [f for k, f in failures.items() if k in mine], out)
