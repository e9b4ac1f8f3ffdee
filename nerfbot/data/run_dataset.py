"""Which dataset a run folder was trained on, wherever the run and the dataset have moved.

A run's ``config.json`` stores the dataset path twice: absolute (``data``) and relative to the
run folder (``data_relative``), so a run moved together with its dataset (the relative layout
kept) still finds it. The run's spec stores the dataset's identity
(:func:`nerfbot.data.identity.dataset_identity`), so a dataset found at a stored path is used
only if it is the one the run was trained on. A path is never resolved against the current
directory.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Optional

from nerfbot.data.dataset import Dataset
from nerfbot.data.errors import DatasetError
from nerfbot.data.identity import identity_mismatch
from nerfbot.data.readers import load_dataset

CONFIG = "config.json"


def run_data_fields(dataset_root, run_dir) -> dict:
    """The ``data`` (absolute) and ``data_relative`` (relative to ``run_dir``) entries of a
    run's ``config.json`` for the dataset at ``dataset_root``."""
    data = os.path.abspath(dataset_root)
    return {"data": data, "data_relative": os.path.relpath(data, os.path.abspath(run_dir))}


def _read_config(run: Path) -> tuple[Path, dict]:
    path = run / CONFIG
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing, so the run's dataset is unknown; pass "
                                "--data DIR")
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: not readable JSON ({err}); pass --data DIR") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: not a JSON object; pass --data DIR")
    return path, doc


def stored_dataset_paths(run) -> list[Path]:
    """Where the dataset of ``run`` may be, in the order to try: the absolute path in its
    ``config.json``, then ``data_relative`` joined to the run folder.

    Raises:
        FileNotFoundError: no ``config.json``, or it names no dataset (``data`` missing or
            null: a baked run of an unknown dataset).
        DatasetError: ``config.json`` is unreadable, or ``data`` is not a path this function
            can place (a relative path from an older nerfbot, relative to an unknown
            directory, with no ``data_relative``).
    """
    run = Path(run)
    path, doc = _read_config(run)
    data, relative = doc.get("data"), doc.get("data_relative")
    if data is None:
        raise FileNotFoundError(f"{path}: data: no dataset recorded; pass --data DIR")
    if not isinstance(data, str) or (relative is not None and not isinstance(relative, str)):
        raise DatasetError(f"{path}: data: expected a path string, got {data!r}; pass --data DIR")
    candidates = []
    if os.path.isabs(data):
        candidates.append(Path(data))
    if relative is not None:
        candidates.append(Path(os.path.normpath(os.path.join(os.path.abspath(run), relative))))
    if not candidates:
        raise DatasetError(f"{path}: data: {data!r} is relative to the directory the run was "
                           "trained from, which is not recorded; pass --data DIR")
    return list(dict.fromkeys(candidates))


def stored_identity(run) -> Optional[dict]:
    """The dataset identity in ``run``'s ``config.json`` spec (None if it has none)."""
    _, doc = _read_config(Path(run))
    spec = doc.get("spec")
    identity = spec.get("dataset") if isinstance(spec, dict) else None
    return identity if isinstance(identity, dict) else None


def resolve_run_dataset(run, identity: Optional[dict] = None) -> tuple[Path, Dataset]:
    """(folder, loaded dataset) of the dataset ``run`` was trained on.

    Tries the stored absolute path, then the path relative to the run folder
    (:func:`stored_dataset_paths`); the first dataset found there whose identity matches
    ``identity`` (default: the one in the run's ``config.json``; a run without one accepts the
    first dataset found) is returned.

    Raises:
        FileNotFoundError: no dataset at any stored path (or none is recorded).
        DatasetError: unreadable ``config.json``; or a dataset at a stored path is not the one
            the run was trained on, e.g. ``RUN/config.json: data: the dataset at X is not the
            one this run was trained on (other camera poses or intrinsics); pass --data DIR``.
    """
    run = Path(run)
    candidates = stored_dataset_paths(run)
    if identity is None:
        identity = stored_identity(run)
    where = run / CONFIG
    mismatch = None
    for candidate in candidates:
        if not candidate.exists():
            continue
        dataset = load_dataset(candidate)
        why = identity_mismatch(identity, dataset)
        if why is None:
            return candidate, dataset
        mismatch = mismatch or (candidate, why)
    if mismatch is not None:
        raise DatasetError(f"{where}: data: the dataset at {mismatch[0]} is not the one this run "
                           f"was trained on ({mismatch[1]}); pass --data DIR")
    raise FileNotFoundError(f"{where}: data: no dataset at "
                            f"{' nor at '.join(str(c) for c in candidates)} (moved?); pass "
                            "--data DIR")
