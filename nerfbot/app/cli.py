"""The ``nerfbot`` command: capture, colmap, train, eval, label, bake, estimate-joints, render,
view, export, demo, bench, pixelnerf.

Heavy imports happen inside each command so ``nerfbot --help`` stays instant. ``sims`` is
imported before anything that imports ``mujoco``, so headless machines get ``MUJOCO_GL=egl``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from nerfbot.app import pixelnerf_cli

log = logging.getLogger("nerfbot")

#: Exit codes: 0 success, 1 a failure inside nerfbot (a bug, or a run that diverged), 2 bad
#: input (a flag, a file, a folder), 130 interrupted.
EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 1, 2, 130


class UsageError(Exception):
    """A flag, or a combination of flags, that the command cannot run with."""


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line naming the flag, with exit code 2."""

    def error(self, message: str):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


class DeferredParser(OneLineParser):
    """A sub-parser that can add its arguments when it is first used (to parse, or to print its
    help) rather than when it is made: ``add_arguments(parser)`` may import what it needs then.

    The ``capture`` command's arguments come from :mod:`sims.cli`, which imports mujoco.
    """

    def __init__(self, *args, add_arguments=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._add_arguments = add_arguments

    def add_deferred_arguments(self) -> None:
        """Add the deferred arguments now (once)."""
        add, self._add_arguments = self._add_arguments, None
        if add is not None:
            add(self)

    def parse_known_args(self, args=None, namespace=None):
        self.add_deferred_arguments()
        return super().parse_known_args(args, namespace)

    def format_usage(self):
        self.add_deferred_arguments()
        return super().format_usage()

    def format_help(self):
        self.add_deferred_arguments()
        return super().format_help()


def one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line (an OSError's strerror and file name kept)."""
    text = str(exc) or type(exc).__name__
    if isinstance(exc, KeyError) and exc.args:
        text = str(exc.args[0])
    return " ".join(part.strip() for part in text.splitlines() if part.strip())


# -- helpers ---------------------------------------------------------------------------------
def parse_option(text: str) -> tuple[str, object]:
    """``key=value`` -> (key, value), the value parsed as JSON when it is JSON (numbers, bools)."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"--option expects key=value, got {text!r}")
    key, value = text.split("=", 1)
    try:
        return key.strip(), json.loads(value)
    except json.JSONDecodeError:
        return key.strip(), value


def _parse_background(text: str | None):
    if text is None or text in ("learned", "white", "black"):
        return text
    try:
        parts = [float(v) for v in text.split(",")]
    except ValueError:
        parts = []
    if len(parts) != 3 or not all(0.0 <= p <= 1.0 for p in parts):
        raise UsageError(f"--background: expected learned, white, black or R,G,B in [0, 1], "
                         f"got {text!r}")
    return parts


def _number(convert, accept, expected: str):
    """An argparse type: ``convert(text)`` (int or float) when ``accept`` takes it, else an
    error saying what was ``expected``."""
    def parse(text: str):
        try:
            value = convert(text)
        except ValueError:
            value = None
        if value is None or not accept(value):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value
    return parse


_positive_int = _number(int, lambda v: v >= 1, "a positive integer")
#: An integer >= 0: a count, or a random seed (numpy's generators take no negative seeds).
_non_negative_int = _number(int, lambda v: v >= 0, "an integer >= 0")
_positive_float = _number(float, lambda v: 0.0 < v < math.inf, "a positive finite number")
#: A number >= 0, ``inf`` allowed (a cadence that never comes).
_non_negative_float = _number(float, lambda v: v >= 0.0, "a number >= 0")
_fraction = _number(float, lambda v: 0.0 <= v <= 1.0, "a number in [0, 1]")
#: A distance between unit vectors.
_unit_distance = _number(float, lambda v: 0.0 <= v <= 2.0, "a number from 0 to 2")
#: A time in [0, 1] (the span of a dynamic capture).
_unit_time = _number(float, lambda v: 0.0 <= v <= 1.0, "a time in [0, 1]")
#: A TCP port; 0 lets the system pick a free one.
_port = _number(int, lambda v: 0 <= v <= 65535, "a port in [0, 65535]")


#: The longest image side a command renders (pixels); larger requests are refused up front
#: rather than failing in an allocation.
MAX_IMAGE_SIDE = 16384


def _image_side(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_IMAGE_SIDE:
        raise argparse.ArgumentTypeError(f"an image side of at most {MAX_IMAGE_SIDE} pixels, "
                                         f"got {text!r}")
    return value


def _device(text: str) -> str:
    """A torch device this machine has ("cpu", "cuda", "cuda:1", ...)."""
    import torch

    try:
        device = torch.device(text)
        torch.empty(0, device=device)
    except (RuntimeError, AssertionError) as err:  # unknown name, or no such device here
        reason = str(err).strip().splitlines()[0] if str(err).strip() else "not available"
        raise argparse.ArgumentTypeError(f"no device {text!r} here ({reason[:120]})")
    return text


def _times(text: str) -> tuple[float, ...]:
    """``S1,S2,...``: non-negative finite seconds."""
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = ()
    if not values or not all(0.0 <= v < math.inf for v in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated times in seconds, >= 0, "
                                         f"got {text!r}")
    return values


def _load_dataset(path, aabb=None, background=None):
    from nerfbot.data import load_dataset

    return load_dataset(path, aabb=aabb, background=background)


def _check_option_names(method: str, options: dict) -> None:
    """Refuse ``--option`` keys ``method`` does not have (before anything is written)."""
    from nerfbot.methods import option_names

    unknown = sorted(set(options) - set(option_names(method)))
    if unknown:
        raise UsageError(f"--option: method {method!r} has no option(s) {unknown}; known: "
                         f"{option_names(method)}")


# -- commands --------------------------------------------------------------------------------
def cmd_capture(args) -> int:
    from sims.cli import run_capture

    run_capture(args)
    return 0


#: ``nerfbot train`` flags that define what a run is (argparse dest -> the saved training
#: configuration's field; the bounds come from the saved spec): with ``--config`` or
#: ``--resume`` those not given come from the saved run (:func:`_follow_saved_config`).
RUN_FLAGS = {"method": "method", "seed": "seed", "lr": "lr", "option": "options",
             "background": "background", "depth_weight": "depth_weight",
             "depth_from": "depth_from", "sparse_depth_weight": "sparse_depth_weight",
             "sparse_depth_robust": "sparse_depth_robust",
             "sparse_depth_until": "sparse_depth_until", "labels": "labels",
             "label_clicks": "label_clicks", "label_weight": "label_weight",
             "dynamic_rays": "dynamic_rays", "dynamic_rays_debias": "dynamic_rays_debias",
             "error_rays": "error_rays", "error_rays_debias": "error_rays_debias",
             "error_tile": "error_tile", "eval_at": "eval_at_seconds", "aabb": None}


def _given_train_flags(argv: list[str]) -> set[str]:
    """The argparse dests of the ``nerfbot train`` flags written on the command line."""
    parser = build_parser()
    # argparse keeps its subparsers private; a copy of the train parser without defaults
    # parses to the flags that were written and nothing else
    train = next(a for a in parser._subparsers._group_actions
                 if isinstance(a, argparse._SubParsersAction)).choices["train"]
    for action in train._actions:
        action.default = argparse.SUPPRESS
        action.required = False
    given = train.parse_known_args(argv[argv.index("train") + 1:])[0]
    return set(vars(given))


def _saved_run(args) -> "tuple[Path, dict] | None":
    """(run folder, saved config.json) whose configuration this ``nerfbot train`` follows:
    ``--config FILE``, or with ``--resume`` the run in ``--out``; None otherwise."""
    from nerfbot.data.run_dataset import CONFIG
    from nerfbot.data.spec import read_json

    if args.config is not None:
        path = args.config / CONFIG if args.config.is_dir() else args.config
        if not path.is_file():
            raise UsageError(f"--config {path}: no such file")
        return path.parent, read_json(path)
    if args.resume and (Path(args.out) / CONFIG).is_file():
        return Path(args.out), read_json(Path(args.out) / CONFIG)
    return None


def _follow_saved_config(args, run: Path, saved: dict) -> dict:
    """Fill ``args`` from a run's saved configuration (``saved``: its config.json): every run
    flag (:data:`RUN_FLAGS`) not written on the command line takes the run's value. With
    ``--config`` a written one must equal it; with ``--resume`` the model's spec is compared
    when the checkpoint loads (:func:`nerfbot.train.runs.spec_differences`), the training
    weights here. Returns the saved training configuration."""
    from nerfbot.data.run_dataset import resolve_run_dataset

    where = run / "config.json"
    train, spec = saved.get("train"), saved.get("spec")
    if not isinstance(train, dict) or not isinstance(spec, dict):
        raise UsageError(f"{where}: not a run configuration (no 'train' and 'spec' objects)")
    given = _given_train_flags(getattr(args, "argv", None) or ["train"])
    values = {dest: train.get(key) for dest, key in RUN_FLAGS.items() if key is not None}
    values.update(option=dict(train.get("options") or {}), labels=bool(train.get("labels")),
                  eval_at=list(train.get("eval_at_seconds") or []) or None,
                  aabb=[v for corner in spec.get("aabb", []) for v in corner] or None,
                  background=None if train.get("background") is None else
                  _background_text(train["background"]),
                  # runs from before these flags drew rays uniformly
                  dynamic_rays=train.get("dynamic_rays", 0.0),
                  dynamic_rays_debias=train.get("dynamic_rays_debias", 0.5),
                  error_rays=train.get("error_rays", 0.0),
                  error_rays_debias=train.get("error_rays_debias", 1.0),
                  error_tile=train.get("error_tile", 8),
                  sparse_depth_robust=train.get("sparse_depth_robust", 0.0),
                  depth_from=train.get("depth_from", "depth"),
                  sparse_depth_until=train.get("sparse_depth_until", 1.0))
    checked = set(RUN_FLAGS) if args.config is not None else \
        {"lr", "depth_weight", "depth_from", "sparse_depth_weight", "sparse_depth_robust",
         "sparse_depth_until", "label_clicks", "label_weight", "dynamic_rays",
         "dynamic_rays_debias", "error_rays", "error_rays_debias", "error_tile", "eval_at"}
    conflicts = []
    for dest in sorted(checked & given):
        mine, theirs = _comparable(dest, getattr(args, dest)), _comparable(dest, values[dest])
        if mine != theirs:
            conflicts.append(f"--{dest.replace('_', '-')} {_shown(mine)} (the run's: "
                             f"{_shown(theirs)})")
    if conflicts and args.config is not None:
        raise UsageError(f"--config: {'; '.join(conflicts)} differ from {where}; leave them "
                         "out, or train without --config")
    if conflicts:
        raise UsageError(f"{run}: --resume with {'; '.join(conflicts)}; resume with the run's "
                         "options or train into a new --out")
    for dest, value in values.items():
        if dest not in given:
            setattr(args, dest, list(value.items()) if dest == "option" else value)
    if args.data is None:
        try:
            args.data, _ = resolve_run_dataset(run)
        except FileNotFoundError as err:
            raise UsageError(f"{where}: its dataset was not found ({err}); pass --data DIR")
    if "max_steps" not in given and "max_seconds" not in given:
        args.max_steps, args.max_seconds = train.get("max_steps"), train.get("max_seconds")
    return train


def _comparable(dest: str, value):
    """A run flag's value in one form for comparing the command line with a saved run."""
    if dest == "option":
        return dict(value or {})
    if dest == "background":
        return _parse_background(value) if isinstance(value, str) or value is None else value
    if dest == "aabb":
        return None if value is None else [round(float(v), 6) for v in value]
    if dest == "eval_at":
        return None if not value else [float(v) for v in value]
    return value


def _shown(value) -> str:
    return json.dumps(value) if isinstance(value, (dict, list, tuple)) else str(value)


def _background_text(background) -> str:
    """A saved background ("learned", or [r, g, b]) as ``--background`` text."""
    return background if isinstance(background, str) else ",".join(str(v) for v in background)


def cmd_train(args) -> int:
    from nerfbot.data.outputs import check_output_folder
    from nerfbot.train.checkpoints import CHECKPOINT

    if args.config is not None and args.resume:
        raise UsageError("give --config (train a new run as a saved one was) or --resume "
                         "(continue the run in --out), not both")
    saved = _saved_run(args)
    args.saved_train = _follow_saved_config(args, *saved) if saved else None
    # a run that --method auto made keeps its choice (and the query defaults) in auto.json
    args.saved_auto = saved[0] / "auto.json" if saved and args.config is not None and \
        (saved[0] / "auto.json").is_file() else None
    if args.data is None:
        raise UsageError("--data DIR is needed (or --config RUN/config.json, or --resume)")
    auto_goal = args.target_psnr is not None or args.time_budget is not None
    if args.method != "auto" and (auto_goal or args.bench_table is not None):
        raise UsageError("--target-psnr / --time-budget / --bench-table need "
                         "--method auto")
    if args.target_psnr is not None and args.time_budget is not None:
        raise UsageError("give --target-psnr or --time-budget, not both")
    if args.max_steps is None and args.max_seconds is None and not auto_goal:
        raise UsageError("give a budget, --max-steps N and/or --max-seconds S"
                         + (" (or, with --method auto, --target-psnr / --time-budget)"
                            if args.method == "auto" else ""))
    if args.resume and args.overwrite:
        raise UsageError("give --resume (continue the run in --out) or --overwrite (start it "
                         "over), not both")
    out = Path(args.out)
    folder = check_output_folder(out, "run", overwrite=args.overwrite, resume=args.resume)
    aabb = None if args.aabb is None else [args.aabb[:3], args.aabb[3:]]
    background = _parse_background(args.background)
    colour = None if background in (None, "learned") else background  # compositing colour
    ds = _load_dataset(args.data, aabb, colour)
    options = dict(args.option or [])
    if args.method != "auto":
        _check_option_names(args.method, options)
        _train_config(args, args.method, options, args.max_seconds, background).validate()
    # the run folder exists from here on; a failure before the first checkpoint removes it
    with folder.writing(keep=lambda: (out / CHECKPOINT).exists()):
        return _train_into(args, folder.path, ds, options, background)


def _train_config(args, method: str, options: dict, max_seconds, background):
    from nerfbot.train.trainer import TrainConfig

    saved = getattr(args, "saved_train", None) or {}
    # fields without a flag (e.g. label_rays, eval_at_steps) come from a followed run
    keep = {k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()
            if k in {"sparse_depth_rays", "label_rays", "eval_at_steps"}}
    return TrainConfig(**{**_flag_train_config(args, method, options, max_seconds, background),
                          **keep})


def _flag_train_config(args, method: str, options: dict, max_seconds, background) -> dict:
    """The training-configuration fields ``nerfbot train``'s flags set."""
    return dict(method=method, max_steps=args.max_steps,
                max_seconds=max_seconds, seed=args.seed, lr=args.lr,
                options=options, background=background,
                depth_weight=args.depth_weight, depth_from=args.depth_from,
                sparse_depth_weight=args.sparse_depth_weight,
                sparse_depth_robust=args.sparse_depth_robust,
                sparse_depth_until=args.sparse_depth_until,
                labels=args.labels or args.label_clicks is not None,
                label_weight=args.label_weight, label_clicks=args.label_clicks,
                dynamic_rays=args.dynamic_rays, dynamic_rays_debias=args.dynamic_rays_debias,
                error_rays=args.error_rays, error_rays_debias=args.error_rays_debias,
                error_tile=args.error_tile,
                eval_at_seconds=args.eval_at or (),
                checkpoint_every_seconds=args.checkpoint_every_seconds,
                checkpoint_every_steps=args.checkpoint_every_steps,
                device=args.device, progress=not args.no_progress)


def _train_into(args, out: Path, ds, options: dict, background) -> int:
    """The part of ``nerfbot train`` that writes into the run folder ``out``."""
    from nerfbot.eval.evaluation import evaluate
    from nerfbot.models.base import num_params
    from nerfbot.data.spec import read_json
    from nerfbot.data.writers import write_json_atomic
    from nerfbot.train.trainer import Trainer

    method, max_seconds = args.method, args.max_seconds
    if method == "auto":
        from nerfbot.bench.auto_sweep import auto_train_config
        from nerfbot.train.auto import choose_for_dataset

        try:
            choice = auto_train_config(choose_for_dataset(ds), Path(args.data), out, options,
                                       args.target_psnr, args.time_budget, args.bench_table)
        except (ValueError, FileNotFoundError) as err:
            raise UsageError(f"--method auto: {err}")
        method, options = choice.method, choice.options
        if choice.budget_seconds is not None:
            max_seconds = choice.budget_seconds
        for line in choice.reasons:
            log.info("auto: %s", line)
    config = _train_config(args, method, options, max_seconds, background)

    def curve_eval(model):
        return {"psnr": evaluate(model, ds, "test", max_images=args.eval_images,
                                 with_ssim=False)["psnr"]}

    scored = bool(ds.splits.get("test"))  # a one-frame dataset has no test frame
    if not scored:
        log.warning("%s: no 'test' frame (splits: %s); the run gets no test metrics", ds.root,
                    ds.split_sizes())
    trainer = Trainer(ds, out, config,
                      evaluate_fn=curve_eval if args.eval_at and scored else None,
                      command=getattr(args, "argv", None))
    if args.resume and trainer.load():
        log.info("resumed %s at step %d (%.1f s trained)", out, trainer.step, trainer.train_seconds)
    if args.method == "auto":  # after a resume was found consistent with the run
        write_json_atomic(out / "auto.json", choice.to_dict())
    elif getattr(args, "saved_auto", None) is not None:  # --config of a run auto chose
        write_json_atomic(out / "auto.json", read_json(args.saved_auto))
    summary = trainer.train()
    metrics = evaluate(trainer.model, ds, "test") if scored else {}
    metrics.update(method=method, num_params=num_params(trainer.model), **summary)
    write_json_atomic(out / "metrics.json", metrics, allow_nan=True)
    print(json.dumps(metrics, indent=2))
    return 0


def _float_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}")
    if not values:
        raise argparse.ArgumentTypeError("expected at least one number")
    return values


def _condition_pixelnerf(model, ds, args, run: Path) -> None:
    """Condition a pixelNeRF run on the frames ``args.sources`` of ``ds`` (the scene it
    renders), fine-tuned on them for ``args.finetune_seconds`` when given; UsageError for
    either option with any other run, or a pixelNeRF run without sources."""
    from nerfbot.models.pixelnerf import PixelNeRFModel
    from nerfbot.train.pixelnerf import FinetuneConfig, condition_on, finetune_on

    sources = getattr(args, "sources", None)
    finetune = getattr(args, "finetune_seconds", None)
    if not isinstance(model, PixelNeRFModel):
        if sources or finetune:
            option = "--sources" if sources else "--finetune-seconds"
            raise UsageError(f"{option}: {run} is not a pixelNeRF run (its scene is its own)")
        return
    if ds is None or not sources:
        raise UsageError(f"{run} is a pixelNeRF run: give the scene (--data) and the frames it "
                         "renders the scene from (--sources I,J,...)")
    try:
        if finetune:
            progress = not getattr(args, "no_progress", False)
            finetune_on(model, ds, sources, FinetuneConfig(steps=None, max_seconds=finetune,
                                                           progress=progress))
        else:
            condition_on(model, ds, sources)
    except ValueError as err:
        raise UsageError(f"--sources: {one_line(err)}") from None


def _run_and_dataset(args):
    """(model, checkpoint info, dataset folder, dataset) of ``args.run`` evaluated on
    ``args.data`` (default: the dataset the run was trained on); a pixelNeRF run is
    conditioned on the ``args.sources`` frames of ``args.data``."""
    from nerfbot.data.run_dataset import resolve_run_dataset
    from nerfbot.train.runs import load_model

    run = Path(args.run)
    model, info = load_model(run, args.device)
    if args.data:
        data, ds = Path(args.data), _load_dataset(args.data)
    elif info["spec"]["method"] == "pixelnerf":
        data, ds = None, None
    else:
        data, ds = resolve_run_dataset(run, info["spec"].get("dataset"))
    _condition_pixelnerf(model, ds, args, run)
    return model, info, data, ds


def cmd_eval(args) -> int:
    from nerfbot.eval.evaluation import evaluate
    from nerfbot.models.base import num_params

    model, info, data, ds = _run_and_dataset(args)
    refine = None
    if args.refine_poses:
        from nerfbot.query.localise import InerfConfig
        refine = InerfConfig(iterations=100, rays=1024, lr=2e-3)
    metrics = evaluate(model, ds, args.split, downscale=args.downscale,
                       supersample=args.supersample, refine_poses=refine,
                       supersample_pattern=args.supersample_pattern)
    metrics.update(method=info["spec"]["method"], num_params=num_params(model),
                   train_seconds=info["train_seconds"], steps=info["step"], split=args.split,
                   data=str(data))
    if args.depth_sweep:
        from nerfbot.eval.depth_eval import (DEFAULT_THRESHOLDS, depth_mode_sweep,
                                             plot_threshold_sweep)

        sweep = depth_mode_sweep(model, ds, args.split, args.thresholds or DEFAULT_THRESHOLDS,
                                 progress=not args.json)
        metrics["depth_sweep"] = sweep.to_dict()
        if args.plot:
            plot_threshold_sweep(sweep, args.plot, title=f"{data.name}: {args.split} split")
    if args.json:
        print(json.dumps(metrics))
    else:
        for k, v in metrics.items():
            print(f"{k:>22}: {v}")
    return 0


def cmd_label(args) -> int:
    """Train a label head on a finished run's frozen field and write the labelled run."""
    from nerfbot.eval.evaluation import evaluate
    from nerfbot.train.labelling import LabelTrainConfig, label_run

    _refuse_source_run(Path(args.run), Path(args.out), "labelled")
    model, info, data, ds = _run_and_dataset(args)
    config = LabelTrainConfig(steps=args.steps, clicks=args.clicks,
                              click_choice=args.click_choice, seed=args.seed)
    report = label_run(model, info, ds, data, Path(args.out), config, overwrite=args.overwrite,
                       progress=not args.no_progress)
    if ds.splits.get("test"):
        metrics = evaluate(model, ds, "test", with_ssim=False)
        report.update(label_miou=metrics.get("label_miou"), label_iou=metrics.get("label_iou"))
    report["out"] = str(args.out)
    print(json.dumps(report, indent=2))
    return 0


def _bake_request(args) -> tuple[str, dict]:
    """(baked method, bake options) of ``nerfbot bake``'s flags: ``--method M`` with its
    ``--option``s, where ``--cache NP,ND`` spells fastnerf_cache with options np, nd,
    ``--octree DEPTH`` plenoctree_octree with depth, and ``--finetune-steps N`` the option
    finetune_steps."""
    spelled = []  # (flag, the baked method it names or None, the options it gives)
    if args.method is not None:
        spelled.append(("--method", args.method, {}))
    if args.cache is not None:
        if len(args.cache) != 2:
            raise UsageError(f"--cache wants NP,ND (two integers), got {args.cache}")
        spelled.append(("--cache", "fastnerf_cache", {"np": args.cache[0], "nd": args.cache[1]}))
    if args.octree is not None:
        spelled.append(("--octree", "plenoctree_octree", {"depth": args.octree}))
    if args.finetune_steps is not None:
        spelled.append(("--finetune-steps", None, {"finetune_steps": args.finetune_steps}))
    methods = {method for _, method, _ in spelled if method}
    if not methods:
        from nerfbot.method_names import BAKED

        raise UsageError(f"give the baked method: --method {'|'.join(sorted(BAKED))}, or "
                         "--cache NP,ND (fastnerf) / --octree DEPTH (plenoctree)")
    if len(methods) > 1:
        raise UsageError(f"{' / '.join(f for f, m, _ in spelled if m)}: these name different "
                         f"baked methods ({', '.join(sorted(methods))}); give one")
    options = {k: v for _, _, given in spelled for k, v in given.items()}
    for key, value in args.option or []:
        if key in options:
            raise UsageError(f"--option {key}: given twice (--cache / --octree / "
                             "--finetune-steps set it too)")
        options[key] = value
    return methods.pop(), options


def _check_bake_options(method: str, options: dict) -> None:
    """Refuse options that the recipe of ``method`` does not bake with (before anything is
    written)."""
    from nerfbot.methods import bake_option_names

    known = bake_option_names(method)
    for key in options:
        if key not in known:
            flag = "--finetune-steps" if key == "finetune_steps" else f"--option {key}"
            raise UsageError(f"{flag}: {method} is baked with option(s) {', '.join(known)}")


def cmd_bake(args) -> int:
    """Bake a trained run into a faster renderer (a run folder of its own) with the recipe of
    the baked method in the registry, as a bench point does."""
    from nerfbot.train.baked_runs import write_baked_run
    from nerfbot.data.identity import dataset_identity
    from nerfbot.data.outputs import check_output_folder
    from nerfbot.methods import bake_model

    method, options = _bake_request(args)
    _check_bake_options(method, options)
    _refuse_source_run(Path(args.run), Path(args.out))
    check_output_folder(args.out, "baked_run", overwrite=args.overwrite)  # before baking
    model, info, data, ds = _run_and_dataset(args)
    baked, spec, extra = bake_model(method, model, info["spec"], ds, options, seed=args.seed,
                                    progress=not args.no_progress)
    extra = {"source_run": str(args.run), "source_method": info["spec"]["method"], **extra}
    spec = {**spec, "dataset": dataset_identity(ds)}  # the dataset at ``data``, as eval checks
    write_baked_run(baked, spec, info, args.out, data=data, extra=extra,
                    overwrite=args.overwrite)
    print(json.dumps(extra | {"out": str(args.out)}))
    return 0


def _refuse_source_run(run: Path, out: Path, what: str = "baked") -> None:
    """``nerfbot bake RUN --out RUN`` (or ``label``) would overwrite its source run."""
    import os

    same = out.exists() and run.exists() and os.path.samefile(out, run)
    if same or out.absolute() == run.absolute():
        raise FileExistsError(f"{out}: the run being {what}; choose another --out for the {what} "
                              "run")


def cmd_estimate_joints(args) -> int:
    from nerfbot.data.conditioning import Conditioning
    from nerfbot.query.joint_estimation import JointEstimateConfig, evaluate_joint_estimation

    model, info, data, ds = _run_and_dataset(args)
    conditioning = Conditioning.from_dict(info["spec"].get("conditioning"))
    cfg = JointEstimateConfig(seed=args.seed)
    if args.steps is not None:
        cfg.steps = args.steps
    idx = ds.indices(args.split)[::args.every]
    if args.max_images:
        idx = idx[:args.max_images]
    result = evaluate_joint_estimation(model, ds, conditioning, idx, config=cfg,
                                       progress=not args.json and not args.no_progress)
    result.update(method=info["spec"]["method"], split=args.split, data=str(data),
                  num_images=len(idx))
    if args.json:
        print(json.dumps(result))
    else:
        for r in result["per_image"]:
            errs = ", ".join(f"{n} {e:.2f} {result['units'][n]}" for n, e in r["error"].items())
            print(f"{r['frame']}: {errs}")
        for n, e in result["median_error"].items():
            print(f"median error {n}: {e:.2f} {result['units'][n]} (mean "
                  f"{result['mean_error'][n]:.2f})")
    return 0


def _view_intrinsics(model, size, ds) -> tuple:
    """(vertical fov in degrees, width, height, target (3,), radius, elevation in degrees) of
    rendered views that are framed like the training cameras of the dataset ``ds`` when it is
    known (not None), else from the run's bounds; ``size`` (``--size``) overrides the size."""
    import numpy as np

    aabb = model.aabb.cpu().numpy()
    target = 0.5 * (aabb[0] + aabb[1])
    radius, elevation, fov = 2.0 * float(np.linalg.norm(aabb[1] - aabb[0])), 30.0, 40.0
    width = height = 128
    if ds is not None:
        idx = ds.indices("train") if ds.splits.get("train") else list(range(len(ds)))
        offsets = ds.c2w[idx, :3, 3] - target
        dist = np.linalg.norm(offsets, axis=1)
        radius = float(np.median(dist))
        elevation = float(np.degrees(np.median(np.arcsin(offsets[:, 2] / dist))))
        width, height = (int(v) for v in ds.sizes[idx[0]])
        fov = float(np.degrees(2 * np.arctan(0.5 * height / ds.intrinsics[idx[0], 1])))
    if size:
        width, height = (size[0], size[0]) if len(size) == 1 else size[:2]
    return fov, width, height, target, radius, elevation


def _orbit_cameras(model, frames: int, size, ds):
    """An orbit around the scene, framed like the training cameras of the dataset ``ds`` when
    it is known (not None)."""
    from nerfbot.ops.cameras import Cameras, orbit_poses

    fov, width, height, target, radius, elevation = _view_intrinsics(model, size, ds)
    return Cameras.pinhole(orbit_poses(target, radius, elevation, frames), fov, width, height)


def _path_cameras(path: Path, frames: int, model, size, ds):
    """Cameras along the keyframes of pose file ``path`` (the format ``nerfbot capture
    --poses`` reads: :func:`sims.rigs.read_pose_file`), ``frames`` of them, interpolated
    (:func:`nerfbot.ops.camera_path.interpolate_poses`); intrinsics as the orbit's."""
    import numpy as np

    from nerfbot.ops.camera_path import interpolate_poses
    from nerfbot.ops.cameras import Cameras
    from sims.rigs import read_pose_file

    try:
        keys = read_pose_file(path)
    except FileNotFoundError as err:
        raise UsageError(f"--poses: {err}") from err
    except ValueError as err:
        raise UsageError(f"--poses {err}") from err
    if isinstance(keys, dict):
        raise UsageError(f"--poses {path}: a camera path is one list of poses (a list, or "
                         f"'poses' / 'frames'), not per-split lists {sorted(keys)}")
    if not keys:
        raise UsageError(f"--poses {path}: the file holds no pose")
    try:
        poses = interpolate_poses(np.stack(keys), frames)
    except ValueError as err:
        raise UsageError(f"--poses {path}: {err}") from err
    fov, width, height, *_ = _view_intrinsics(model, size, ds)
    return Cameras.pinhole(poses, fov, width, height)


def _render_dataset(args, run: Path, info, needed: bool):
    """The dataset ``nerfbot render`` takes its views from: ``--data``, else the one the run
    was trained on (found and checked by :func:`resolve_run_dataset`). When it is not
    ``needed`` (an orbit) and cannot be found, None: the orbit is framed from the bounds."""
    from nerfbot.data.run_dataset import resolve_run_dataset

    if args.data:
        return _load_dataset(args.data)
    if info["spec"]["method"] == "pixelnerf":
        return None  # trained across scenes: the scene is --data
    try:
        return resolve_run_dataset(run, info["spec"].get("dataset"))[1]
    except FileNotFoundError as err:
        if needed:
            raise
        log.warning("%s; framing the orbit from the scene bounds", one_line(err))
        return None


def _check_condition_flags(args, conditioning) -> None:
    """--time / --joints only for runs conditioned on them (UsageError otherwise)."""
    for flag, given, kind in (("--time", args.time is not None, "time"),
                              ("--joints", bool(args.joints), "joints")):
        if given and conditioning.kind != kind:
            raise UsageError(f"{flag}: {args.run} is a {conditioning.kind} run, not conditioned "
                             f"on {kind}")


def _render_plan(args, model, info, ds):
    """Cameras and per-image conditions (or None) for ``nerfbot render`` (``ds``: the dataset
    of :func:`_render_dataset`)."""
    import numpy as np
    import torch

    from nerfbot.data.conditioning import Conditioning, frame_conditions
    from nerfbot.query.render import sweep_conditions

    conditioning = Conditioning.from_dict(info["spec"].get("conditioning"))
    _check_condition_flags(args, conditioning)
    fixed = None
    if args.time is not None or args.joints:
        fixed = conditioning.vector(args.time, args.joints)
    if args.sweep and args.poses:
        raise UsageError("--sweep and --poses: a sweep orbits the scene; give one of them")
    if args.sweep:
        if conditioning.is_static:
            raise ValueError(f"{args.run}: --sweep needs a time- or joint-conditioned run; this "
                             "one is static")
        conds = sweep_conditions(conditioning, args.sweep, args.frames, fixed)
        views = max(args.sweep_views, 1)
        cams = _orbit_cameras(model, views, args.size, ds)
        return cams[torch.as_tensor(np.arange(len(conds)) * views // len(conds))], conds
    if args.path == "orbit" or args.poses:
        cams = _path_cameras(args.poses, args.frames, model, args.size, ds) if args.poses \
            else _orbit_cameras(model, args.frames, args.size, ds)
        if fixed is None and not conditioning.is_static:
            fixed = conditioning.vector(0.0, {}) if conditioning.kind == "time" else \
                conditioning.vector(None, {})
        return cams, [fixed] * len(cams)
    idx = ds.indices(args.path)
    per_frame = frame_conditions(ds, conditioning)
    conds = [fixed if fixed is not None else (None if per_frame is None else per_frame[i].tolist())
             for i in idx]
    return ds.cameras(idx), conds


def _render_depth_query(args, run: Path) -> tuple[str, float | None, str]:
    """(mode, threshold in 1/m or None, where they came from) of ``nerfbot render``'s depth:
    the flags, else the ``query_defaults`` that ``--method auto`` wrote to RUN/auto.json
    (threshold depth for scenes with glass), else expected depth."""
    from nerfbot.data.spec import read_json
    from nerfbot.query.render import as_thresholds

    auto = run / "auto.json"
    defaults = (read_json(auto).get("query_defaults") or {}) if auto.exists() else {}
    mode = args.depth_mode or defaults.get("depth_mode", "expected")
    threshold = args.threshold if args.threshold is not None else defaults.get("threshold")
    source = "--depth-mode" if args.depth_mode else (f"{auto}" if "depth_mode" in defaults
                                                     else "default")
    if mode != "threshold":
        return mode, None, source
    if threshold is None:
        raise UsageError(f"threshold depth needs --threshold M (density, "
                         f"1/m; {auto} gives none)")
    return mode, as_thresholds(threshold)[0], source


#: The video files ``nerfbot render --out`` writes; any other --out is a folder of images.
def cmd_render(args) -> int:
    import numpy as np

    from nerfbot.data.outputs import check_output_file, check_output_folder
    from nerfbot.query.export import colorize_depth, colorize_labels, save_image, to_uint8
    from nerfbot.query.render import depth_of, render_image
    from nerfbot.query.video import VIDEO_SUFFIXES, write_video
    from nerfbot.train.runs import load_model
    from tqdm.auto import tqdm

    run, out = Path(args.run), Path(args.out)
    if args.size is not None and len(args.size) > 2:
        raise UsageError(f"--size: give N or W H, got {len(args.size)} numbers")
    video = out.suffix.lower() in VIDEO_SUFFIXES
    if out.suffix and not video and not out.is_dir():
        raise UsageError(f"--out {out}: nerfbot writes videos as {', '.join(VIDEO_SUFFIXES)}; "
                         f"not {out.suffix} (a folder name without an extension gets images)")
    folder = None if video else check_output_folder(out, "render", overwrite=args.overwrite)
    if video:
        check_output_file(out, overwrite=args.overwrite)
    if args.poses and args.path != "orbit":
        raise UsageError(f"--poses and --path {args.path}: give one camera path")
    mode, threshold, source = _render_depth_query(args, run)
    model, info = load_model(run, args.device)
    pixelnerf = info["spec"]["method"] == "pixelnerf"
    ds = _render_dataset(args, run, info, needed=not pixelnerf and args.path != "orbit"
                         and not args.sweep and not args.poses)
    _condition_pixelnerf(model, ds, args, run)
    cams, conds = _render_plan(args, model, info, ds)
    thresholds = [threshold] if mode == "threshold" else []
    labels = model.label_head is not None
    if args.what == "labels" and not labels:
        raise UsageError(f"--what labels: {run} was trained without labels (train with --labels)")
    n_classes = model.label_head.n_classes if labels else 0
    images = (render_image(model, cams, i, cond=conds[i], supersample=args.supersample,
                           thresholds=thresholds, labels=labels,
                           supersample_pattern=args.supersample_pattern)
              for i in range(len(cams)))
    images = tqdm(images, total=len(cams), desc="render", disable=args.no_progress)
    if video:
        def frames():
            for img in images:
                if args.what == "rgb":
                    yield to_uint8(img["rgb"])
                elif args.what == "depth":
                    yield colorize_depth(*depth_of(img, mode))
                elif args.what == "labels":
                    yield colorize_labels(img["labels"].argmax(-1), n_classes)
                else:
                    yield to_uint8(np.repeat(img["opacity"][..., None], 3, -1))
        write_video(out, frames(), args.fps)
    else:
        with folder.writing():
            for i, img in enumerate(images):
                z, valid = depth_of(img, mode)
                save_image(out / f"rgb_{i:04d}.png", img["rgb"])
                save_image(out / f"depth_{i:04d}.png", colorize_depth(z, valid))
                save_image(out / f"opacity_{i:04d}.png",
                           np.repeat(img["opacity"][..., None], 3, -1))
                np.save(out / f"depth_{i:04d}.npy", z.astype(np.float32))
                if labels:
                    classes = img["labels"].argmax(-1).astype(np.uint8)
                    save_image(out / f"labels_{i:04d}.png", colorize_labels(classes, n_classes))
                    np.save(out / f"labels_{i:04d}.npy", classes)
    what = f"a {args.sweep} sweep" if args.sweep else \
        (f"the path of {args.poses}" if args.poses else f"{args.path} views")
    depth = mode + (f" (m = {threshold:g} /m)" if threshold is not None else "")
    classes = f"; labels: {', '.join(model.label_head.classes.names)}" if labels else ""
    print(f"wrote {len(cams)} images of {what} to {out}; depth: {depth}, from {source}{classes}")
    return 0


#: What ``nerfbot export`` writes: kind -> the file suffixes it accepts.
EXPORT_KINDS = {"pointcloud": (".ply", ".pcd", ".xyz"), "mesh": (".ply", ".obj", ".glb"),
                "tsdf": (".ply", ".obj", ".glb")}


def _export_bounds(args, model):
    """(2, 3) export box: ``--aabb``, else the run's bounds."""
    import numpy as np

    if args.aabb is None:
        return model.aabb.detach().cpu().numpy().astype(float)
    box = np.asarray(args.aabb, float).reshape(2, 3)
    if not np.all(box[1] > box[0]):
        raise UsageError(f"--aabb: every max must exceed its min, got {args.aabb}")
    return box


def _export_condition(args, info):
    """The one condition vector the export shows (None for a static run)."""
    from nerfbot.data.conditioning import Conditioning

    conditioning = Conditioning.from_dict(info["spec"].get("conditioning"))
    _check_condition_flags(args, conditioning)
    if conditioning.kind == "time" and args.time is None:
        raise UsageError(f"{args.run} is time-conditioned: give --time T (one state is exported)")
    return conditioning.vector(args.time, args.joints)


def cmd_export(args) -> int:
    from nerfbot.data.outputs import check_output_file
    from nerfbot.query.density import default_density_threshold
    from nerfbot.query.export import label_palette
    from nerfbot.query.geometry import (DepthQuery, colour_by_labels, density_mesh,
                                        point_cloud, tsdf_mesh, write_mesh, write_point_cloud)
    from nerfbot.train.runs import load_model

    run, out = Path(args.run), Path(args.out)
    suffixes = EXPORT_KINDS[args.kind]
    if out.suffix.lower() not in suffixes:
        raise UsageError(f"--out {out}: a {args.kind} is written as {', '.join(suffixes)}")
    check_output_file(out, overwrite=args.overwrite)
    if not out.parent.is_dir():
        raise UsageError(f"--out {out}: folder {out.parent} does not exist")
    mode, threshold, source = _render_depth_query(args, run)
    model, info = load_model(run, args.device)
    if args.what == "labels" and model.label_head is None:
        raise UsageError(f"--what labels: {run} was trained without labels (train with --labels)")
    cond = _export_condition(args, info)
    bounds = _export_bounds(args, model)
    paint = (lambda g: colour_by_labels(model, g)) if args.what == "labels" else (lambda g: g)
    progress = not args.no_progress
    if args.kind == "mesh":
        level = args.threshold if args.threshold is not None else threshold
        if level is None:
            level = default_density_threshold(model.aabb.detach().cpu().numpy())
        mesh = density_mesh(model, threshold=level, resolution=args.resolution, bounds=bounds,
                            cond=cond)
        if not len(mesh.faces):
            raise ValueError(f"{run}: no density reaches {level:g} /m inside the box: no surface "
                             "to write; give a lower --threshold")
        write_mesh(paint(mesh), out)
        what = f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces, marching cubes at " \
            f"{level:g} /m"
    else:
        query = DepthQuery(mode, threshold)
        ds = _render_dataset(args, run, info, needed=True)
        idx = ds.indices(args.views) if args.views != "all" else list(range(len(ds)))
        if not idx:
            raise UsageError(f"--views {args.views}: the dataset has no such views")
        cams = ds.cameras(idx)
        conds = None if cond is None else [cond] * len(cams)
        nothing = (f"{run}: no rendered depth ({query.describe()}) inside the box at the "
                   f"{len(cams)} {args.views} views: nothing to write")
        if args.kind == "pointcloud":
            cloud = point_cloud(model, cams, query, conds, bounds=bounds, stride=args.stride,
                                voxel=args.voxel, progress=progress)
            if not len(cloud.points):
                raise ValueError(nothing)
            write_point_cloud(paint(cloud), out)
            what = f"{len(cloud.points)} points"
        else:
            mesh = tsdf_mesh(model, cams, query, conds, voxel=args.voxel, bounds=bounds,
                             progress=progress)
            if not len(mesh.faces):
                raise ValueError(nothing)
            write_mesh(paint(mesh), out)
            what = f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces, TSDF"
        what += f" from {len(cams)} {args.views} views, depth: {query.describe()} ({source})"
    if args.what == "labels":
        what += "; coloured by class (" + ", ".join(
            f"{name} {'#%02x%02x%02x' % tuple(rgb)}" for name, rgb in
            zip(model.label_head.classes.names, label_palette(model.label_head.n_classes))) + ")"
    print(f"wrote {out}: {what}; world frame, metres")
    return 0


def cmd_colmap(args) -> int:
    from nerfbot.data.readers import is_dataset_folder
    from nerfbot.sfm.dataset import (check_new_folder, dataset_input, images_input,
                                     poses_from_images)
    from nerfbot.sfm.pipeline import DROP_REPEATED, SfmOptions

    source, out = Path(args.input), Path(args.out)
    if not source.is_dir():
        raise UsageError(f"{source}: expected a folder of images or a dataset folder")
    check_new_folder(out)
    is_dataset = is_dataset_folder(source)
    if is_dataset:
        if args.focal is not None:
            raise UsageError(f"--focal: {source} is a dataset; its own intrinsics are used")
        sfm_input = dataset_input(source)
    else:
        sfm_input = images_input(source, focal_px=args.focal)
    if args.known_poses and not is_dataset:
        raise UsageError(f"--known-poses: {source} is a folder of images; the poses come "
                         "with a dataset")
    if args.baseline is not None and sfm_input.true_c2w is not None:
        raise UsageError(f"--baseline: {source} has poses, which fix the scale already")
    baseline = None
    if args.baseline is not None:
        a, b, metres = args.baseline
        try:
            distance = float(metres)
        except ValueError:
            distance = math.nan
        if not 0.0 < distance < math.inf:
            raise UsageError(f"--baseline: the distance must be a positive number of metres, "
                             f"got {metres!r}")
        baseline = (a, b, distance)
    options = SfmOptions(matcher=args.matcher, max_reproj_error_px=args.max_error,
                         refine_rounds=args.refine_rounds, seed=args.seed,
                         guided_matching=not args.no_guided_matching,
                         mapper_runs=args.mapper_runs,
                         refine_all_features=not args.no_refine_all_features,
                         drop_repeated=(args.drop_repeated if args.drop_repeated is not None
                                        else 0.0 if args.known_poses else DROP_REPEATED))
    report = poses_from_images(sfm_input, out, options, downscale=args.downscale,
                               baseline=baseline, known_poses=args.known_poses,
                               progress=not args.no_progress)
    print(f"registered {report['registered']} of {report['images']} images in "
          f"{report['seconds']['total']:.1f} s; {report['points']} points, "
          f"{report['mean_reprojection_error_px']:.2f} px mean reprojection error")
    agreement = report.get("agreement")
    if agreement:
        print(f"verified image pairs agreeing with the recovered poses: "
              f"{100 * agreement['pairs_agreeing']:.0f} % of {agreement['pairs']}")
    if report["unregistered"]:
        shown = ", ".join(report["unregistered"][:5])
        more = " ..." if len(report["unregistered"]) > 5 else ""
        print(f"not registered: {shown}{more}")
    if "pose_errors" in report:
        e = report["pose_errors"]
        print(f"against the input's poses (after a similarity): rotation median "
              f"{e['rotation_deg_median']:.3f} deg (max {e['rotation_deg_max']:.3f}), centre "
              f"median {e['translation_percent_median']:.3f} % of the scene size "
              f"(max {e['translation_percent_max']:.3f} %)")
    print(f"poses: {report['frame']}")
    print(f"wrote {out} (nerfstudio dataset; sfm_report.json, COLMAP model in colmap/)")
    return 0


def cmd_demo(args) -> int:
    from nerfbot.app.demo import run_demo

    metrics = run_demo(Path(args.out), seconds=args.seconds, size=args.size, views=args.views,
                       test_views=args.test_views, seed=args.seed, progress=not args.no_progress,
                       overwrite=args.overwrite)
    print(json.dumps(metrics, indent=2))
    return 0


def _joint_values(text: str) -> dict[str, float]:
    out = {}
    for item in _str_list(text):
        name, sep, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            sep = ""
        if sep and not math.isfinite(out[name.strip()]):
            sep = ""
        if not sep or not name.strip():
            raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {item!r}")
    return out


def _str_list(text: str) -> list[str]:
    values = [v.strip() for v in text.split(",") if v.strip()]
    if not values:
        raise argparse.ArgumentTypeError("expected a comma-separated list")
    return values


def _ints(text: str, minimum: int, what: str) -> list[int]:
    """``N1,N2,...``: integers of at least ``minimum`` (ArgumentTypeError naming ``what``)."""
    try:
        values = [int(v) for v in _str_list(text)]
    except ValueError:
        values = []
    if not values or min(values) < minimum:
        raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}")
    return values


def _frame_list(text: str) -> list[int]:
    """``I,J,...``: frame indices (non-negative integers)."""
    return _ints(text, 0, "frame indices")


def _int_list(text: str) -> list[int]:
    """``N1,N2,...``: positive integers (grid sizes, image sizes)."""
    return _ints(text, 1, "positive integers")


def _positive_float(text: str) -> float:
    """A number above zero (seconds, lengths)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _option_sweep(text: str):
    from nerfbot.bench.sweep import parse_option_sweep

    try:
        return parse_option_sweep(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err))


def cmd_bench(args) -> int:
    from nerfbot.bench.sweep import BenchConfig, BenchError, run_bench

    options: dict = {}
    for key, values in args.option or []:  # a repeated key adds values
        merged = options.setdefault(key, [])
        merged += [v for v in values if v not in merged]
    cfg = BenchConfig(data=[d for entry in args.data for d in entry], methods=args.methods,
                      budgets=args.budgets, out=args.out, budget_kind=args.budget_kind,
                      sizes=args.sizes or [None], options=options, repeats=args.repeats,
                      seed=args.seed, views=args.views, test_views=args.test_views,
                      eval_images=args.eval_images, chamfer=not args.no_chamfer,
                      mesh_resolution=args.mesh_resolution, mesh_threshold=args.mesh_threshold,
                      chamfer_points=args.chamfer_points, executor=args.executor,
                      address=args.address, ray_num_cpus=args.ray_num_cpus, force=args.force,
                      keep_checkpoints=args.keep_checkpoints, progress=not args.no_progress)
    try:
        result = run_bench(cfg)
    except BenchError as err:
        print(f"nerfbot bench: error: {err}", file=sys.stderr)
        return 2
    print(f"{result.ran} point(s) run, {result.skipped} already measured; "
          f"{len(result.rows)} configuration(s) in {result.out / 'bench.md'}")
    if result.failures:
        print(f"nerfbot bench: {len(result.failures)} point(s) failed (see bench.json "
              "'failures'; a rerun retries them)", file=sys.stderr)
        return 1
    return 0


def _view_start(args, model, ds):
    """(StartView, image height) where browsers start: ``--camera split:K`` of the dataset
    (default the first test view, else the first training view), else an orbit view framed
    from the bounds when the dataset is unknown."""
    import numpy as np

    from nerfbot.app.viewer import StartView
    from nerfbot.ops.cameras import orbit_poses

    fov, _, height, target, radius, elevation = _view_intrinsics(model, None, ds)
    if ds is None:
        if args.camera:
            raise UsageError(f"--camera {args.camera}: the run's dataset is not found; give "
                             "--data")
        pose = orbit_poses(target, radius, elevation, 1)[0]
        return StartView.of_camera(pose, fov, radius), height
    split, _, k = (args.camera or ("test:0" if ds.splits.get("test") else "train:0")).partition(":")
    try:
        idx = ds.indices(split)[int(k or 0)]
    except (IndexError, ValueError):
        raise UsageError(f"--camera {args.camera}: expected SPLIT:K with K below the split's "
                         f"{len(ds.splits.get(split, []))} views ({ds.split_sizes()})") from None
    c2w = ds.c2w[idx]
    fov = float(np.degrees(2 * np.arctan(0.5 * ds.sizes[idx][1] / ds.intrinsics[idx, 1])))
    ahead = float(np.dot(target - c2w[:3, 3], -c2w[:3, 2]))
    return StartView.of_camera(c2w, fov, ahead if ahead > 0 else radius), int(ds.sizes[idx][1])


def make_viewer(args):
    """The :class:`~nerfbot.app.viewer.Viewer` of ``nerfbot view``'s parsed ``args``, serving."""
    from nerfbot.app.viewer import Settings, Viewer
    from nerfbot.data.conditioning import Conditioning
    from nerfbot.query.density import default_density_threshold
    from nerfbot.train.runs import load_model

    run = Path(args.run)
    if args.depth_mode == "threshold" and args.threshold is None:
        mode, threshold = "threshold", None  # the default density below
    else:
        mode, threshold, _ = _render_depth_query(args, run)
    model, info = load_model(run, args.device)
    ds = _render_dataset(args, run, info, needed=bool(args.data or args.camera))
    conditioning = Conditioning.from_dict(info["spec"].get("conditioning"))
    start, height = _view_start(args, model, ds)
    if threshold is None:
        threshold = default_density_threshold(model.aabb.detach().cpu().numpy())
    cond = None if conditioning.is_static else (
        conditioning.vector(0.0, {}) if conditioning.kind == "time" else conditioning.vector())
    train = None
    if ds is not None and not args.no_cameras:
        train = ds.cameras(ds.indices("train") if ds.splits.get("train") else list(range(len(ds))))
    settings = Settings(depth_mode=mode, threshold=float(threshold), condition=cond,
                        height=args.resolution or height)
    return Viewer(model, conditioning, train_cameras=train, start=start, settings=settings,
                  path_file=args.path_file or run / "camera_path.json",
                  geometry=args.geometry or (),
                  title=f"{run.name}: {info['spec']['method']}, step {info['step']}",
                  host=args.host, port=args.port)


def cmd_view(args) -> int:
    import signal
    import threading

    viewer = make_viewer(args)
    logging.getLogger("websockets").setLevel(logging.WARNING)
    print(f"nerfbot view: {args.run} at http://{args.host}:{viewer.port} (Ctrl-C to stop); "
          f"saved cameras go to {viewer.path_file.path}", flush=True)
    stopping = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stopping.set())  # stop cleanly when terminated
    try:
        while not stopping.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    print("nerfbot view: stopped", flush=True)
    return 0


# -- parser ----------------------------------------------------------------------------------
def _capture_arguments(parser: argparse.ArgumentParser) -> None:
    from sims.cli import add_capture_arguments

    add_capture_arguments(parser)


def _add_supersample_pattern(p: argparse.ArgumentParser) -> None:
    """``--supersample-pattern`` of ``eval`` and ``render`` (the patterns of
    :data:`nerfbot.query.render.SUPERSAMPLE_PATTERNS`, named here so the parser needs no
    torch)."""
    p.add_argument("--supersample-pattern", default=None,
                   choices=("grid", "corners", "adaptive"),
                   help="where supersampled colour rays go: an S x S grid in each pixel; the "
                        "pixel's centre and its 4 corners, shared with its neighbours (about 2 "
                        "rays per pixel); or the corners, and the grid where centre and "
                        "corners disagree (default: the run's option)")


def build_parser(eager: bool = False) -> argparse.ArgumentParser:
    """The ``nerfbot`` parser. It imports no method, torch or mujoco: the ``capture`` command's
    arguments are added when that command is parsed or its help printed (at once with
    ``eager``)."""
    from nerfbot.method_names import BAKED, DESCRIPTIONS

    parser = OneLineParser(prog="nerfbot", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=DeferredParser)

    p = sub.add_parser("capture", help="render a MuJoCo scene into a posed-image dataset",
                       add_arguments=_capture_arguments)
    if eager:
        p.add_deferred_arguments()
    p.set_defaults(func=cmd_capture)

    p = sub.add_parser("train", help="train a radiance field on a dataset")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset folder or transforms JSON (with --config / --resume: the "
                        "run's, unless it moved)")
    p.add_argument("--config", type=Path, default=None, metavar="RUN/config.json",
                   help="train again exactly as a run was trained: its data, method, options, "
                        "bounds, seed and budgets (the budgets may be given anew)")
    p.add_argument("--method", default="ngp", choices=sorted(DESCRIPTIONS) + ["auto"],
                   help="; ".join(f"{k}: {v}" for k, v in DESCRIPTIONS.items())
                   + "; auto: model only what the scene manifest says it needs (see "
                     "--target-psnr / --time-budget)")
    p.add_argument("--target-psnr", type=_positive_float, default=None, metavar="DB",
                   help="with --method auto: train for the shortest budget that reaches this "
                        "test PSNR (from --bench-table, or a short built-in sweep)")
    p.add_argument("--time-budget", type=_positive_float, default=None, metavar="S",
                   help="with --method auto: the best configuration that trains within S s")
    p.add_argument("--bench-table", type=Path, default=None,
                   help="a `nerfbot bench` output (bench.json or its folder) to choose from")
    p.add_argument("--out", required=True, type=Path, help="run folder")
    p.add_argument("--max-steps", type=int, default=None, help="step budget")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="training-loop time budget in seconds (loading and evaluation excluded)")
    p.add_argument("--seed", type=_non_negative_int, default=0)
    p.add_argument("--lr", type=float, default=None, help="learning rate (default: the method's)")
    p.add_argument("--depth-weight", type=float, default=0.0, metavar="W",
                   help="dense depth supervision from the dataset's depth maps (RGB-D "
                        "captures): weight of the L1 depth error in scene-cube diagonals "
                        "(default 0: RGB only)")
    p.add_argument("--depth-from", choices=("depth", "sensor_depth"), default="depth",
                   help="the depth maps --depth-weight trains on: the frames' depth_file_path "
                        "(a simulator's true depth, or an RGB-D camera's) or "
                        "sensor_depth_file_path (nerfbot capture --sensor-depth: a simulated "
                        "depth sensor's noisy, gappy reading); default depth")
    p.add_argument("--sparse-depth-weight", type=float, default=0.0, metavar="W",
                   help="DS-NeRF sparse depth supervision on the structure-from-motion "
                        "keypoints nerfbot colmap writes (frames[].sparse_depth_file_path); "
                        "0.1 is DS-NeRF's weight (default 0: off)")
    p.add_argument("--sparse-depth-robust", type=float, default=0.0, metavar="C",
                   help="robust keypoint weights: from a quarter of the budget on, a "
                        "keypoint whose rendered depth is r from its own weighs "
                        "1 / (1 + (r / (C sigma))^2) (default 0: every keypoint in full)")
    p.add_argument("--sparse-depth-until", type=float, default=1.0, metavar="F",
                   help="keypoints leave the batch after a fraction F of the budget, so the "
                        "rest trains colour on every pixel (default 1: to the end)")
    p.add_argument("--labels", action="store_true",
                   help="train a semantic label head (Semantic-NeRF) on the capture's "
                        "segmentation; classes: background, each object of the manifest, "
                        "structure")
    p.add_argument("--label-clicks", type=_positive_int, default=None, metavar="N",
                   help="labels from N labelled pixels per class over the training frames "
                        "(iLabel's clicks, drawn at random) instead of full label maps; implies "
                        "--labels. `nerfbot label --clicks` on the finished run asks for them "
                        "where the head is unsure, which scores higher")
    p.add_argument("--label-weight", type=_non_negative_float, default=0.04, metavar="W",
                   help="weight of the labels' cross-entropy (default 0.04, Semantic-NeRF's)")
    p.add_argument("--dynamic-rays", type=_fraction, default=0.5, metavar="F",
                   help="captures over time: fraction of each batch's pixels drawn where the "
                        "images change over time (DyNeRF's importance sampling; needs cameras "
                        "that film several time steps), the rest uniformly (default 0.5; 0: "
                        "uniform)")
    p.add_argument("--dynamic-rays-debias", type=_fraction, default=0.5, metavar="D",
                   help="how much of the bias of those draws the loss undoes: 1 = unbiased, "
                        "0 = the changing pixels also weigh more (DyNeRF's) (default 0.5)")
    p.add_argument("--error-rays", type=_fraction, default=0.0, metavar="F",
                   help="fraction of each batch's pixels drawn where the training error is "
                        "high (Instant-NGP's error map, tiles of --error-tile pixels), the rest "
                        "uniformly (default 0: uniform; not with --dynamic-rays on a capture "
                        "over time; a resume starts the map afresh)")
    p.add_argument("--error-rays-debias", type=_fraction, default=1.0, metavar="D",
                   help="how much of the bias of those draws the loss undoes: 1 = unbiased "
                        "(default), 0 = the pixels drawn there also weigh more")
    p.add_argument("--error-tile", type=_positive_int, default=8, metavar="PX",
                   help="side of the error map's tiles, pixels (default 8)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out with its saved configuration (flags that "
                        "differ from it are refused; the budgets may change)")
    p.add_argument("--checkpoint-every-seconds", type=_non_negative_float, default=60.0,
                   metavar="S", help="write a checkpoint at least every S s of training "
                                     "(default 60; inf: only at the end)")
    p.add_argument("--checkpoint-every-steps", type=_positive_int, default=None, metavar="N",
                   help="also write a checkpoint after every N-th step (default: none)")
    p.add_argument("--overwrite", action="store_true",
                   help="start over in --out when it holds an earlier run (its files are "
                        "deleted; a folder holding files nerfbot did not write is still refused)")
    p.add_argument("--aabb", type=float, nargs=6, default=None,
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="scene bounds in metres (overrides the manifest and the camera estimate)")
    p.add_argument("--background", default=None,
                   help="learned | white | black | R,G,B (default: learned for RGB captures, "
                        "the compositing colour for RGBA ones)")
    p.add_argument("--option", action="append", type=parse_option, metavar="KEY=VALUE",
                   help="method option, e.g. log2_hashmap_size=19 (repeatable)")
    p.add_argument("--eval-at", type=_times, default=None, metavar="S1,S2,...",
                   help="record test PSNR at these training times (s), e.g. 30,60,120,180")
    p.add_argument("--eval-images", type=_positive_int, default=None, metavar="N",
                   help="learning-curve points use the first N test images (default: all)")
    p.add_argument("--device", type=_device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="evaluate a run on a dataset split")
    p.add_argument("run", type=Path)
    p.add_argument("--data", type=Path, default=None,
                   help="dataset folder (default: the one the run was trained on)")
    p.add_argument("--split", default="test")
    p.add_argument("--downscale", type=_positive_int, default=1, metavar="K",
                   help="evaluate at 1/K resolution: cameras scaled by 1/K, ground truth "
                        "area-averaged (the multiscale protocol; default 1)")
    p.add_argument("--supersample", type=_positive_int, default=None, metavar="S",
                   help="S x S rays per pixel for colour (default: what the run was trained with)")
    _add_supersample_pattern(p)
    p.add_argument("--refine-poses", action="store_true",
                   help="refine each view's pose against the field first (iNeRF, 100 steps): "
                        "for views posed by structure from motion, whose errors are the poses'")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--depth-sweep", action="store_true",
                   help="also compare expected, median and threshold depth (and the simulated "
                        "sensor's) per pixel class: transparent / opaque objects / scene")
    p.add_argument("--thresholds", type=_float_list, default=None, metavar="M1,M2,...",
                   help="density thresholds of the sweep, 1/m (default 0.5 ... 1000)")
    p.add_argument("--plot", type=Path, default=None,
                   help="with --depth-sweep: write the sweep as a PNG plot here")
    p.add_argument("--sources", type=_frame_list, default=None, metavar="I,J,...",
                   help="a pixelNeRF run: the frames of --data it renders the scene from")
    p.add_argument("--finetune-seconds", type=_positive_float, default=None, metavar="S",
                   help="a pixelNeRF run: fine-tune it on the --sources frames' pixels for S "
                        "seconds first (default: no fine-tuning)")
    p.add_argument("--device", type=_device, default="cpu")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("label", help="add semantic labels to a trained run: a label head "
                                     "trained on its frozen field (a run of its own)",
                       description="Train Semantic-NeRF's label head on a finished static "
                                   "run, from the capture's segmentation (classes: background, "
                                   "each object of the manifest, structure) or a few clicks "
                                   "per class; the field is not changed. Writes a run with "
                                   "labels (render --what labels, export --what labels) and "
                                   "prints the test views' mean IoU.")
    p.add_argument("run", type=Path, help="trained run folder (a static method)")
    p.add_argument("--out", required=True, type=Path,
                   help="run folder for the labelled run (new or empty; not RUN)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out when it holds an earlier run")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset (default: the one the run was trained on)")
    p.add_argument("--clicks", type=_positive_int, default=None, metavar="N",
                   help="N labelled pixels per class on average over the training frames "
                        "(iLabel) instead of full label maps")
    p.add_argument("--click-choice", choices=("uncertain", "random"), default="uncertain",
                   help="with --clicks: where they fall. uncertain (default, iLabel's active "
                        "choice): one random click per class, the rest asked in rounds where "
                        "the head is least sure, answered from the capture's segmentation as a "
                        "user would; random: N per class, uniformly over each class's pixels")
    p.add_argument("--steps", type=_positive_int, default=1000, help="head steps (default 1000)")
    p.add_argument("--seed", type=_non_negative_int, default=0)
    p.add_argument("--device", type=_device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_label)

    p = sub.add_parser("bake", help="bake a trained run into a faster renderer: a FastNeRF "
                                    "cache (--cache) or a PlenOctree (--octree)",
                       description="Bake a trained run into a faster renderer (a run of its "
                                   "own) with the baked method's recipe, as `nerfbot bench` "
                                   "does: --method M [--option KEY=VALUE ...]; --cache NP,ND "
                                   "spells --method fastnerf_cache --option np=NP --option "
                                   "nd=ND, --octree DEPTH --method plenoctree_octree --option "
                                   "depth=DEPTH, --finetune-steps N --option finetune_steps=N.")
    p.add_argument("run", type=Path, help="trained run folder (fastnerf or plenoctree)")
    p.add_argument("--out", required=True, type=Path,
                   help="run folder for the baked renderer (new or empty; not RUN)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out when it holds an earlier baked run")
    p.add_argument("--method", default=None, choices=sorted(BAKED),
                   help="the baked method: " + "; ".join(f"{k}, from a {v} run"
                                                        for k, v in BAKED.items()))
    p.add_argument("--option", action="append", type=parse_option, metavar="KEY=VALUE",
                   help="bake option, e.g. np=192, depth=7, finetune_steps=200 (repeatable)")
    p.add_argument("--cache", type=_int_list, default=None, metavar="NP,ND",
                   help="FastNeRF cache: position outputs on an NP^3 grid (occupied cells "
                        "only), direction outputs on an ND x ND grid")
    p.add_argument("--octree", type=_positive_int, default=None, metavar="DEPTH",
                   help="PlenOctree: octree of this depth (leaf size = cube / 2^DEPTH)")
    p.add_argument("--finetune-steps", type=_non_negative_int, default=None, metavar="N",
                   help="PlenOctree: fine-tune the octree leaves on the training images for N "
                        "steps (default 0)")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset folder (default: the one the run was trained on)")
    p.add_argument("--seed", type=_non_negative_int, default=0)
    p.add_argument("--device", type=_device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_bake)

    p = sub.add_parser("estimate-joints",
                       help="estimate the joint configuration of each image of a split by "
                            "inverse rendering, and its error against the truth")
    p.add_argument("run", type=Path)
    p.add_argument("--data", type=Path, default=None, help="dataset (default: the run's)")
    p.add_argument("--split", default="test")
    p.add_argument("--every", type=_positive_int, default=1, metavar="K",
                   help="use every K-th image of the split (e.g. one view per configuration)")
    p.add_argument("--max-images", type=_positive_int, default=None)
    p.add_argument("--steps", type=_positive_int, default=None,
                   help="gradient steps per start (default: JointEstimateConfig.steps, 60)")
    p.add_argument("--seed", type=_non_negative_int, default=0)
    p.add_argument("--json", action="store_true")
    p.add_argument("--device", type=_device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_estimate_joints)

    p = sub.add_parser("render", help="render views of a run: a video or images")
    p.add_argument("run", type=Path)
    p.add_argument("--path", default="orbit", choices=("orbit", "test", "train"))
    p.add_argument("--poses", type=Path, default=None, metavar="FILE",
                   help="render along the keyframes of a pose file (the format of capture "
                        "--poses): --frames views, centres on a spline, rotations by slerp")
    p.add_argument("--out", required=True, type=Path,
                   help="video file (.mp4 H.264, .webm VP9, .gif) or a folder for "
                        "rgb/depth/opacity images (new or empty)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing video file, or the images of an earlier render "
                        "folder")
    p.add_argument("--what", default="rgb", choices=("rgb", "depth", "opacity", "labels"),
                   help="what a video shows (labels: runs trained with --labels; image "
                        "folders get labels_*.png / .npy class indices for them always)")
    p.add_argument("--frames", type=_positive_int, default=60,
                   help="orbit or --poses frames, or images of a --sweep (default 60)")
    p.add_argument("--fps", type=_positive_float, default=24.0)
    p.add_argument("--supersample", type=_positive_int, default=None, metavar="S",
                   help="S x S rays per pixel for colour (default: what the run was trained "
                        "with; 1 renders S^2 + 1 times fewer rays)")
    _add_supersample_pattern(p)
    p.add_argument("--size", type=_image_side, nargs="+", default=None, metavar="N",
                   help="orbit image size N or W H (default: the training size)")
    p.add_argument("--depth-mode", default=None, choices=("expected", "median", "threshold"),
                   help="depth images (z-depth; .npy in metres, NaN where a threshold is never "
                        "reached): default the run's auto.json query default (threshold for "
                        "glass), else expected")
    p.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="density threshold of --depth-mode threshold (1/m, Dex-NeRF)")
    p.add_argument("--data", type=Path, default=None)
    p.add_argument("--sources", type=_frame_list, default=None, metavar="I,J,...",
                   help="a pixelNeRF run: the frames of --data it renders the scene from")
    p.add_argument("--finetune-seconds", type=_positive_float, default=None, metavar="S",
                   help="a pixelNeRF run: fine-tune it on the --sources frames' pixels for S "
                        "seconds first (default: no fine-tuning)")
    p.add_argument("--device", type=_device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    cond = p.add_argument_group("dynamic and articulated runs")
    cond.add_argument("--time", type=_unit_time, default=None, metavar="T",
                      help="render at time T in [0, 1] (orbit; test/train views use their own)")
    cond.add_argument("--joints", type=_joint_values, default=None, metavar="NAME=V,...",
                      help="render at these joint positions (radians / metres; others at the "
                           "middle of their range)")
    cond.add_argument("--sweep", default=None, metavar="time|JOINT",
                      help="a video over time, or over one joint's whole range (--frames "
                           "images), seen from one orbit camera (or --sweep-views cameras)")
    cond.add_argument("--sweep-views", type=_positive_int, default=1, metavar="K",
                      help="--sweep: the camera moves through K orbit positions (default 1: "
                           "a fixed camera)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("view", help="open a run in the browser (viser): the field rendered "
                                    "at your camera, training cameras, bounds, geometry files")
    p.add_argument("run", type=Path)
    p.add_argument("--port", type=_port, default=8080, help="default 8080; 0 picks a free one")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default: this machine only; 0.0.0.0 for all)")
    p.add_argument("--camera", default=None, metavar="SPLIT:K",
                   help="start at this dataset view, e.g. test:0 (default: the first test view)")
    p.add_argument("--resolution", type=_image_side, default=None, metavar="H",
                   help="height of still frames in pixels (default: the training images'); "
                        "frames while the camera moves have a quarter of it")
    p.add_argument("--geometry", type=Path, action="append", metavar="FILE",
                   help="a mesh or point cloud to show with the field (e.g. from nerfbot "
                        "export; .ply .obj .glb; repeatable)")
    p.add_argument("--path-file", type=Path, default=None, metavar="FILE",
                   help="where 'save camera' appends keyframes for render --poses (default "
                        "RUN/camera_path.json)")
    p.add_argument("--no-cameras", action="store_true", help="do not draw the training cameras")
    p.add_argument("--depth-mode", default=None, choices=("expected", "median", "threshold"),
                   help="initial depth query (default: the run's auto.json default, else "
                        "expected)")
    p.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="initial density threshold of threshold depth (1/m)")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset of the training cameras (default: the run's)")
    p.add_argument("--device", type=_device, default="cpu")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("export", help="a run's geometry as files: point cloud, mesh or TSDF "
                                      "mesh, in world metres")
    p.add_argument("run", type=Path)
    p.add_argument("kind", choices=tuple(EXPORT_KINDS),
                   help="pointcloud: rendered depth back-projected; mesh: marching cubes on "
                        "density; tsdf: rendered depth fused in a TSDF and meshed")
    p.add_argument("--out", required=True, type=Path,
                   help="file: .ply/.pcd/.xyz (pointcloud) or .ply/.obj/.glb (mesh, tsdf)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.add_argument("--what", default="rgb", choices=("rgb", "labels"),
                   help="colours: the field's (rgb) or each point's class (labels: runs "
                        "trained with --labels)")
    p.add_argument("--views", default="train", choices=("train", "test", "all"),
                   help="cameras whose rendered depth makes a pointcloud or tsdf (default train)")
    p.add_argument("--aabb", type=float, nargs=6, default=None,
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="crop to this box, metres (default: the run's bounds)")
    p.add_argument("--resolution", type=_positive_int, default=256,
                   help="mesh: marching-cubes cells along the box's longest side (default 256)")
    p.add_argument("--voxel", type=_positive_float, default=None, metavar="M",
                   help="tsdf: voxel size in metres (default: the box's longest side / 256); "
                        "pointcloud: merge points within voxels of this size (default: keep all)")
    p.add_argument("--stride", type=_positive_int, default=1,
                   help="pointcloud: every N-th pixel per axis")
    p.add_argument("--depth-mode", default=None, choices=("expected", "median", "threshold"),
                   help="depth of pointcloud and tsdf: default the run's auto.json query "
                        "default (threshold for glass), else expected")
    p.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="density threshold, 1/m: of --depth-mode threshold, and the surface of "
                        "a mesh")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset whose cameras to render (default: the run's)")
    p.add_argument("--device", type=_device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    cond = p.add_argument_group("dynamic and articulated runs (one state is exported)")
    cond.add_argument("--time", type=_unit_time, default=None, metavar="T",
                      help="export the scene at time T in [0, 1]")
    cond.add_argument("--joints", type=_joint_values, default=None, metavar="NAME=V,...",
                      help="export at these joint positions (others at the middle of their range)")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("colmap", help="camera poses from images (structure from motion with "
                                      "pycolmap), written as a nerfstudio dataset")
    p.add_argument("input", type=Path,
                   help="a folder of images (.png, .jpg), or a dataset whose images to pose "
                        "(its intrinsics are kept; its poses only measure and align the result)")
    p.add_argument("--out", required=True, type=Path, help="dataset folder to write (new)")
    p.add_argument("--matcher", default="exhaustive", choices=("exhaustive", "sequential"),
                   help="match every pair (default), or each image with its next ones "
                        "(video-like captures)")
    p.add_argument("--no-guided-matching", action="store_true",
                   help="skip matching each verified pair again along its epipolar geometry "
                        "(fewer and shorter tracks, less matching time)")
    p.add_argument("--mapper-runs", type=_positive_int, default=2, metavar="N",
                   help="incremental mapping runs from N seeds; the model that explains the "
                        "most verified matches is kept (default 2; repeated texture can fold "
                        "a run's model)")
    p.add_argument("--drop-repeated", type=_unit_distance, default=None, metavar="D",
                   help="drop features whose SIFT descriptor has a twin in its own image "
                        "closer than D (unit-descriptor distance, 0-2; 0 keeps all): a texture "
                        "repeated within a view matches its wrong copy in others (default "
                        "0.4; 0 with --known-poses)")
    p.add_argument("--no-refine-all-features", action="store_true",
                   help="keep the poses found from the distinct features (default: match every "
                        "feature of the verified pairs again and bundle-adjust with them)")
    p.add_argument("--focal", type=_positive_float, default=None, metavar="PX",
                   help="images: known focal length in pixels (square pixels, centred); "
                        "default: estimated")
    p.add_argument("--downscale", type=_positive_int, default=1, metavar="N",
                   help="write images N times smaller than the ones posed (default 1); SfM "
                        "runs on the full images")
    p.add_argument("--baseline", nargs=3, default=None, metavar=("IMAGE_A", "IMAGE_B", "M"),
                   help="images: the distance in metres between two cameras, for metric poses")
    p.add_argument("--known-poses", action="store_true",
                   help="a dataset: keep its poses and only triangulate sparse points (sparse "
                        "depth for --sparse-depth-weight)")
    p.add_argument("--max-error", type=_positive_float, default=1.0, metavar="PX",
                   help="refinement drops observations beyond this reprojection error "
                        "(default 1 px)")
    p.add_argument("--refine-rounds", type=int, default=3,
                   help="filter + bundle-adjustment rounds after mapping (default 3; 0 = off)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_colmap)

    p = sub.add_parser("demo", help="capture the tabletop, train ngp, evaluate, write renders")
    p.add_argument("--out", type=Path, default=Path("nerfbot-demo"),
                   help="demo folder, new or empty (default nerfbot-demo)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out when it holds an earlier demo")
    p.add_argument("--seconds", type=_positive_float, default=60.0, help="training budget (s)")
    p.add_argument("--size", type=_image_side, default=128)
    p.add_argument("--views", type=_positive_int, default=60)
    p.add_argument("--test-views", type=_positive_int, default=10)
    p.add_argument("--seed", type=_non_negative_int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "bench", help="sweep methods x budgets x knobs x scenes: speed, memory, quality, Pareto",
        description="Train and evaluate every point of a sweep (scene x size x method x option "
                    "values x budget x repeat), each in a fresh process, STRICTLY ONE AT A TIME "
                    "on this machine: timings on a few cores must never overlap (with "
                    "--executor ray, one point per cluster node). Writes bench.csv, bench.json, "
                    "bench.md and PSNR-vs-train-time / PSNR-vs-render-FPS plots (Pareto fronts "
                    "marked) to --out; metrics are medians over --repeats. Rerunning resumes: "
                    "points already in bench.json are skipped unless --force.")
    p.add_argument("--data", required=True, type=_str_list, action="append",
                   metavar="DIR|SCENE[,...]",
                   help="dataset folders and/or built-in scenes (tabletop, glassware, "
                        "builtin:glassware:3, ...), comma-separated or repeated; built-in scenes "
                        "are captured into OUT/data at each --sizes (an existing folder of the "
                        "same name wins unless the name has the builtin: prefix)")
    p.add_argument("--methods", default=["ngp"], type=_str_list, metavar="M1,M2,...",
                   help="methods to compare (default ngp; available: "
                        + ", ".join(sorted(DESCRIPTIONS)) + ", and auto: what --method auto "
                        "picks for each scene)")
    p.add_argument("--budgets", required=True, type=_float_list, metavar="B1,B2,...",
                   help="training budgets: seconds of the training loop (or steps, see "
                        "--budget-kind)")
    p.add_argument("--budget-kind", choices=("seconds", "steps"), default="seconds")
    p.add_argument("--out", required=True, type=Path, help="bench folder (resumed if it exists)")
    p.add_argument("--sizes", type=_int_list, default=None, metavar="N1,N2,...",
                   help="image sizes, pixels of the longer side: built-in scenes are captured "
                        "at NxN, datasets downscaled (default: 128 for built-ins, datasets as "
                        "they are)")
    p.add_argument("--option", action="append", type=_option_sweep, metavar="KEY=V1,V2,...",
                   help="sweep a method option (repeatable), e.g. log2_hashmap_size=15,17,19 "
                        "(hash-table size), render_steps=128,256 (samples per ray), "
                        "grid_resolution=32,64 (occupancy grid); a method sweeps only the "
                        "options it has")
    p.add_argument("--repeats", type=_positive_int, default=1,
                   help="runs per point; tables show medians")
    p.add_argument("--seed", type=_non_negative_int, default=0,
                   help="repeat r trains with seed SEED+r; also the capture rig's seed")
    p.add_argument("--views", type=_positive_int, default=60,
                   help="train views of built-in captures")
    p.add_argument("--test-views", type=_positive_int, default=10,
                   help="test views of built-in captures")
    p.add_argument("--eval-images", type=_positive_int, default=None, metavar="N",
                   help="evaluate on the first N test images (default all)")
    p.add_argument("--no-chamfer", action="store_true",
                   help="skip meshing and the Chamfer distance to the MuJoCo geometry")
    p.add_argument("--mesh-resolution", type=_positive_int, default=128,
                   help="marching-cubes cells along the longest side of the content bounds")
    p.add_argument("--mesh-threshold", type=_positive_float, default=None, metavar="SIGMA",
                   help="surface density, 1/m (default: where one step of the default marcher, "
                        "cube diagonal / 256, is 50%% opaque; about 80 for the tabletop)")
    p.add_argument("--chamfer-points", type=_positive_int, default=100_000,
                   help="surface samples per mesh for the Chamfer distance")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: one subprocess per point, one at a time (default); ray: points "
                        "as Ray tasks, each taking a whole node (pip install 'nerfbot[ray]')")
    p.add_argument("--address", default=None,
                   help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--ray-num-cpus", type=_positive_int, default=None, metavar="N",
                   help="CPUs each Ray task reserves (default: all CPUs of the largest node)")
    p.add_argument("--force", action="store_true", help="rerun points already in bench.json")
    p.add_argument("--keep-checkpoints", action="store_true",
                   help="keep each point's checkpoint.pt in OUT/runs (default: deleted)")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=cmd_bench)

    pixelnerf_cli.add_parser(sub, _device)
    return parser


def main(argv=None) -> int:
    from nerfbot.ops.runtime import keep_freed_memory

    keep_freed_memory()  # first, before anything allocates large blocks
    import sims  # noqa: F401  (sets MUJOCO_GL before anything imports mujoco)

    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = ["nerfbot", *(str(a) for a in argv)]
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f"nerfbot {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (UsageError, ValueError, OSError) as exc:  # DatasetError is a ValueError
        if args.verbose:
            raise
        print(f"nerfbot {args.command}: error: {one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:  # a bug, or a run that failed (e.g. diverged): not the input's fault
        if args.verbose:
            raise
        print(f"nerfbot {args.command}: error: {type(exc).__name__}: {one_line(exc)} "
              "(a failure inside nerfbot; -v shows where)", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
