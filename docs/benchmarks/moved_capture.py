"""A nerfstudio capture moved and scaled in the world, for the exports' frame test.

usage: python docs/benchmarks/moved_capture.py SRC DST --scale S --offset TX TY TZ

Every world point p becomes S * p + T: camera positions move so, rotations stay, intrinsics and
images stay (a similarity of the world and the cameras together leaves every image unchanged),
depth maps are multiplied by S, and the manifest's bounds (and obstacle boxes) are moved. The
manifest records the move as ``moved`` = {"scale": S, "offset": T}, which
``docs/benchmarks/exports.py`` applies to the true geometry. Images and segmentations are
copied; DST must not exist.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from nerfbot.data.spec import EXACT_DEPTH_FIELD
from nerfbot.data.writers import write_depth_files


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path)
    p.add_argument("--scale", type=float, required=True)
    p.add_argument("--offset", type=float, nargs=3, required=True)
    args = p.parse_args(argv)
    if args.dst.exists():
        raise SystemExit(f"{args.dst}: exists; choose a new folder")
    if not args.scale > 0:
        raise SystemExit(f"--scale must be > 0, got {args.scale}")
    s, t = args.scale, np.asarray(args.offset, float)
    shutil.copytree(args.src, args.dst)
    meta = json.loads((args.src / "transforms.json").read_text())
    for frame in meta["frames"]:
        c2w = np.asarray(frame["transform_matrix"], float)
        c2w[:3, 3] = s * c2w[:3, 3] + t
        frame["transform_matrix"] = c2w.tolist()
        if frame.get(EXACT_DEPTH_FIELD):  # the exact depth and nerfstudio's millimetre PNG
            stem = str(Path(frame[EXACT_DEPTH_FIELD]).with_suffix(""))
            frame.update(write_depth_files(args.dst, stem,
                                           np.load(args.src / frame[EXACT_DEPTH_FIELD]) * s))
    scene = meta.get("scene") or {}
    if "bounds" in scene:
        scene["bounds"] = (s * np.asarray(scene["bounds"], float) + t).tolist()
    for name, box in (scene.get("obstacles") or {}).items():
        scene["obstacles"][name] = (s * np.asarray(box, float) + t).tolist()
    scene["moved"] = {"scale": s, "offset": t.tolist()}
    (args.dst / "transforms.json").write_text(json.dumps(meta, indent=2))
    print(f"wrote {args.dst}: world points p -> {s:g} p + {t.tolist()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
