"""Captures of many scenes of one zoo family (``workspace:0``, ``workspace:1``, ...), one dataset
folder per seed: what a model trained across scenes (pixelNeRF) learns from."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

from tqdm.auto import tqdm

from sims.capture import capture
from sims.rigs import default_rig, make_test_rig


def family_folder(root: Path, family: str, seed: int) -> Path:
    """The dataset folder of ``family:seed`` under ``root``."""
    return Path(root) / f"{family}-{int(seed)}"


def capture_family(family: str, seeds: Iterable[int], root: Path, views: int = 24,
                   test_views: int = 6, size: int = 64, progress: bool = True) -> list[Path]:
    """Capture ``views`` training and ``test_views`` test views of every ``family:seed`` at
    ``size`` x ``size`` pixels (the family's default rig, seeded by the scene seed) into
    ``root/family-seed``; a folder that already holds a capture (``transforms.json``) is kept
    as it is. Returns the dataset folders in seed order."""
    folders = []
    for seed in tqdm(list(seeds), desc=f"{family} scenes", unit="scene", disable=not progress):
        scene = f"{family}:{int(seed)}"
        out = family_folder(root, family, seed)
        if not (out / "transforms.json").exists():
            rig = default_rig(scene, count=views, width=size, height=size, seed=int(seed))
            capture(scene, rig, make_test_rig(rig, test_views), out, progress=False)
        folders.append(out)
    return folders
