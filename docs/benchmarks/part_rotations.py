"""Do a ``rigid`` run's parts turn with their bodies? Trained rotations against MuJoCo's.

    python docs/benchmarks/part_rotations.py RUN [RUN ...] [--out NAME]

Each RUN is a ``rigid`` run trained on a ``sims`` dynamic capture, found as ``nerfbot eval``
finds it. A part's frame is its own (it starts at the identity), so the comparison is between
turns: the world-frame rotation carrying the body from the first training step to step j,
``R_j R_0^T`` for the part and ``Q_j Q_0^T`` for MuJoCo's recorded body orientation
(``states.npz``), which agree whatever constant rotation separates the two frames.

Prints per run and body: the largest true turn over the capture, the largest trained one, and
the angle between the two turns (degrees; median and largest over the training steps); writes
``docs/benchmarks/<NAME>.png`` (NAME default ``part_rotations``): per body, the true and the
trained turn angle over time.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import mujoco
import numpy as np
import torch
from matplotlib.figure import Figure

from nerfbot.data.run_dataset import resolve_run_dataset
from nerfbot.train.runs import load_model

matplotlib.use("Agg")
HERE = Path(__file__).resolve().parent


def quaternion_matrices(quat: np.ndarray) -> np.ndarray:
    """(N, 4) w-x-y-z unit quaternions -> (N, 3, 3) rotation matrices (MuJoCo's conversion)."""
    out = np.empty((len(quat), 9))
    for row, q in zip(out, np.asarray(quat, np.float64)):
        mujoco.mju_quat2Mat(row, q)
    return out.reshape(-1, 3, 3)


def angle_deg(rot: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (...) their angles, degrees."""
    cos = (np.trace(rot, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def rotations_of(path: Path):
    """(dataset, [(body, times (J,), rotations (J, 3, 3))]) of a run's trained parts."""
    model, _ = load_model(path)
    _, dataset = resolve_run_dataset(path)
    with torch.no_grad():
        return dataset, [(p.name, p.times.numpy().astype(np.float64),
                          p.step_rotations().numpy().astype(np.float64))
                         for p in model.field.parts]


def part_turns(path: Path) -> dict:
    """{body: (times (J,), true turn angles (J,), trained turn angles (J,), errors (J,))}."""
    dataset, found = rotations_of(path)
    states = np.load(dataset.root / dataset.manifest["capture"]["state_file"])
    names = [str(n) for n in states["body_names"]]
    out = {}
    for name, times, rot in found:
        steps = np.abs(states["time"][None, :] - times[:, None]).argmin(1)
        true = quaternion_matrices(states["body_quat"][steps, names.index(name)])
        true_turn = true @ true[:1].transpose(0, 2, 1)
        found_turn = rot @ rot[:1].transpose(0, 2, 1)
        error = angle_deg(found_turn.transpose(0, 2, 1) @ true_turn)
        out[name] = (times, angle_deg(true_turn), angle_deg(found_turn), error)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path)
    parser.add_argument("--out", default="part_rotations")
    args = parser.parse_args()
    results = {path: part_turns(path) for path in args.paths}
    print("| run | body | largest true turn | largest trained turn | error: median / largest |")
    print("|---|---|---|---|---|")
    for run, parts in results.items():
        for name, (_, true, found, error) in parts.items():
            print(f"| {run.name} | {name} | {true.max():.1f}° | {found.max():.1f}° | "
                  f"{np.median(error):.1f}° / {error.max():.1f}° |")
    n = max(len(p) for p in results.values())
    fig = Figure(figsize=(3.2 * n, 2.6 * len(results)))
    for r, (run, parts) in enumerate(results.items()):
        for c, (name, (times, true, found, _)) in enumerate(parts.items()):
            ax = fig.add_subplot(len(results), n, r * n + c + 1)
            ax.plot(times, true, "k-", label="MuJoCo")
            ax.plot(times, found, "C1--", label="trained")
            ax.set_title(f"{run.name}: {name}", fontsize=8)
            ax.set_xlabel("time")
            ax.set_ylabel("turn since the first step, °")
            if r == 0 and c == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    path = HERE / f"{args.out}.png"
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
