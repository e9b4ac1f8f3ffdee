"""Per-step training scalars of a run: ``RUN/scalars.csv`` (one row per step) and
``RUN/curve.png`` (their plot beside the held-out PSNR of ``curve.json``).

Columns (:data:`COLUMNS`): ``step``; ``seconds`` (training time after the step, s);
``loss`` (the batch's total loss); ``psnr`` (dB, -10 log10 of the loss: the batch's colour
PSNR when no other loss term is on); ``rays`` (rays in the batch); ``samples_per_ray``;
``occupied`` (share of the occupancy grid marked occupied, empty for methods without one);
``lr`` (learning rate of the first parameter group); ``step_ms`` (wall-clock time of the step,
ms). Rows are written with the checkpoint, so after an interruption the file ends where the
checkpoint does.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Optional, Sequence

from matplotlib.figure import Figure

#: File name of the table in a run folder.
SCALARS = "scalars.csv"
#: Column order of ``scalars.csv``.
COLUMNS = ("step", "seconds", "loss", "psnr", "rays", "samples_per_ray", "occupied", "lr",
           "step_ms")


def step_row(step: int, seconds: float, loss: float, rays: int, samples: int,
             occupied: Optional[float], lr: float, step_seconds: float) -> dict:
    """One row of :data:`COLUMNS` for a finished step."""
    return {"step": step, "seconds": seconds, "loss": loss,
            "psnr": -10.0 * math.log10(max(loss, 1e-10)), "rays": rays,
            "samples_per_ray": samples / max(rays, 1), "occupied": occupied, "lr": lr,
            "step_ms": 1000.0 * step_seconds}


def write_scalars(path: Path, rows: Sequence[dict]) -> Path:
    """Write ``rows`` as CSV with :data:`COLUMNS` (missing values empty), atomically."""
    path = Path(path)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: ("" if row.get(k) is None else f"{row[k]:.6g}"
                             if isinstance(row[k], float) else row[k]) for k in COLUMNS})
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(buf.getvalue())
    os.replace(tmp, path)
    return path


def read_scalars(path: Path, up_to_step: Optional[int] = None) -> list[dict]:
    """Rows of a ``scalars.csv`` (numbers as floats, ``step`` and ``rays`` as ints, empty as
    None), those after ``up_to_step`` dropped. A missing file gives []; ValueError naming the
    file for one that is not such a table."""
    path = Path(path)
    if not path.exists():
        return []
    rows = []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or set(COLUMNS) - set(reader.fieldnames):
            raise ValueError(f"{path}: not a scalars table (expected the columns "
                             f"{', '.join(COLUMNS)})")
        for line, raw in enumerate(reader, start=2):
            try:
                row = {k: (None if raw[k] in ("", None) else
                           int(raw[k]) if k in ("step", "rays") else float(raw[k]))
                       for k in COLUMNS}
            except ValueError as err:
                raise ValueError(f"{path}: line {line}: {err}") from None
            if up_to_step is None or row["step"] <= up_to_step:
                rows.append(row)
    return rows


def plot_scalars(path: Path, rows: Sequence[dict], evaluations: Sequence[dict] = (),
                 title: str = "") -> Path:
    """``curve.png``: batch PSNR (and the held-out PSNR of ``evaluations``, the records of
    ``curve.json``), loss, and step time against the step."""
    steps = [r["step"] for r in rows]
    # a Figure of its own, not pyplot's: a run trained in a notebook leaves its backend alone
    fig = Figure(figsize=(15, 4))
    axes = fig.subplots(1, 3)
    ax = axes[0]
    ax.plot(steps, [r["psnr"] for r in rows], lw=0.6, alpha=0.5, label="batch (from the loss)")
    held = [e for e in evaluations if e.get("psnr") is not None and "step" in e]
    if held:
        ax.plot([e["step"] for e in held], [e["psnr"] for e in held], "o-", color="C3",
                label="held-out views")
    ax.set_xlabel("step"); ax.set_ylabel("PSNR (dB)"); ax.legend(); ax.grid(alpha=0.3)
    axes[1].semilogy(steps, [max(r["loss"], 1e-12) for r in rows], lw=0.6)
    axes[1].set_xlabel("step"); axes[1].set_ylabel("loss"); axes[1].grid(alpha=0.3)
    axes[2].plot(steps, [r["step_ms"] for r in rows], lw=0.6)
    axes[2].set_xlabel("step"); axes[2].set_ylabel("step time (ms)"); axes[2].grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.png")
    fig.savefig(tmp, dpi=90)
    os.replace(tmp, path)
    return path
