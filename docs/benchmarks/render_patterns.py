"""One test view of each run rendered with every supersampling pattern, beside the truth
(BENCHMARKS.md, section 7, "The corners, and the grid where they disagree").

usage: python docs/benchmarks/render_patterns.py OUT.png DATA RUN [DATA RUN ...] [--view K]

Per run, one row: the test image, the grid, corners and adaptive renders, and the adaptive
render's difference from the grid's (largest channel, times 10).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.query.export import labelled_row, save_image
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

PATTERNS = ("grid", "corners", "adaptive")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("pairs", nargs="+", help="DATA RUN, repeated")
    parser.add_argument("--view", type=int, default=3, help="index among the test views")
    args = parser.parse_args()
    if len(args.pairs) % 2:
        parser.error("give DATA RUN pairs")
    rows = []
    for data, run in zip(args.pairs[::2], args.pairs[1::2]):
        ds = load_dataset(data)
        model = load_model(run)[0].eval()
        test = ds.indices("test")
        cams = ds.cameras(test)
        renders = [render_image(model, cams, args.view, supersample_pattern=p)["rgb"]
                   for p in PATTERNS]
        diff = np.abs(renders[2] - renders[0]).max(-1, keepdims=True).repeat(3, -1) * 10
        rows.append(labelled_row([ds.image_float(test[args.view]), *renders, diff.clip(0, 1)],
                                 [Path(data).name[:18], *PATTERNS, "|adaptive - grid| x 10"]))
    print("wrote", save_image(args.out, np.vstack(rows)))


if __name__ == "__main__":
    main()
