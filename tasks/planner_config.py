"""Parameters of the antipodal grasp planner (:mod:`tasks.planner`), shared with the scene-cloud
preparation (:mod:`tasks.scene_cloud`) and the gripper collision model
(:mod:`tasks.gripper_collision`), which therefore do not depend on the planner itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class PlannerConfig:
    """Planner parameters (lengths in metres, angles in degrees).

    Attributes:
        friction: Coulomb friction coefficient mu; friction-cone half-angle atan(mu).
        max_axis_tilt_deg: largest angle of the contact line (p -> q) from horizontal. The
            approach is always straight down, so the gripper's closing axis is the horizontal
            projection of the contact line.
        width_margin: open width = contact width + this (must be <= ``max_opening``).
        min_width: smallest contact width (rejects pinches of thin walls and noise pairs).
        smoothing_radius: contact points and normals are averaged over this radius (same side
            of the surface only) before the antipodal test, against depth noise (0 disables).
        table_clearance: smallest height of the fingertips above the table plane.
        min_object_height: points this far above the table belong to objects (raised to 4 sigma
            of the measured table noise when that is larger).
        approach_height: the finger and palm boxes sweep from this height above the grasp down
            to it; the swept volume must be free of points.
        num_samples: contact points p sampled per planning call (shared between clusters).
        pairs_per_sample: best opposite contacts q kept per sampled p.
        max_grasps: at most this many grasps returned (after near-duplicate suppression).
        nms_distance: grasps whose centres are closer than this and whose axes differ by less
            than ``nms_angle_deg`` are duplicates; the better one is kept.
        nms_angle_deg: see ``nms_distance``.
        voxel_size: voxel downsampling size (0 disables downsampling).
        normal_radius: neighbourhood radius for normal estimation.
        normal_max_nn: most neighbours used for a normal.
        outlier_neighbors: statistical outlier removal: neighbours per point (0 disables).
        outlier_std_ratio: statistical outlier removal: standard-deviation ratio.
        outlier_radius: radius outlier removal: points with fewer than ``outlier_min_points``
            points (themselves included) within this radius are dropped. Absolute, so it also
            removes isolated floaters right next to an object, which the statistical test
            misses when floaters are many (0 disables).
        outlier_min_points: see ``outlier_radius``.
        plane_distance: RANSAC inlier distance for the table plane.
        plane_iterations: RANSAC iterations.
        max_table_tilt_deg: largest angle of the table normal from +z.
        cluster_eps: DBSCAN neighbourhood radius (must be below the gap between objects).
        cluster_min_points: DBSCAN core-point neighbour count.
        min_cluster_points: smaller clusters are not grasped (they remain obstacles).
        ignore_unclustered: points above the table that DBSCAN calls noise (isolated floaters)
            are not obstacles. False treats every remaining point as an obstacle.
        center_scale: centring term falls linearly to 0 at this horizontal distance of the grasp
            centre from the cluster's vertical axis.
        height_scale: height term saturates at this clearance (fingertips over the table, palm
            over the object, contact below the object's local top).
        weight_friction, weight_center, weight_height, weight_width: score weights; the score is
            their weighted sum of terms in [0, 1], divided by the total weight. Terms: friction
            1 - (worst cone angle / cone half-angle)^2 (flat near 0 so normal noise of a few
            degrees matters little); centre 1 - offset / ``center_scale``; height
            min(fingertip-table gap, palm-object gap, object top above the contact) /
            ``height_scale``; width 1 - width / (max_opening - width_margin) (narrower grasps
            need less free space and keep the fingers near the object).
        seed: seed for the sampling and for open3d's RANSAC.
    """

    friction: float = 0.5
    max_axis_tilt_deg: float = 15.0
    width_margin: float = 0.02
    min_width: float = 0.01
    smoothing_radius: float = 0.005
    table_clearance: float = 0.005
    min_object_height: float = 0.005
    approach_height: float = 0.15
    num_samples: int = 400
    pairs_per_sample: int = 2
    max_grasps: int = 20
    nms_distance: float = 0.005
    nms_angle_deg: float = 10.0
    voxel_size: float = 0.003
    normal_radius: float = 0.01
    normal_max_nn: int = 30
    outlier_neighbors: int = 20
    outlier_std_ratio: float = 2.0
    outlier_radius: float = 0.008
    outlier_min_points: int = 4
    plane_distance: float = 0.004
    plane_iterations: int = 500
    max_table_tilt_deg: float = 10.0
    cluster_eps: float = 0.01
    cluster_min_points: int = 10
    min_cluster_points: int = 30
    ignore_unclustered: bool = True
    center_scale: float = 0.02
    height_scale: float = 0.02
    weight_friction: float = 0.35
    weight_center: float = 0.25
    weight_height: float = 0.2
    weight_width: float = 0.2
    seed: int = 0

    def __post_init__(self):
        positive = ("friction", "width_margin", "approach_height", "plane_distance",
                    "normal_radius", "cluster_eps", "center_scale", "height_scale")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("min_width", "table_clearance", "min_object_height", "voxel_size",
                     "nms_distance", "smoothing_radius", "outlier_radius", "weight_friction",
                     "weight_center", "weight_height", "weight_width"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"PlannerConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.max_axis_tilt_deg < 90 or not 0 <= self.max_table_tilt_deg < 90:
            raise ValueError("PlannerConfig tilt angles must be in [0, 90) degrees")
        if self.num_samples < 1 or self.pairs_per_sample < 1 or self.max_grasps < 1:
            raise ValueError("PlannerConfig num_samples, pairs_per_sample, max_grasps must be >= 1")
        if (self.weight_friction + self.weight_center + self.weight_height
                + self.weight_width) <= 0:
            raise ValueError("PlannerConfig score weights must not all be 0")

    @property
    def cone_half_angle(self) -> float:
        """Friction-cone half-angle atan(mu), radians."""
        return math.atan(self.friction)
