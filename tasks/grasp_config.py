"""The settings of a grasping experiment and the record of one attempt."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional


#: Scene seed of the held-out scene on which the Dex-NeRF threshold is calibrated.
CALIBRATION_SEED = 1000


@dataclass
class GraspTaskConfig:
    """Settings of a grasping experiment (lengths in metres, angles in degrees)."""

    scene: str = "glassware"
    depth: str = "dexnerf"
    trials: int = 10
    seed: int = 0
    objects: str = "all"
    """"glass" (transparent objects), "opaque" (the look-alikes), "all", or comma-separated names."""
    threshold: Optional[float] = None
    """Dex-NeRF density threshold (1/m); None = calibrate on scene seed CALIBRATION_SEED."""
    target: Optional[str] = None
    """Grasp this object, found by the field's labels (a label head trained on each scene's
    run: :func:`tasks.grasp.ensure_labelled`): where it is comes from the occupied points the
    head gives its class (:func:`nerfbot.query.semantic.locate_class`), not from the
    simulator."""
    capture_views: int = 100
    capture_test_views: int = 10
    capture_size: int = 160
    train_steps: Optional[int] = 1000
    """Training budget in steps (deterministic, unaffected by machine load); None = seconds."""
    train_seconds: float = 300.0
    """Training budget in seconds when ``train_steps`` is None."""
    method: str = "ngp"
    train_options: dict = field(default_factory=lambda: {"distortion_weight": 0.01,
                                                         "supersample": 1,
                                                         "density_noise": 0.0,
                                                         "samples_per_batch": 1 << 17})
    """Method options of the training runs. The distortion loss (weight 0.01) halves the
    floaters a threshold catches at low densities.
    One ray per pixel: the grasp figures and the threshold calibration were measured so; ngp's
    2 x 2 rays per pixel (its default) cost 0.7 dB on the glazed look-alike scene.
    No density noise (ngp's default adds it): glass is a real veil that the
    threshold finds, and the calibration was measured without it. 2^17 samples per step
    (ngp's default is 2^15): the step budget was set with it."""
    query_views: int = 8
    query_size: int = 128
    query_fov: float = 40.0
    query_radius: float = 0.5
    query_elevation: float = 40.0
    crop_radius: float = 0.2
    """Points farther than this (horizontally) from the object are dropped before planning."""
    edge_jump: float = 0.02
    """Depth pixels at discontinuities above this fraction of the depth are dropped, for every
    source alike (flying pixels; a field's expected depth blends silhouettes)."""
    sensor_mode: str = "behind"
    cache: Path = field(default_factory=lambda: Path.home() / ".cache" / "nerfbot" / "grasp")
    out: Path = Path("grasp_out")
    device: str = "cpu"
    progress: bool = True


# ------------------------------------------------------------------------------ one attempt
@dataclass
class Attempt:
    """One grasp attempt on one object of one trial scene."""

    trial: int
    scene_seed: int
    object: str
    transparent: bool
    depth_source: str
    success: bool
    reason: str
    points: int
    grasp: Optional[dict] = None
    lift_height: Optional[float] = None
    seconds: float = 0.0
    located_error_m: Optional[float] = None
    """With a target found by labels: horizontal distance from where the labels put it to the
    body's true position, metres."""
