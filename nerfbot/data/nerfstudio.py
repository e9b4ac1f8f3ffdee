"""nerfstudio / instant-ngp ``transforms.json``: one file, global or per-frame intrinsics.

Splits come from the optional ``train_filenames`` / ``val_filenames`` / ``test_filenames``
lists, matched against ``frames[].file_path`` after normalisation (``./`` and ``a/..``
collapsed, ``\\`` read as ``/``). Without any list the caller applies the default rule.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from nerfbot.data.errors import DatasetError
from nerfbot.data.spec import (ParsedDataset, camera_fields, depth_scale_value, frames_list,
                               manifest_value, normalise_rel, parse_frame, read_json)

SPLIT_NAMES = ("train", "val", "test")
#: Top-level keys kept in ``Dataset.extras`` as written (nerfbot does not apply them).
PASSTHROUGH_KEYS = ("applied_transform", "applied_scale", "aabb_scale", "scale", "offset",
                    "ply_file_path")


def _split_lists(meta: dict, json_path: Path, file_paths: list[str]) -> Optional[dict]:
    """split name -> sorted frame indices from the ``*_filenames`` lists, or None if none."""
    keys = [name for name in SPLIT_NAMES if f"{name}_filenames" in meta]
    if not keys:
        return None
    index: dict[str, list[int]] = {}
    for i, fp in enumerate(file_paths):
        index.setdefault(normalise_rel(fp), []).append(i)
    splits = {}
    for name in keys:
        field = f"{name}_filenames"
        names = meta[field]
        if not isinstance(names, list):
            raise DatasetError(f"{json_path}: {field}: expected a list of file paths, "
                               f"got {type(names).__name__}")
        chosen: set[int] = set()
        for k, value in enumerate(names):
            if not isinstance(value, str):
                raise DatasetError(f"{json_path}: {field}[{k}]: expected a file path string, "
                                   f"got {value!r}")
            hits = index.get(normalise_rel(value))
            if hits is None:
                raise DatasetError(f"{json_path}: {field}[{k}]: {value!r} is not the file_path "
                                   "of any frame")
            chosen.update(hits)
        splits[name] = sorted(chosen)
    return splits


def parse_nerfstudio(json_path: Path) -> ParsedDataset:
    """Validate a nerfstudio / instant-ngp transforms file (its folder is the dataset root)."""
    root = json_path.parent
    meta = read_json(json_path)
    frames = frames_list(meta, json_path)
    global_camera = camera_fields(meta, f"{json_path}: ")
    depth_scale = depth_scale_value(meta, json_path)
    specs = [parse_frame(f, i, json_path, root, global_camera, depth_scale)
             for i, f in enumerate(frames)]
    return ParsedDataset(
        root=root, format="nerfstudio", frames=specs,
        splits=_split_lists(meta, json_path, [s.file_path for s in specs]),
        manifest=manifest_value(meta, json_path), manifest_where=str(json_path),
        json_files=[str(json_path)],
        extras={k: meta[k] for k in PASSTHROUGH_KEYS if k in meta},
    )
