"""Presenting a benchmark sweep: the Markdown table and the PSNR trade-off plots."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

#: (column title, summary key, format, scale)
_TABLE = (
    ("method", "method", "{}", None),
    ("size", "image_size", "{}", None),
    ("budget", "budget", "{}", None),
    ("options", "options", "{}", None),
    ("PSNR", "psnr", "{:.2f}", None),
    ("non-sky PSNR", "psnr_non_sky", "{:.2f}", None),
    ("object PSNR", "psnr_objects", "{:.2f}", None),
    ("SSIM", "ssim", "{:.3f}", None),
    ("depth MAE mm", "depth_mae_m", "{:.1f}", 1e3),
    ("object depth MAE mm", "depth_mae_objects_m", "{:.1f}", 1e3),
    ("depth RMSE mm", "depth_rmse_m", "{:.1f}", 1e3),
    ("Chamfer mm", "chamfer_mm", "{:.1f}", None),
    ("train s", "train_seconds", "{:.1f}", None),
    ("steps", "steps", "{:.0f}", None),
    ("steps/s", "steps_per_second", "{:.2f}", None),
    ("render ms", "render_ms_per_image", "{:.1f}", None),
    ("FPS", "render_fps", "{:.2f}", None),
    ("peak RSS MB", "peak_rss_mb", "{:.0f}", None),
    ("params", "num_params", "{:,}", None),
    ("model MB", "size_mb", "{:.1f}", None),
    ("FPS x base", "speedup_vs_baseline", "{:.2f}", None),
    ("train time x base", "train_time_ratio", "{:.2f}", None),
)


def _cell(value, fmt: str, scale: Optional[float]) -> str:
    if value is None or value == "":
        return "-"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "-"
        value = value * scale if scale else value
    try:
        return fmt.format(value)
    except (ValueError, TypeError):
        return str(value)


def markdown_table(rows: list[dict], cfg) -> str:
    """Markdown: one table per scene, one row per configuration (medians over repeats).
    Pareto column: T = on the PSNR / train-time front, F = on the PSNR / render-FPS front."""
    unit = "s" if cfg.budget_kind == "seconds" else "steps"
    lines = ["# nerfbot bench", "",
             f"Medians over {cfg.repeats} repeat(s); budget in training {unit}; "
             "ratios against each scene's first configuration (marked *). "
             "Pareto: T = best PSNR for its train time, F = best PSNR for its render FPS. "
             "Chamfer: marching-cubes mesh of the field vs the true MuJoCo geometry, "
             "surfaces seen by the training cameras.", ""]
    if not rows:
        return "\n".join(lines + ["(no completed points yet)", ""])
    for scene in dict.fromkeys(r["scene"] for r in rows):
        lines += [f"## {scene}", ""]
        titles = [t for t, *_ in _TABLE] + ["Pareto"]
        lines.append("| " + " | ".join(titles) + " |")
        lines.append("|" + "|".join("---" for _ in titles) + "|")
        for r in (r for r in rows if r["scene"] == scene):
            cells = [_cell(r.get(key), fmt, scale) for _, key, fmt, scale in _TABLE]
            if r.get("baseline"):
                cells[0] += " *"
            marks = ("T" if r.get("pareto_train_time") else "") + \
                    ("F" if r.get("pareto_render_fps") else "")
            lines.append("| " + " | ".join(cells + [marks or "-"]) + " |")
        lines.append("")
        for r in (r for r in rows if r["scene"] == scene and "psnr_gap_to_best" in r):
            lines += [f"`{r['method']}` ({r['options'] or 'defaults'}): "
                      f"{r['psnr_gap_to_best']:+.2f} dB behind the best other configuration "
                      f"at budget {r['budget']:g} ({r['best_config']}; negative = ahead), trained "
                      f"{r['train_seconds']:.0f} s vs {r['best_train_seconds']:.0f} s.", ""]
        for r in (r for r in rows if r["scene"] == scene and r.get("source_method")):
            lines += [f"`{r['method']}` ({r['options'] or 'defaults'}, budget {r['budget']:g}): "
                      f"baked in {_cell(r.get('bake_seconds'), '{:.0f}', None)} s from "
                      f"`{r['source_method']}` ({_cell(r.get('source_psnr'), '{:.2f}', None)} dB, "
                      f"{_cell(r.get('source_render_ms_per_image'), '{:.1f}', None)} ms per "
                      f"image): renders "
                      f"{_cell(r.get('render_speedup_vs_source'), '{:.1f}', None)}x faster, "
                      f"PSNR {_cell(r.get('psnr_change_vs_source'), '{:+.2f}', None)} dB, "
                      f"{_cell(r.get('size_mb'), '{:.1f}', None)} MB.", ""]
    return "\n".join(lines)


def _labeller(rows: list[dict]):
    """Point labels: the budget, plus the image size and options where they vary."""
    varying = [k for k in dict.fromkeys(k for r in rows for k in r if k.startswith("option_"))
               if len({str(r.get(k)) for r in rows}) > 1]
    sizes_vary = len({r.get("image_size") for r in rows}) > 1

    def label(r: dict) -> str:
        unit = "s" if r["budget_kind"] == "seconds" else " steps"
        parts = [f"{r['budget']:g}{unit}"]
        if sizes_vary:
            parts.append(str(r.get("image_size")))
        parts += [f"{k[len('option_'):]}={r[k]}" for k in varying if r.get(k) is not None]
        return ", ".join(parts)

    return label


def plot_tradeoff(rows: list[dict], x_key: str, front_key: str, xlabel: str, path: Path,
                  log_x: bool = False) -> Path:
    """PSNR against ``x_key``, one panel per scene, a colour per method, every point labelled
    with its budget (and the size / options that vary); the Pareto front (rows flagged ``front_key``) drawn as
    a line through ringed points."""
    scenes = list(dict.fromkeys(r["scene"] for r in rows)) or ["(no data)"]
    fig = Figure(figsize=(7.0 * len(scenes), 5.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(scenes), squeeze=False)[0]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colours = {m: f"C{i % 10}" for i, m in enumerate(methods)}
    for ax, scene in zip(axes, scenes):
        mine = [r for r in rows if r["scene"] == scene
                and r.get(x_key) is not None and r.get("psnr") is not None]
        label = _labeller(mine)
        for m in methods:
            pts = [r for r in mine if r["method"] == m]
            if pts:
                ax.scatter([r[x_key] for r in pts], [r["psnr"] for r in pts], color=colours[m],
                           label=m, s=36, zorder=3)
            for r in pts:
                ax.annotate(label(r), (r[x_key], r["psnr"]), textcoords="offset points",
                            xytext=(4, 4), fontsize=7, color=colours[m])
        front = sorted((r for r in mine if r.get(front_key)), key=lambda r: r[x_key])
        if front:
            ax.plot([r[x_key] for r in front], [r["psnr"] for r in front], color="k", lw=1,
                    ls="--", zorder=2, label="Pareto front")
            ax.scatter([r[x_key] for r in front], [r["psnr"] for r in front], s=110,
                       facecolors="none", edgecolors="k", zorder=4)
        if log_x and mine and all(r[x_key] > 0 for r in mine):
            ax.set_xscale("log")
            plain = FuncFormatter(lambda v, _: f"{v:g}")
            ax.xaxis.set_major_formatter(plain)
            ax.xaxis.set_minor_formatter(plain)
        ax.set_title(scene)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("test PSNR (dB)")
        ax.grid(alpha=0.3)
        if mine:
            ax.legend(fontsize=8)
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=120)
    tmp.replace(path)
    return path


def plot_tradeoffs(rows: list[dict], out: Path) -> list[Path]:
    """``psnr_vs_train_time.png`` and ``psnr_vs_render_fps.png`` in ``out``."""
    out = Path(out)
    return [plot_tradeoff(rows, "train_seconds", "pareto_train_time", "training time (s)",
                          out / "psnr_vs_train_time.png"),
            plot_tradeoff(rows, "render_fps", "pareto_render_fps", "render speed (images / s)",
                          out / "psnr_vs_render_fps.png", log_x=True)]
