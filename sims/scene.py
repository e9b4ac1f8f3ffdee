"""Find and load MuJoCo scenes: built-in names (``tabletop``) or paths to any MJCF file."""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import mujoco  # sims/__init__ has selected the GL backend before this import

#: Name of the camera :func:`load_capture_model` adds to the world body.
CAPTURE_CAMERA = "nerfbot_capture"


def builtin_scenes() -> list[str]:
    """Names of the scenes packaged in ``sims/scenes/*.xml``."""
    root = importlib.resources.files("sims") / "scenes"
    return sorted(p.name[:-4] for p in root.iterdir() if p.name.endswith(".xml"))


def resolve_scene(scene: str | Path) -> Path:
    """Path of the MJCF file for ``scene``: a built-in name or a path to an ``.xml`` file.

    Raises:
        FileNotFoundError: neither a built-in scene nor an existing file; the message lists the
            built-in names.
    """
    text = str(scene)
    if isinstance(scene, str) and "/" not in text and not text.endswith(".xml"):
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
