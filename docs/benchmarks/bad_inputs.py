"""Malformed and unusual inputs against the `nerfbot` command: the catalogue behind the
"Bad input" table of BENCHMARKS.md.

Each case builds a sandbox folder (copies of a tiny capture, a second capture, a tiny
articulated capture and a tiny trained run), changes one thing, runs one `nerfbot` command in a
fresh process with the sandbox as working directory, and checks:

- the outcome: a **clear error** (exit code 2, one stderr line `nerfbot CMD: error: ...` naming
  the file, field or flag, no traceback) or a **correct result** (exit code 0 and the case's
  own check, e.g. the same PSNR as the untouched dataset, a warning that names the problem);
- that no file outside the command's output folder was created, changed or deleted (every file
  of the sandbox is hashed before and after);
- for the malicious checkpoints, that their payload did not run (a marker file is absent).

usage: python docs/benchmarks/bad_inputs.py OUT [--only ID ...] [--list]

Writes OUT/bad_inputs.md (the table) and OUT/bad_inputs.json (with --only, those cases are
updated in them); exits 1 if any case fails.
Takes about 15 minutes on two cores (one process at a time).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

HASH = "log2_hashmap_size=14"  # a small table keeps the base run's checkpoint at a few MB
TRAIN1 = ["train", "--data", "data", "--max-steps", "1", "--out", "out", "--no-progress",
          "--option", HASH]
EVAL = ["eval", "run", "--json"]
RESUME = ["train", "--data", "data", "--max-steps", "25", "--out", "run", "--resume",
          "--no-progress", "--option", HASH]
MARKER = "PAYLOAD_RAN"


# -- the base fixtures -----------------------------------------------------------------------
def nerfbot(args: list, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, "-m", "nerfbot.app.cli", *map(str, args)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=timeout)


def build_base(base: Path) -> None:
    """The shared fixtures, made once: data (tabletop, 8 + 2 views at 32 px), data2 (the same
    scene from other cameras), art (articulated, 3 + 2 configurations x 2 views) and run (ngp,
    20 steps on data, trained with the relative path `data`)."""
    stamp = base / "complete"
    if stamp.exists():
        return
    shutil.rmtree(base, ignore_errors=True)
    base.mkdir(parents=True)
    steps = [
        ["capture", "--scene", "tabletop", "--views", "8", "--test-views", "2", "--size", "32",
         "--out", "data", "--no-progress"],
        ["capture", "--scene", "tabletop", "--views", "8", "--test-views", "2", "--size", "32",
         "--seed", "1", "--out", "data2", "--no-progress"],
        ["capture", "--scene", "articulated", "--configs", "3", "--test-configs", "2",
         "--views-per-frame", "2", "--size", "32", "--out", "art", "--no-progress"],
        ["train", "--data", "data", "--max-steps", "20", "--out", "run", "--no-progress",
         "--option", HASH],
    ]
    for args in steps:
        proc = nerfbot(args, base)
        if proc.returncode != 0:
            raise SystemExit(f"base fixture failed: nerfbot {' '.join(args)}\n{proc.stderr}")
    stamp.write_text("ok\n")


# -- sandbox helpers -------------------------------------------------------------------------
def doc(sb: Path, rel: str = "data/transforms.json") -> dict:
    return json.loads((sb / rel).read_text())


def put(sb: Path, value, rel: str = "data/transforms.json") -> None:
    (sb / rel).write_text(json.dumps(value))


def edit(sb: Path, change: Callable[[dict], object], rel: str = "data/transforms.json") -> None:
    """Change the JSON document ``rel`` in place (what ``change`` returns is ignored)."""
    d = doc(sb, rel)
    change(d)
    put(sb, d, rel)


def rewrite(sb: Path, make: Callable[[dict], dict], rel: str = "data/transforms.json") -> None:
    """Replace the JSON document ``rel`` by what ``make`` returns from it."""
    put(sb, make(doc(sb, rel)), rel)


def frame0(d: dict) -> dict:
    return d["frames"][0]


def write_png(path: Path, array: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), array):
        raise RuntimeError(f"could not write {path}")


def read_png(path: Path) -> np.ndarray:
    import cv2

    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def malicious_checkpoint(sb: Path, rel: str = "run/checkpoint.pt") -> None:
    """A pickle whose loading would create MARKER in the sandbox (what an attacker's
    checkpoint does with a real payload)."""
    import pickle

    class Payload:
        def __reduce__(self):
            return (open, (str(sb / MARKER), "w"))

    (sb / rel).write_bytes(pickle.dumps({"spec": Payload()}))


def torch_save(sb: Path, rel: str, value) -> None:
    import torch

    torch.save(value, sb / rel)


def eval_json(proc) -> dict:
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- cases -----------------------------------------------------------------------------------
@dataclass
class Case:
    id: str
    group: str
    what: str
    setup: Callable[[Path], list]
    """Changes the sandbox; returns the command's arguments."""
    expect: str = "error"
    """'error' or 'ok'."""
    needs: tuple = ("data",)
    mentions: tuple = ()
    """Substrings the error line must contain (case-insensitive)."""
    check: Optional[Callable[[Path, subprocess.CompletedProcess], Optional[str]]] = None
    """For 'ok' (and optionally 'error') cases: None if right, else what is wrong."""
    outputs: tuple = ("out",)
    """Paths (relative to the sandbox) the command may create or change."""
    baseline: Optional[list] = None
    """A command run before the case, in the same sandbox, whose stdout the check may use."""


CASES: list[Case] = []


def case(id, group, what, expect="error", needs=("data",), mentions=(), check=None,
         outputs=("out",), baseline=None):
    def register(setup):
        CASES.append(Case(id, group, what, setup, expect, tuple(needs), tuple(mentions), check,
                          tuple(outputs), baseline))
        return setup
    return register


def same_psnr(sb, proc, baseline_stdout) -> Optional[str]:
    a, b = eval_json(proc)["psnr"], json.loads(baseline_stdout.strip().splitlines()[-1])["psnr"]
    return None if abs(a - b) < 1e-6 else f"PSNR {a:.4f} dB, expected {b:.4f} dB"


def result_note(c: Case, proc, baseline_stdout) -> str:
    """What a correct result shows: its warning, or the PSNR it shares with the baseline."""
    warnings = [line for line in proc.stderr.splitlines() if line.startswith("WARNING")]
    if warnings:
        return warnings[0]
    if baseline_stdout is not None:
        return f"PSNR {eval_json(proc)['psnr']:.4f} dB, as `nerfbot {' '.join(c.baseline)}`"
    return ""


def warns(*words):
    def check(sb, proc):
        text = proc.stderr.lower()
        missing = [w for w in words if w.lower() not in text]
        return None if not missing else f"no warning mentioning {missing}"
    return check


def marker_absent(sb, proc):
    return f"the payload ran ({MARKER} exists)" if (sb / MARKER).exists() else None


# Run folders and checkpoints ----------------------------------------------------------------
R = "run folder"


@case("R01", R, "checkpoint.pt is a pickle with a payload: eval", needs=("data", "run"),
      mentions=("checkpoint",), check=marker_absent)
def _(sb):
    malicious_checkpoint(sb)
    return EVAL


@case("R02", R, "checkpoint.pt is a pickle with a payload: train --resume",
      needs=("data", "run"), mentions=("checkpoint",), check=marker_absent, outputs=())
def _(sb):
    malicious_checkpoint(sb)
    return RESUME


@case("R03", R, "checkpoint.pt is a pickle with a payload: render", needs=("data", "run"),
      mentions=("checkpoint",), check=marker_absent)
def _(sb):
    malicious_checkpoint(sb)
    return ["render", "run", "--path", "test", "--out", "out", "--no-progress"]


@case("R04", R, "checkpoint.pt truncated to half its bytes", needs=("data", "run"),
      mentions=("checkpoint",))
def _(sb):
    p = sb / "run/checkpoint.pt"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return EVAL


@case("R05", R, "checkpoint.pt empty (0 bytes)", needs=("data", "run"), mentions=("checkpoint",))
def _(sb):
    (sb / "run/checkpoint.pt").write_bytes(b"")
    return EVAL


@case("R06", R, "checkpoint.pt of random bytes", needs=("data", "run"),
      mentions=("checkpoint",))
def _(sb):
    (sb / "run/checkpoint.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    return EVAL


@case("R07", R, "checkpoint.pt is another program's torch file (a dict of tensors)",
      needs=("data", "run"), mentions=("checkpoint",))
def _(sb):
    import torch

    torch_save(sb, "run/checkpoint.pt", {"state_dict": {"w": torch.zeros(3)}, "epoch": 3})
    return EVAL


@case("R08", R, "checkpoint.pt is a bare tensor", needs=("data", "run"),
      mentions=("checkpoint",))
def _(sb):
    import torch

    torch_save(sb, "run/checkpoint.pt", torch.zeros(4))
    return EVAL


@case("R09", R, "checkpoint.pt is a folder", needs=("data", "run"), mentions=("checkpoint",))
def _(sb):
    (sb / "run/checkpoint.pt").unlink()
    (sb / "run/checkpoint.pt").mkdir()
    return EVAL


@case("R10", R, "checkpoint truncated, the previous one (checkpoint.prev.pt) good: eval uses it",
      expect="ok", needs=("data", "run"), check=warns("checkpoint.prev.pt"))
def _(sb):
    p = sb / "run/checkpoint.pt"
    shutil.copy(p, sb / "run/checkpoint.prev.pt")
    p.write_bytes(p.read_bytes()[:1000])
    return EVAL


@case("R11", R, "config.json without `data`", needs=("data", "run"),
      mentions=("config.json", "data"))
def _(sb):
    rewrite(sb, lambda d: {k: v for k, v in d.items() if k not in ("data", "data_relative")},
         "run/config.json")
    return EVAL


@case("R12", R, "config.json is not JSON", needs=("data", "run"), mentions=("config.json",))
def _(sb):
    (sb / "run/config.json").write_text("{data: nope")
    return EVAL


@case("R13", R, "config.json missing (the run names no dataset)", needs=("data", "run"),
      mentions=("--data",))
def _(sb):
    (sb / "run/config.json").unlink()
    return EVAL


@case("R14", R, "the run folder does not exist", needs=(), mentions=("nope",))
def _(sb):
    return ["eval", "nope"]


@case("R15", R, "the run path is a file", needs=(), mentions=("notes.txt",))
def _(sb):
    (sb / "notes.txt").write_text("mine\n")
    return ["eval", "notes.txt"]


@case("R16", R, "eval from another directory holding another `data` folder: the run's own "
      "dataset is scored (the path is relative)", expect="ok", needs=("data", "data2", "run"),
      baseline=EVAL)
def _(sb):
    (sb / "elsewhere").mkdir()
    shutil.copytree(sb / "data2", sb / "elsewhere/data")
    return ["eval", "../run", "--json"]


@case("R17", R, "the dataset was moved away", needs=("data", "run"), mentions=("--data",))
def _(sb):
    (sb / "data").rename(sb / "moved")
    return EVAL


@case("R18", R, "another dataset now lies at the run's dataset path",
      needs=("data", "data2", "run"),
      mentions=("--data",))
def _(sb):
    shutil.rmtree(sb / "data")
    (sb / "data2").rename(sb / "data")
    return EVAL


@case("R19", R, "run and dataset moved together (relative layout kept)", expect="ok",
      needs=("data", "run"), baseline=EVAL)
def _(sb):
    (sb / "moved").mkdir()
    (sb / "data").rename(sb / "moved/data")
    (sb / "run").rename(sb / "moved/run")
    return ["eval", "moved/run", "--json"]


@case("R20", R, "train --resume --option log2_hashmap_size=13 (the run has 14)",
      needs=("data", "run"), mentions=("log2_hashmap_size",), outputs=())
def _(sb):
    return [a if a != HASH else "log2_hashmap_size=13" for a in RESUME]


@case("R21", R, "train --resume on another dataset", needs=("data", "data2", "run"),
      mentions=("dataset",), outputs=())
def _(sb):
    return [a if a != "data" else "data2" for a in RESUME]


@case("R22", R, "train --resume with other --aabb bounds", needs=("data", "run"),
      mentions=("aabb",), outputs=())
def _(sb):
    return RESUME + ["--aabb", "-1", "-1", "0", "1", "1", "1"]


@case("R23", R, "train --resume --method nerf (the run is ngp)", needs=("data", "run"),
      mentions=("method",), outputs=())
def _(sb):
    return RESUME + ["--method", "nerf"]


@case("R24", R, "train --resume --seed 5 (the run has seed 0)", needs=("data", "run"),
      mentions=("seed",), outputs=())
def _(sb):
    return RESUME + ["--seed", "5"]


@case("R25", R, "train --resume --background white (the run learned its background)",
      needs=("data", "run"), mentions=("background",), outputs=())
def _(sb):
    return RESUME + ["--background", "white"]


def _resumed_to(steps):
    def check(sb, proc):
        metrics = json.loads((sb / "run/metrics.json").read_text())
        return None if metrics["steps"] == steps else f"{metrics['steps']} steps, not {steps}"
    return check


@case("R26", R, "train --resume with a larger step budget continues the run", expect="ok",
      needs=("data", "run"), outputs=("run",), check=_resumed_to(25))
def _(sb):
    return RESUME


def _no_stale(sb, proc):
    left = [p.name for p in (sb / "run").iterdir() if ".tmp" in p.name]
    return f"stale temporaries remain: {left}" if left else _resumed_to(25)(sb, proc)


@case("R27", R, "a stale checkpoint temporary from a killed process is removed on resume",
      expect="ok", needs=("data", "run"), outputs=("run",), check=_no_stale)
def _(sb):
    (sb / "run/.checkpoint.pt.tmp-99999").write_bytes(b"partial")
    return RESUME


@case("R28", R, "resume with a truncated checkpoint and a good previous one", expect="ok",
      needs=("data", "run"), outputs=("run",), check=_resumed_to(25))
def _(sb):
    p = sb / "run/checkpoint.pt"
    shutil.copy(p, sb / "run/checkpoint.prev.pt")
    p.write_bytes(p.read_bytes()[:1000])
    return RESUME


@case("R29", R, "eval --split nope", needs=("data", "run"), mentions=("nope",))
def _(sb):
    return EVAL + ["--split", "nope"]


@case("R30", R, "eval --split val (the capture writes val = test)", expect="ok",
      needs=("data", "run"))
def _(sb):
    return EVAL + ["--split", "val"]


@case("R31", R, "eval --data of a one-frame dataset (no test frame)", needs=("data", "run"),
      mentions=("test",), outputs=("out", "one"))
def _(sb):
    shutil.copytree(sb / "data", sb / "one")
    rewrite(sb, lambda d: {k: v for k, v in d.items() if not k.endswith("_filenames")} | {
        "frames": d["frames"][:1]}, "one/transforms.json")
    return EVAL + ["--data", "one"]


@case("R32", R, "eval --data of a dataset whose test split is empty", needs=("data", "run"),
      mentions=("test",))
def _(sb):
    shutil.copytree(sb / "data", sb / "notest")
    rewrite(sb, lambda d: {**d, "test_filenames": [], "val_filenames": []},
         "notest/transforms.json")
    return EVAL + ["--data", "notest"]


@case("R33", R, "render --frames 0", needs=("data", "run"), mentions=("--frames",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--frames", "0"]


@case("R34", R, "render --size 0", needs=("data", "run"), mentions=("--size",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--size", "0"]


@case("R35", R, "render --size 100000000 (an absurd size)", needs=("data", "run"),
      mentions=("--size",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--size", "100000000"]


@case("R36", R, "render --size 32 99999 (an absurd height)", needs=("data", "run"),
      mentions=("--size",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--size", "32", "99999"]


@case("R37", R, "render --size with three numbers", needs=("data", "run"), mentions=("--size",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--size", "32", "32", "32"]


@case("R38", R, "render --fps 0", needs=("data", "run"), mentions=("--fps",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--fps", "0"]


@case("R39", R, "render --out out.mov (an extension it cannot write)", needs=("data", "run"),
      mentions=("mov",), outputs=("out.mov",))
def _(sb):
    return ["render", "run", "--out", "out.mov", "--frames", "2", "--no-progress"]


@case("R40", R, "render --time 2 (outside [0, 1])", needs=("data", "run"), mentions=("time",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--time", "2"]


@case("R41", R, "render --sweep time of a static run", needs=("data", "run"),
      mentions=("static",))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--sweep", "time"]


@case("R42", R, "render --joints door=1 of a static run", needs=("data", "run"),
      mentions=("--joints", "static"))
def _(sb):
    return ["render", "run", "--out", "out.mp4", "--joints", "door=1"]


@case("R43", R, "render --depth-mode threshold without --threshold", needs=("data", "run"),
      mentions=("--threshold",))
def _(sb):
    return ["render", "run", "--path", "test", "--out", "out", "--depth-mode", "threshold"]


@case("R44", R, "render --threshold -1", needs=("data", "run"), mentions=("threshold",))
def _(sb):
    return ["render", "run", "--path", "test", "--out", "out", "--depth-mode", "threshold",
            "--threshold", "-1"]


@case("R45", R, "render --path test --data of a missing folder", needs=("data", "run"),
      mentions=("missing",))
def _(sb):
    return ["render", "run", "--path", "test", "--out", "out", "--data", "missing"]


@case("R46", R, "eval --downscale 0", needs=("data", "run"), mentions=("--downscale",))
def _(sb):
    return EVAL + ["--downscale", "0"]


@case("R47", R, "eval --supersample 0", needs=("data", "run"), mentions=("--supersample",))
def _(sb):
    return EVAL + ["--supersample", "0"]


@case("R48", R, "eval --depth-sweep --thresholds a,b", needs=("data", "run"),
      mentions=("--thresholds",))
def _(sb):
    return EVAL + ["--depth-sweep", "--thresholds", "a,b"]


@case("R49", R, "bake RUN --out RUN (would overwrite the trained checkpoint)",
      needs=("data", "run"), mentions=("run",), outputs=())
def _(sb):
    return ["bake", "run", "--out", "run", "--octree", "4", "--no-progress"]


@case("R50", R, "bake with both --cache and --octree", needs=("data", "run"),
      mentions=("--cache", "--octree"))
def _(sb):
    return ["bake", "run", "--out", "out", "--cache", "8,8", "--octree", "4"]


@case("R51", R, "bake --cache of an ngp run (only fastnerf runs have a cache)",
      needs=("data", "run"), mentions=("fastnerf",))
def _(sb):
    return ["bake", "run", "--out", "out", "--cache", "8,8", "--no-progress"]


@case("R52", R, "bake --octree 0", needs=("data", "run"), mentions=("octree",))
def _(sb):
    return ["bake", "run", "--out", "out", "--octree", "0", "--no-progress"]


@case("R53", R, "bake --cache 0,0", needs=("data", "run"), mentions=("--cache",))
def _(sb):
    return ["bake", "run", "--out", "out", "--cache", "0,0", "--no-progress"]


@case("R54", R, "estimate-joints of a static run", needs=("data", "run"), mentions=("joint",))
def _(sb):
    return ["estimate-joints", "run", "--no-progress"]


@case("R55", R, "estimate-joints --every 0", needs=("data", "run"), mentions=("--every",))
def _(sb):
    return ["estimate-joints", "run", "--every", "0"]


@case("R56", R, "view a folder that is not a run", needs=("data",), mentions=("data",
                                                                        "checkpoint"))
def _(sb):
    return ["view", "data", "--port", "0"]


@case("R57", R, "view --camera test:99 (the dataset has 2 test views)", needs=("data", "run"),
      mentions=("--camera",))
def _(sb):
    return ["view", "run", "--port", "0", "--camera", "test:99"]


@case("R58", R, "view --port 70000", needs=("data", "run"), mentions=("--port",))
def _(sb):
    return ["view", "run", "--port", "70000"]


@case("R59", R, "view --geometry of a file that is not a mesh", needs=("data", "run"),
      mentions=("notes.ply",))
def _(sb):
    (sb / "notes.ply").write_text("not a mesh\n")
    return ["view", "run", "--port", "0", "--geometry", "notes.ply"]


# Output folders -------------------------------------------------------------------------------
O = "output folder"
CAPTURE = ["capture", "--scene", "tabletop", "--views", "4", "--test-views", "1", "--size", "16",
           "--no-progress", "--out"]


@case("O01", O, "capture --out a user's dataset folder (transforms.json and notes.txt)",
      needs=("data",), mentions=("data",), outputs=())
def _(sb):
    (sb / "data/notes.txt").write_text("my calibration notes\n")
    return CAPTURE + ["data"]


@case("O02", O, "capture --out a folder holding only notes.txt", needs=(), mentions=("mine",),
      outputs=())
def _(sb):
    (sb / "mine").mkdir()
    (sb / "mine/notes.txt").write_text("notes\n")
    return CAPTURE + ["mine"]


@case("O03", O, "capture --out an existing file", needs=(), mentions=("notes.txt",), outputs=())
def _(sb):
    (sb / "notes.txt").write_text("notes\n")
    return CAPTURE + ["notes.txt"]


@case("O04", O, "capture --out a previous capture, without --overwrite", needs=("data",),
      mentions=("--overwrite",), outputs=())
def _(sb):
    return CAPTURE + ["data"]


def _recaptured(sb, proc):
    n = len(doc(sb)["frames"])
    return None if n == 5 else f"{n} frames in the replaced dataset, expected 5"


@case("O05", O, "capture --out a previous capture with --overwrite replaces it", expect="ok",
      needs=("data",), outputs=("data",), check=_recaptured)
def _(sb):
    return CAPTURE + ["data", "--overwrite"]


@case("O06", O, "train --out a folder with someone's config.json and metrics.json",
      needs=("data",), mentions=("theirs",), outputs=())
def _(sb):
    (sb / "theirs").mkdir()
    (sb / "theirs/config.json").write_text('{"lr": 0.1}\n')
    (sb / "theirs/metrics.json").write_text('{"psnr": 31.2}\n')
    return [a if a != "out" else "theirs" for a in TRAIN1]


@case("O07", O, "train --out an existing file", needs=("data",), mentions=("notes.txt",),
      outputs=())
def _(sb):
    (sb / "notes.txt").write_text("notes\n")
    return [a if a != "out" else "notes.txt" for a in TRAIN1]


def _no_out(sb, proc):
    return "a run folder was left behind" if (sb / "out").exists() else None


@case("O08", O, "train with an unknown --option: no run folder is left behind",
      needs=("data",), mentions=("nope",), check=_no_out)
def _(sb):
    return TRAIN1 + ["--option", "nope=1"]


@case("O09", O, "train on a missing dataset: no run folder is left behind", needs=(),
      mentions=("data",), check=_no_out)
def _(sb):
    return TRAIN1


@case("O10", O, "train --out an existing run without --resume", needs=("data", "run"),
      mentions=("--resume",), outputs=())
def _(sb):
    return [a if a != "out" else "run" for a in TRAIN1]


def _fresh_run(sb, proc):
    metrics = json.loads((sb / "run/metrics.json").read_text())
    return None if metrics["steps"] == 1 else f"{metrics['steps']} steps, expected a new 1-step run"


@case("O11", O, "train --out an existing run with --overwrite starts over", expect="ok",
      needs=("data", "run"), outputs=("run",), check=_fresh_run)
def _(sb):
    return [a if a != "out" else "run" for a in TRAIN1] + ["--overwrite"]


@case("O12", O, "bench --out a folder with a user's files", needs=("data",), mentions=("mine",),
      outputs=())
def _(sb):
    (sb / "mine").mkdir()
    (sb / "mine/results.csv").write_text("a,b\n1,2\n")
    return ["bench", "--data", "data", "--budgets", "1", "--budget-kind", "steps", "--out",
            "mine", "--no-progress", "--no-chamfer"]


@case("O13", O, "demo --out a folder with a user's files", needs=(), mentions=("mine",),
      outputs=())
def _(sb):
    (sb / "mine").mkdir()
    (sb / "mine/notes.txt").write_text("notes\n")
    return ["demo", "--out", "mine", "--seconds", "1", "--size", "16", "--views", "4",
            "--test-views", "1", "--no-progress"]


@case("O14", O, "render --out a folder with a user's files", needs=("data", "run"),
      mentions=("mine",), outputs=())
def _(sb):
    (sb / "mine").mkdir()
    (sb / "mine/rgb_0000.png").write_bytes(b"not ours")
    return ["render", "run", "--path", "test", "--out", "mine", "--no-progress"]


@case("O15", O, "render --out an existing video file", needs=("data", "run"),
      mentions=("mine.mp4",), outputs=())
def _(sb):
    (sb / "mine.mp4").write_bytes(b"someone's video")
    return ["render", "run", "--frames", "2", "--out", "mine.mp4", "--no-progress"]


@case("O16", O, "bake --out a folder with a user's files", needs=("data", "run"),
      mentions=("mine",), outputs=())
def _(sb):
    (sb / "mine").mkdir()
    (sb / "mine/notes.txt").write_text("notes\n")
    return ["bake", "run", "--out", "mine", "--octree", "4", "--no-progress"]


# Dataset files --------------------------------------------------------------------------------
D = "dataset"


@case("D01", D, "--data names a missing folder", needs=(), mentions=("data",))
def _(sb):
    return TRAIN1


@case("D02", D, "a folder without transforms*.json", needs=(), mentions=("transforms",))
def _(sb):
    (sb / "data").mkdir()
    (sb / "data/readme.txt").write_text("hi\n")
    return TRAIN1


@case("D03", D, "transforms.json is not JSON", mentions=("transforms.json", "line"))
def _(sb):
    (sb / "data/transforms.json").write_text('{"frames": [')
    return TRAIN1


@case("D04", D, "transforms.json is a JSON list", mentions=("transforms.json",))
def _(sb):
    (sb / "data/transforms.json").write_text("[1, 2]")
    return TRAIN1


@case("D05", D, "transforms.json is not UTF-8", mentions=("transforms.json",))
def _(sb):
    (sb / "data/transforms.json").write_bytes(b'{"frames": "\xff\xfe"}')
    return TRAIN1


@case("D06", D, "transforms.json nested 100000 levels deep", mentions=("transforms.json",))
def _(sb):
    (sb / "data/transforms.json").write_text("[" * 100000 + "]" * 100000)
    return TRAIN1


@case("D07", D, "`frames` missing", mentions=("frames",))
def _(sb):
    rewrite(sb, lambda d: {k: v for k, v in d.items() if k != "frames"})
    return TRAIN1


@case("D08", D, "`frames` empty", mentions=("frames",))
def _(sb):
    rewrite(sb, lambda d: {**d, "frames": []})
    return TRAIN1


@case("D09", D, "`frames` is an object", mentions=("frames",))
def _(sb):
    rewrite(sb, lambda d: {**d, "frames": {"a": 1}})
    return TRAIN1


@case("D10", D, "a frame is a number", mentions=("frames[3]",))
def _(sb):
    edit(sb, lambda d: d["frames"].__setitem__(3, 7))
    return TRAIN1


@case("D11", D, "a frame without file_path", mentions=("frames[0].file_path",))
def _(sb):
    edit(sb, lambda d: frame0(d).pop("file_path"))
    return TRAIN1


@case("D12", D, "an image file missing", mentions=("frame_00002",))
def _(sb):
    (sb / "data/images/frame_00002.png").unlink()
    return TRAIN1


@case("D13", D, "an image file of 0 bytes", mentions=("frame_00002",))
def _(sb):
    (sb / "data/images/frame_00002.png").write_bytes(b"")
    return TRAIN1


@case("D14", D, "a truncated PNG", mentions=("frame_00002",))
def _(sb):
    p = sb / "data/images/frame_00002.png"
    p.write_bytes(p.read_bytes()[:60])
    return TRAIN1


@case("D15", D, "a text file named .png", mentions=("frame_00002",))
def _(sb):
    (sb / "data/images/frame_00002.png").write_text("hello\n")
    return TRAIN1


@case("D16", D, "an image whose size differs from w / h", mentions=("frame_00002", "w"))
def _(sb):
    write_png(sb / "data/images/frame_00002.png", np.zeros((32, 40, 3), np.uint8))
    return TRAIN1


@case("D17", D, "a file_path naming a folder", mentions=("frames[0].file_path",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__("file_path", "images"))
    return TRAIN1


@case("D18", D, "16-bit PNG images", expect="ok")
def _(sb):
    for p in sorted((sb / "data/images").glob("*.png")):
        write_png(p, read_png(p).astype(np.uint16) * 257)
    return TRAIN1


@case("D19", D, "greyscale PNG images", expect="ok")
def _(sb):
    import cv2

    for p in sorted((sb / "data/images").glob("*.png")):
        write_png(p, cv2.cvtColor(read_png(p), cv2.COLOR_BGR2GRAY))
    return TRAIN1


@case("D20", D, "RGBA PNG images with a transparent background", expect="ok")
def _(sb):
    for p in sorted((sb / "data/images").glob("*.png")):
        img = read_png(p)
        alpha = np.full(img.shape[:2], 255, np.uint8)
        alpha[:8] = 0
        write_png(p, np.dstack([img, alpha]))
    return TRAIN1


def write_grey_alpha_png(path: Path, grey: np.ndarray, alpha: np.ndarray) -> None:
    """A PNG of colour type 4 (grey + alpha), which OpenCV cannot write."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    h, w = grey.shape
    rows = np.dstack([grey, alpha]).reshape(h, 2 * w)
    raw = b"".join(b"\x00" + r.tobytes() for r in rows)
    header = struct.pack(">IIBBBBB", w, h, 8, 4, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


@case("D21", D, "a grey + alpha PNG (two channels)", expect="ok")
def _(sb):
    import cv2

    for p in sorted((sb / "data/images").glob("*.png")):
        grey = cv2.cvtColor(read_png(p), cv2.COLOR_BGR2GRAY)
        write_grey_alpha_png(p, grey, np.full_like(grey, 255))
    return TRAIN1


@case("D22", D, "transform_matrix missing", mentions=("frames[0].transform_matrix",))
def _(sb):
    edit(sb, lambda d: frame0(d).pop("transform_matrix"))
    return TRAIN1


@case("D23", D, "transform_matrix with a NaN", mentions=("frames[0].transform_matrix",))
def _(sb):
    edit(sb, lambda d: frame0(d)["transform_matrix"][0].__setitem__(3, float("nan")))
    return TRAIN1


@case("D24", D, "transform_matrix 3 x 3", mentions=("frames[0].transform_matrix",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__(
        "transform_matrix", [r[:3] for r in frame0(d)["transform_matrix"][:3]]))
    return TRAIN1


@case("D25", D, "transform_matrix scaled by 2 (not a rotation)",
      mentions=("frames[0].transform_matrix",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__(
        "transform_matrix", [[2 * v for v in r[:3]] + [r[3]] for r in
                             frame0(d)["transform_matrix"][:3]] + [[0, 0, 0, 1]]))
    return TRAIN1


@case("D26", D, "a camera at 1e300 m", mentions=("frames[0].transform_matrix",))
def _(sb):
    edit(sb, lambda d: frame0(d)["transform_matrix"][0].__setitem__(3, 1e300))
    return TRAIN1


@case("D27", D, "a camera 1e7 m from the scene", mentions=("frames[0]",))
def _(sb):
    edit(sb, lambda d: frame0(d)["transform_matrix"][0].__setitem__(3, 1e7))
    return TRAIN1


@case("D28", D, "transform_matrix of strings", mentions=("frames[0].transform_matrix",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__("transform_matrix", [["a"] * 4] * 4))
    return TRAIN1


@case("D29", D, "negative fl_x", mentions=("fl_x",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("fl_x", -50.0))
    return TRAIN1


@case("D30", D, "no focal length at all", mentions=("fl_x",))
def _(sb):
    edit(sb, lambda d: [d.pop(k) for k in ("fl_x", "fl_y")])
    return TRAIN1


@case("D31", D, "w is a string", mentions=("w",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("w", "32"))
    return TRAIN1


@case("D32", D, "w = 0", mentions=("w",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("w", 0))
    return TRAIN1


@case("D33", D, "w = 10^9 for a 32-pixel image", mentions=("w",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("w", 10 ** 9))
    return TRAIN1


@case("D34", D, "an unknown camera_model", mentions=("camera_model",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("camera_model", "KANNALA"))
    return TRAIN1


@case("D35", D, "fl_x = 1e300", mentions=("fl_x",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("fl_x", 1e300))
    return TRAIN1


@case("D36", D, "an absolute file_path", mentions=("frames[0].file_path",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__("file_path", "/etc/passwd"))
    return TRAIN1


@case("D37", D, "a file_path escaping the folder with ..", mentions=("frames[0].file_path",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__("file_path", "../outside.png"))
    write_png(sb / "outside.png", np.zeros((32, 32, 3), np.uint8))
    return TRAIN1


@case("D38", D, "an image that is a symlink out of the dataset folder",
      mentions=("frame_00002",))
def _(sb):
    write_png(sb / "outside.png", np.zeros((32, 32, 3), np.uint8))
    p = sb / "data/images/frame_00002.png"
    p.unlink()
    p.symlink_to(sb / "outside.png")
    return TRAIN1


@case("D39", D, "the images folder is a symlink out of the dataset folder",
      mentions=("images",))
def _(sb):
    (sb / "data/images").rename(sb / "elsewhere")
    (sb / "data/images").symlink_to(sb / "elsewhere", target_is_directory=True)
    return TRAIN1


@case("D40", D, "an image symlinked inside the dataset folder", expect="ok")
def _(sb):
    p = sb / "data/images/frame_00002.png"
    p.rename(sb / "data/images/real.png")
    p.symlink_to("real.png")
    return TRAIN1


@case("D41", D, "a frame listed twice (duplicate file_path)", expect="ok",
      check=warns("frame_00001"))
def _(sb):
    edit(sb, lambda d: d["frames"].append(dict(d["frames"][1])))
    return TRAIN1


@case("D42", D, "train_filenames = test_filenames (overlapping splits)", expect="ok",
      check=warns("test"))
def _(sb):
    edit(sb, lambda d: d.__setitem__("test_filenames", list(d["train_filenames"])))
    return TRAIN1


@case("D43", D, "train_filenames names a file that is not a frame", mentions=("train_filenames",))
def _(sb):
    edit(sb, lambda d: d["train_filenames"].append("images/nope.png"))
    return TRAIN1


@case("D44", D, "only a test split: train", mentions=("train",))
def _(sb):
    rewrite(sb, lambda d: {**d, "train_filenames": [], "test_filenames": [
        f["file_path"] for f in d["frames"]]})
    return TRAIN1


@case("D45", D, "only a test split: eval", expect="ok", needs=("data", "run"))
def _(sb):
    rewrite(sb, lambda d: {**d, "train_filenames": [], "test_filenames": [
        f["file_path"] for f in d["frames"]]})
    return ["eval", "run", "--data", "data", "--json"]


@case("D46", D, "a one-frame dataset: train (no test frame to score)", expect="ok",
      check=warns("test"))
def _(sb):
    rewrite(sb, lambda d: {k: v for k, v in d.items() if not k.endswith("_filenames")} | {
        "frames": d["frames"][:1]})
    return TRAIN1


@case("D47", D, "a depth file missing", mentions=("depth_file_path",))
def _(sb):
    (sb / "data/depth/frame_00003.npy").unlink()
    return TRAIN1


@case("D48", D, "a depth map of the wrong shape", mentions=("depth",))
def _(sb):
    np.save(sb / "data/depth/frame_00003.npy", np.ones((16, 16), np.float32))
    return TRAIN1


@case("D49", D, "negative depth", mentions=("depth",))
def _(sb):
    np.save(sb / "data/depth/frame_00003.npy", -np.ones((32, 32), np.float32))
    return TRAIN1


@case("D50", D, "an integer .npy depth map", mentions=("depth",))
def _(sb):
    np.save(sb / "data/depth/frame_00003.npy", np.ones((32, 32), np.int32))
    return TRAIN1


@case("D51", D, "a .npy depth map holding a pickled object", mentions=("depth",))
def _(sb):
    np.save(sb / "data/depth/frame_00003.npy", np.array([{"a": 1}], dtype=object),
            allow_pickle=True)
    return TRAIN1


@case("D52", D, "a mask of the wrong shape", mentions=("mask",))
def _(sb):
    write_png(sb / "data/masks/m.png", np.full((8, 8), 255, np.uint8))
    edit(sb, lambda d: frame0(d).__setitem__("mask_path", "masks/m.png"))
    return TRAIN1


def _mask_baseline(sb):
    """Mask the left half of every frame of data, copy it to clean, then paint the masked
    half of data's images magenta."""
    mask = np.zeros((32, 32), np.uint8)
    mask[:, 16:] = 255
    write_png(sb / "data/masks/half.png", mask)
    edit(sb, lambda d: [f.__setitem__("mask_path", "masks/half.png") for f in d["frames"]])
    shutil.copytree(sb / "data", sb / "clean")
    for p in sorted((sb / "data/images").glob("*.png")):
        img = read_png(p)
        img[:, :16] = (255, 0, 255)
        write_png(p, img)


@case("D53", D, "masked pixels painted magenta: eval on the masked region's truth changes "
      "nothing (masks honoured)", expect="ok", needs=("data", "run"),
      baseline=["eval", "run", "--data", "clean", "--json"])
def _(sb):
    return ["eval", "run", "--data", "data", "--json"]


@case("D54", D, "a segmentation map of floats", mentions=("segmentation",))
def _(sb):
    np.save(sb / "data/segmentation/frame_00003.npy", np.zeros((32, 32), np.float32))
    return TRAIN1


@case("D55", D, "a time of 1.5", mentions=("time",))
def _(sb):
    edit(sb, lambda d: [f.__setitem__("time", 0.5) for f in d["frames"]] and
         frame0(d).__setitem__("time", 1.5))
    return TRAIN1


@case("D56", D, "a time on some frames only", mentions=("time",))
def _(sb):
    edit(sb, lambda d: frame0(d).__setitem__("time", 0.5))
    return TRAIN1


@case("D57", D, "a time that is a string", mentions=("time",))
def _(sb):
    edit(sb, lambda d: [f.__setitem__("time", "0.5") for f in d["frames"]])
    return TRAIN1


ART_TRAIN = ["train", "--data", "art", "--method", "articulated", "--max-steps", "1", "--out",
             "out", "--no-progress", "--option", HASH]


@case("D58", D, "articulated: joint names differ between frames", needs=("art",),
      mentions=("joints",))
def _(sb):
    edit(sb, lambda d: d["frames"][2]["joints"].__setitem__(
        "lid", d["frames"][2]["joints"].pop("drawer_slide")), "art/transforms.json")
    return ART_TRAIN


@case("D59", D, "articulated: joints on some frames only", needs=("art",), mentions=("joints",))
def _(sb):
    edit(sb, lambda d: d["frames"][2].pop("joints"), "art/transforms.json")
    return ART_TRAIN


@case("D60", D, "articulated: a one-element joint range", needs=("art",), mentions=("range",))
def _(sb):
    edit(sb, lambda d: d["scene"]["joint_info"]["door_hinge"].__setitem__("range", [0.0]),
         "art/transforms.json")
    return ART_TRAIN


@case("D61", D, "articulated: a reversed joint range", needs=("art",), mentions=("range",))
def _(sb):
    edit(sb, lambda d: d["scene"]["joint_info"]["door_hinge"].__setitem__("range", [1.9, 0.0]),
         "art/transforms.json")
    return ART_TRAIN


@case("D62", D, "articulated: a NaN joint range", needs=("art",), mentions=("range",))
def _(sb):
    edit(sb, lambda d: d["scene"]["joint_info"]["door_hinge"].__setitem__(
        "range", [0.0, float("nan")]), "art/transforms.json")
    return ART_TRAIN


@case("D63", D, "articulated: a joint position that is a string", needs=("art",),
      mentions=("joints",))
def _(sb):
    edit(sb, lambda d: d["frames"][1]["joints"].__setitem__("door_hinge", "open"),
         "art/transforms.json")
    return ART_TRAIN


@case("D64", D, "articulated: a moving joint no frame gives", needs=("art",),
      mentions=("lid",))
def _(sb):
    edit(sb, lambda d: d["scene"]["moving_joints"].append("lid"), "art/transforms.json")
    return ART_TRAIN


@case("D65", D, "`scene` (the manifest) is a list", mentions=("scene",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("scene", [1, 2]))
    return TRAIN1


@case("D66", D, "scene.bounds with min > max", mentions=("bounds",))
def _(sb):
    edit(sb, lambda d: d["scene"].__setitem__("bounds", [[1, 1, 1], [0, 0, 0]]))
    return TRAIN1


@case("D67", D, "scene.bounds of two numbers", mentions=("bounds",))
def _(sb):
    edit(sb, lambda d: d["scene"].__setitem__("bounds", [0, 1]))
    return TRAIN1


@case("D68", D, "depth_unit_scale_factor negative", mentions=("depth_unit_scale_factor",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("depth_unit_scale_factor", -1))
    return TRAIN1


@case("D69", D, "k1 = 1e6 (an absurd distortion)", mentions=("k1",))
def _(sb):
    edit(sb, lambda d: d.__setitem__("k1", 1e6))
    return TRAIN1


def blender(sb):
    """data -> a Blender layout (transforms_train / _test.json, camera_angle_x)."""
    import math

    d = doc(sb)
    split = {name: s for s in ("train", "test") for name in d[f"{s}_filenames"]}
    angle = 2 * math.atan(0.5 * d["w"] / d["fl_x"])
    for s in ("train", "test"):
        frames = [{"file_path": f["file_path"][:-4], "transform_matrix": f["transform_matrix"]}
                  for f in d["frames"] if split[f["file_path"]] == s]
        put(sb, {"camera_angle_x": angle, "frames": frames}, f"data/transforms_{s}.json")
    (sb / "data/transforms.json").unlink()


@case("D70", D, "Blender layout without camera_angle_x", mentions=("camera_angle_x",))
def _(sb):
    blender(sb)
    edit(sb, lambda d: d.pop("camera_angle_x"), "data/transforms_train.json")
    return TRAIN1


@case("D71", D, "Blender layout, extension-less file paths", expect="ok")
def _(sb):
    blender(sb)
    return TRAIN1


@case("D72", D, "Blender layout with only transforms_test.json: train", mentions=("train",))
def _(sb):
    blender(sb)
    (sb / "data/transforms_train.json").unlink()
    return TRAIN1


@case("D73", D, "Blender layout, transforms_train.json is empty", mentions=("transforms_train",))
def _(sb):
    blender(sb)
    (sb / "data/transforms_train.json").write_text("")
    return TRAIN1


@case("D74", D, "a transforms JSON given as a file path", expect="ok")
def _(sb):
    return [a if a != "data" else "data/transforms.json" for a in TRAIN1]


@case("D75", D, "--data names a PNG file", mentions=("frame_00000.png",))
def _(sb):
    return [a if a != "data" else "data/images/frame_00000.png" for a in TRAIN1]


@case("D76", D, "a segmentation map of the wrong shape", mentions=("segmentation",))
def _(sb):
    np.save(sb / "data/segmentation/frame_00003.npy", np.zeros((3, 3), np.int32))
    return TRAIN1


@case("D77", D, "NaN written in the JSON (Python's json reads it)",
      mentions=("frames[0].transform_matrix",))
def _(sb):
    text = (sb / "data/transforms.json").read_text()
    d = json.loads(text)
    frame0(d)["transform_matrix"][1][3] = float("nan")
    (sb / "data/transforms.json").write_text(json.dumps(d))
    return TRAIN1


# Flags ----------------------------------------------------------------------------------------
F = "flags"


@case("F01", F, "train without a budget", mentions=("--max-steps",))
def _(sb):
    return ["train", "--data", "data", "--out", "out"]


@case("F02", F, "--max-steps -1", mentions=("max_steps",))
def _(sb):
    return [a if a != "1" else "-1" for a in TRAIN1]


@case("F03", F, "--max-steps abc", mentions=("--max-steps",))
def _(sb):
    return [a if a != "1" else "abc" for a in TRAIN1]


@case("F04", F, "--max-seconds nan", mentions=("max_seconds",))
def _(sb):
    return ["train", "--data", "data", "--max-seconds", "nan", "--out", "out"]


@case("F05", F, "--max-seconds -5", mentions=("max_seconds",))
def _(sb):
    return ["train", "--data", "data", "--max-seconds", "-5", "--out", "out"]


@case("F06", F, "--lr 0", mentions=("lr",))
def _(sb):
    return TRAIN1 + ["--lr", "0"]


@case("F07", F, "--lr inf", mentions=("lr",))
def _(sb):
    return TRAIN1 + ["--lr", "inf"]


@case("F08", F, "--option without =", mentions=("--option",))
def _(sb):
    return TRAIN1 + ["--option", "log2_hashmap_size"]


@case("F09", F, "--option of an unknown name", mentions=("bogus",))
def _(sb):
    return TRAIN1 + ["--option", "bogus=3"]


@case("F10", F, "--option log2_hashmap_size=-3", mentions=("log2_hashmap_size",))
def _(sb):
    return TRAIN1 + ["--option", "log2_hashmap_size=-3"]


@case("F11", F, "--option log2_hashmap_size=100", mentions=("log2_hashmap_size",))
def _(sb):
    return TRAIN1 + ["--option", "log2_hashmap_size=100"]


@case("F12", F, "--option samples_per_batch=0", mentions=("samples_per_batch",))
def _(sb):
    return TRAIN1 + ["--option", "samples_per_batch=0"]


@case("F13", F, "--option log2_hashmap_size=abc", mentions=("log2_hashmap_size",))
def _(sb):
    return TRAIN1 + ["--option", "log2_hashmap_size=abc"]


@case("F14", F, "--method nope", mentions=("--method",))
def _(sb):
    return TRAIN1 + ["--method", "nope"]


@case("F15", F, "--depth-weight -1", mentions=("depth_weight",))
def _(sb):
    return TRAIN1 + ["--depth-weight", "-1"]


@case("F16", F, "--depth-weight on a dataset without depth maps", mentions=("depth",))
def _(sb):
    edit(sb, lambda d: [(f.pop("depth_file_path"), f.pop("nerfbot_depth_file_path"))
                        for f in d["frames"]])
    return TRAIN1 + ["--depth-weight", "0.1"]


@case("F17", F, "--eval-at abc", mentions=("--eval-at",))
def _(sb):
    return TRAIN1 + ["--eval-at", "abc"]


@case("F18", F, "--target-psnr with --method ngp", mentions=("--method auto",))
def _(sb):
    return TRAIN1 + ["--target-psnr", "30"]


@case("F19", F, "train --method plenoctree_octree (a baked method)", mentions=("bake",))
def _(sb):
    return TRAIN1[:-2] + ["--method", "plenoctree_octree"]


@case("F20", F, "--device nope", mentions=("nope",))
def _(sb):
    return TRAIN1 + ["--device", "nope"]


@case("F21", F, "--aabb with min > max", mentions=("aabb",))
def _(sb):
    return TRAIN1 + ["--aabb", "1", "1", "1", "0", "0", "0"]


@case("F22", F, "--aabb with a NaN", mentions=("aabb",))
def _(sb):
    return TRAIN1 + ["--aabb", "nan", "0", "0", "1", "1", "1"]


@case("F23", F, "--background 2,0,0", mentions=("--background",))
def _(sb):
    return TRAIN1 + ["--background", "2,0,0"]


@case("F24", F, "--background nope", mentions=("--background",))
def _(sb):
    return TRAIN1 + ["--background", "nope"]


@case("F25", F, "--option log2_hashmap_size=40 (a 2^40-row table)",
      mentions=("log2_hashmap_size",))
def _(sb):
    return TRAIN1 + ["--option", "log2_hashmap_size=40"]


@case("F26", F, "--seed -1", mentions=("seed",))
def _(sb):
    return TRAIN1 + ["--seed", "-1"]


@case("F27", F, "no subcommand", needs=(), mentions=("command",))
def _(sb):
    return []


@case("F28", F, "an unknown subcommand", needs=(), mentions=("fly",))
def _(sb):
    return ["fly"]


@case("F29", F, "capture --scene nope", needs=(), mentions=("nope",))
def _(sb):
    return ["capture", "--scene", "nope", "--out", "out", "--no-progress"]


@case("F30", F, "capture --views 0", needs=(), mentions=("views",))
def _(sb):
    return CAPTURE[:4] + ["0"] + CAPTURE[5:] + ["out"]


@case("F31", F, "capture --views -3", needs=(), mentions=("views",))
def _(sb):
    return CAPTURE[:4] + ["-3"] + CAPTURE[5:] + ["out"]


@case("F32", F, "capture --size 0", needs=(), mentions=("size",))
def _(sb):
    return ["capture", "--size", "0", "--out", "out", "--no-progress"]


@case("F33", F, "capture --size 1000000", needs=(), mentions=("size",))
def _(sb):
    return ["capture", "--size", "1000000", "--out", "out", "--no-progress"]


@case("F34", F, "capture --fov 0", needs=(), mentions=("fov",))
def _(sb):
    return CAPTURE + ["out", "--fov", "0"]


@case("F35", F, "capture --fov 180", needs=(), mentions=("fov",))
def _(sb):
    return CAPTURE + ["out", "--fov", "180"]


@case("F36", F, "capture --radius -1", needs=(), mentions=("radius",))
def _(sb):
    return CAPTURE + ["out", "--radius", "-1"]


@case("F37", F, "capture --format nope", needs=(), mentions=("--format",))
def _(sb):
    return CAPTURE + ["out", "--format", "nope"]


@case("F38", F, "capture --rig explicit without --poses", needs=(), mentions=("--poses",))
def _(sb):
    return CAPTURE + ["out", "--rig", "explicit"]


@case("F39", F, "capture --poses of a file with a NaN pose", needs=(), mentions=("poses.json",))
def _(sb):
    (sb / "poses.json").write_text(json.dumps({"train": [
        [[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]]}))
    return ["capture", "--rig", "explicit", "--poses", "poses.json", "--size", "16", "--out",
            "out", "--no-progress"]


@case("F40", F, "capture --poses of a missing file", needs=(), mentions=("poses.json",))
def _(sb):
    return ["capture", "--rig", "explicit", "--poses", "poses.json", "--out", "out",
            "--no-progress"]


@case("F41", F, "capture --rig monocular of a static scene", needs=(), mentions=("--rig",))
def _(sb):
    return CAPTURE + ["out", "--rig", "monocular"]


@case("F42", F, "capture --frames 5 of a static scene", needs=(), mentions=("--frames",))
def _(sb):
    return CAPTURE + ["out", "--frames", "5"]


@case("F43", F, "capture --elevation-range 70 15 (reversed)", needs=(), mentions=("elevation",))
def _(sb):
    return CAPTURE + ["out", "--elevation-range", "70", "15"]


@case("F44", F, "capture dynamic --frames 0", needs=(), mentions=("frames",))
def _(sb):
    return ["capture", "--scene", "dynamic", "--frames", "0", "--size", "16", "--out", "out",
            "--no-progress"]


@case("F45", F, "capture articulated --train-range 0.9 0.1", needs=(), mentions=("range",))
def _(sb):
    return ["capture", "--scene", "articulated", "--configs", "2", "--test-configs", "1",
            "--train-range", "0.9", "0.1", "--size", "16", "--out", "out", "--no-progress"]


@case("F46", F, "bench --budgets -1", needs=("data",), mentions=("budget",))
def _(sb):
    return ["bench", "--data", "data", "--budgets", "-1", "--out", "out", "--no-progress"]


@case("F47", F, "bench --methods nope", needs=("data",), mentions=("nope",))
def _(sb):
    return ["bench", "--data", "data", "--methods", "nope", "--budgets", "1", "--out", "out",
            "--no-progress"]


@case("F48", F, "bench --repeats 0", needs=("data",), mentions=("--repeats",))
def _(sb):
    return ["bench", "--data", "data", "--budgets", "1", "--repeats", "0", "--out", "out"]


@case("F49", F, "bench --data of a missing folder", needs=(), mentions=("missing",))
def _(sb):
    return ["bench", "--data", "missing", "--budgets", "1", "--out", "out", "--no-progress"]


@case("F50", F, "demo --seconds 0", needs=(), mentions=("--seconds",))
def _(sb):
    return ["demo", "--seconds", "0", "--out", "out"]


@case("F51", F, "render --what nope", needs=("data", "run"), mentions=("--what",))
def _(sb):
    return ["render", "run", "--what", "nope", "--out", "out.mp4"]


@case("F52", F, "train --eval-images 0", mentions=("--eval-images",))
def _(sb):
    return TRAIN1 + ["--eval-images", "0"]


@case("F53", F, "train --time-budget -5 --method auto", mentions=("budget",))
def _(sb):
    return ["train", "--data", "data", "--method", "auto", "--time-budget", "-5", "--out", "out"]


@case("F54", F, "train --checkpoint-every-steps 0", mentions=("checkpoint",))
def _(sb):
    return TRAIN1 + ["--checkpoint-every-steps", "0"]


@case("F55", F, "train --dynamic-rays 1.5", mentions=("--dynamic-rays",))
def _(sb):
    return TRAIN1 + ["--dynamic-rays", "1.5"]


# MJCF scenes --------------------------------------------------------------------------------
M = "MJCF scene"


def mjcf(sb, text, name="scene.xml"):
    (sb / name).write_text(text)
    return ["capture", "--scene", name, "--views", "2", "--test-views", "1", "--size", "16",
            "--out", "out", "--no-progress"]


@case("M01", M, "malformed XML", needs=(), mentions=("scene.xml",))
def _(sb):
    return mjcf(sb, "<mujoco><worldbody><geom type='box'</worldbody>")


@case("M02", M, "an MJCF path that does not exist", needs=(), mentions=("missing.xml",))
def _(sb):
    return ["capture", "--scene", "missing.xml", "--out", "out", "--no-progress"]


@case("M03", M, "an include of a missing file", needs=(), mentions=("scene.xml",))
def _(sb):
    return mjcf(sb, "<mujoco><include file='parts.xml'/><worldbody/></mujoco>")


@case("M04", M, "an empty worldbody (nothing to frame)", needs=(), mentions=("scene.xml",))
def _(sb):
    return mjcf(sb, "<mujoco><worldbody/></mujoco>")


@case("M05", M, "a texture file that is missing", needs=(), mentions=("scene.xml",))
def _(sb):
    return mjcf(sb, "<mujoco><asset><texture name='t' type='2d' file='wood.png'/></asset>"
                    "<worldbody><geom type='box' size='.1 .1 .1'/></worldbody></mujoco>")


@case("M06", M, "binary garbage named .xml", needs=(), mentions=("scene.xml",))
def _(sb):
    (sb / "scene.xml").write_bytes(np.random.default_rng(1).bytes(512))
    return ["capture", "--scene", "scene.xml", "--out", "out", "--no-progress"]


@case("M07", M, "an unknown nerfbot_capture kind", needs=(), mentions=("nerfbot_capture",))
def _(sb):
    return mjcf(sb, "<mujoco><custom><text name='nerfbot_capture' data='wobbly'/></custom>"
                    "<worldbody><geom type='box' size='.1 .1 .1'/></worldbody></mujoco>")


@case("M08", M, "a folder given as the scene", needs=(), mentions=("scenes",))
def _(sb):
    (sb / "scenes").mkdir()
    return ["capture", "--scene", "scenes", "--out", "out", "--no-progress"]


@case("M09", M, "a one-box scene captures", expect="ok", needs=())
def _(sb):
    return mjcf(sb, "<mujoco><worldbody><light pos='0 0 3'/><geom type='box' size='.1 .1 .1' "
                    "rgba='1 0 0 1'/></worldbody></mujoco>")


@case("M10", M, "a geom of size 1e12", needs=(), mentions=("scene.xml",))
def _(sb):
    return mjcf(sb, "<mujoco><worldbody><geom type='box' size='1e12 1e12 1e12'/>"
                    "</worldbody></mujoco>")


# -- the runner -------------------------------------------------------------------------------
CWD = {"R16": "elsewhere"}
SETUP_BEFORE_BASELINE = {"D53": _mask_baseline}


def snapshot(root: Path) -> dict:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        dirnames.sort()
        for name in filenames + [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        for d in dirnames:
            out.setdefault(str((Path(dirpath) / d).relative_to(root)) + "/", "dir")
    return out


def changed_outside(before: dict, after: dict, outputs: tuple) -> list:
    def allowed(rel):
        return any(rel == o or rel.startswith(o.rstrip("/") + "/") or rel == o + "/"
                   for o in outputs)
    keys = set(before) | set(after)
    return sorted(k for k in keys if before.get(k) != after.get(k) and not allowed(k)
                  and k != MARKER)


def error_lines(stderr: str) -> list:
    return [line for line in stderr.splitlines() if line.startswith("nerfbot") and "error:" in line]


def run_case(c: Case, base: Path, work: Path) -> dict:
    sb = work / c.id
    if sb.exists():
        for p in sb.rglob("*"):
            if p.is_dir() and not p.is_symlink():
                os.chmod(p, 0o755)
        shutil.rmtree(sb)
    sb.mkdir(parents=True)
    for name in c.needs:
        shutil.copytree(base / name, sb / name, symlinks=True)
    for config in sb.glob("*/config.json"):  # as if the fixtures had been made in the sandbox
        config.write_text(config.read_text().replace(str(base), str(sb)))
    baseline_out = None
    if c.baseline is not None:
        if c.id in SETUP_BEFORE_BASELINE:
            SETUP_BEFORE_BASELINE[c.id](sb)
        proc = nerfbot(c.baseline, sb)
        if proc.returncode != 0:
            return {"id": c.id, "pass": False, "outcome": "baseline failed",
                    "detail": proc.stderr.strip().splitlines()[-1:]}
        baseline_out = proc.stdout
    argv = [str(a) for a in c.setup(sb)]
    cwd = sb / CWD.get(c.id, ".")
    before = snapshot(sb)
    t0 = time.perf_counter()
    try:
        proc = nerfbot(argv, cwd)
    except subprocess.TimeoutExpired:
        return {"id": c.id, "pass": False, "outcome": "timeout", "argv": argv, "detail": ""}
    seconds = time.perf_counter() - t0
    after = snapshot(sb)
    changed = changed_outside(before, after, c.outputs)
    lines = error_lines(proc.stderr)
    traceback = "Traceback" in proc.stderr
    problems = []
    if proc.returncode < 0:
        problems.append(f"killed by signal {-proc.returncode}")
    if c.expect == "error":
        if proc.returncode != 2:
            problems.append(f"exit {proc.returncode}, expected 2")
        if len(lines) != 1:
            problems.append(f"{len(lines)} error lines")
        elif c.mentions:
            missing = [m for m in c.mentions if m.lower() not in lines[0].lower()]
            if missing:
                problems.append(f"message does not name {missing}")
    else:
        if proc.returncode != 0:
            problems.append(f"exit {proc.returncode}, expected 0")
    if traceback:
        problems.append("traceback")
    if changed:
        problems.append(f"changed outside the output: {changed[:4]}")
    if not problems:
        note = None if c.baseline is None else same_psnr(sb, proc, baseline_out)
        note = note or (None if c.check is None else c.check(sb, proc))
        if note:
            problems.append(note)
    message = lines[0] if lines else (proc.stderr.strip().splitlines() or [""])[-1]
    if c.expect == "ok" and not problems:
        message = result_note(c, proc, baseline_out)
    message = message.replace(str(sb), "SANDBOX")  # the table names no machine's folders
    outcome = ("clear error" if c.expect == "error" else "correct result") if not problems \
        else "FAIL: " + "; ".join(problems)
    return {"id": c.id, "group": c.group, "what": c.what, "argv": argv, "expect": c.expect,
            "exit": proc.returncode, "pass": not problems, "outcome": outcome,
            "unchanged": not changed, "message": message, "seconds": round(seconds, 2)}


def table(results: list) -> str:
    rows = ["| id | case | command | outcome | files outside the output | message |",
            "|---|---|---|---|---|---|"]
    for r in results:
        cmd = "nerfbot " + " ".join(r.get("argv", []))
        msg = r.get("message", "").replace("|", "\\|")
        if len(msg) > 140:
            msg = msg[:137] + "..."
        rows.append(f"| {r['id']} | {r.get('what', '')} | `{cmd}` | {r['outcome']} | "
                    f"{'unchanged' if r.get('unchanged') else 'CHANGED'} | {msg} |")
    return "\n".join(rows) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="work folder (fixtures, sandboxes, the table)")
    parser.add_argument("--only", nargs="+", default=None, metavar="ID")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    args = parser.parse_args()
    if args.list:
        for c in CASES:
            print(f"{c.id}  {c.group:14s} {c.expect:5s}  {c.what}")
        return 0
    out = args.out.absolute()
    build_base(out / "base")
    chosen = [c for c in CASES if args.only is None or c.id in args.only]
    results = []
    for k, c in enumerate(chosen):
        r = run_case(c, out / "base", out / "cases")
        results.append(r)
        print(f"[{k + 1}/{len(chosen)}] {c.id} {r['outcome']}: {r.get('message', '')[:120]}",
              flush=True)
    if args.only is not None and (out / "bad_inputs.json").exists():  # update those cases
        earlier = {r["id"]: r for r in json.loads((out / "bad_inputs.json").read_text())}
        earlier.update({r["id"]: r for r in results})
        results = [earlier[c.id] for c in CASES if c.id in earlier]
    (out / "bad_inputs.json").write_text(json.dumps(results, indent=1))
    (out / "bad_inputs.md").write_text(table(results))
    failed = [r["id"] for r in results if not r["pass"]]
    print(f"{len(results) - len(failed)} / {len(results)} cases pass"
          + (f"; failing: {' '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
