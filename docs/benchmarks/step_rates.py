"""Training step times of several configurations of one method, interleaved in one process.

Time-budget sweeps on a shared machine mix two things: how much a configuration learns per
step, and how many steps the machine happened to give it (blocks of steps here ran at 280 ms
and at 560 ms minutes apart). A step-budget sweep (`nerfbot bench --budget-kind steps`) measures
the first without noise. This script measures the second: each configuration trains 40 steps
to settle (occupancy grid warm-up), then all of them take turns, BLOCK steps each, for ROUNDS
rounds (the order reversed every other round), and the median milliseconds per step of each
block is reported. Equal step times mean a step budget compares them at equal training time.

usage: python docs/benchmarks/step_rates.py DATA METHOD LABEL=OPTIONS_JSON [LABEL=OPTIONS_JSON ...]
example: python docs/benchmarks/step_rates.py bench/final/data_ns ngp 'sh4={}' 'sh0={"sh_degree": 0}'
"""
import json
import statistics
import sys
import tempfile
import time

from nerfbot.data import load_dataset
from nerfbot.train.trainer import TrainConfig, Trainer

SETTLE_STEPS, BLOCK, ROUNDS = 40, 12, 6

if len(sys.argv) < 4:
    sys.exit(__doc__)
ds = load_dataset(sys.argv[1])
method = sys.argv[2]
configs = [arg.split("=", 1) for arg in sys.argv[3:]]


def run(trainer: Trainer, steps: int) -> list[float]:
    """Continue training for ``steps`` steps; the wall-clock time after each step."""
    stamps: list[float] = []
    trainer.config.max_steps = trainer.step + steps
    trainer.train(lambda t: stamps.append(time.perf_counter()))
    return stamps


with tempfile.TemporaryDirectory() as tmp:
    trainers = {}
    for label, options in configs:
        cfg = TrainConfig(method=method, max_steps=SETTLE_STEPS, options=json.loads(options),
                          progress=False, checkpoint_every_seconds=float("inf"))
        trainers[label] = Trainer(ds, f"{tmp}/{label}", cfg)
        run(trainers[label], SETTLE_STEPS)
    block_ms: dict[str, list[float]] = {label: [] for label in trainers}
    for r in range(ROUNDS):
        for label in (list(trainers) if r % 2 == 0 else list(trainers)[::-1]):
            stamps = run(trainers[label], BLOCK + 1)
            block_ms[label].append((stamps[-1] - stamps[0]) / BLOCK * 1000)
first = statistics.median(block_ms[configs[0][0]])
for label, ms in block_ms.items():
    med = statistics.median(ms)
    print(f"{label:>12}: {med:6.1f} ms/step (x{med / first:.2f} of {configs[0][0]}), blocks "
          + ", ".join(f"{m:.0f}" for m in ms))
