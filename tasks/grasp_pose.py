"""A parallel-jaw grasp in the world frame: what the planner proposes and the executor carries out."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Grasp:
    """One parallel-jaw grasp.

    Attributes:
        center: (3,) world point midway between the two finger contacts, metres. The gripper's
            tool-centre point (TCP) is placed here.
        axis: (3,) unit closing direction (from one finger pad to the other), world frame.
        approach: (3,) unit direction the gripper travels to reach ``center`` (default straight
            down, (0, 0, -1)); the fingers point along it. Orthogonal to ``axis``.
        width: distance between the two contact points, metres (object width along ``axis``).
        score: planner score, higher is better (0 for scripted grasps).
        info: free-form details (e.g. the score terms) for logs.
    """

    center: np.ndarray
    axis: np.ndarray
    width: float
    approach: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    score: float = 0.0
    info: dict = field(default_factory=dict)

    def rotation(self) -> np.ndarray:
        """(3, 3) gripper-to-world rotation: columns x = closing axis, y = z × x,
        z = -approach (from the fingertips up towards the palm)."""
        x = np.asarray(self.axis, dtype=np.float64)
        z = -np.asarray(self.approach, dtype=np.float64)
        x = x - z * float(x @ z)
        x /= np.linalg.norm(x)
        z /= np.linalg.norm(z)
        return np.stack([x, np.cross(z, x), z], axis=1)

    def to_dict(self) -> dict:
        return {"center": [float(v) for v in self.center], "axis": [float(v) for v in self.axis],
                "approach": [float(v) for v in self.approach], "width": float(self.width),
                "score": float(self.score), "info": self.info}
