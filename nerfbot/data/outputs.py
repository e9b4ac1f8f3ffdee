"""Where nerfbot may write: the one rule every command that makes an output folder follows.

An output folder may be written only if it is

* missing, or an empty folder: it is created and marked as nerfbot's; or
* a folder nerfbot made of the same kind, and the user asked for it: ``--overwrite`` replaces
  it, ``--resume`` continues a training run, and a bench folder is resumed by rerunning.

Anything else is a :class:`FileExistsError` naming the folder, what is in the way and what to
do instead. Nothing the user made is deleted or overwritten.

Marker: every folder nerfbot creates holds :data:`MARKER` (``.nerfbot.json``), the JSON object
``{"kind": KIND}`` with KIND one of :data:`KINDS`: ``dataset`` (``capture``), ``run``
(``train``), ``baked_run`` (``bake``), ``bench``, ``demo`` and ``render`` (``render``'s image
folders; a video path is :func:`check_output_file`'s). Ownership is read from the marker, never
guessed from file names.

A command that fails removes what it wrote (:meth:`OutputFolder.writing`): a folder it created
is removed, an empty one emptied again; ``train`` keeps its folder once it holds a checkpoint.

Folders made before the marker existed are recognised by what nerfbot wrote into them (and get
the marker when written again): a run is a folder with ``checkpoint.pt`` and a ``config.json``
holding a ``spec`` object (a baked run when ``bake.json`` is there too); a bench folder has a
``bench.json`` with ``settings``; a dataset has a ``transforms*.json`` carrying the scene
manifest ``sims`` writes (a ``scene`` object with a ``source``), so a user's dataset with a
plain ``transforms.json`` is never taken for one; a demo folder has ``metrics.json``, ``data/``
and a ``run/`` that is a run. Older render folders and ``--no-manifest`` captures are not
recognised: they are refused like any folder nerfbot did not make.

Files the user added to a folder of ours: replacing a folder removes its contents, so a folder
holding an entry its kind does not write (:data:`LAYOUTS`, checked at its top level and in the
nerfbot folders nested in it) is refused even with ``--overwrite``, naming the entry. Resuming
deletes nothing, so it is allowed whatever else the folder holds.
"""

from __future__ import annotations

import json
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path
from typing import Callable, Iterator, Optional

from nerfbot.data.writers import write_json_atomic

MARKER = ".nerfbot.json"

KINDS = ("dataset", "run", "baked_run", "bench", "demo", "render")

#: How messages name a folder of each kind.
DESCRIPTIONS = {"dataset": "a nerfbot dataset", "run": "a training run",
                "baked_run": "a baked run", "bench": "a bench folder",
                "demo": "a demo folder", "render": "a folder of rendered images"}

#: Top-level entries nerfbot writes into a folder of each kind (fnmatch patterns), besides the
#: marker and the hidden temporaries of atomic writes (:data:`TEMPORARIES`).
LAYOUTS = {
    "dataset": ("transforms*.json", "images", "depth", "segmentation", "sensor_depth", "train",
                "val", "test", "states.npz"),
    "run": ("checkpoint*.pt", "checkpoints", "config.json", "curve.json", "metrics.json",
            "auto.json", "auto_sweep", "labels.json", "scalars.csv", "curve.png"),
    "baked_run": ("checkpoint*.pt", "config.json", "curve.json", "bake.json"),
    "bench": ("bench.json", "bench.csv", "bench_runs.csv", "bench.md", "psnr_vs_*.png", "data",
              "runs"),
    "demo": ("data", "run", "renders", "metrics.json", "sheet.png", "depth.png", "depth.npy",
             "depth_gt.png"),
    "render": ("rgb_*.png", "depth_*.png", "opacity_*.png", "depth_*.npy", "labels_*.png",
               "labels_*.npy"),
}

#: Entries of a kind that are nerfbot folders of another kind (checked with that kind's layout).
NESTED = {"demo": {"data": "dataset", "run": "run"}, "run": {"auto_sweep": "bench"}}

#: Hidden files atomic writes leave behind when interrupted (``.NAME.XXXX.tmp``, ``.NAME.tmpPID``).
TEMPORARIES = (".*.tmp*",)

#: How to ask for a folder of each kind to be written again.
AGAIN = {"run": "pass --resume to continue it or --overwrite to start over",
         "bench": "rerun to resume it"}
_DEFAULT_AGAIN = "pass --overwrite to replace it"


def read_marker(folder: Path) -> Optional[str]:
    """The kind in ``folder``'s marker, or None (no marker, or not a readable one)."""
    try:
        kind = json.loads((Path(folder) / MARKER).read_text()).get("kind")
    except (OSError, ValueError, AttributeError):
        return None
    return kind if kind in KINDS else None


def write_marker(folder: Path, kind: str) -> None:
    """Mark ``folder`` (created if missing) as a nerfbot folder of ``kind``."""
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r} (known: {', '.join(KINDS)})")
    write_json_atomic(Path(folder) / MARKER, {"kind": kind})


def _json_field(path: Path, key: str):
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc.get(key) if isinstance(doc, dict) else None


def _legacy_kind(folder: Path) -> Optional[str]:
    """The kind of a folder nerfbot wrote before it marked its folders (see the module doc)."""
    names = set(os.listdir(folder))
    if "checkpoint.pt" in names and isinstance(_json_field(folder / "config.json", "spec"), dict):
        return "baked_run" if "bake.json" in names else "run"
    if isinstance(_json_field(folder / "bench.json", "settings"), dict):
        return "bench"
    if "metrics.json" in names and (folder / "data").is_dir() and (folder / "run").is_dir() \
            and folder_kind(folder / "run") == "run":
        return "demo"
    for name in sorted(n for n in names if fnmatch(n, "transforms*.json")):
        scene = _json_field(folder / name, "scene")
        if isinstance(scene, dict) and isinstance(scene.get("source"), str):
            return "dataset"
    return None


def folder_kind(folder: Path) -> Optional[str]:
    """The kind of nerfbot folder ``folder`` is (from its marker, else the legacy rules), or
    None when nerfbot did not make it (or it is not a folder)."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    return read_marker(folder) or _legacy_kind(folder)


def _ours(name: str, kind: str) -> bool:
    return name == MARKER or any(fnmatch(name, p) for p in LAYOUTS[kind] + TEMPORARIES)


def foreign_entries(folder: Path, kind: str) -> list[Path]:
    """Entries of the ``kind`` folder ``folder`` that nerfbot does not write there: those its
    layout does not name, and those of the nerfbot folders nested in it."""
    found = []
    for entry in sorted(Path(folder).iterdir()):
        if not _ours(entry.name, kind):
            found.append(entry)
        elif entry.name in NESTED.get(kind, {}) and entry.is_dir():
            found += foreign_entries(entry, NESTED[kind][entry.name])
    return found


def _names(entries, limit: int = 3) -> str:
    names = [str(e) for e in entries[:limit]]
    return ", ".join(names) + (f" and {len(entries) - limit} more" if len(entries) > limit else "")


def _refuse_foreign(folder: Path, kind: str) -> None:
    """FileExistsError naming the entries of ``folder`` that replacing it would delete."""
    foreign = foreign_entries(folder, kind)
    if foreign:
        raise FileExistsError(f"{folder}: also holds files nerfbot did not write "
                              f"({_names([str(e.relative_to(folder)) for e in foreign])}); "
                              "--overwrite would delete them: move them away or choose another "
                              "--out")


def _first_missing(path: Path) -> Path:
    """The topmost folder of ``path``'s ancestry (``path`` included) that does not exist."""
    top = path
    while not top.parent.exists() and top.parent != top:
        top = top.parent
    return top


@dataclass
class OutputFolder:
    """An output folder that :func:`check_output_folder` allowed, and how it will be written.

    ``state``: "new" (missing), "empty" (an empty folder), "replace" (a folder of ours, with
    ``--overwrite``) or "resume" (a folder of ours to continue).
    """

    path: Path
    kind: str
    state: str
    created: Optional[Path] = field(default=None, init=False, repr=False)
    """The topmost folder :meth:`prepare` created (``path`` or one of its parents)."""

    def prepare(self) -> Path:
        """Make the folder ready: create it, or empty a folder being replaced; mark it."""
        if self.state == "new":
            self.created = _first_missing(self.path.absolute())
            self.path.mkdir(parents=True, exist_ok=True)
        elif self.state == "replace":
            _refuse_foreign(self.path, self.kind)  # again: files may have come since the check
            self._clear()
        write_marker(self.path, self.kind)
        return self.path

    def undo(self) -> None:
        """After a failure: remove the folder if :meth:`prepare` created it, empty it if it was
        empty, leave it empty (marked) if it was being replaced; a resumed folder stays."""
        if self.state == "new":
            shutil.rmtree(self.created or self.path, ignore_errors=True)
        elif self.state == "empty":
            self._clear(keep_marker=False)
        elif self.state == "replace":
            self._clear()

    def _clear(self, keep_marker: bool = True) -> None:
        for entry in self.path.iterdir():
            if keep_marker and entry.name == MARKER:
                continue
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()

    @contextmanager
    def writing(self, keep: Optional[Callable[[], bool]] = None) -> Iterator[Path]:
        """:meth:`prepare`, then on an exception in the body :meth:`undo` (unless ``keep()``
        says the folder already holds something worth keeping, e.g. a checkpoint)."""
        self.prepare()
        try:
            yield self.path
        except BaseException:
            if keep is None or not keep():
                self.undo()
            raise


def check_output_folder(path, kind: str, *, overwrite: bool = False,
                        resume: bool = False) -> OutputFolder:
    """Whether ``path`` may be written as a ``kind`` folder (see the module doc); nothing is
    written. ``overwrite`` replaces a folder of ours, ``resume`` continues one (a bench folder
    is always resumed).

    Raises:
        FileExistsError: a one-line message naming the folder, what is in the way, and the
            flag or folder to use.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown output kind {kind!r} (known: {', '.join(KINDS)})")
    path = Path(path)
    what = DESCRIPTIONS[kind]
    if not path.exists() and not path.is_symlink():
        return OutputFolder(path, kind, "new")
    if not path.is_dir():
        raise FileExistsError(f"{path}: a file is in the way (the output is {what}); choose "
                              "another --out")
    entries = sorted(path.iterdir())
    if not entries:
        return OutputFolder(path, kind, "empty")
    found = folder_kind(path)
    if found is None:
        raise FileExistsError(f"{path}: not empty and not made by nerfbot (it holds "
                              f"{_names([e.name for e in entries])}); choose a new or empty "
                              "--out")
    if found != kind:
        raise FileExistsError(f"{path}: {DESCRIPTIONS[found]}, not {what}; choose another --out")
    if kind == "bench" or (resume and kind == "run"):
        return OutputFolder(path, kind, "resume")
    if not overwrite:
        raise FileExistsError(f"{path}: already {what}; {AGAIN.get(kind, _DEFAULT_AGAIN)}, or "
                              "choose another --out")
    _refuse_foreign(path, kind)
    return OutputFolder(path, kind, "replace")


def check_output_file(path, overwrite: bool = False) -> Path:
    """``path`` as an output file (e.g. a video): refused if it is a folder, or an existing
    file without ``overwrite`` (FileExistsError)."""
    path = Path(path)
    if path.is_dir():
        raise FileExistsError(f"{path}: a folder is in the way; choose another --out")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists; pass --overwrite to replace it, or "
                              "choose another --out")
    return path
