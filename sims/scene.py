"""Find and load MuJoCo scenes: built-in names (``tabletop``), generated scene families
(``glassware`` or ``glassware:SEED``, ``glazed[:SEED]``, and the zoo of :mod:`sims.zoo`:
``workspace``, ``room``, ``room_glass``, ``bins``, ``yard`` and the dynamic ``tossed``, each
``[:SEED]``) or paths to any MJCF file.

A generated family is a function of the seed returning the MJCF text, or a
:class:`~sims.zoo.mjcf.GeneratedScene`: the text plus asset files (textures) it refers to by
relative path. :func:`generated_scene` writes it into :func:`scene_cache_dir`: text alone as
``FAMILY-SEED.xml``; with assets into a folder of its own, ``FAMILY-SEED/FAMILY-SEED.xml`` with
the assets beside it.
"""

from __future__ import annotations

import functools
import importlib.resources
import os
from pathlib import Path
from typing import Callable, Union

import mujoco  # sims/__init__ has selected the GL backend before this import
import numpy as np

from nerfbot.data.writers import encode_png, write_bytes_atomic, write_text_atomic
from sims.glassware import glassware_xml, glazed_xml
from sims.zoo.bins import bins_scene
from sims.zoo.mjcf import GeneratedScene
from sims.zoo.room import room_glass_scene, room_scene
from sims.zoo.tossed import tossed_scene
from sims.zoo.workspace import workspace_scene
from sims.zoo.yard import yard_scene

#: Name of the camera :func:`load_capture_model` adds to the world body.
CAPTURE_CAMERA = "nerfbot_capture"

#: What a scene generator returns for a seed: the MJCF text, or the text and its assets.
Generated = Union[str, GeneratedScene]


def _generators() -> dict[str, Callable[[int], Generated]]:
    return {"glassware": glassware_xml, "glazed": glazed_xml, "workspace": workspace_scene,
            "room": room_scene, "room_glass": room_glass_scene, "bins": bins_scene,
            "yard": yard_scene, "tossed": tossed_scene}


def builtin_scenes() -> list[str]:
    """Names of the scenes packaged in ``sims/scenes/*.xml`` and of the generated families."""
    root = importlib.resources.files("sims") / "scenes"
    files = [p.name[:-4] for p in root.iterdir() if p.name.endswith(".xml")]
    return sorted(files + list(_generators()))


def scene_cache_dir() -> Path:
    """Where generated scenes are written: ``$NERFBOT_CACHE/scenes`` (default
    ``~/.cache/nerfbot/scenes``)."""
    base = os.environ.get("NERFBOT_CACHE") or Path.home() / ".cache" / "nerfbot"
    return Path(base) / "scenes"


def parse_generated(text: str) -> tuple[str, int] | None:
    """("glassware", 3) for ``glassware:3`` (seed 0 without ``:SEED``); None if ``text`` does not
    name a generated scene family. ValueError for a malformed seed."""
    family, _, seed = text.partition(":")
    if family not in _generators():
        return None
    try:
        return family, int(seed) if seed else 0
    except ValueError:
        raise ValueError(f"scene '{text}': the seed after ':' must be an integer") from None


@functools.lru_cache(maxsize=16)
def _generate(family: str, seed: int) -> tuple[str, tuple[tuple[str, bytes], ...]]:
    """(MJCF text, ((asset file name, file bytes), ...)) of ``family`` with ``seed``; arrays
    among the assets are encoded as PNG. Cached: a capture resolves its scene several times."""
    made = _generators()[family](seed)
    if isinstance(made, str):
        return made, ()
    assets = []
    for name, content in sorted(made.assets.items()):
        if not name or Path(name).name != name or name.startswith(".") or name.endswith(".xml"):
            raise ValueError(f"scene family '{family}': asset name {name!r} must be a plain "
                             "file name (no folder, not hidden, not .xml)")
        if isinstance(content, np.ndarray):
            content = encode_png(content)
        assets.append((name, bytes(content)))
    return made.xml, tuple(assets)


def _write_if_changed(path: Path, content: bytes) -> None:
    """Write ``content`` to ``path`` atomically unless the file already holds exactly that."""
    if path.is_file() and path.read_bytes() == content:
        return
    write_bytes_atomic(path, content)


def generated_scene(family: str, seed: int) -> Path:
    """Write generated scene ``family`` with ``seed`` to the scene cache and return its MJCF file.

    Every file is written atomically and only when its content changed. A scene without
    assets is ``FAMILY-SEED.xml`` in :func:`scene_cache_dir`; a scene with assets gets a folder
    ``FAMILY-SEED/`` holding its assets and then (last, so that a reader finding the MJCF finds
    its assets too) ``FAMILY-SEED.xml``, which names them by relative path.
    """
    text, assets = _generate(family, seed)
    stem = f"{family}-{seed}"
    if not assets:
        path = scene_cache_dir() / f"{stem}.xml"
        if path.is_file() and path.read_text() == text:
            return path
        return write_text_atomic(path, text)
    folder = scene_cache_dir() / stem
    for name, content in assets:
        _write_if_changed(folder / name, content)
    path = folder / f"{stem}.xml"
    _write_if_changed(path, text.encode("utf-8"))
    return path


def resolve_scene(scene: str | Path) -> Path:
    """Path of the MJCF file for ``scene``: a built-in name, a generated family with an optional
    seed (``glassware:3``, written to :func:`scene_cache_dir`), or a path to an ``.xml`` file.

    Raises:
        FileNotFoundError: neither a built-in scene nor an existing file; the message lists the
            built-in names.
    """
    text = str(scene)
    if isinstance(scene, str) and "/" not in text and not text.endswith(".xml"):
        generated = parse_generated(text)
        if generated is not None:
            return generated_scene(*generated)
        resource = importlib.resources.files("sims") / "scenes" / f"{text}.xml"
        if resource.is_file():
            return Path(str(resource))
    path = Path(text).expanduser()
    if path.is_file():
        return path.resolve()
    raise FileNotFoundError(
        f"scene '{text}': no such MJCF file and not a built-in scene "
        f"(built-in: {', '.join(builtin_scenes())})"
    )


def load_model(scene: str | Path) -> mujoco.MjModel:
    """Compile the scene as written (no extra camera).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: MuJoCo could not parse or compile it; the message names the file and carries
            MuJoCo's own error text.
    """
    path = resolve_scene(scene)
    try:
        return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as err:
        raise ValueError(f"{path}: MuJoCo could not load this MJCF: {err}".rstrip()) from err


def load_capture_model(scene: str | Path) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """Compile the scene with a fixed world-body camera named :data:`CAPTURE_CAMERA` added.

    The camera is a plain perspective camera (``fovy`` driven, no sensor size), so a capture can
    place it anywhere by writing ``model.cam_pos/cam_quat/cam_fovy``. ``mj_forward`` has been run
    on the returned data (positions from ``qpos0``; physics is never stepped).

    Raises:
        FileNotFoundError, ValueError: as :func:`load_model`.
    """
    load_model(scene)  # validates with MuJoCo's plain XML loader and gives the clear errors
    path = resolve_scene(scene)
    spec = mujoco.MjSpec.from_file(str(path))
    if any(cam.name == CAPTURE_CAMERA for cam in spec.cameras):
        raise ValueError(f"{path}: a camera is already named '{CAPTURE_CAMERA}' (reserved)")
    spec.worldbody.add_camera(name=CAPTURE_CAMERA, pos=[0.0, 0.0, 0.0], quat=[1.0, 0.0, 0.0, 0.0])
    try:
        model = spec.compile()
    except ValueError as err:
        raise ValueError(f"{path}: MuJoCo could not compile this MJCF: {err}") from err
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def scene_name(scene: str | Path) -> str:
    """Short name of a scene: the built-in name, or the file stem."""
    return resolve_scene(scene).stem
