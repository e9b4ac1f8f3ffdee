"""Plan and drive through a room with a map made from images, in MuJoCo physics.

``python -m tasks.navigate --scene room --scenes 3 --trials 10 --seed 0 --map nerf --pose gt``

For each of ``--scenes`` room seeds (``--seed`` on):

1. the room is captured from inside (posed RGB and a simulated depth sensor, the zoo's ``inside``
   rig) and ``ngp`` is trained on the images, unless cached runs exist;
2. a floor map is made for a cylindrical base (:mod:`tasks.nav_map`) from ``--map``:

   - ``nerf``: the field's density on a 3D grid over the room
     (:func:`nerfbot.query.density.density_grid`), thresholded;
   - ``sensor``: the depth sensor's readings of the training views fused into a TSDF (open3d);
   - ``gt``: the scene's true geometry;

3. ``--trials`` start/goal pairs are drawn where the base can stand on the true map, at least
   1.5 m apart (``NavTaskConfig.min_distance``); for each, A* on the map (inflated by the
   base's radius and a margin) gives the warm start, shortcuts shorten it and, on a field
   map, trajectory optimisation through the field's density (NeRF-Nav's collision cost)
   refines it;
4. the base drives the path in physics, steering by its true pose (``--pose gt``) or by poses
   estimated from its own camera every few control steps (``--pose inerf`` or ``wide``,
   :mod:`nerfbot.query.localise`, with the ground robot's planar pose model; an estimate
   farther than ``--gate`` from the pose predicted by the commanded velocities is rejected,
   :func:`tasks.nav_execute.within_gate`). Success: within 10 cm of the goal without any
   contact.

Glass (``--scene room_glass``) is an obstacle the depth sensor's map misses (its pulses pass
through); a field map counts faint density as obstacle at a low ``--threshold`` (Dex-NeRF's),
or at a second, lower ``--glass-threshold`` from ``--glass-clearance`` above the floor up
and ``--glass-halo`` away from dense surfaces, as far as the field holds the glass at all
(BENCHMARKS.md, section 9). Map records carry the share of the transparent obstacles' cells
the map blocks.

Outputs in ``--out``: ``log.json`` (every trial), ``summary.json`` and one top-down PNG per
trial in ``trials/`` (map, planned and driven paths, contacts).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional

import cv2
import mujoco
import numpy as np
import open3d as o3d
from scipy import ndimage
from tqdm import tqdm

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from nerfbot.app.cli import parse_option
from nerfbot.data import load_dataset
from nerfbot.data.writers import write_json_atomic
from nerfbot.query.density import (OccupancyVolume, default_obstacle_threshold, density_grid,
                                    grid_points)
from nerfbot.query.localise import InerfConfig, WideConfig, inerf, localise_wide
from nerfbot.train.checkpoints import CHECKPOINT
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer
from sims.camera import CaptureCamera
from sims.capture import capture, set_lighting
from sims.rigs import default_rig, make_test_rig, rig_poses
from sims.robot import (RobotConfig, add_robot, robot_ids, robot_pose, set_robot_pose)
from sims.scene import CAPTURE_CAMERA, resolve_scene
from sims.sensor import DepthSensorModel
from tasks.nav_execute import DriveConfig, DriveLog, drive
from tasks.nav_map import (FloorMap, RobotBody, floor_map_from_volume, map_agreement,
                           room_area, true_floor_map)
from tasks.nav_planner import (PlanningError, TrajectoryConfig, optimise_trajectory,
                               path_length, plan_grid_path, shortcut)

log = logging.getLogger(__name__)

MAPS = ("nerf", "sensor", "gt")
POSES = ("gt", "inerf", "wide")
#: A trial succeeds when the base ends within this distance (metres) of the goal, untouched.
GOAL_DISTANCE = 0.10


#: ``ngp`` options of a room's field. A room's plain walls and partitions are learnt as their
#: visual hulls, thick bands of density on both sides that close passages; the carving prior
#: (:attr:`~nerfbot.models.occupancy.OccupancyModelConfig.carving_weight`) thins them, and
#: near-camera gradient damping (``near_gradient_distance``, metres) keeps floaters from the
#: space beside the cameras, which stand among the content (BENCHMARKS.md, section 9).
NAV_FIELD_OPTIONS = {"carving_weight": 1e-4, "near_gradient_distance": 1}


@dataclass
class NavTaskConfig:
    """Settings of a navigation experiment (lengths in metres)."""

    scene: str = "room"
    scenes: int = 3
    trials: int = 10
    """Start/goal pairs per scene."""
    seed: int = 0
    map: str = "nerf"
    pose: str = "gt"
    capture_views: int = 400
    """Training views of a room: 150 leave a 7 x 5.6 m room sparse enough for the field to fit
    them with fog (BENCHMARKS.md, section 9)."""
    capture_robot_views: float = 0.0
    """Share of the training views taken by the robot's own camera (its height, pitch and field
    of view) at base poses drawn uniformly over the floor it can stand on, as a robot exploring
    the room would record them; the rest come from the room's ``inside`` rig (0.4-1.6 m high,
    0.3 m from obstacles). The robot's views are what localisation later sees, and the only
    ones closer to furniture than the rig's clearance (BENCHMARKS.md, section 9)."""
    capture_test_views: int = 10
    capture_size: int = 128
    train_steps: int = 2000
    method: str = "ngp"
    train_options: dict = field(default_factory=lambda: dict(NAV_FIELD_OPTIONS))
    """Field options of the training runs (``--option`` adds to or overrides
    :data:`NAV_FIELD_OPTIONS`)."""
    sensor_depth_weight: float = 0.0
    """Depth supervision of the training runs from the capture's simulated depth sensor
    (``nerfbot train --depth-weight W --depth-from sensor_depth``: mapping with an RGB-D
    camera); 0: images only."""
    map_cell: float = 0.05
    threshold: Optional[float] = None
    """Obstacle density threshold of a field map, 1/m (None:
    :func:`nerfbot.query.density.default_obstacle_threshold`)."""
    map_floor_clearance: float = 0.1
    """A field map ignores density this close to the floor (metres; the base's own clearance,
    :attr:`tasks.nav_map.RobotBody.floor_clearance`, if higher): a field's floor is a few
    centimetres thick, and its fuzz would block open floor (BENCHMARKS.md, section 9)."""
    glass_threshold: Optional[float] = None
    """A second, lower obstacle density of a field map (1/m; None: none), counted only from
    :attr:`glass_clearance` above the floor up: Dex-NeRF's low threshold, for glass that the
    field holds as faint density. A field's floor fades out over the first 10-15 cm above it,
    which such a threshold would count as obstacle everywhere; above that, free space in the
    room fields is clear (BENCHMARKS.md, section 9, "Glass partitions")."""
    glass_clearance: float = 0.2
    """Height above the floor (metres) from which :attr:`glass_threshold` counts."""
    glass_halo: float = 0.1
    """:attr:`glass_threshold` ignores cells within this distance (metres) of the cells the
    first threshold blocks: around a dense surface a field's density fades out over 5-15 cm,
    which a low threshold counts as a thicker obstacle (in rooms without glass, with 0.1 m
    the second threshold refused 1 of 60 pairs, without a halo 3 of 30; BENCHMARKS.md,
    section 9)."""
    margin: float = 0.03
    """Planning keeps the base this much farther from obstacles than its radius."""
    min_distance: float = 1.5
    robot: RobotConfig = RobotConfig()
    drive: DriveConfig = DriveConfig()
    trajectory: TrajectoryConfig = TrajectoryConfig()
    cache: Path = field(default_factory=lambda: Path.home() / ".cache" / "nerfbot" / "navigate")
    out: Path = Path("navigate_out")
    device: str = "cpu"
    progress: bool = True

    @property
    def body(self) -> RobotBody:
        return RobotBody(radius=self.robot.radius, height=self.robot.height)


# ------------------------------------------------------------------------------ data and field
def scene_folder(cfg: NavTaskConfig, seed: int) -> Path:
    robot = round(100 * cfg.capture_robot_views)
    views = f"{cfg.capture_views}v" + (f"-robot{robot}" if robot else "")
    return Path(cfg.cache) / f"{cfg.scene}-{seed}" / f"{cfg.capture_size}px-{views}"


def robot_camera_pose(robot: RobotConfig, pose) -> np.ndarray:
    """(4, 4) c2w (OpenGL) of the robot's camera when the base is at (x, y, yaw)."""
    x, y, yaw = (float(v) for v in pose)
    pitch = np.radians(robot.camera_pitch)
    forward = np.array([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch),
                        -np.sin(pitch)])
    up = np.array([np.cos(yaw) * np.sin(pitch), np.sin(yaw) * np.sin(pitch), np.cos(pitch)])
    c2w = np.eye(4)
    c2w[:3, 0] = np.cross(forward, up)
    c2w[:3, 1] = up
    c2w[:3, 2] = -forward
    c2w[:3, 3] = [x, y, robot.camera_height]
    return c2w


def free_base_poses(world: "World", cfg: NavTaskConfig, count: int, rng: np.random.Generator,
                    jitter: float = 0.0) -> list[np.ndarray]:
    """``count`` base poses (x, y, yaw) at cells of the true floor map the base fits on
    (``radius + margin`` from obstacles), each moved by up to ``jitter`` cells in x and y,
    yaw uniform; ValueError when no cell fits."""
    floor = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell)
    free = np.argwhere(floor.free_for(cfg.robot.radius + cfg.margin))
    if len(free) == 0:
        raise ValueError(f"no floor cell fits the robot (radius {cfg.robot.radius} m)")
    cells = free[rng.choice(len(free), size=count, replace=len(free) < count)]
    xy = floor.to_world(cells)
    if jitter:
        xy = xy + rng.uniform(-jitter, jitter, size=(count, 2)) * cfg.map_cell
    yaw = rng.uniform(-np.pi, np.pi, size=count)
    return [np.array([x, y, a]) for (x, y), a in zip(xy, yaw)]


def ensure_capture(cfg: NavTaskConfig, seed: int) -> Path:
    """The room's capture from inside (RGB, depth, segmentation, sensor depth), made if missing:
    :attr:`NavTaskConfig.capture_robot_views` of the training views from the robot's camera,
    the rest and the test views from the room's rig."""
    folder = scene_folder(cfg, seed)
    out = folder / "data"
    if (out / "transforms.json").exists():
        return out
    if not 0.0 <= cfg.capture_robot_views <= 1.0:
        raise ValueError(f"capture_robot_views must be in [0, 1], got {cfg.capture_robot_views}")
    name = f"{cfg.scene}:{seed}"
    rig = default_rig(name, count=cfg.capture_views, width=cfg.capture_size,
                      height=cfg.capture_size, seed=seed)
    test_rig = make_test_rig(rig, cfg.capture_test_views)
    robot = round(cfg.capture_robot_views * cfg.capture_views)
    if robot:
        if abs(rig.fov_deg - cfg.robot.camera_fovy) > 1e-6:
            raise ValueError(f"{name}: the room rig's field of view ({rig.fov_deg} deg) is not "
                             f"the robot camera's ({cfg.robot.camera_fovy} deg); a capture "
                             "holds one camera")
        from_rig = cfg.capture_views - robot
        train = rig_poses(replace(rig, count=from_rig)) if from_rig else []
        world = World(name, cfg)
        try:
            bases = free_base_poses(world, cfg, robot, np.random.default_rng([seed, 7919]),
                                    jitter=0.5)
        finally:
            world.close()
        train += [robot_camera_pose(cfg.robot, base) for base in bases]
        poses_file = folder / "capture_poses.json"
        write_json_atomic(poses_file, {"train": [p.tolist() for p in train],
                                       "test": [p.tolist() for p in rig_poses(test_rig)]})
        rig = replace(rig, kind="explicit", poses_file=poses_file, count=0)
        test_rig = make_test_rig(rig, cfg.capture_test_views)
    capture(name, rig, test_rig, out, progress=cfg.progress, sensor=DepthSensorModel(seed=seed))
    return out


def ensure_trained(cfg: NavTaskConfig, seed: int) -> Path:
    """The field trained ``train_steps`` steps on the capture (resumed if interrupted), in a
    folder named by every option given (not only those that differ from the method's current
    defaults, so a cached run never stands for other options after the defaults change)."""
    data = ensure_capture(cfg, seed)
    opts = "".join(f"-{k}={v}" for k, v in sorted(cfg.train_options.items()))
    if cfg.sensor_depth_weight > 0:
        opts += f"-sensor_depth_weight={cfg.sensor_depth_weight}"
    run = scene_folder(cfg, seed) / f"{cfg.method}-{cfg.train_steps}steps{opts}"
    done = run / "done.json"
    if done.exists():
        return run
    trainer = Trainer(load_dataset(data), run, TrainConfig(
        method=cfg.method, max_steps=cfg.train_steps, seed=seed, options=dict(cfg.train_options),
        depth_weight=cfg.sensor_depth_weight, depth_from="sensor_depth", device=cfg.device,
        progress=cfg.progress))
    if (run / CHECKPOINT).exists():
        trainer.load()
    write_json_atomic(done, trainer.train())
    return run


# ------------------------------------------------------------------------------ the world
class World:
    """The room with the base and a capture camera, statically lit as the captures are."""

    def __init__(self, scene: str, cfg: NavTaskConfig):
        spec = mujoco.MjSpec.from_file(str(resolve_scene(scene)))
        spec.worldbody.add_camera(name=CAPTURE_CAMERA, pos=[0, 0, 0], quat=[1, 0, 0, 0])
        add_robot(spec, cfg.robot)
        self.model = spec.compile()
        set_lighting(self.model)
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.ids = robot_ids(self.model)
        self.floor = tuple(i for i in range(self.model.ngeom)
                           if self.model.geom(i).name == "floor")
        self.robot = cfg.robot
        self.camera = CaptureCamera(self.model, self.data, cfg.capture_size, cfg.capture_size,
                                    cfg.robot.camera_fovy)
        k = self.camera.intrinsics
        self.intrinsics = (k.fx, k.fy, k.cx, k.cy)

    def reset(self, x: float, y: float, yaw: float) -> None:
        mujoco.mj_resetData(self.model, self.data)
        set_robot_pose(self.data, self.ids, x, y, yaw)
        mujoco.mj_forward(self.model, self.data)

    def camera_pose(self, pose) -> np.ndarray:
        """(4, 4) c2w (OpenGL) of the robot's camera when the base is at (x, y, yaw)."""
        return robot_camera_pose(self.robot, pose)

    def observe(self) -> np.ndarray:
        """The robot camera's RGB image now (H, W, 3) uint8."""
        return self.camera.render(self.camera_pose(robot_pose(self.data, self.ids))).rgb

    def close(self) -> None:
        self.camera.close()


def base_pose_from_camera(c2w: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of the base whose camera has pose ``c2w`` (the camera's heading)."""
    forward = -np.asarray(c2w)[:3, 2]
    return np.array([c2w[0, 3], c2w[1, 3], np.arctan2(forward[1], forward[0])])


# ------------------------------------------------------------------------------ maps
def map_grid(world: World, cfg: NavTaskConfig) -> tuple[np.ndarray, int]:
    """Bounds (2, 3) of the 3D grid a floor map is made from, the room from the floor to just
    above the base, each edge a whole number of ``map_cell`` (so the grid's cells are exactly
    ``map_cell`` on every axis), and its resolution along the longest edge."""
    xmin, ymin, xmax, ymax = room_area(world.model)
    counts = np.ceil(np.array([xmax - xmin, ymax - ymin, cfg.robot.height + cfg.map_cell])
                     / cfg.map_cell - 1e-9)
    lo = np.array([xmin, ymin, 0.0])
    return np.stack([lo, lo + counts * cfg.map_cell]), int(counts.max())


#: Where a field map tests each cell, in cells from its centre along x, y and z: the corners
#: of the cell's inner half (2 x 2 x 2 points). A blocked cell means an obstacle somewhere
#: in it (:meth:`FloorMap.free_for`, and the true map's rasterisation), so a cell is blocked
#: when the density reaches the threshold at any of them; the centre alone misses an
#: obstacle's edge that covers less than half a cell.
CELL_TESTS = (-0.25, 0.25)


def true_maps(world: World, cfg: NavTaskConfig) -> tuple[FloorMap, Optional[FloorMap]]:
    """The room's true floor map, and that of its transparent obstacles alone (None when it
    has none), on the same cells (:func:`tasks.nav_map.map_agreement`'s ``transparent``)."""
    truth = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell)
    glass = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell,
                           transparent_only=True)
    return truth, (glass if glass.blocked.any() else None)


def field_floor_map(model, world: World, cfg: NavTaskConfig) -> FloorMap:
    """Floor map of the field's density on a grid over the room (floor to the base's top),
    each cell tested at :data:`CELL_TESTS`: blocked where the density reaches ``threshold``
    from ``map_floor_clearance`` up, or ``glass_threshold`` from ``glass_clearance`` up
    farther than ``glass_halo`` from the cells the first threshold blocks."""
    bounds, resolution = map_grid(world, cfg)
    bands = [(default_obstacle_threshold(model) if cfg.threshold is None else cfg.threshold,
              cfg.map_floor_clearance)]
    if cfg.glass_threshold is not None:
        bands.append((cfg.glass_threshold, cfg.glass_clearance))
    for threshold, _ in bands:
        if not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"obstacle threshold must be finite and > 0 (1/m), got {threshold}")
    blocked = [None] * len(bands)
    for offset in itertools.product(CELL_TESTS, repeat=3):
        shifted = bounds + np.asarray(offset) * cfg.map_cell
        density, spacing = density_grid(model, shifted, resolution)
        for k, (threshold, clearance) in enumerate(bands):
            body = replace(cfg.body, floor_clearance=max(cfg.body.floor_clearance, clearance))
            volume = OccupancyVolume(density >= threshold, shifted[0], spacing, threshold)
            cells = floor_map_from_volume(volume, body).blocked
            blocked[k] = cells if blocked[k] is None else blocked[k] | cells
    dense = blocked[0]
    if len(bands) > 1:
        faint = blocked[1]
        if cfg.glass_halo > 0 and dense.any():
            faint &= ndimage.distance_transform_edt(~dense, sampling=cfg.map_cell) \
                > cfg.glass_halo + 1e-9
        dense = dense | faint
    return FloorMap(dense, bounds[0, :2], cfg.map_cell)


def sensor_floor_map(data: Path, world: World, cfg: NavTaskConfig) -> FloorMap:
    """Floor map of the depth sensor's training-view readings fused into a TSDF (open3d)."""
    ds = load_dataset(data)
    depths = []
    for i in ds.indices("train"):
        if i >= len(ds.sensor_depths) or ds.sensor_depths[i] is None:
            raise ValueError(f"{data}: view {i} has no sensor depth (capture with a sensor)")
        depths.append(ds.sensor_depths[i])
    return tsdf_floor_map(ds.cameras(list(ds.indices("train"))), depths, world, cfg)


def tsdf_floor_map(cams, depths: list, world: World, cfg: NavTaskConfig) -> FloorMap:
    """Floor map of z-depth images (each (H, W) metres, NaN = no reading) from cameras
    ``cams`` fused into a TSDF (open3d): the surface points of the fused volume mark occupied
    grid points."""
    bounds, resolution = map_grid(world, cfg)
    voxel = cfg.map_cell / 2
    edge = float((bounds[1] - bounds[0]).max()) + 2 * voxel
    # a cube over the room (open3d 0.20's ScalableTSDFVolume extracted no surface from these
    # 128x128 views); z from just below the floor
    tsdf = o3d.pipelines.integration.UniformTSDFVolume(
        length=edge, resolution=int(np.ceil(edge / voxel)), sdf_trunc=4 * voxel,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor,
        origin=(bounds[0] - voxel).astype(np.float64))
    flip = np.diag([1.0, -1.0, -1.0, 1.0])           # OpenGL camera -> OpenCV camera
    for i, depth in enumerate(depths):
        h, w = depth.shape
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, float(cams.fx[i]), float(cams.fy[i]),
                                                 float(cams.cx[i]) - 0.5, float(cams.cy[i]) - 0.5)
        d = np.nan_to_num(depth, nan=0.0, posinf=0.0).astype(np.float32)
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.zeros((h, w, 3), np.uint8)), o3d.geometry.Image(d),
            depth_scale=1.0, depth_trunc=20.0, convert_rgb_to_intensity=False)
        extrinsic = np.linalg.inv(cams.c2w[i].cpu().numpy().astype(float) @ flip)
        tsdf.integrate(rgbd, intr, extrinsic)
    points = np.asarray(tsdf.extract_point_cloud().points)
    shape, spacing = grid_points(bounds, resolution)
    occupied = np.zeros(tuple(shape), bool)
    idx = np.rint((points - bounds[0]) / spacing).astype(int)
    ok = np.all((idx >= 0) & (idx < shape), axis=1)
    occupied[tuple(idx[ok].T)] = True
    return floor_map_from_volume(OccupancyVolume(occupied, bounds[0], spacing, 1.0), cfg.body)


# ------------------------------------------------------------------------------ trials
def draw_pairs(gt_map: FloorMap, cfg: NavTaskConfig, seed: int) -> list[tuple[np.ndarray, ...]]:
    """``cfg.trials`` (start, goal) pairs of cells where the base stands on the true map with
    room to spare (radius + 2 margins), at least ``min_distance`` apart, seeded."""
    rng = np.random.default_rng(seed)
    free = np.argwhere(gt_map.free_for(cfg.robot.radius + 2 * cfg.margin))
    pairs = []
    for _ in range(10000):
        if len(pairs) == cfg.trials:
            break
        a, b = (gt_map.to_world(free[rng.integers(len(free))]) for _ in range(2))
        if np.linalg.norm(a - b) >= cfg.min_distance:
            yaw = float(rng.uniform(-np.pi, np.pi))
            pairs.append((a, b, yaw))
    return pairs


def plan(model, fmap: FloorMap, cfg: NavTaskConfig, start, goal) -> tuple[np.ndarray, dict]:
    """A* + shortcuts on ``fmap`` (the floor the robot covers at ``start`` counted free); with a
    field, trajectory optimisation through its density."""
    body = cfg.body
    fmap = fmap.cleared(start, body.radius + cfg.margin)   # the robot stands there
    # a goal counts as reached within GOAL_DISTANCE and the drive stops within its tolerance:
    # a goal the map will not let the robot stand on may move by the difference
    reach = max(GOAL_DISTANCE - cfg.drive.goal_tolerance, 0.0)
    path = plan_grid_path(fmap, body, start, goal, margin=cfg.margin, goal_reach=reach)
    path = shortcut(path, fmap, body.radius + cfg.margin)
    info = {}
    if model is not None:
        path, info = optimise_trajectory(model, path, body, fmap, cfg.trajectory,
                                         margin=cfg.margin)
    return path, info


def _pose_source(model, world: World, cfg: NavTaskConfig, seconds: list):
    if cfg.pose == "gt":
        return None

    def estimate(_model, _data, predicted):
        image = world.observe()
        guess = world.camera_pose(predicted)
        if cfg.pose == "inerf":
            est = inerf(model, image, world.intrinsics, guess, InerfConfig(planar=True))
        else:
            est = localise_wide(model, image, world.intrinsics, guess, WideConfig(planar=True))
        seconds.append(est.seconds)
        return base_pose_from_camera(est.c2w)

    return estimate


def trial_sheet(fmap: FloorMap, gt_map: FloorMap, planned: Optional[np.ndarray],
                drive_log: Optional[DriveLog], start, goal, path: Path, scale: int = 4) -> None:
    """Top-down PNG, x to the right and y up: true obstacles the map misses grey, obstacles on
    both dark red, the map's phantom obstacles light red; planned path blue, driven path green
    (the pose estimates steered by yellow), start green and goal magenta circles."""
    nx, ny = gt_map.shape
    img = np.full((nx, ny, 3), 255, np.uint8)
    img[gt_map.blocked] = (150, 150, 150)
    cells = gt_map.to_cell(fmap.to_world(np.argwhere(fmap.blocked)))
    cells = cells[gt_map.inside(cells)]
    both = gt_map.blocked[cells[:, 0], cells[:, 1]]
    img[cells[both, 0], cells[both, 1]] = (120, 40, 40)
    img[cells[~both, 0], cells[~both, 1]] = (240, 110, 110)
    img = np.ascontiguousarray(img.transpose(1, 0, 2)[::-1])          # rows: y, top = max y
    img = cv2.resize(img, (nx * scale, ny * scale), interpolation=cv2.INTER_NEAREST)

    def px(points):
        c = gt_map.to_cell(np.asarray(points)[:, :2])
        return np.stack([c[:, 0] * scale + scale // 2,
                         (ny - 1 - c[:, 1]) * scale + scale // 2], -1).astype(np.int32)

    if planned is not None:
        cv2.polylines(img, [px(planned)], False, (40, 90, 230), 2)
    if drive_log is not None and len(drive_log.poses):
        if len(drive_log.estimates):
            cv2.polylines(img, [px(drive_log.estimates)], False, (230, 200, 40), 1)
        cv2.polylines(img, [px(drive_log.poses)], False, (40, 170, 60), 2)
    r = max(int(0.18 / gt_map.cell * scale), 2)
    if start is not None:
        cv2.circle(img, tuple(int(v) for v in px([start])[0]), r, (40, 170, 60), 2)
    if goal is not None:
        cv2.circle(img, tuple(int(v) for v in px([goal])[0]), r, (230, 60, 200), 2)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))


def run_experiment(cfg: NavTaskConfig) -> dict:
    """Every scene and pair; returns the summary (also written to ``cfg.out``)."""
    if cfg.map not in MAPS:
        raise ValueError(f"--map must be one of {MAPS}, got {cfg.map!r}")
    if cfg.pose not in POSES:
        raise ValueError(f"--pose must be one of {POSES}, got {cfg.pose!r}")
    out = Path(cfg.out)
    records, maps = [], []
    for s in range(cfg.scenes):
        seed = cfg.seed + s
        name = f"{cfg.scene}:{seed}"
        data = ensure_capture(cfg, seed) if cfg.map == "sensor" else None
        model = None
        if cfg.map == "nerf" or cfg.pose != "gt":
            model, _ = load_model(ensure_trained(cfg, seed), cfg.device)
        world = World(name, cfg)
        try:
            gt_map, glass_map = true_maps(world, cfg)
            t0 = time.perf_counter()
            if cfg.map == "nerf":
                fmap = field_floor_map(model, world, cfg)
            elif cfg.map == "sensor":
                fmap = sensor_floor_map(data, world, cfg)
            else:
                fmap = gt_map
            map_seconds = time.perf_counter() - t0
            agreement = map_agreement(fmap, gt_map, cfg.robot.radius + cfg.margin, glass_map)
            maps.append({"scene": name, "map_seconds": map_seconds, **agreement})
            log.info("%s map of %s: IoU %.3f with the true map, phantom %.3f, missed %.3f, "
                     "standable kept %.3f, wrong %.3f", cfg.map, name, agreement["iou"],
                     agreement["phantom"], agreement["missed"], agreement["standable_kept"],
                     agreement["standable_wrong"])
            if "transparent_blocked" in agreement:
                log.info("%s map of %s blocks %.3f of the transparent obstacles' cells", cfg.map,
                         name, agreement["transparent_blocked"])
            trial_sheet(fmap, gt_map, None, None, None, None, out / f"map_{cfg.scene}-{seed}.png")
            pairs = draw_pairs(gt_map, cfg, seed)
            bar = tqdm(pairs, desc=f"scene {s + 1}/{cfg.scenes} ({name})", unit="trial",
                       disable=not cfg.progress)
            for k, (start, goal, yaw) in enumerate(bar):
                rec = {"scene": name, "trial": k, "start": start.tolist(), "goal": goal.tolist(),
                       "map": cfg.map, "pose": cfg.pose, "map_seconds": map_seconds}
                ref, _ = plan(None, gt_map, cfg, start, goal)
                rec["reference_length"] = path_length(ref)
                t0 = time.perf_counter()
                planned, drive_log = None, None
                try:
                    planned, info = plan(model if cfg.map == "nerf" else None, fmap, cfg,
                                         start, goal)
                    rec.update(info)
                except PlanningError as err:
                    rec.update(success=False, reason=f"planning: {err}")
                rec["planning_seconds"] = time.perf_counter() - t0
                if planned is not None:
                    rec["path_length"] = path_length(planned)
                    world.reset(start[0], start[1], yaw)
                    loc_seconds: list[float] = []
                    t0 = time.perf_counter()
                    drive_log = drive(world.model, world.data, world.ids, planned, cfg.drive,
                                      _pose_source(model, world, cfg, loc_seconds), world.floor)
                    final = robot_pose(world.data, world.ids)
                    error = float(np.linalg.norm(final[:2] - goal))
                    rec.update(
                        trial_seconds=time.perf_counter() - t0, sim_seconds=drive_log.seconds,
                        contacts=drive_log.contacts, goal_error=error,
                        estimates_rejected=drive_log.rejected,
                        localise_seconds=float(np.median(loc_seconds)) if loc_seconds else None,
                        **(drive_log.estimate_errors(cfg.drive.localise_every)
                           if cfg.pose != "gt" else {}),
                        success=bool(error <= GOAL_DISTANCE and not drive_log.contacts),
                        reason="" if error <= GOAL_DISTANCE and not drive_log.contacts else
                        ("contact with " + ", ".join(sorted(set(drive_log.contacts)))
                         if drive_log.contacts else f"stopped {error:.2f} m from the goal"))
                trial_sheet(fmap, gt_map, planned, drive_log, start, goal,
                            out / "trials" / f"{cfg.scene}-{seed}_{k:02d}.png")
                records.append(rec)
                bar.set_postfix(ok=sum(r["success"] for r in records), refresh=False)
                write_json_atomic(out / "log.json", {"config": _config_dict(cfg),
                                                     "maps": maps, "trials": records})
        finally:
            world.close()
    summary = {**summarize(records), "maps": maps}
    write_json_atomic(out / "summary.json", {"config": _config_dict(cfg), **summary})
    return summary


def summarize(records: list[dict]) -> dict:
    """Success rate, path length against the true-geometry planner's, planning and trial
    seconds (medians), contacts."""
    n = len(records)
    ok = [r for r in records if r["success"]]
    ratios = [r["path_length"] / r["reference_length"] for r in records
              if "path_length" in r and r["reference_length"] > 0]
    med = (lambda v: float(np.median(v)) if v else None)
    return {"trials": n, "success_rate": len(ok) / n if n else None,
            "collisions": sum(1 for r in records if r.get("contacts")),
            "planning_failures": sum(1 for r in records if r.get("reason", "").startswith("planning")),
            "path_length_ratio_median": med(ratios),
            "path_length_ratio_max": max(ratios) if ratios else None,
            "planning_seconds_median": med([r["planning_seconds"] for r in records]),
            "planning_seconds_max": max((r["planning_seconds"] for r in records), default=None),
            "trial_seconds_median": med([r["trial_seconds"] for r in records
                                         if "trial_seconds" in r]),
            "localise_seconds_median": med([r["localise_seconds"] for r in records
                                            if r.get("localise_seconds") is not None]),
            "estimate_error_m_median": med([r["estimate_error_m_median"] for r in records
                                            if "estimate_error_m_median" in r]),
            "estimate_error_m_max": max((r["estimate_error_m_max"] for r in records
                                         if "estimate_error_m_max" in r), default=None),
            "estimates_rejected": sum(r.get("estimates_rejected", 0) for r in records)}


def _config_dict(cfg: NavTaskConfig) -> dict:
    d = asdict(cfg)
    d["cache"], d["out"] = str(cfg.cache), str(cfg.out)
    return d


def format_summary(summary: dict) -> str:
    fmt = (lambda v, f: "-" if v is None else format(v, f))
    lines = [f"{'map of':<14} {'IoU':>6} {'phantom':>8} {'missed':>7} {'stand kept':>11} "
             f"{'stand wrong':>12} {'glass':>6} {'s':>6}"]
    for m in summary["maps"]:
        lines.append(f"{m['scene']:<14} {m['iou']:>6.3f} {m['phantom']:>8.3f} {m['missed']:>7.3f} "
                     f"{m['standable_kept']:>11.3f} {m['standable_wrong']:>12.3f} "
                     f"{fmt(m.get('transparent_blocked'), '.3f'):>6} {m['map_seconds']:>6.1f}")
    if not summary["trials"]:
        return "\n".join(lines)
    rows = [("trials", summary["trials"]), ("success rate", fmt(summary["success_rate"], ".0%")),
            ("with contacts", summary["collisions"]),
            ("planning failures", summary["planning_failures"]),
            ("path length / true-map planner (median, max)",
             f"{summary['path_length_ratio_median']:.3f}, {summary['path_length_ratio_max']:.3f}"
             if summary["path_length_ratio_median"] else "-"),
            ("planning s (median, max)",
             f"{fmt(summary['planning_seconds_median'], '.2f')}, "
             f"{fmt(summary['planning_seconds_max'], '.2f')}"),
            ("localisation s per estimate (median)",
             fmt(summary["localise_seconds_median"], ".2f")),
            ("estimate position error m (median, max)",
             f"{fmt(summary.get('estimate_error_m_median'), '.3f')}, "
             f"{fmt(summary.get('estimate_error_m_max'), '.3f')}"),
            ("estimates rejected by the gate", summary.get("estimates_rejected", 0))]
    return "\n".join(lines + [""] + [f"{k:<48} {v}" for k, v in rows])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tasks.navigate", description=__doc__.split(
        "\n\n")[0])
    parser.add_argument("--scene", default="room", help="room scene family (default room)")
    parser.add_argument("--scenes", type=int, default=3, help="room seeds, from --seed on")
    parser.add_argument("--trials", type=int, default=10,
                        help="start/goal pairs per room (0: measure the maps only)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--map", choices=MAPS, default="nerf")
    parser.add_argument("--pose", choices=POSES, default="gt")
    parser.add_argument("--train-steps", type=int, default=NavTaskConfig.train_steps)
    parser.add_argument("--capture-views", type=int, default=NavTaskConfig.capture_views)
    parser.add_argument("--capture-size", type=int, default=NavTaskConfig.capture_size)
    parser.add_argument("--capture-robot-views", type=float,
                        default=NavTaskConfig.capture_robot_views,
                        help="share of the training views taken by the robot's camera (0-1; "
                             "the rest from the room's rig)")
    parser.add_argument("--option", action="append", default=[], type=parse_option,
                        metavar="KEY=VALUE",
                        help="field option of the training runs (repeatable), added to "
                        + ", ".join(f"{k}={v}" for k, v in NAV_FIELD_OPTIONS.items()))
    parser.add_argument("--sensor-depth-weight", type=float, default=0.0, metavar="W",
                        help="train the fields with depth supervision from the capture's "
                             "simulated depth sensor, weight W (an RGB-D robot's map; default "
                             "0: images only)")
    parser.add_argument("--threshold", type=float, default=None,
                        help="obstacle density of a field map, 1/m")
    parser.add_argument("--glass-threshold", type=float, default=None,
                        help="a second, lower obstacle density of a field map (1/m), counted "
                             "from --glass-clearance above the floor up (Dex-NeRF's, for glass)")
    parser.add_argument("--glass-clearance", type=float, default=NavTaskConfig.glass_clearance,
                        help="height above the floor (metres) from which --glass-threshold "
                             "counts")
    parser.add_argument("--glass-halo", type=float, default=NavTaskConfig.glass_halo,
                        help="--glass-threshold ignores cells within this distance (metres) of "
                             "the obstacles of the first threshold")
    parser.add_argument("--gate", type=float, default=DriveConfig.gate_distance,
                        help="with estimated poses, reject an estimate this far (metres) from "
                             "the predicted pose (0: accept every estimate)")
    parser.add_argument("--floor-clearance", type=float, default=NavTaskConfig.map_floor_clearance,
                        help="a field map ignores density this close to the floor, metres")
    parser.add_argument("--cache", type=Path, default=None, help="capture/run cache folder")
    parser.add_argument("--out", type=Path, default=Path("navigate_out"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if args.trials < 0:
        parser.error("--trials must be at least 0 (0: measure the maps only)")
    if not args.gate >= 0:
        parser.error(f"--gate must be at least 0 metres, got {args.gate}")
    for name in ("scenes", "train_steps", "capture_views", "capture_size"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    if not 0.0 <= args.sensor_depth_weight < float("inf"):
        parser.error(f"--sensor-depth-weight must be at least 0, got {args.sensor_depth_weight}")
    for name in ("threshold", "glass_threshold"):
        value = getattr(args, name)
        if value is not None and not value > 0:
            parser.error(f"--{name.replace('_', '-')} must be above 0 /m, got {value}")
    if not args.glass_halo >= 0:
        parser.error(f"--glass-halo must be at least 0 m, got {args.glass_halo}")
    if not 0.0 <= args.glass_clearance < RobotConfig.height:
        parser.error(f"--glass-clearance must be in [0, {RobotConfig.height}) m (the base's "
                     f"height), got {args.glass_clearance}")
    if not 0.0 <= args.capture_robot_views <= 1.0:
        parser.error(f"--capture-robot-views must be in [0, 1], got {args.capture_robot_views}")
    cfg = NavTaskConfig(scene=args.scene, scenes=args.scenes, trials=args.trials, seed=args.seed,
                        map=args.map, pose=args.pose, train_steps=args.train_steps,
                        capture_views=args.capture_views, capture_size=args.capture_size,
                        capture_robot_views=args.capture_robot_views,
                        threshold=args.threshold, map_floor_clearance=args.floor_clearance,
                        glass_threshold=args.glass_threshold,
                        glass_clearance=args.glass_clearance, glass_halo=args.glass_halo,
                        out=args.out, device=args.device,
                        train_options={**NAV_FIELD_OPTIONS, **dict(args.option)},
                        sensor_depth_weight=args.sensor_depth_weight,
                        drive=replace(DriveConfig(), gate_distance=args.gate,
                                      gate_angle=DriveConfig.gate_angle if args.gate > 0 else 0.0),
                        progress=not args.no_progress)
    if args.cache is not None:
        cfg = replace(cfg, cache=args.cache)
    if args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out {args.out} is not empty: choose a new folder")
    try:
        summary = run_experiment(cfg)
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        parser.exit(2, f"{parser.prog}: error: {err}\n")
    print(json.dumps(summary) if args.json else format_summary(summary))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    raise SystemExit(main())
