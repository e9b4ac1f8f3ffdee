"""``nerfbot pixelnerf``: capture the scenes of a zoo family and train pixelNeRF across them.

The trained run renders and scores any scene of the family from a few of its views, without
per-scene training: ``nerfbot eval RUN --data SCENE --sources 0,3`` and ``nerfbot render RUN
--data SCENE --sources 0,3 ...``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np


def family_cache_dir() -> Path:
    """Where family captures go by default: ``$NERFBOT_CACHE/families`` (default
    ``~/.cache/nerfbot/families``)."""
    base = os.environ.get("NERFBOT_CACHE") or Path.home() / ".cache" / "nerfbot"
    return Path(base) / "families"


def seed_list(text: str) -> list[int]:
    """``A-B`` (inclusive) or ``I,J,...``: scene seeds."""
    try:
        if "-" in text and "," not in text:
            lo, hi = (int(v) for v in text.split("-", 1))
            values = list(range(lo, hi + 1))
        else:
            values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 0:
        raise argparse.ArgumentTypeError(f"expected seeds as A-B or I,J,..., got {text!r}")
    return values


def source_range(text: str) -> tuple[int, int]:
    """``N`` or ``LO-HI``: source views per training step."""
    try:
        lo, _, hi = text.partition("-")
        pair = (int(lo), int(hi or lo))
    except ValueError:
        pair = (0, 0)
    if not 1 <= pair[0] <= pair[1]:
        raise argparse.ArgumentTypeError(f"expected N or LO-HI with 1 <= LO <= HI, got {text!r}")
    return pair


def cmd_pixelnerf(args) -> int:
    from sims.family import capture_family
    from sims.scene import builtin_scenes

    from nerfbot.data import load_dataset
    from nerfbot.data.outputs import check_output_folder
    from nerfbot.fields.pixelnerf import PixelNeRFFieldConfig
    from nerfbot.train.pixelnerf import PixelTrainConfig, build_pixelnerf, train_pixelnerf

    if args.family not in builtin_scenes() or ":" in args.family:
        raise ValueError(f"--family {args.family!r}: not a scene family (known: "
                         f"{', '.join(builtin_scenes())})")
    config = PixelTrainConfig(steps=args.steps, max_seconds=args.max_seconds,
                              sources=args.sources, seed=args.seed,
                              progress=not args.no_progress)
    config.validate()
    folder = check_output_folder(args.out, "run", overwrite=args.overwrite)
    captures = args.captures or family_cache_dir() / (
        f"{args.family}-{args.size}px-{args.views}+{args.test_views}v")
    datasets = [load_dataset(p) for p in capture_family(
        args.family, args.seeds, captures, args.views, args.test_views, args.size,
        progress=not args.no_progress)]
    # one set of bounds for the family: every scene's box fits in it (each scene renders
    # within its own bounds; these only initialise the saved model)
    lo = min(float(v) for ds in datasets for v in ds.aabb[0])
    hi = max(float(v) for ds in datasets for v in ds.aabb[1])
    scale = float(np.mean([np.linalg.norm(ds.c2w[:, :3, 3] - ds.aabb.mean(0), axis=1).mean()
                           for ds in datasets]))  # the cameras' distance, metres
    model = build_pixelnerf([[lo] * 3, [hi] * 3], PixelNeRFFieldConfig(position_scale=scale),
                            seed=args.seed).to(args.device)
    with folder.writing():
        summary = train_pixelnerf(model, datasets, config, args.out)
    print(json.dumps({"out": str(args.out), "scenes": len(datasets), "captures": str(captures),
                      **{k: v for k, v in summary.items() if k != "curve"}}, indent=2))
    return 0


def add_parser(sub, device_type) -> None:
    p = sub.add_parser("pixelnerf", help="train pixelNeRF across the scenes of a zoo family, to "
                                         "render unseen scenes of it from 1-3 of their views")
    p.add_argument("--family", default="workspace",
                   help="a generated scene family (workspace, bins, room, ...; default workspace)")
    p.add_argument("--seeds", type=seed_list, default=seed_list("0-31"), metavar="A-B|I,J,...",
                   help="the family's scenes to train on (default 0-31)")
    p.add_argument("--views", type=int, default=24, help="training views per scene (24)")
    p.add_argument("--test-views", type=int, default=6, help="test views per scene (6)")
    p.add_argument("--size", type=int, default=64, help="image size, pixels (64)")
    p.add_argument("--captures", type=Path, default=None,
                   help="folder of the family's captures, one per seed, reused when present "
                        "(default: $NERFBOT_CACHE/families/FAMILY-SIZEpx-VIEWS+TESTv)")
    p.add_argument("--steps", type=int, default=20000, help="training steps (20000)")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="stop after this many seconds of training")
    p.add_argument("--sources", type=source_range, default=(1, 3), metavar="N|LO-HI",
                   help="source views per training step, drawn uniformly (default 1-3)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="the run folder to write")
    p.add_argument("--overwrite", action="store_true", help="replace a run folder of nerfbot's")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--device", type=device_type, default="cpu")
    p.set_defaults(func=cmd_pixelnerf)
