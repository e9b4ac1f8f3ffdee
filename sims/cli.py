"""Command-line wiring of a capture: ``nerfbot capture ...`` and ``python -m sims.capture ...``.

The ``nerfbot`` CLI calls :func:`add_capture_arguments` on its ``capture`` sub-parser and
:func:`run_capture` on the parsed arguments.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mujoco

from nerfbot.data.writers import FORMATS
from sims.capture import capture
from sims.manifest import content_bounds, rendered_geoms
from sims.rigs import RIG_KINDS, RigConfig, make_test_rig, parse_size, scene_rig_defaults
from sims.scene import load_model
from sims.sensor import DepthSensorModel

DEFAULT_VIEWS = 60
DEFAULT_TEST_VIEWS = 10


def add_capture_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the capture options to ``parser`` (returned for chaining)."""
    parser.add_argument("--scene", default="tabletop",
                        help="built-in scene name or path to an MJCF file (default: tabletop)")
    parser.add_argument("--out", required=True, type=Path, help="dataset folder to write")
    parser.add_argument("--views", type=int, default=None,
                        help=f"training views (default {DEFAULT_VIEWS}; explicit rig: all)")
    parser.add_argument("--test-views", type=int, default=None,
                        help=f"test views (default {DEFAULT_TEST_VIEWS}; explicit rig: the "
                             "file's test list)")
    parser.add_argument("--size", type=int, nargs="+", default=[128], metavar="N",
                        help="image size: N (square) or W H, pixels (default 128)")
    parser.add_argument("--rig", choices=RIG_KINDS, default="hemisphere",
                        help="camera rig (default hemisphere)")
    parser.add_argument("--poses", type=Path, default=None,
                        help="JSON pose file of the explicit rig (4x4 matrices or eye/target)")
    parser.add_argument("--fov", type=float, default=None,
                        help="vertical field of view, degrees (default: the scene's)")
    parser.add_argument("--radius", type=float, default=None,
                        help="camera distance to the target, metres (default: the scene's)")
    parser.add_argument("--target", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="look-at point, world metres (default: the scene's)")
    parser.add_argument("--elevation-range", type=float, nargs=2, default=(15.0, 70.0),
                        metavar=("LO", "HI"), help="hemisphere elevations, degrees (15 70)")
    parser.add_argument("--elevation", type=float, default=30.0,
                        help="orbit elevation, degrees (default 30)")
    parser.add_argument("--target-jitter", type=float, default=0.0,
                        help="hemisphere: random look-at offset half-width, metres (default 0)")
    parser.add_argument("--format", choices=FORMATS, default="nerfstudio", dest="format",
                        help="dataset format (default nerfstudio)")
    parser.add_argument("--no-manifest", action="store_true",
                        help="do not write the scene manifest ('scene' object)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the rig (default 0)")
    parser.add_argument("--sensor-depth", choices=("auto", "behind", "invalid", "off"),
                        default="auto",
                        help="also write a simulated depth sensor's reading (sensor_depth): "
                             "transparent surfaces return what lies 'behind' them or are "
                             "'invalid' (no return); 'auto' = 'behind' when the scene has "
                             "transparent geoms, else off (default auto)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


def default_rig(scene: str | Path, **overrides) -> RigConfig:
    """A rig framed for ``scene``: its declared or bounds-derived target/radius/fov + overrides.

    ``overrides`` are :class:`RigConfig` fields; ``None`` values are ignored.
    """
    model = load_model(scene)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    ids = sorted({int(g.objid) for g in rendered_geoms(model, data)})
    defaults = scene_rig_defaults(model, content_bounds(model, data, ids) if ids else None)
    defaults.update({k: v for k, v in overrides.items() if v is not None})
    return RigConfig(**defaults)


def rigs_from_args(args: argparse.Namespace) -> tuple[RigConfig, RigConfig | None]:
    """(train rig, test rig or None) from parsed capture arguments; ValueError if inconsistent."""
    explicit = args.rig == "explicit"
    if explicit and args.poses is None:
        raise ValueError("--rig explicit needs --poses FILE")
    views = args.views if args.views is not None else (0 if explicit else DEFAULT_VIEWS)
    test_views = (args.test_views if args.test_views is not None
                  else (0 if explicit else DEFAULT_TEST_VIEWS))
    width, height = parse_size(args.size)
    rig = default_rig(args.scene, kind=args.rig, count=views, width=width, height=height,
                      fov_deg=args.fov, radius=args.radius,
                      target=tuple(args.target) if args.target else None,
                      elevation_range=tuple(args.elevation_range), elevation=args.elevation,
                      target_jitter=args.target_jitter, seed=args.seed, poses_file=args.poses)
    if explicit:
        return rig, make_test_rig(rig, test_views)
    return rig, (make_test_rig(rig, test_views) if test_views > 0 else None)


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


def run_capture(args: argparse.Namespace) -> Path:
    """Capture the dataset described by ``args``; print where it went; return its folder."""
    rig, test = rigs_from_args(args)
    out = capture(args.scene, rig, test, args.out, fmt=args.format,
                  manifest=not args.no_manifest, progress=not args.no_progress,
                  sensor=sensor_from_arg(args.scene, args.sensor_depth, args.seed))
    n_train, n_test = _count_frames(out, args.format)
    print(f"wrote {n_train + n_test} frames ({n_train} train, {n_test} test) of "
          f"'{args.scene}' at {rig.width}x{rig.height} to {out} ({args.format})")
    return out


def _count_frames(out: Path, fmt: str) -> tuple[int, int]:
    import json

    if fmt == "nerfstudio":
        doc = json.loads((out / "transforms.json").read_text())
        return len(doc.get("train_filenames", [])), len(doc.get("test_filenames", []))
    counts = []
    for split in ("train", "test"):
        path = out / f"transforms_{split}.json"
        counts.append(len(json.loads(path.read_text())["frames"]) if path.exists() else 0)
    return counts[0], counts[1]
