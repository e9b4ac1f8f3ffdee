"""``--method auto`` with a target PSNR or a time budget and no bench table: a short sweep of
the chosen configuration at a few budgets (:func:`builtin_sweep_rows`), and everything ``nerfbot
train --method auto`` decides (:func:`auto_train_config`). The choices themselves are in
:mod:`nerfbot.train.auto`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional, Sequence

from nerfbot.bench.sweep import BenchConfig, run_bench
from nerfbot.train.auto import AutoChoice, bench_rows, choose_budget


log = logging.getLogger(__name__)


#: Budgets (training seconds) of the built-in sweep when no bench table is given.
BUILTIN_SWEEP_SECONDS = (30.0, 60.0, 120.0)


def builtin_sweep_rows(data: Path, choice: AutoChoice, out: Path,
                       budgets: Sequence[float] = BUILTIN_SWEEP_SECONDS) -> list[dict]:
    """Bench the chosen configuration at a few budgets on ``data`` (one point per budget, in
    ``out``; resumed if run before) and return its rows."""
    cfg = BenchConfig(data=[str(data)], methods=[choice.method], budgets=list(budgets),
                      out=Path(out), options={k: [v] for k, v in choice.options.items()},
                      chamfer=False)
    result = run_bench(cfg)
    if result.failures:
        raise RuntimeError(f"the built-in sweep in {out} failed for {len(result.failures)} "
                           "point(s); see bench.json")
    return [r for r in result.rows if r["method"] == choice.method]


def auto_train_config(choice: AutoChoice, data: Path, run: Path, user_options: dict,
                      target_psnr: Optional[float] = None, time_budget: Optional[float] = None,
                      bench_table: Optional[Path] = None) -> AutoChoice:
    """Everything ``nerfbot train --method auto`` decides beyond the scene's ``choice``
    (:func:`~nerfbot.train.auto.choose_for_dataset`): ``user_options`` override its options,
    and with a target or time budget, the training seconds come from a bench table (or a
    built-in sweep in ``run/auto_sweep``)."""
    for k, v in user_options.items():
        if choice.options.get(k) != v:
            choice.reasons.append(f"option {k}={v} given by the user")
        choice.options[k] = v
    if target_psnr is None and time_budget is None:
        return choice
    if bench_table is not None:
        label = Path(data).resolve().name if Path(data).exists() else str(data)
        rows = bench_rows(bench_table, scene=label, method=choice.method, options=choice.options)
        if not rows:
            raise ValueError(f"{bench_table}: no rows for scene {label!r}, method "
                             f"{choice.method!r} with options {choice.options}")
        source = f"bench table {bench_table}"
    else:
        rows = builtin_sweep_rows(data, choice, Path(run) / "auto_sweep")
        source = f"built-in sweep at {', '.join(f'{b:g}' for b in BUILTIN_SWEEP_SECONDS)} s"
    row = choose_budget(rows, target_psnr, time_budget)
    choice.budget_seconds = float(row["budget"])
    goal = (f"reaches {target_psnr:g} dB" if target_psnr is not None
            else f"is best within {time_budget:g} s")
    choice.reasons.append(f"budget {row['budget']:g} s: the cheapest configuration that {goal} "
                          f"({row['psnr']:.2f} dB in {row['train_seconds']:.0f} s, {source})"
                          if target_psnr is not None else
                          f"budget {row['budget']:g} s: {row['psnr']:.2f} dB, the best that "
                          f"{goal} ({source})")
    return choice
