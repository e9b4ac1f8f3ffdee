"""sims: MuJoCo scenes, camera rigs and dataset capture for nerfbot.

Importing this package selects a headless OpenGL backend (``MUJOCO_GL=egl``) when none is set and
no display is available; it must therefore be imported before ``mujoco`` for that to take effect.
"""

from sims.gl import select_backend as _select_backend

_select_backend()
