"""OpenGL backend selection for MuJoCo's offscreen renderer, with errors that say what to try.

MuJoCo reads ``MUJOCO_GL`` once, when ``mujoco`` is first imported. :func:`select_backend` must
therefore run before that import; ``sims/__init__.py`` calls it, so importing any ``sims`` module
first is enough. On a headless machine (no ``DISPLAY``) the default becomes EGL.
"""

from __future__ import annotations

import os
import sys

# Whether mujoco was imported before this module (then a MUJOCO_GL set here came too late),
# and the MUJOCO_GL it saw.
_MUJOCO_IMPORTED_FIRST = "mujoco" in sys.modules
_MUJOCO_GL_AT_IMPORT = os.environ.get("MUJOCO_GL", "")

_HINT = (
    "Try another backend by setting the environment variable before starting Python: "
    "MUJOCO_GL=egl (GPU or Mesa EGL, headless), MUJOCO_GL=osmesa (software, needs libOSMesa), "
    "or MUJOCO_GL=glfw with a display (DISPLAY set, e.g. under xvfb-run)."
)


def select_backend() -> str:
    """Set ``MUJOCO_GL=egl`` when neither ``MUJOCO_GL`` nor ``DISPLAY`` is set; return the choice.

    Does nothing if the user already chose a backend. Returns ``"default"`` when a display is
    available and no backend was chosen (MuJoCo then uses GLFW).
    """
    if not os.environ.get("MUJOCO_GL") and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"
    return os.environ.get("MUJOCO_GL", "") or "default"


def backend_name() -> str:
    """The backend MuJoCo will use (or did use), for messages."""
    return os.environ.get("MUJOCO_GL", "") or "default (glfw)"


def make_renderer(model, height: int, width: int):
    """Create a ``mujoco.Renderer`` of ``height`` x ``width`` pixels for ``model``.

    Raises:
        ValueError: the image is larger than the model's offscreen buffer (MuJoCo's message).
        RuntimeError: the OpenGL context could not be created; the message names the backend
            that failed and the alternatives to try.
    """
    select_backend()
    import mujoco  # noqa: E402  (after select_backend, on purpose)

    try:
        return mujoco.Renderer(model, height=height, width=width)
    except ValueError:
        raise
    except Exception as err:  # GL errors surface as ImportError, RuntimeError, mujoco.FatalError
        backend = backend_name()
        extra = ""
        if _MUJOCO_IMPORTED_FIRST and _MUJOCO_GL_AT_IMPORT != os.environ.get("MUJOCO_GL", ""):
            backend = _MUJOCO_GL_AT_IMPORT or "default (glfw)"
            extra = (" (mujoco was imported before sims, so it kept that backend; import sims "
                     "first or set MUJOCO_GL before starting Python)")
        raise RuntimeError(
            f"Could not create a MuJoCo offscreen renderer with backend MUJOCO_GL={backend}"
            f"{extra}: {type(err).__name__}: {err}. {_HINT}"
        ) from err
