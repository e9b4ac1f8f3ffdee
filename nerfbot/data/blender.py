"""Blender synthetic and D-NeRF: ``transforms_{train,val,test}.json`` in one folder.

Each split file carries its own ``camera_angle_x`` (radians, horizontal field of view); the
image size is read from the images. ``file_path`` usually omits ".png". Frames are concatenated
in train, val, test order and the splits are those files (missing files give no split; at
least one must exist). The dataset is D-NeRF when any frame
carries ``"time"``; then a frame without one gets ``i / (N - 1)``, with ``i`` its position in
its split file and ``N`` that file's frame count (0 when ``N == 1``), as in the D-NeRF code.
"""

from __future__ import annotations

from pathlib import Path

from nerfbot.data.errors import DatasetError
from nerfbot.data.spec import (ParsedDataset, camera_fields, depth_scale_value, frames_list,
                               manifest_value, parse_frame, read_json)

SPLIT_NAMES = ("train", "val", "test")


def parse_blender(root: Path) -> ParsedDataset:
    """Validate the split files of a Blender / D-NeRF folder (at least one must exist)."""
    specs, splits, json_files = [], {}, []
    split_frames: dict[str, list] = {}
    manifest, manifest_where = None, ""
    for split in SPLIT_NAMES:
        json_path = root / f"transforms_{split}.json"
        if not json_path.exists():
            continue
        meta = read_json(json_path)
        json_files.append(str(json_path))
        frames = frames_list(meta, json_path)
        global_camera = camera_fields(meta, f"{json_path}: ")
        depth_scale = depth_scale_value(meta, json_path)
        parsed = [parse_frame(f, i, json_path, root, global_camera, depth_scale)
                  for i, f in enumerate(frames)]
        splits[split] = list(range(len(specs), len(specs) + len(parsed)))
        split_frames[split] = parsed
        specs.extend(parsed)
        if manifest is None:
            manifest = manifest_value(meta, json_path)
            manifest_where = str(json_path)

    if not specs:
        raise DatasetError(f"{root / 'transforms_train.json'}: file not found (nor "
                           "transforms_val.json, transforms_test.json)")
    dynamic = any(s.time is not None for s in specs)
    if dynamic:
        for parsed in split_frames.values():
            n = len(parsed)
            for i, spec in enumerate(parsed):
                if spec.time is None:
                    spec.time = i / (n - 1) if n > 1 else 0.0
    return ParsedDataset(
        root=root, format="dnerf" if dynamic else "blender", frames=specs, splits=splits,
        manifest=manifest, manifest_where=manifest_where, json_files=json_files, extras={},
    )
