"""Numba CPU kernels, and the one place that decides whether they or their plain-torch twins run.

Every kernel that fields, samplers and renderers call has a plain-torch twin (same arithmetic,
any device, usually differentiable; ``tests/test_twins.py`` checks each pair); only the
helpers ``nerfbot bake`` runs on numpy arrays have none. Call sites ask :func:`use_kernels`
and take the kernel only when it answers True; whatever else an op needs from its inputs (no
position gradient, no NaN, a 2-D batch) they check next to the call, as it belongs to that
kernel.

The environment variable ``NERFBOT_KERNELS`` (read at every call, so tests can set it):

* ``auto`` (default, also when unset or empty) or ``numba``: the kernels serve every CPU input
  they apply to; other devices use the twins.
* ``torch``: the twins everywhere, as on a GPU, so the paths a GPU takes run on the CPU too.
"""

from __future__ import annotations

import os

import torch

#: The environment variable that picks the implementation (see the module docstring).
ENV_VAR = "NERFBOT_KERNELS"
#: Its values; "numba" is the same as "auto": the kernels are CPU kernels, so no input they do
#: not already serve could be forced onto them.
MODES = ("auto", "numba", "torch")


def kernel_mode() -> str:
    """The value of ``NERFBOT_KERNELS`` ("auto" when unset or empty); ValueError for others."""
    mode = os.environ.get(ENV_VAR, "").strip().lower() or "auto"
    if mode not in MODES:
        raise ValueError(f"{ENV_VAR} must be one of {', '.join(MODES)}; got {mode!r}")
    return mode


def use_kernels(*tensors: torch.Tensor, backend: str = "numba",
                dtype: torch.dtype | None = torch.float32) -> bool:
    """Whether the numba kernels (True) or the plain-torch twins (False) serve an op.

    Args:
        tensors: the op's inputs: every one must be on the CPU, and every floating-point one
            of ``dtype`` (None: any dtype, for kernels that convert their inputs).
        backend: the implementation a config asks for: "numba" (the default: kernels where
            they apply) or "torch" (always the twins).
    Returns:
        False when ``NERFBOT_KERNELS=torch`` or ``backend`` is "torch" or an input does not
        fit; True otherwise.
    """
    if backend != "numba" or kernel_mode() == "torch":
        return False
    return all(t.device.type == "cpu"
               and (dtype is None or not t.is_floating_point() or t.dtype == dtype)
               for t in tensors)
