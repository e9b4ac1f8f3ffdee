"""Reporting of grasp experiments: success rates per object and source, tables and plots."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
from matplotlib.figure import Figure

from tasks.grasp_config import Attempt, GraspTaskConfig


def _rate(items: list[Attempt]) -> Optional[float]:
    return sum(a.success for a in items) / len(items) if items else None


def summarize(attempts: list[Attempt], source: str, cfg: GraspTaskConfig,
              threshold: Optional[float]) -> dict:
    """Success rates overall, by transparency and by object, for one depth source."""
    names = sorted({a.object for a in attempts}, key=lambda n: (not n.startswith("glass"), n))
    reasons: dict[str, int] = {}
    for a in attempts:
        if not a.success:
            key = a.reason.split(" (")[0] if a.reason else "unknown"
            reasons[key] = reasons.get(key, 0) + 1
    return {
        "depth_source": source,
        "trials": cfg.trials,
        "attempts": len(attempts),
        "success_rate": _rate(attempts),
        "transparent_success_rate": _rate([a for a in attempts if a.transparent]),
        "opaque_success_rate": _rate([a for a in attempts if not a.transparent]),
        "per_object": {n: _rate([a for a in attempts if a.object == n]) for n in names},
        "failures": reasons,
        "threshold": threshold if source == "dexnerf" else None,
        "scene": cfg.scene,
        "seeds": [cfg.seed, cfg.seed + cfg.trials - 1],
        "target": cfg.target,
        "located_error_m_median": _median([a.located_error_m for a in attempts
                                            if a.located_error_m is not None]),
    }


def _median(values: list[float]) -> Optional[float]:
    return float(np.median(values)) if values else None


def plot_success(summaries: dict, path: Path, title: str = "") -> Path:
    """PNG bar chart: success rate per object (rows grouped glass / opaque) for each source."""
    sources = list(summaries)
    names = []
    for s in sources:
        names += [n for n in summaries[s]["per_object"] if n not in names]
    fig = Figure(figsize=(max(6.0, 0.9 * len(names) + 2), 3.8))
    ax = fig.subplots()
    width = 0.8 / max(len(sources), 1)
    for k, s in enumerate(sources):
        rates = [100 * (summaries[s]["per_object"].get(n) or 0) for n in names]
        ax.bar(np.arange(len(names)) + (k - (len(sources) - 1) / 2) * width, rates, width,
               label=f"{s} (glass {100 * (summaries[s]['transparent_success_rate'] or 0):.0f} %, "
                     f"opaque {100 * (summaries[s]['opaque_success_rate'] or 0):.0f} %)")
    ax.set_xticks(np.arange(len(names)), [n.replace("_", " ") for n in names], rotation=30,
                  ha="right", fontsize=8)
    ax.set_ylabel("grasp success (%)")
    ax.set_ylim(0, 140)  # headroom for the legend above the bars
    ax.set_yticks(range(0, 101, 20))
    ax.set_title(title or "lifted 10 cm and held 2 s", fontsize=10)
    ax.legend(fontsize=7, loc="upper center", ncol=2, frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return Path(path)


def format_table(summaries: dict) -> str:
    """A plain-text table: objects as rows, depth sources as columns (success %)."""
    sources = list(summaries)
    names = []
    for s in sources:
        names += [n for n in summaries[s]["per_object"] if n not in names]
    width = max([len(n) for n in names] + [14])
    lines = [f"{'object':<{width}} " + " ".join(f"{s:>8}" for s in sources)]

    def cell(v):
        return f"{100 * v:7.0f}%" if v is not None else f"{'-':>8}"

    for n in names:
        lines.append(f"{n:<{width}} " + " ".join(cell(summaries[s]["per_object"].get(n))
                                                 for s in sources))
    lines.append("-" * len(lines[0]))
    for label, key in (("transparent", "transparent_success_rate"),
                       ("opaque", "opaque_success_rate"), ("all", "success_rate")):
        lines.append(f"{label:<{width}} " + " ".join(cell(summaries[s][key]) for s in sources))
    located = [summaries[s].get("located_error_m_median") for s in sources]
    if any(v is not None for v in located):
        lines.append(f"{'located (cm)':<{width}} " + " ".join(
            f"{100 * v:8.1f}" if v is not None else f"{'-':>8}" for v in located))
    return "\n".join(lines)


def format_depth_report(report: dict) -> str:
    """Rows: pixel class; columns: MAE / RMSE (cm) and valid fraction per depth mode."""
    modes = [k for k in report["transparent"] if k != "best_threshold"]
    lines = [f"{'pixels':<16}" + "".join(f"{m:>24}" for m in modes)]
    for c in ("transparent", "opaque_objects", "scene"):
        cells = []
        for m in modes:
            e = report[c].get(m)
            if not e or e["mae_m"] is None:
                cells.append(f"{'-':>24}")
            else:
                cells.append(f"{100 * e['mae_m']:>7.2f} /{100 * e['rmse_m']:6.2f} cm"
                             f" {100 * e['valid_fraction']:4.0f}%")
        lines.append(f"{c:<16}" + "".join(cells))
    lines.append("cells: MAE / RMSE of z-depth against ground truth (glass opaque), and the "
                 "share of pixels with a depth")
    return "\n".join(lines)
