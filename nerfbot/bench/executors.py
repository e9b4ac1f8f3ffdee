"""Executors of a benchmark sweep: where and how the points run.

Both give each point a fresh process and never let two points share a machine, so train and
render timings and peak memory are the point's own:

- ``local`` (default): one subprocess per point (``python -m nerfbot.bench.point RUN_DIR``),
  strictly one after the other.
- ``ray``: every point is a Ray task asking for all the CPUs of a node (``num_cpus``) in a
  worker used for that task only (``max_calls=1``); nodes run points in parallel, one each.
  ``address=None`` starts a local Ray (one point at a time, like ``local``). Needs the optional
  extra: ``pip install 'nerfbot[ray]'``, and nerfbot installed on every node. A node captures
  built-in scenes itself when the driver's ``OUT/data`` is not on its disk; dataset folders
  must be (a shared file system), at the same path.

An executor's :meth:`run` yields ``(point, result)`` as points finish; a point that fails
yields a result with ``status: "failed"`` and the error, and the sweep goes on.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
from pathlib import Path
from typing import Iterator, Optional

from nerfbot.bench.point import LOG_FILE, POINT_FILE, RESULT_FILE, run_point_elsewhere

log = logging.getLogger(__name__)

#: The folder holding the ``nerfbot`` package (put on a point process's PYTHONPATH).
SOURCE_ROOT = Path(__file__).resolve().parents[2]

RAY_INSTALL_HINT = "pip install 'nerfbot[ray]'"


class BenchError(ValueError):
    """A benchmark request that cannot run (unknown method, dataset, option, executor...)."""


def failure(point: dict, error: str) -> dict:
    """The result recorded for a point that did not complete."""
    return {"key": point["key"], "status": "failed", "error": error}


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


class LocalExecutor:
    """Each point in its own subprocess, one at a time (timings never overlap)."""

    name = "local"

    def __init__(self, **_ignored):
        pass

    def run(self, points: list[dict], run_root: Path) -> Iterator[tuple[dict, dict]]:
        env = dict(os.environ)
        src = str(SOURCE_ROOT)  # importable without install
        env["PYTHONPATH"] = os.pathsep.join(p for p in (src, env.get("PYTHONPATH")) if p)
        for point in points:
            run_dir = Path(run_root) / point["run_name"]
            run_dir.mkdir(parents=True, exist_ok=True)
            (run_dir / RESULT_FILE).unlink(missing_ok=True)
            (run_dir / POINT_FILE).write_text(json.dumps(point, indent=2))
            with open(run_dir / LOG_FILE, "w") as out:
                proc = subprocess.run([sys.executable, "-m", "nerfbot.bench.point", str(run_dir)],
                                      stdout=out, stderr=subprocess.STDOUT, env=env)
            result_path = run_dir / RESULT_FILE
            if proc.returncode == 0 and result_path.exists():
                yield point, json.loads(result_path.read_text())
            else:
                yield point, failure(point, f"exit code {proc.returncode}; end of "
                                            f"{run_dir / LOG_FILE}:\n{_tail(run_dir / LOG_FILE)}")


def import_ray():
    """The ``ray`` module, or a :class:`BenchError` saying how to install it."""
    try:
        import ray
    except ImportError as err:
        raise BenchError(f"the ray executor needs Ray, which is not installed: "
                         f"{RAY_INSTALL_HINT}") from err
    return ray


class RayExecutor:
    """Points as Ray tasks, each holding every CPU of a node, in a worker used once.

    Args:
        address: Ray cluster address (``ray://host:10001``, ``host:6379`` or ``auto``); None
            starts a local Ray for this sweep.
        num_cpus: CPUs each task asks for; default the most CPUs any alive node has, so a task
            fills its node (on a mixed cluster, smaller nodes then get no points).
    """

    name = "ray"

    def __init__(self, address: Optional[str] = None, num_cpus: Optional[int] = None, **_ignored):
        self.ray = import_ray()
        self.address, self.num_cpus = address, num_cpus

    def node_cpus(self) -> int:
        cpus = [int(n.get("Resources", {}).get("CPU", 0)) for n in self.ray.nodes() if n.get("Alive")]
        return max([c for c in cpus if c > 0] or [os.cpu_count() or 1])

    def run(self, points: list[dict], run_root: Path) -> Iterator[tuple[dict, dict]]:
        ray = self.ray
        started = not ray.is_initialized()
        if started:
            ray.init(address=self.address, include_dashboard=False, log_to_driver=False,
                     logging_level=logging.WARNING)
        try:
            cpus = self.num_cpus or self.node_cpus()
            task = ray.remote(num_cpus=cpus, max_calls=1)(run_point_elsewhere)
            refs = {task.remote(p, str(Path(run_root).resolve())): p for p in points}
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                point = refs[done[0]]
                try:
                    yield point, ray.get(done[0])
                except Exception as err:  # a failed task: record it, keep sweeping
                    yield point, failure(point, f"ray task failed: {err}")
        finally:
            if started:
                ray.shutdown()


#: Executor name -> class; ``nerfbot bench --executor NAME``.
EXECUTORS = {"local": LocalExecutor, "ray": RayExecutor}


def make_executor(name: str, **kwargs):
    """The executor called ``name`` (see :data:`EXECUTORS`)."""
    if name not in EXECUTORS:
        raise BenchError(f"unknown executor {name!r}; available: {', '.join(EXECUTORS)}")
    return EXECUTORS[name](**kwargs)
