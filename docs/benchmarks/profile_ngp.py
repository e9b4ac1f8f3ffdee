"""Where an `ngp` training step and a render spend their time, per phase, against the machine's
limits.

usage: python docs/benchmarks/profile_ngp.py DATA [--warmup-steps 300] [--steps 100]
                                             [--samples 32768] [--option KEY=VALUE]
                                             [--json OUT.json] [--out RUN]

Trains `ngp` with its defaults on DATA for ``--warmup-steps`` (untimed: the occupancy grid has
pruned and the field has structure, as in the middle of a budget), then times ``--steps`` more,
phase by phase, at ``--samples`` samples per batch, then renders every test view (the phases of
rendering timed the same way, per image, the evaluation's own work in "other"). The phases of a
step are the trainer's own calls: grid upkeep (`before_step`, with its density queries),
drawing the batch, marching, the density-only pass that finds where rays saturate (in steps
that march in rounds), the field's density and colour forward passes, compositing and
losses, backward, and the optimiser. Timers synchronise nothing (CPU
only) and add one `perf_counter` pair per call.

The bound: a step that trains on M samples must at least (a) run the MLPs' FLOPs forward and
backward (3x the forward's) for them, at the measured rate of a (M, 64) x (64, 64) matmul in
the MLPs' precision (``mlp_precision``: float32, or bfloat16 with ``--option mlp_precision=bf16``),
(b) stream the Adam state of every parameter (parameters, gradients and two moments read, three
written) at the measured copy bandwidth, and (c) read the hash-table rows of every sample's 8
cell corners on every level, and add into them in the backward pass: the memory floor of the
encoding. (c) is timed on the rows of the last timed step's own points (every hash-encoding call
that step made with autograd on), by two kernels that do nothing but those reads (a sum of the 8
rows) and those read-modify-writes (an add into them), in the encoding kernels' level-major,
one-level-per-worker order; the row indices are computed beforehand, untimed, and the time to
stream them (at the copy bandwidth) is taken off. The report gives
the step's ratio to the whole bound and to (a) + (b) alone. The
rates are the best of five timings, taken three times in the same run (before the warm-up,
before the timed steps and after them) and the best of the three kept: a virtual machine's
rates drift by tens of percent within minutes, and the bound is the machine at its best. Run
alone: two processes on two cores halve each other's rate.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
from numba import njit, prange

from nerfbot.app.cli import parse_option
from nerfbot.data import load_dataset
from nerfbot.eval.evaluation import evaluate
from nerfbot.kernels.hashgrid import _cell, _corner_rows, _level
from nerfbot.models import occupancy as occupancy_module
from nerfbot.ops.runtime import keep_freed_memory
from nerfbot.train.trainer import TrainConfig, Trainer, batch_loss


class PhaseTimer:
    """Wall-clock seconds per phase name, exclusive of nested timed phases (the grid upkeep's
    density queries count as upkeep, not as density). ``wrap(obj, attr, name)`` times every
    call of ``obj.attr``; ``split_grad`` splits the calls by whether autograd records them."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self._children = []
        self._absorbing = 0

    def wrap(self, obj, attr: str, name: str, split_grad: bool = False,
             absorb: bool = False) -> None:
        """Time calls of ``obj.attr`` as phase ``name``; with ``absorb`` the timed calls made
        inside it count as part of it."""
        fn = getattr(obj, attr)

        def timed(*args, **kwargs):
            if self._absorbing:
                return fn(*args, **kwargs)
            key = name
            if split_grad:
                key = f"{name} (train)" if torch.is_grad_enabled() else f"{name} (no grad)"
            self._absorbing += absorb
            self._children.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - t0
                self._absorbing -= absorb
                nested = self._children.pop()
                self.seconds[key] += elapsed - nested
                if self._children:
                    self._children[-1] += elapsed

        setattr(obj, attr, timed)


def _best_rate(work: float, fn, repeats: int = 10, trials: int = 5) -> float:
    """``work`` units per second of ``fn``: the best of ``trials`` timings of ``repeats`` calls
    (the bound takes the machine at its best)."""
    fn()
    best = 0.0
    for _ in range(trials):
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        best = max(best, work * repeats / (time.perf_counter() - t0))
    return best


def matmul_gflops(n: int = 1024) -> float:
    """Measured float32 matmul rate (GFLOP/s) with torch's threads."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    return _best_rate(2 * n ** 3 / 1e9, lambda: a @ b)


def mlp_like_gflops(rows: int = 1 << 15, width: int = 64,
                    dtype: torch.dtype = torch.float32) -> float:
    """Measured rate (GFLOP/s) of the matmul shape a tiny MLP runs: (rows, 64) x (64, 64), in
    ``dtype``."""
    x, w = torch.randn(rows, width, dtype=dtype), torch.randn(width, width, dtype=dtype)
    return _best_rate(2 * rows * width * width / 1e9, lambda: x @ w)


def copy_gbps(mb: int = 256) -> float:
    """Measured memory bandwidth (GB/s) of a large copy (read + write counted)."""
    src = torch.empty(mb * (1 << 20) // 4)
    dst = torch.empty_like(src)
    return _best_rate(2 * src.numel() * 4 / 1e9, lambda: dst.copy_(src))


def machine_rates(best: dict | None = None) -> dict:
    """The three rates of the bound, each the best of this measurement and ``best``'s."""
    rates = {"matmul_gflops": matmul_gflops(), "mlp_shape_gflops": mlp_like_gflops(),
             "mlp_shape_gflops_bf16": mlp_like_gflops(dtype=torch.bfloat16),
             "copy_gbps": copy_gbps()}
    return {k: max(v, (best or {}).get(k, 0.0)) for k, v in rates.items()}


@njit(parallel=True, cache=True)
def _corner_table_rows(x, offsets, res, rows):
    """(L, N, 8) int32 absolute table rows of every point's cell corners on every level."""
    for lvl in prange(res.shape[0]):
        r, rf, res1, off, size, dense = _level(res, offsets, lvl)
        for n in range(x.shape[0]):
            ix, iy, iz, _, _, _ = _cell(x, n, rf, r)
            corners = _corner_rows(ix, iy, iz, res1, size - 1, dense)
            for c in range(8):
                rows[lvl, n, c] = off + corners[c]


@njit(parallel=True, fastmath=True, cache=True)
def _gather_rows(rows, table, out, n_threads):
    """out[l, n] = sum of the 8 rows: the forward pass's reads and nothing else."""
    n_levels, n_points = rows.shape[0], rows.shape[1]
    for tid in prange(n_threads):
        for lvl in range(tid, n_levels, n_threads):
            for n in range(n_points):
                a0 = np.float32(0.0)
                a1 = np.float32(0.0)
                for c in range(8):
                    a0 += table[rows[lvl, n, c], 0]
                    a1 += table[rows[lvl, n, c], 1]
                out[lvl, n, 0] = a0
                out[lvl, n, 1] = a1


@njit(parallel=True, fastmath=True, cache=True)
def _scatter_rows(rows, grad, table_grad, n_threads):
    """table_grad[row] += grad[l, n] for the 8 rows: the backward pass's read-modify-writes."""
    n_levels, n_points = rows.shape[0], rows.shape[1]
    for tid in prange(n_threads):
        for lvl in range(tid, n_levels, n_threads):
            for n in range(n_points):
                g0 = grad[lvl, n, 0]
                g1 = grad[lvl, n, 1]
                for c in range(8):
                    table_grad[rows[lvl, n, c], 0] += g0
                    table_grad[rows[lvl, n, c], 1] += g1


def hash_memory_floor_ms(encoding, calls: list, copy_gbps: float) -> float:
    """Milliseconds of the encoding's bare row reads and read-modify-writes for the points of
    ``calls`` (each an (N, 3) array of positions in [0, 1]^3 given to the encoding), the best of
    five timings of each. The bare kernels also stream their array of row indices, which the
    encoding's kernels (computing rows on the fly) never read: its time at ``copy_gbps`` is
    taken off."""
    if encoding.n_features != 2:
        raise SystemExit("the hash memory floor is written for 2 features per level")
    offsets, res = encoding._offsets_np, encoding._res_np
    table = encoding.table.detach().numpy()
    threads = torch.get_num_threads()
    total = 0.0
    for x in calls:
        rows = np.empty((len(res), len(x), 8), np.int32)
        _corner_table_rows(np.ascontiguousarray(x, np.float32), offsets, res, rows)
        out = np.empty((len(res), len(x), 2), np.float32)
        grad_table = np.zeros_like(table)
        for kernel, args in ((_gather_rows, (rows, table, out, threads)),
                             (_scatter_rows, (rows, out, grad_table, threads))):
            seconds = 1.0 / _best_rate(1.0, lambda: kernel(*args), repeats=3)
            total += max(0.0, seconds - rows.nbytes / (copy_gbps * 1e9))
    return 1e3 * total


def mlp_flops_per_sample(model) -> float:
    """Forward FLOPs of the density and colour MLPs for one sample (2 per multiply-add)."""
    total = 0
    for mlp in (model.field.density_mlp, model.field.color_mlp):
        total += sum(2 * m.in_features * m.out_features for m in mlp
                     if isinstance(m, torch.nn.Linear))
    return float(total)


def main() -> None:
    keep_freed_memory()  # as `nerfbot train` does
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data")
    p.add_argument("--warmup-steps", type=int, default=300)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--samples", type=int, default=1 << 15)
    p.add_argument("--option", action="append", default=[], type=parse_option,
                   metavar="KEY=VALUE", help="ngp option (repeatable)")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--out", type=Path, default=None,
                   help="run folder of the warm-up training (new or empty; default: a "
                        "temporary folder, deleted at the end)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="profile_ngp_") as scratch:
        profile(args, args.out or Path(scratch) / "run")


def profile(args, out: Path) -> None:
    rates = machine_rates()
    ds = load_dataset(args.data)
    options = {"samples_per_batch": args.samples, **dict(args.option)}
    trainer = Trainer(ds, out, TrainConfig(method="ngp", max_steps=args.warmup_steps,
                                           seed=0, progress=False, options=options))
    trainer.train()
    model, bank, gen = trainer.model, trainer.bank, trainer.generator

    timer = PhaseTimer()
    timer.wrap(model, "before_step", "grid upkeep", absorb=True)
    timer.wrap(bank, "sample", "draw batch")
    timer.wrap(model, "_march", "march")
    timer.wrap(model.field, "density", "density", split_grad=True)
    timer.wrap(model.field, "color", "colour", split_grad=True)
    timer.wrap(occupancy_module, "composite", "composite")
    timer.wrap(occupancy_module, "distortion_loss", "distortion loss")
    timer.wrap(occupancy_module, "render_weights", "transmittance (no grad)")

    encoded = []          # positions given to the hash encoding with autograd on, this step

    def record_positions(module, inputs):
        if torch.is_grad_enabled():
            encoded.append(inputs[0].detach().clamp(0.0, 1.0).numpy().copy())

    hook = model.field.encoding.register_forward_pre_hook(record_positions)
    rates = machine_rates(rates)
    model.train()
    density_only, kept, rays, full_march_steps = 0, 0, 0, 0
    in_rounds = False
    timed_rounds, timed_density = model._march_until_opaque, model.field.density

    def counting_rounds(*a, **k):
        nonlocal in_rounds
        in_rounds = True
        try:
            return timed_rounds(*a, **k)
        finally:
            in_rounds = False

    def counting_density(x, *a, **k):
        nonlocal density_only
        if in_rounds:
            density_only += len(x)
        return timed_density(x, *a, **k)

    model._march_until_opaque, model.field.density = counting_rounds, counting_density
    step_seconds = []
    backward = optimiser = 0.0
    n_rays = trainer.n_rays
    last = trainer.last_samples
    for i in range(args.steps):
        encoded.clear()
        t0 = time.perf_counter()
        progress = (args.warmup_steps + i) / (args.warmup_steps + args.steps)
        full_march_steps += bool(model.train_full_march)
        model.before_step(args.warmup_steps + i, gen, progress)
        n_rays = model.rays_for_next_batch(last, n_rays)
        loss, out, _ = batch_loss(model, bank, n_rays, gen, progress)
        trainer.optimizer.zero_grad(set_to_none=True)
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        trainer.optimizer_step()
        t3 = time.perf_counter()
        backward += t2 - t1
        optimiser += t3 - t2
        last = out.num_samples
        kept += out.num_samples
        rays += n_rays
        step_seconds.append(t3 - t0)
    model._march_until_opaque, model.field.density = timed_rounds, timed_density
    hook.remove()
    total = sum(step_seconds)
    phases = dict(timer.seconds)
    phases["backward"] = backward
    phases["optimiser (Adam)"] = optimiser
    phases["other (Python, losses, glue)"] = max(0.0, total - sum(phases.values()))

    steps = args.steps
    params = sum(p.numel() for p in model.parameters())
    flops = mlp_flops_per_sample(model)
    rates = machine_rates(rates)
    bf16 = model.field.config.mlp_precision == "bf16"
    mlp_gflops = rates["mlp_shape_gflops_bf16" if bf16 else "mlp_shape_gflops"]
    gbps = rates["copy_gbps"]
    kept_per_step = kept / steps
    bound_mlp = 3 * flops * kept_per_step / (mlp_gflops * 1e9)
    adam_bytes = params * 4 * 7          # read p, g, m, v; write p, m, v
    bound_adam = adam_bytes / (gbps * 1e9)
    bound_hash = hash_memory_floor_ms(model.field.encoding, encoded, gbps) / 1e3
    bound = bound_mlp + bound_adam + bound_hash

    model.eval()
    timer.seconds.clear()
    t0 = time.perf_counter()
    metrics = evaluate(model, ds, "test", with_ssim=False)
    eval_s = time.perf_counter() - t0
    images = max(metrics["num_images"], 1)
    render_phases = {k: 1e3 * v / images for k, v in sorted(timer.seconds.items(),
                                                           key=lambda kv: -kv[1])}
    render_phases["other (evaluation, metrics, glue)"] = max(
        0.0, 1e3 * eval_s / images - sum(render_phases.values()))

    median_step = sorted(step_seconds)[steps // 2]
    by_cost = sorted(phases.items(), key=lambda kv: -kv[1])
    result = {
        "data": str(args.data), "warmup_steps": args.warmup_steps, "steps": steps,
        "samples_per_batch": args.samples, "ms_per_step_median": 1e3 * median_step,
        "ms_per_step_mean": 1e3 * total / steps,
        "phases_ms_per_step": {k: 1e3 * v / steps for k, v in by_cost},
        "rays_per_step": rays / steps, "density_only_samples_per_step": density_only / steps,
        "trained_samples_per_step": kept_per_step, "full_march_steps": full_march_steps,
        "params": params,
        "mlp_flops_per_sample_forward": flops,
        "machine": {**rates, "threads": torch.get_num_threads()},
        "bound_ms": {"mlp_fwd_bwd": 1e3 * bound_mlp, "adam_dense": 1e3 * bound_adam,
                     "hash_rows": 1e3 * bound_hash, "total": 1e3 * bound},
        "hash_points_last_step": int(sum(len(x) for x in encoded)),
        "step_over_bound": (total / steps) / bound,
        "step_over_mlp_and_adam_bound": (total / steps) / (bound_mlp + bound_adam),
        "mlp_precision": model.field.config.mlp_precision,
        # the bound with the MLPs' FLOPs at the float32 rate, whatever precision they ran in
        "step_over_bound_fp32_mlp": (total / steps) / (
            bound_adam + bound_hash + 3 * flops * kept_per_step / (rates["mlp_shape_gflops"] * 1e9)),
        "render_ms_per_image": metrics["render_ms_per_image"],
        "render_phases_ms_per_image": render_phases,
        "eval_seconds": eval_s, "psnr": metrics["psnr"],
    }
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
