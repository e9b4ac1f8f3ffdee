"""Work scheduling for numba's parallel loops over rays.

``prange`` hands each thread one contiguous range of iterations. The rays of an image come in
row order, and rows that see the scene cost many times more than rows of sky, so contiguous
halves leave one core waiting for the other (perf showed 18% of the FastNeRF cache renderer's
time spinning in the OpenMP barrier). Loops therefore visit blocks of rays in a scattered order.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Stride of the permutation (a prime, so it permutes any count it does not divide).
SPREAD = 7919


@njit(inline="always")
def scattered(i, n):
    """The block visited at iteration ``i`` of ``n``: a permutation of 0 .. n - 1 that spreads
    neighbouring blocks over the whole range. Signed: numba may type a ``prange`` index as
    uint64, and uint64 mixed with int64 arithmetic gives float64."""
    i = np.int64(i)
    n = np.int64(n)
    return (i * SPREAD) % n if n % SPREAD else i


@njit(inline="always")
def block_range(i, n_items, block):
    """(start, stop) of the ``block``-sized block of ``n_items`` visited at iteration ``i`` of
    ``ceil(n_items / block)``."""
    nb = (n_items + block - 1) // block
    b = scattered(i, nb)
    return b * block, min(n_items, (b + 1) * block)
