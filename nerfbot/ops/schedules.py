"""Learning-rate schedules.
"""

from __future__ import annotations

import logging


log = logging.getLogger(__name__)


def learning_rate(base: float, final_factor: float, progress: float) -> float:
    """Exponential decay from ``base`` to ``base * final_factor`` as progress goes 0 -> 1."""
    return base * final_factor ** min(max(progress, 0.0), 1.0)
