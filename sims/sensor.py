"""A simulated RGB-D depth sensor: what a structured-light / time-of-flight camera returns.

Such sensors do not see glass: the projected pattern or pulse passes through a transparent
surface (the sensor returns the depth of what lies behind it) or is scattered away (no return).
They also add depth-dependent noise, quantise, lose pixels at depth discontinuities and have a
working range. :class:`DepthSensorModel` turns MuJoCo's exact z-depth into such a reading.

Inputs are rendered by :class:`sims.camera.CaptureCamera`: the ground-truth depth (glass drawn,
so opaque to it) and the see-through depth (the same view with the transparent geoms hidden).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from nerfbot.ops.pointcloud import depth_discontinuities

TRANSPARENT_MODES = ("behind", "invalid")


@dataclass(frozen=True)
class DepthSensorModel:
    """Noise and failure model of a depth sensor. Lengths in metres.

    Attributes:
        transparent: "behind" (transparent surfaces return the depth of what lies behind them)
            or "invalid" (no return on transparent pixels).
        noise_base, noise_quadratic, noise_offset: axial noise standard deviation
            ``sigma(z) = noise_base + noise_quadratic * (z - noise_offset)**2`` (the Kinect
            model of Nguyen et al. 2012; defaults are its published values).
        quantization: depth step of the reading (0 = none).
        min_range, max_range: readings outside [min_range, max_range] are no return.
        edge_jump: relative depth jump between 4-neighbours (``|dz| > edge_jump * z``) at which
            both pixels are lost (mixed pixels at silhouettes); 0 disables.
        dropout: fraction of remaining pixels lost at random.
        seed: base seed of the noise; each view adds its index.
    """

    transparent: str = "behind"
    noise_base: float = 0.0012
    noise_quadratic: float = 0.0019
    noise_offset: float = 0.4
    quantization: float = 0.001
    min_range: float = 0.2
    max_range: float = 5.0
    edge_jump: float = 0.03
    dropout: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if self.transparent not in TRANSPARENT_MODES:
            raise ValueError(f"transparent must be one of {TRANSPARENT_MODES}, "
                             f"got {self.transparent!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")
        if not 0.0 <= self.min_range < self.max_range:
            raise ValueError(f"need 0 <= min_range < max_range, got {self.min_range}, "
                             f"{self.max_range}")

    def to_dict(self) -> dict:
        return asdict(self)

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Axial noise standard deviation (metres) at z-depth ``z`` (metres)."""
        return self.noise_base + self.noise_quadratic * (z - self.noise_offset) ** 2

    def read(self, see_through_depth: np.ndarray, transparent_mask: np.ndarray,
             view_index: int = 0) -> np.ndarray:
        """The sensor's z-depth reading of one view.

        Args:
            see_through_depth: (H, W) exact z-depth with transparent geoms hidden, metres
                (``inf`` = nothing).
            transparent_mask: (H, W) bool, pixels whose first surface is transparent.
            view_index: added to ``seed`` so views get independent noise.

        Returns:
            (H, W) float32 z-depth in metres; NaN where the sensor gives no return.
        """
        z = np.asarray(see_through_depth, dtype=np.float64).copy()
        mask = np.asarray(transparent_mask, dtype=bool)
        if z.shape != mask.shape:
            raise ValueError(f"depth {z.shape} and transparent mask {mask.shape} differ in shape")
        rng = np.random.default_rng([self.seed, view_index])
        lost = ~np.isfinite(z) | (z < self.min_range) | (z > self.max_range)
        if self.transparent == "invalid":
            lost |= mask
        if self.edge_jump > 0:
            lost |= depth_discontinuities(z, self.edge_jump)
        if self.dropout > 0:
            lost |= rng.random(z.shape) < self.dropout
        noisy = z + rng.standard_normal(z.shape) * self.sigma(np.where(lost, 1.0, z))
        if self.quantization > 0:
            noisy = np.round(noisy / self.quantization) * self.quantization
        noisy[lost] = np.nan
        return noisy.astype(np.float32)


def valid_fraction(sensor_depth: np.ndarray, pixels: np.ndarray | None = None) -> float:
    """Fraction of ``pixels`` (bool mask; default all) where the sensor returned a depth."""
    valid = np.isfinite(sensor_depth)
    if pixels is not None:
        valid = valid[pixels]
    return float(valid.mean()) if valid.size else float("nan")
