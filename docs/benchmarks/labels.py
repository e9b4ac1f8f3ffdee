"""Semantic labels from the field: mean IoU with full label maps and with a few clicks per
class, and what the label head costs.

usage: python docs/benchmarks/labels.py WORK [--scenes tabletop,glassware,workspace:0]
                                       [--steps 1000] [--clicks 1,5,20]
                                       [--click-choices uncertain,random]

For each scene (128 px, the scene's default rig, 60 training and 10 test views):

1. ``nerfbot capture``;
2. ``nerfbot train --method ngp --max-steps N`` without labels and with ``--labels`` (the head
   trained jointly on full label maps): test PSNR of both (the head never changes the field,
   so they match) and the training time of the second over the first (the head's cost);
3. ``nerfbot label`` on the run without labels: the head trained on the frozen field, from full
   label maps and from 1, 5 and 20 clicks per class on average (iLabel's setting), placed where
   the head is least sure (``--click-choice uncertain``) and at random over each class's pixels
   (``random``), 1000 head steps each;
4. mean IoU on the test views (``nerfbot eval``), classes: background, each object of the
   manifest, structure.

Writes WORK/labels.json, WORK/labels.png (one test view: image, true classes, joint head,
20 and 5 clicks of the first click choice, 20 of the second) and prints a markdown table. Runs
one thing at a time.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from nerfbot.data import load_dataset
from nerfbot.data.labels import label_map
from nerfbot.query.export import colorize_labels, labelled_row, save_image
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

NERFBOT = [sys.executable, "-m", "nerfbot.app.cli"]


def run(cmd: list) -> str:
    print("$", " ".join(str(c) for c in cmd), flush=True)
    return subprocess.run([str(c) for c in cmd], check=True, capture_output=True,
                          text=True).stdout


def metrics(run_dir: Path) -> dict:
    return json.loads((run_dir / "metrics.json").read_text())


def evaluate(run_dir: Path) -> dict:
    return json.loads(run(NERFBOT + ["eval", run_dir, "--json"]))


def scene_row(work: Path, scene: str, steps: int, clicks: list[int], choices: list[str]
              ) -> dict:
    tag = scene.replace(":", "-")
    data = work / tag / "data"
    if not (data / "transforms.json").exists():
        run(NERFBOT + ["capture", "--scene", scene, "--out", data, "--no-progress"])
    row = {"scene": scene}
    for name, extra in (("plain", []), ("joint", ["--labels"])):
        out = work / tag / name
        if not (out / "metrics.json").exists():
            run(NERFBOT + ["train", "--data", data, "--method", "ngp", "--max-steps", steps,
                           "--out", out, "--no-progress", "--overwrite"] + extra)
        m = metrics(out)
        row[name] = {"psnr": m["psnr"], "train_seconds": m["train_seconds"],
                     "label_miou": m.get("label_miou"), "label_iou": m.get("label_iou")}
    row["cost_ratio"] = row["joint"]["train_seconds"] / row["plain"]["train_seconds"]
    for n, choice in [(None, None)] + [(n, c) for c in choices for n in clicks]:
        name = "full" if n is None else f"clicks{n}-{choice}"
        out = work / tag / f"label-{name}"
        if not (out / "labels.json").exists():
            run(NERFBOT + ["label", work / tag / "plain", "--out", out, "--no-progress",
                           "--overwrite"]
                + ([] if n is None else ["--clicks", n, "--click-choice", choice]))
        report = json.loads((out / "labels.json").read_text())
        m = evaluate(out)
        row[name] = {"label_miou": m["label_miou"], "label_iou": m["label_iou"],
                     "seconds": report["seconds"]}
    return row


def sheet(work: Path, scene: str, choices: list[str]) -> np.ndarray:
    """One test view: image | true classes | joint head | 20 and 5 clicks of the first choice
    | 20 clicks of the second."""
    tag = scene.replace(":", "-")
    ds = load_dataset(work / tag / "data")
    i = ds.indices("test")[0]
    cams = ds.cameras([i])
    images, names = [ds.images[i]], [scene]
    panels = [("joint", "labels (joint)")]
    panels += [(f"label-clicks{n}-{choices[0]}", f"{n} clicks, {choices[0]}") for n in (20, 5)]
    panels += [(f"label-clicks20-{c}", f"20 clicks, {c}") for c in choices[1:]]
    for run_name, title in panels:
        path = work / tag / run_name
        if not (path / "checkpoint.pt").exists():
            continue
        model, _ = load_model(path)
        if not names[1:]:
            truth = label_map(ds.segmentations[i], model.label_head.classes)
            images.append(colorize_labels(truth, model.label_head.n_classes))
            names.append("true classes")
        pred = render_image(model, cams, 0, labels=True, supersample=1)["labels"].argmax(-1)
        images.append(colorize_labels(pred, model.label_head.n_classes))
        names.append(title)
    return labelled_row(images, names)


def table(rows: list[dict], clicks: list[int], choices: list[str]) -> str:
    columns = [f"{n} clicks, {c}" for c in choices for n in clicks]
    head = ("| scene | PSNR without / with labels | training time with labels | mIoU joint "
            "| mIoU on the frozen field: full | " + " | ".join(columns) + " |")
    lines = [head, "|" + "---|" * (5 + len(columns))]
    for r in rows:
        cells = [f"`{r['scene']}`", f"{r['plain']['psnr']:.2f} / {r['joint']['psnr']:.2f} dB",
                 f"{r['cost_ratio']:.2f}x", f"{r['joint']['label_miou']:.3f}",
                 f"{r['full']['label_miou']:.3f}"]
        cells += [f"{r[f'clicks{n}-{c}']['label_miou']:.3f}" for c in choices for n in clicks]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--scenes", default="tabletop,glassware,workspace:0")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--clicks", default="1,5,20")
    parser.add_argument("--click-choices", default="uncertain,random")
    args = parser.parse_args()
    clicks = [int(c) for c in args.clicks.split(",")]
    choices = [c for c in args.click_choices.split(",") if c]
    scenes = [s for s in args.scenes.split(",") if s]
    args.work.mkdir(parents=True, exist_ok=True)
    rows = [scene_row(args.work, s, args.steps, clicks, choices) for s in scenes]
    (args.work / "labels.json").write_text(json.dumps(rows, indent=2))
    save_image(args.work / "labels.png",
               np.concatenate([sheet(args.work, s, choices) for s in scenes], 0))
    print(table(rows, clicks, choices))


if __name__ == "__main__":
    main()
