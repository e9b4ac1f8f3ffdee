"""Checkpoint files: durable writes, safe reads, clear errors.

A checkpoint is one ``torch.save`` of a dict holding tensors and plain data only (dict, list,
tuple, str, int, float, bool, None), tagged ``"format": "nerfbot-checkpoint"`` and
``"version"``. It is read with ``torch.load(..., weights_only=True)``, so a crafted file can
never run code: anything but tensors and plain data is refused.

A run folder holds ``checkpoint.pt`` and, once a second checkpoint has been written,
``checkpoint.prev.pt`` (the one before). A write never leaves the folder without a complete
checkpoint (:func:`save_checkpoint`); a read of a missing, empty, truncated or corrupt
``checkpoint.pt`` falls back to ``checkpoint.prev.pt`` (:func:`load_checkpoint`).
"""

from __future__ import annotations

import io
import logging
import os
import pickle
import pickletools
import re
import shutil
import warnings
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np
import torch

log = logging.getLogger(__name__)

CHECKPOINT = "checkpoint.pt"
FORMAT = "nerfbot-checkpoint"
VERSION = 1

#: Keys every checkpoint has (trained and baked runs).
REQUIRED = ("spec", "model", "step", "train_seconds", "curve", "config")
#: Keys a checkpoint needs to resume training from it.
RESUME_REQUIRED = REQUIRED + ("optimizer", "generator", "n_rays", "last_samples")
#: Keys of ``spec`` every checkpoint has.
SPEC_REQUIRED = ("method", "aabb", "background", "options", "seed")


class CheckpointError(ValueError):
    """A checkpoint file is unusable. The one-line message starts with the file's path.

    ``damaged`` is True for files a crash or a bad disk can leave (empty, truncated, corrupt):
    those may be replaced by the previous checkpoint. Files that read fine but are not nerfbot
    checkpoints (foreign, refused pickles, missing keys) are never replaced silently.
    """

    def __init__(self, problem: str, damaged: bool = False, advice: str = ""):
        super().__init__(f"{problem}; {advice}" if advice else problem)
        self.problem, self.damaged = problem, damaged


# -- paths -----------------------------------------------------------------------------------
def previous_path(path: Path) -> Path:
    """``checkpoint.prev.pt`` beside ``checkpoint.pt`` (the checkpoint before ``path``)."""
    path = Path(path)
    return path.with_name(f"{path.stem}.prev{path.suffix}")


def _temporary_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


def stale_temporaries(path: Path) -> list[Path]:
    """Temporary files of ``path`` and of its previous checkpoint left by killed writers."""
    path = Path(path)
    found = []
    for target in (path, previous_path(path)):
        found += sorted(target.parent.glob(f".{target.name}.tmp*"))
    return found


def remove_stale_temporaries(path: Path) -> None:
    """Delete what :func:`stale_temporaries` finds (only one trainer writes a run folder)."""
    for tmp in stale_temporaries(path):
        log.info("removing %s, a partial checkpoint left by an interrupted writer", tmp)
        tmp.unlink(missing_ok=True)


# -- plain data ------------------------------------------------------------------------------
def plain(value, where: str = "value"):
    """``value`` with numpy scalars and arrays turned into Python numbers and lists, tuples and
    lists and dicts walked; TypeError naming ``where`` for anything else that is not plain data
    or a tensor (weights-only loading would refuse it)."""
    if isinstance(value, (np.generic, np.ndarray)):  # first: np.float64 is a float subclass
        return value.tolist()
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return value
    if isinstance(value, dict):
        return {plain(k, f"{where} key"): plain(v, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        items = [plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
        return items if isinstance(value, list) else tuple(items)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"{where}: a {type(value).__name__} cannot be stored in a checkpoint "
                    "(tensors and plain data only)")


# -- writing ---------------------------------------------------------------------------------
def _fsync_folder(folder: Path) -> None:
    """Make renames in ``folder`` durable (no-op where folders cannot be opened, e.g. Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_synced(obj, tmp: Path) -> None:
    """torch.save ``obj`` to ``tmp``, flushed and fsynced; ``tmp`` is removed on failure."""
    try:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _keep_previous(path: Path) -> None:
    """Make ``checkpoint.prev.pt`` the current ``path`` while ``path`` stays in place: a hard
    link (a synced copy where links are not supported) under a temporary name, renamed over
    the previous one."""
    prev = previous_path(path)
    tmp = _temporary_path(prev)
    tmp.unlink(missing_ok=True)
    try:
        os.link(path, tmp)
    except OSError:
        try:
            with open(path, "rb") as src, open(tmp, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
                dst.flush()
                os.fsync(dst.fileno())
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    os.replace(tmp, prev)


def write_durable(obj, path: Path) -> Path:
    """torch.save ``obj`` to ``path`` so that a crash at any instant leaves a complete
    checkpoint on disk.

    Order: (1) write ``.checkpoint.pt.tmp<pid>`` and fsync it; (2) if ``checkpoint.pt``
    exists, link it as ``checkpoint.prev.pt`` (via its own temporary name) and fsync the
    folder; (3) rename the temporary over ``checkpoint.pt``; (4) fsync the folder.
    ``checkpoint.pt`` is therefore always complete once it exists (the old or the new one),
    and ``checkpoint.prev.pt`` is replaced only by a complete file."""
    path = Path(path)
    tmp = _temporary_path(path)
    _write_synced(obj, tmp)
    try:
        if path.exists():
            _keep_previous(path)
            _fsync_folder(path.parent)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_folder(path.parent)
    return path


def save_checkpoint(ckpt: dict, path: Path) -> Path:
    """Write the checkpoint ``ckpt`` (a dict with at least :data:`REQUIRED`) to ``path``
    durably (:func:`write_durable`), tagged with :data:`FORMAT` and :data:`VERSION`; its
    ``spec``, ``config`` and ``curve`` are converted to plain data (:func:`plain`)."""
    missing = [k for k in REQUIRED if k not in ckpt]
    if missing:
        raise ValueError(f"{path}: refusing to write a checkpoint without {', '.join(missing)}")
    out = dict(ckpt)
    for key in ("spec", "config", "curve"):
        out[key] = plain(out[key], key)
    out["format"], out["version"] = FORMAT, VERSION
    return write_durable(out, path)


# -- reading ---------------------------------------------------------------------------------
_DAMAGED_ADVICE = "delete it or restore it from a backup"


def _reason(err: Exception) -> str:
    """``Type: first sentence of the message`` of a low-level read error, one short line."""
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    text = text.split(". ")[0][:100]
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def _pickle_bytes(path: Path) -> Optional[bytes]:
    """The pickle stream of a torch file: ``data.pkl`` of a zip file, else the file itself."""
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if n.endswith("data.pkl")]
            return zf.read(names[0]) if names else None
    return path.read_bytes()


def _pickle_globals(data: bytes) -> Optional[list[str]]:
    """The callables and classes a pickle stream names (``module.name``), read opcode by opcode
    without running anything; None when the stream is not a complete pickle."""
    names, strings = [], []
    try:
        for op, arg, _ in pickletools.genops(io.BytesIO(data)):
            if op.name == "GLOBAL":
                names.append(".".join(str(arg).split(" ", 1)))
            elif op.name == "STACK_GLOBAL" and len(strings) >= 2:
                names.append(f"{strings[-2]}.{strings[-1]}")
            elif isinstance(arg, str):
                strings.append(arg)
    except Exception:  # any malformed stream: genops raises ValueError, EOFError, ...
        return None
    return names


def _refused_or_corrupt(path: Path, err: Exception) -> CheckpointError:
    """The error for a file weights-only unpickling rejected: a complete pickle that names
    something other than tensors and plain data is refused; anything else is corrupt."""
    try:
        data = _pickle_bytes(path)
    except (OSError, zipfile.BadZipFile, RuntimeError):
        data = None
    names = None if data is None else _pickle_globals(data)
    if names is None:
        return CheckpointError(f"{path} is truncated or corrupt (not a readable pickle)",
                               damaged=True, advice=_DAMAGED_ADVICE)
    named = re.search(r"GLOBAL ([\w.]+)", str(err))
    foreign = [n for n in names if not n.startswith(("torch.", "collections.OrderedDict"))]
    culprit = named.group(1) if named else (foreign[0] if foreign else None)
    what = f" (it would call or build {culprit})" if culprit else ""
    return CheckpointError(f"{path} is refused: it is not tensors-only data{what}; it was not "
                           "loaded (nerfbot checkpoints hold tensors and plain data only)")


def _torch_load(path: Path) -> object:
    """torch.load ``path`` (weights only, to CPU) or CheckpointError."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise CheckpointError(f"{path} does not exist", damaged=True) from None
    if path.is_dir():
        raise CheckpointError(f"{path} is a folder, not a checkpoint file")
    if size == 0:
        raise CheckpointError(f"{path} is empty (0 bytes)", damaged=True,
                              advice=_DAMAGED_ADVICE)
    try:
        with warnings.catch_warnings():
            # torch warns about the pickle protocol of files it then refuses; the refusal says it
            warnings.filterwarnings("ignore", message=".*pickle protocol", category=UserWarning)
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        raise _refused_or_corrupt(path, err) from None
    except (OSError, EOFError, RuntimeError, KeyError, ValueError, IndexError,
            AttributeError, TypeError, zipfile.BadZipFile) as err:
        raise CheckpointError(f"{path} is truncated or corrupt ({_reason(err)})", damaged=True,
                              advice=_DAMAGED_ADVICE) from None


def check_checkpoint(ckpt, path: Path, required: tuple = REQUIRED) -> dict:
    """``ckpt`` if it is a nerfbot checkpoint with the ``required`` keys, else CheckpointError.

    Checkpoints written before the format tag existed have no ``format`` key; they are
    accepted when they have the required keys."""
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path} is not a nerfbot checkpoint (a torch file holding a "
                              f"{type(ckpt).__name__}, not a checkpoint dict)")
    if "format" in ckpt and ckpt["format"] != FORMAT:
        raise CheckpointError(f"{path} is not a nerfbot checkpoint (format {ckpt['format']!r}, "
                              f"not {FORMAT!r})")
    version = ckpt.get("version", 0)
    if not isinstance(version, int) or version > VERSION:
        raise CheckpointError(f"{path}: checkpoint version {version!r} was written by a newer "
                              f"nerfbot (this one reads versions up to {VERSION}); upgrade nerfbot")
    if "format" not in ckpt and not {"spec", "model"} <= set(ckpt):
        raise CheckpointError(f"{path} is not a nerfbot checkpoint (a torch file with keys "
                              f"{sorted(map(str, ckpt))[:6]}, no 'format': {FORMAT!r})")
    missing = [k for k in required if k not in ckpt]
    if missing:
        raise CheckpointError(f"{path}: checkpoint has no {missing[0]!r} (needs "
                              f"{', '.join(required)})")
    spec = ckpt["spec"]
    if not isinstance(spec, dict):
        raise CheckpointError(f"{path}: checkpoint 'spec' is a {type(spec).__name__}, not a dict")
    missing = [k for k in SPEC_REQUIRED if k not in spec]
    if missing:
        raise CheckpointError(f"{path}: checkpoint spec has no {missing[0]!r}")
    if not isinstance(ckpt["model"], dict) or not all(
            isinstance(v, torch.Tensor) for v in ckpt["model"].values()):
        raise CheckpointError(f"{path}: checkpoint 'model' is not a dict of tensors")
    return ckpt


def read_checkpoint(path: Path, required: tuple = REQUIRED) -> dict:
    """The checkpoint in the file ``path`` (tensors on CPU), checked (:func:`check_checkpoint`);
    CheckpointError when it is missing, empty, truncated, corrupt, refused or incomplete."""
    path = Path(path)
    return check_checkpoint(_torch_load(path), path, required)


def load_checkpoint(path: Path, required: tuple = REQUIRED) -> Optional[tuple[dict, Path]]:
    """(checkpoint, file read) of the checkpoint ``path`` of a run, or None if neither it nor
    its previous checkpoint exists.

    A missing, empty, truncated or corrupt ``path`` falls back to ``checkpoint.prev.pt``
    (a warning names both); any other problem, or a damaged previous checkpoint as well, is
    a CheckpointError."""
    path = Path(path)
    prev = previous_path(path)
    if not path.exists() and not prev.exists():
        return None
    try:
        return read_checkpoint(path, required), path
    except CheckpointError as err:
        if not err.damaged or not prev.exists():
            raise
        first = err
    try:
        ckpt = read_checkpoint(prev, required)
    except CheckpointError as err:
        raise CheckpointError(f"{first.problem}; the previous checkpoint is unusable too: {err}",
                              damaged=err.damaged) from None
    log.warning("%s; loading the previous checkpoint %s (step %s) instead", first.problem, prev,
                ckpt.get("step"))
    return ckpt, prev
