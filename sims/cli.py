"""Command-line wiring of a capture: ``nerfbot capture ...`` and ``python -m sims.cli ...``.

The ``nerfbot`` CLI calls :func:`add_capture_arguments` on its ``capture`` sub-parser and
:func:`run_capture` on the parsed arguments.

The scene decides the kind of capture (:func:`sims.sequence.capture_kind`): static scenes take
the ``hemisphere`` / ``orbit`` / ``inside`` / ``explicit`` rigs (:mod:`sims.capture`; without
``--rig``, the scene's declared default, e.g. ``inside`` for ``room``); ``dynamic`` scenes a
``monocular`` or ``multiview`` rig over ``--frames`` time steps (:mod:`sims.dynamic`);
``articulated`` scenes ``--configs`` joint configurations seen by ``--views-per-frame`` views
each (:mod:`sims.articulated`). Options of one kind given to another are errors.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
from typing import Optional, Sequence

import mujoco

from nerfbot.data.writers import FORMATS
from sims import articulated as art
from sims import dynamic as dyn
from sims.capture import capture
from sims.manifest import rendered_geoms
from sims.rigs import RIG_KINDS, RigConfig, default_rig, make_test_rig, parse_size
from sims.scene import load_model
from sims.sensor import DepthSensorModel
from sims.sequence import CAMERA_PATHS, SEQUENCE_RIGS, scene_capture_kind, sequence_rig

DEFAULT_VIEWS = 60
DEFAULT_TEST_VIEWS = 10
#: Views per time step (dynamic multiview) or per configuration (articulated multiview).
DEFAULT_VIEWS_PER_FRAME = 4
#: Options of captures over time / configurations (None = not given), by the kind they apply to.
_DYNAMIC_OPTIONS = ("frames", "duration", "test_every", "camera_path")
_ARTICULATED_OPTIONS = ("configs", "test_configs", "train_range")


#: The longest image side a capture renders, pixels.
MAX_IMAGE_SIDE = 16384


def _integer(low: int, high: int | None = None):
    """An argparse type: an integer in [low, high]."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low or (high is not None and value > high):
            bound = f">= {low}" if high is None else f"in [{low}, {high}]"
            raise argparse.ArgumentTypeError(f"expected an integer {bound}, got {text!r}")
        return value
    return parse


def _real(low: float, high: float, *, open_low: bool = True, open_high: bool = True):
    """An argparse type: a finite number between ``low`` and ``high`` (open or closed ends)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        ok = (value > low if open_low else value >= low) and \
            (value < high if open_high else value <= high)
        if not ok or not math.isfinite(value):
            ends = ("(" if open_low else "[") + f"{low:g}, {high:g}" + (")" if open_high else "]")
            raise argparse.ArgumentTypeError(f"expected a number in {ends}, got {text!r}")
        return value
    return parse


_seed = _integer(0)
_DEGREES_OF_ELEVATION = _real(-90.0, 90.0, open_low=False, open_high=False)


def add_capture_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the capture options to ``parser`` (returned for chaining)."""
    parser.add_argument("--scene", default="tabletop",
                        help="built-in scene name or path to an MJCF file (default: tabletop)")
    parser.add_argument("--out", required=True, type=Path,
                        help="dataset folder to write (new or empty)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace --out when it holds a dataset captured before (never a "
                             "folder holding anything else)")
    parser.add_argument("--views", type=_integer(1), default=None,
                        help=f"training views (default {DEFAULT_VIEWS}; explicit rig: all)")
    parser.add_argument("--test-views", type=_integer(0), default=None,
                        help=f"test views (default {DEFAULT_TEST_VIEWS}; explicit rig: the "
                             "file's test list)")
    parser.add_argument("--size", type=_integer(1, MAX_IMAGE_SIDE), nargs="+", default=[128],
                        metavar="N",
                        help="image size: N (square) or W H, pixels (default 128)")
    parser.add_argument("--rig", choices=RIG_KINDS + SEQUENCE_RIGS, default=None,
                        help="camera rig: hemisphere, orbit, inside (cameras standing in a "
                             "room) or explicit for static scenes (default: the scene's, else "
                             "hemisphere); monocular (one view per time step or "
                             "configuration) or multiview (--views-per-frame views each) for "
                             "dynamic (default monocular) and articulated (default multiview) "
                             "scenes")
    parser.add_argument("--poses", type=Path, default=None,
                        help="JSON pose file of the explicit rig (4x4 matrices or eye/target)")
    parser.add_argument("--fov", type=_real(0.0, 180.0), default=None,
                        help="vertical field of view, degrees (default: the scene's)")
    parser.add_argument("--radius", type=_real(0.0, math.inf), default=None,
                        help="camera distance to the target, metres (default: the scene's)")
    parser.add_argument("--target", type=_real(-math.inf, math.inf), nargs=3, default=None,
                        metavar=("X", "Y", "Z"),
                        help="look-at point, world metres (default: the scene's)")
    parser.add_argument("--elevation-range", type=_DEGREES_OF_ELEVATION, nargs=2,
                        default=None, metavar=("LO", "HI"),
                        help="hemisphere elevations, degrees (default: the scene's, else 15 70)")
    parser.add_argument("--elevation", type=_DEGREES_OF_ELEVATION, default=30.0,
                        help="orbit elevation, degrees (default 30)")
    parser.add_argument("--target-jitter", type=_real(0.0, math.inf, open_low=False), default=0.0,
                        help="hemisphere: random look-at offset half-width, metres (default 0)")
    parser.add_argument("--format", choices=FORMATS, default="nerfstudio", dest="format",
                        help="dataset format (default nerfstudio)")
    parser.add_argument("--headlight", action="store_true",
                        help="light with the scene's headlight, whose diffuse and specular light "
                             "follow the camera (as a light on a robot's camera does); a scene "
                             "without one gets MuJoCo's default (diffuse 0.4, specular 0.5); "
                             "default: static lighting, the headlight's ambient term only")
    parser.add_argument("--no-manifest", action="store_true",
                        help="do not write the scene manifest ('scene' object)")
    parser.add_argument("--seed", type=_seed, default=0, help="random seed of the rig (default 0)")
    parser.add_argument("--sensor-depth", choices=("auto", "behind", "invalid", "off"),
                        default="auto",
                        help="also write a simulated depth sensor's reading (sensor_depth): "
                             "transparent surfaces return what lies 'behind' them or are "
                             "'invalid' (no return); 'auto' = 'behind' when the scene has "
                             "transparent geoms, else off (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    seq = parser.add_argument_group("dynamic and articulated scenes")
    seq.add_argument("--views-per-frame", type=_integer(1), default=None, metavar="K",
                     help=f"multiview: cameras per time step / configuration (default "
                          f"{DEFAULT_VIEWS_PER_FRAME}; monocular: 1)")
    seq.add_argument("--frames", type=_integer(1), default=None, metavar="N",
                     help=f"dynamic: time steps of the rollout (default {dyn.DEFAULT_FRAMES})")
    seq.add_argument("--duration", type=_real(0.0, math.inf), default=None, metavar="S",
                     help="dynamic: simulated seconds (default: the scene's, else "
                          f"{dyn.DEFAULT_DURATION_S})")
    seq.add_argument("--test-every", type=_integer(0), default=None, metavar="M",
                     help=f"dynamic: hold out every M-th time step for the test split, from "
                          f"step M // 2 (default {dyn.DEFAULT_TEST_EVERY}; 0 = no test split)")
    seq.add_argument("--camera-path", choices=CAMERA_PATHS, default=None,
                     help="dynamic monocular: the camera moves along a smooth spiral, or "
                          "jumps to a random view every step as in D-NeRF (default spiral)")
    seq.add_argument("--configs", type=_integer(1), default=None, metavar="N",
                     help=f"articulated: training joint configurations (default "
                          f"{art.DEFAULT_CONFIGS})")
    seq.add_argument("--test-configs", type=_integer(0), default=None, metavar="M",
                     help=f"articulated: held-out test configurations, half of them outside "
                          f"the training range (default {art.DEFAULT_TEST_CONFIGS})")
    seq.add_argument("--train-range", type=_real(0.0, 1.0, open_low=False, open_high=False),
                     nargs=2, default=None, metavar=("LO", "HI"),
                     help="articulated: training configurations stay within these fractions "
                          "of each joint's range (default %g %g); extrapolating test "
                          "configurations lie at least %g of the range outside them"
                          % (*art.DEFAULT_TRAIN_RANGE, art.DEFAULT_MARGIN))
    return parser


def rigs_from_args(args: argparse.Namespace) -> tuple[RigConfig, RigConfig | None]:
    """(train rig, test rig or None) from parsed capture arguments; ValueError if inconsistent."""
    kind = args.rig                      # None: the scene's default rig (sims.rigs.default_rig)
    explicit = kind == "explicit"
    if explicit and args.poses is None:
        raise ValueError("--rig explicit needs --poses FILE")
    views = args.views if args.views is not None else (0 if explicit else DEFAULT_VIEWS)
    test_views = (args.test_views if args.test_views is not None
                  else (0 if explicit else DEFAULT_TEST_VIEWS))
    width, height = parse_size(args.size)
    rig = default_rig(args.scene, kind=kind, count=views, width=width, height=height,
                      fov_deg=args.fov, radius=args.radius,
                      target=tuple(args.target) if args.target else None,
                      elevation_range=_pair(args.elevation_range), elevation=args.elevation,
                      target_jitter=args.target_jitter, seed=args.seed, poses_file=args.poses)
    if explicit:
        return rig, make_test_rig(rig, test_views)
    return rig, (make_test_rig(rig, test_views) if test_views > 0 else None)


def _pair(values) -> tuple[float, float] | None:
    """A two-number option as a tuple (None when not given)."""
    return tuple(values) if values is not None else None


def sensor_from_arg(scene, mode: str, seed: int = 0) -> DepthSensorModel | None:
    """The depth-sensor model of ``--sensor-depth MODE`` (None = no sensor depth)."""
    if mode == "off":
        return None
    if mode == "auto":
        model = load_model(scene)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        if not any(g.rgba[3] < 1.0 for g in rendered_geoms(model, data)):
            return None
        mode = "behind"
    return DepthSensorModel(transparent=mode, seed=seed)


def _given(args: argparse.Namespace, names) -> list[str]:
    return ["--" + n.replace("_", "-") for n in names if getattr(args, n, None) is not None]


def check_capture_options(args: argparse.Namespace, kind: str) -> str:
    """The rig of a ``kind`` scene ("static", "dynamic", "articulated") from ``args``
    (defaults filled in); ValueError naming options that do not apply to it."""
    scene = args.scene
    if kind == "static":
        if args.rig in SEQUENCE_RIGS:
            raise ValueError(f"--rig {args.rig} captures dynamic and articulated scenes; scene "
                             f"'{scene}' is static (its MJCF declares no <custom><text "
                             "name=\"nerfbot_capture\" data=\"dynamic|articulated\"/>); use "
                             f"--rig {', '.join(RIG_KINDS)}")
        extra = _given(args, _DYNAMIC_OPTIONS + _ARTICULATED_OPTIONS + ("views_per_frame",))
        if extra:
            raise ValueError(f"{', '.join(extra)}: not options of static scenes like '{scene}' "
                             "(they apply to dynamic / articulated scenes; use --views / "
                             "--test-views)")
        return args.rig or "hemisphere"
    rig = args.rig or ("monocular" if kind == "dynamic" else "multiview")
    if rig not in SEQUENCE_RIGS:
        raise ValueError(f"scene '{scene}' is {kind}: capture it with --rig monocular or "
                         f"multiview (--rig {rig} captures static scenes)")
    extra = _given(args, ("views", "test_views", "poses"))
    extra += ["--target-jitter"] if args.target_jitter else []
    extra += _given(args, _ARTICULATED_OPTIONS if kind == "dynamic" else _DYNAMIC_OPTIONS)
    if extra:
        raise ValueError(f"{', '.join(extra)}: not options of {kind} scenes like '{scene}'")
    if rig == "monocular" and args.views_per_frame not in (None, 1):
        step = "time step" if kind == "dynamic" else "configuration"
        raise ValueError(f"--rig monocular has one view per {step}; got --views-per-frame "
                         f"{args.views_per_frame} (use --rig multiview)")
    if rig == "multiview" and args.camera_path is not None:
        raise ValueError("--camera-path applies to --rig monocular (multiview cameras are fixed)")
    return rig


def sequence_rig_from_args(args: argparse.Namespace, rig: str):
    """The :class:`sims.sequence.SequenceRig` of a dynamic / articulated capture's ``args``."""
    k = 1 if rig == "monocular" else (args.views_per_frame or DEFAULT_VIEWS_PER_FRAME)
    return sequence_rig(args.scene, rig, views_per_step=k, size=args.size, fov_deg=args.fov,
                        radius=args.radius, target=tuple(args.target) if args.target else None,
                        elevation_range=_pair(args.elevation_range),
                        camera_path=args.camera_path, seed=args.seed)


def run_capture(args: argparse.Namespace) -> Path:
    """Capture the dataset described by ``args``; print where it went; return its folder."""
    kind = scene_capture_kind(args.scene)
    rig_kind = check_capture_options(args, kind)
    if kind != "static":
        return _run_sequence_capture(args, kind, rig_kind)
    rig, test = rigs_from_args(args)
    out = capture(args.scene, rig, test, args.out, fmt=args.format,
                  manifest=not args.no_manifest, progress=not args.no_progress,
                  headlight=args.headlight,
                  sensor=sensor_from_arg(args.scene, args.sensor_depth, args.seed),
                  overwrite=args.overwrite)
    n_train, n_test = _count_frames(out, args.format)
    print(f"wrote {n_train + n_test} frames ({n_train} train, {n_test} test) of "
          f"'{args.scene}' at {rig.width}x{rig.height} to {out} ({args.format})")
    return out


def _run_sequence_capture(args: argparse.Namespace, kind: str, rig_kind: str) -> Path:
    rig = sequence_rig_from_args(args, rig_kind)
    common = dict(fmt=args.format, manifest=not args.no_manifest,
                  progress=not args.no_progress, headlight=args.headlight,
                  overwrite=args.overwrite,
                  sensor=sensor_from_arg(args.scene, args.sensor_depth, args.seed))
    if kind == "dynamic":
        steps = args.frames if args.frames is not None else dyn.DEFAULT_FRAMES
        out = dyn.capture_dynamic(args.scene, rig, args.out, frames=steps,
                                  duration_s=args.duration,
                                  test_every=(args.test_every if args.test_every is not None
                                              else dyn.DEFAULT_TEST_EVERY), **common)
        what = f"{steps} time steps"
    else:
        steps = args.configs if args.configs is not None else art.DEFAULT_CONFIGS
        tests = args.test_configs if args.test_configs is not None else art.DEFAULT_TEST_CONFIGS
        out = art.capture_articulated(
            args.scene, rig, args.out, configs=steps, test_configs=tests,
            train_range=(tuple(args.train_range) if args.train_range is not None
                         else art.DEFAULT_TRAIN_RANGE), **common)
        what = f"{steps} + {tests} joint configurations"
    n_train, n_test = _count_frames(out, args.format)
    print(f"wrote {n_train + n_test} frames ({n_train} train, {n_test} test) of "
          f"'{args.scene}' ({kind}, {rig_kind} rig, {rig.views_per_step} view(s) x {what}) at "
          f"{rig.width}x{rig.height} to {out} ({args.format})")
    return out


def _count_frames(out: Path, fmt: str) -> tuple[int, int]:
    if fmt == "nerfstudio":
        doc = json.loads((out / "transforms.json").read_text())
        return len(doc.get("train_filenames", [])), len(doc.get("test_filenames", []))
    counts = []
    for split in ("train", "test"):
        path = out / f"transforms_{split}.json"
        counts.append(len(json.loads(path.read_text())["frames"]) if path.exists() else 0)
    return counts[0], counts[1]


def main(argv: Optional[Sequence[str]] = None) -> Path:
    """``python -m sims.cli``: the same options as ``nerfbot capture``."""
    parser = argparse.ArgumentParser(prog="python -m sims.cli",
                                     description="Capture a dataset of a MuJoCo scene.")
    add_capture_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run_capture(args)
    except (FileNotFoundError, FileExistsError, ValueError, RuntimeError) as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    main()
