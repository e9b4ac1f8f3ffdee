"""Navigation pieces: density queries and NeRF-Nav's collision cost on a field of known
analytic density, A* and its errors, floor maps of the true room, and the MuJoCo base."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch
from torch import nn

from nerfbot.query.density import collision_cost, density_at, occupancy_volume
from sims.robot import (add_robot, command_velocity, robot_contacts, robot_ids, robot_pose,
                        set_robot_pose)
from sims.scene import resolve_scene
from tasks.nav_execute import DriveConfig, DriveLog, drive, within_gate
from tasks.nav_map import (FloorMap, RobotBody, floor_map_from_volume, map_agreement,
                           true_floor_map)
from tasks.nav_planner import (PlanningError, astar, optimise_trajectory, path_length,
                               plan_grid_path, shortcut)

BALL_CENTRE = (0.5, 0.0, 0.25)
BALL_RADIUS = 0.2
BALL_DENSITY = 100.0


class BallField(nn.Module):
    """Density BALL_DENSITY / m inside a ball, falling off smoothly over 5 cm, 0 elsewhere."""

    def density(self, x, cond=None):
        r = torch.linalg.vector_norm(x - torch.tensor(BALL_CENTRE, dtype=x.dtype), dim=-1)
        sigma = BALL_DENSITY * torch.sigmoid((BALL_RADIUS - r) / 0.01)
        return sigma, None


class BallModel(nn.Module):
    """The least a model offers density queries: bounds and a field (no occupancy grid)."""

    def __init__(self):
        super().__init__()
        self.register_buffer("aabb", torch.tensor([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]]))
        self.field = BallField()


def test_density_at_matches_the_field_and_keeps_gradients():
    model = BallModel()
    pts = torch.tensor([[0.5, 0.0, 0.25], [-0.5, 0.0, 0.25]], requires_grad=True)
    sigma = density_at(model, pts, grad=True, chunk=1)
    assert float(sigma[0]) == pytest.approx(BALL_DENSITY, rel=1e-6) and float(sigma[1]) < 1e-6
    sigma.sum().backward()
    assert torch.isfinite(pts.grad).all()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        density_at(model, torch.zeros(4, 2))


def test_collision_cost_is_zero_in_free_space_and_grows_inside_an_obstacle():
    model = BallModel()
    body = torch.as_tensor(RobotBody(radius=0.1, height=0.3).sample_points(), dtype=torch.float32)
    eye = torch.eye(3).expand(5, 3, 3)

    def cost_at(x):
        pos = torch.stack([torch.linspace(x - 0.2, x + 0.2, 5), torch.full((5,), -0.6),
                           torch.zeros(5)], -1) + torch.tensor([0.0, 0.6, 0.0])
        return collision_cost(model, body, pos, eye, dt=0.1)

    free_cost, free_hard = cost_at(-0.5)
    assert float(free_cost) < 1e-8 and float(free_hard.max()) < 1e-3
    grazing, _ = cost_at(0.15)
    inside, hard = cost_at(0.5)
    assert 0 < float(grazing) < float(inside)
    assert float(hard.max()) == pytest.approx(BALL_DENSITY, rel=1e-3)
    # faster through the same poses costs proportionally more (speed weighting)
    pos = torch.tensor([[0.4, 0.0, 0.0], [0.5, 0.0, 0.0], [0.6, 0.0, 0.0]])
    slow, _ = collision_cost(model, body, pos, torch.eye(3).expand(3, 3, 3), dt=1.0)
    fast, _ = collision_cost(model, body, pos, torch.eye(3).expand(3, 3, 3), dt=0.5)
    assert float(fast) == pytest.approx(2 * float(slow), rel=1e-5)


def test_collision_cost_gradient_matches_finite_differences():
    model = BallModel().double()
    body = torch.tensor([[0.0, 0.0, 0.1], [0.1, 0.0, 0.2], [0.0, 0.1, 0.3]], dtype=torch.float64)
    pos = torch.tensor([[0.2, 0.05, 0.0], [0.35, 0.0, 0.05], [0.5, -0.05, 0.0]],
                       dtype=torch.float64, requires_grad=True)
    rot_vec = torch.tensor([[0.0, 0.0, 0.1], [0.0, 0.0, 0.3], [0.05, 0.0, 0.5]],
                           dtype=torch.float64, requires_grad=True)

    def cost(p, w):
        rot = torch.linalg.matrix_exp(torch.stack([
            torch.stack([torch.zeros_like(w[:, 0]), -w[:, 2], w[:, 1]], -1),
            torch.stack([w[:, 2], torch.zeros_like(w[:, 0]), -w[:, 0]], -1),
            torch.stack([-w[:, 1], w[:, 0], torch.zeros_like(w[:, 0])], -1)], -2))
        return collision_cost(model, body, p, rot, dt=0.1)[0]

    assert float(cost(pos, rot_vec)) > 1.0        # the body is inside the ball's fall-off
    assert torch.autograd.gradcheck(cost, (pos, rot_vec), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_occupancy_volume_and_its_floor_map_see_the_ball():
    model = BallModel()
    vol = occupancy_volume(model, [[-1, -1, 0], [1, 1, 1]], 40, threshold=BALL_DENSITY / 2)
    pts = vol.points()[vol.occupied]
    assert np.all(np.linalg.norm(pts - BALL_CENTRE, axis=1) <= BALL_RADIUS + 0.03)
    assert vol.occupied[tuple(vol.index_of([BALL_CENTRE])[0])]
    dist = vol.distance()
    far = vol.index_of([[-0.5, 0.0, 0.25]])[0]
    assert dist[tuple(far)] == pytest.approx(1.0 - BALL_RADIUS, abs=0.06)
    fmap = floor_map_from_volume(vol, RobotBody(radius=0.1, height=0.6))
    blocked = fmap.to_world(np.argwhere(fmap.blocked))
    assert np.all(np.linalg.norm(blocked - BALL_CENTRE[:2], axis=1) <= BALL_RADIUS + 0.03)
    # a body shorter than the ball's bottom (0.05 m) passes under it
    low = floor_map_from_volume(vol, RobotBody(radius=0.1, height=0.04, floor_clearance=0.0))
    assert not low.blocked.any()


def test_astar_finds_the_known_shortest_path_around_a_wall():
    free = np.ones((7, 7), bool)
    free[3, 0:6] = False                      # a wall with a gap at j = 6
    path = astar(free, (0, 0), (6, 0))
    assert path[0] == (0, 0) and path[-1] == (6, 0)
    assert all(free[c] for c in path)
    assert (3, 6) in path
    steps = [math.hypot(a[0] - b[0], a[1] - b[1]) for a, b in zip(path, path[1:])]
    # through the gap without cutting the wall's corner: (0,0)-(2,6), (2,6)-(4,6), (4,6)-(6,0)
    assert sum(steps) == pytest.approx(4 * math.sqrt(2) + 10, abs=1e-9)
    free[3, 6] = False
    assert astar(free, (0, 0), (6, 0)) is None


def test_planner_refuses_a_start_inside_an_obstacle_and_offers_the_nearest_free_point():
    blocked = np.zeros((40, 40), bool)
    blocked[15:25, 15:25] = True
    fmap = FloorMap(blocked, (0.0, 0.0), 0.05)
    body = RobotBody(radius=0.1)
    with pytest.raises(PlanningError, match=r"start \(1\.00, 1\.00\) m is inside an obstacle.*"
                                            r"nearest point where it can is"):
        plan_grid_path(fmap, body, (1.0, 1.0), (0.2, 0.2))
    with pytest.raises(PlanningError, match="goal .* closer than the robot's radius"):
        plan_grid_path(fmap, body, (0.2, 0.2), (0.7, 1.0))
    with pytest.raises(PlanningError, match="outside the map"):
        plan_grid_path(fmap, body, (0.2, 0.2), (5.0, 1.0))
    path = plan_grid_path(fmap, body, (0.2, 0.2), (1.8, 1.8))
    clearance = fmap.clearance()
    cells = fmap.to_cell(path)
    assert np.all(clearance[cells[:, 0], cells[:, 1]] > body.radius)
    short = shortcut(path, fmap, body.radius)
    assert path_length(short) <= path_length(path) + 1e-9 and len(short) < len(path)


def test_clearing_the_robots_footprint_frees_its_start_and_nothing_else():
    blocked = np.zeros((40, 40), bool)
    blocked[20, 16] = True                    # a phantom speck 0.2 m from the start
    blocked[30:, :] = True                    # a wall 0.5 m beyond it
    fmap = FloorMap(blocked, (0.0, 0.0), 0.05)
    body = RobotBody(radius=0.3)
    with pytest.raises(PlanningError, match="start .* closer than the robot's radius"):
        plan_grid_path(fmap, body, (1.0, 1.0), (1.0, 0.4))
    cleared = fmap.cleared((1.0, 1.0), body.radius)
    assert cleared.free_for(body.radius)[20, 20]
    assert not cleared.blocked[20, 16] and cleared.blocked[30:, :].all()
    assert fmap.blocked[20, 16]               # a copy: the map itself is untouched
    path = plan_grid_path(cleared, body, (1.0, 1.0), (1.0, 0.4))
    assert np.allclose(path[[0, -1]], [[1.0, 1.0], [1.0, 0.4]])


def test_a_goal_within_reach_of_standable_floor_moves_there_and_no_further():
    blocked = np.zeros((40, 40), bool)
    blocked[:, 30:] = True                    # a wall at y >= 1.5 m
    fmap = FloorMap(blocked, (0.0, 0.0), 0.05)
    body = RobotBody(radius=0.2)              # stands where y <= 1.5 - 0.2 - 0.035
    with pytest.raises(PlanningError, match="goal .* closer than the robot's radius"):
        plan_grid_path(fmap, body, (1.0, 0.5), (1.0, 1.3))
    path = plan_grid_path(fmap, body, (1.0, 0.5), (1.0, 1.3), goal_reach=0.05)
    assert np.allclose(path[-1], [1.0, 1.25])  # the nearest standable cell centre, 5 cm away
    with pytest.raises(PlanningError, match="nearest point where it can is"):
        plan_grid_path(fmap, body, (1.0, 0.5), (1.0, 1.4), goal_reach=0.05)   # 15 cm away
    exact = plan_grid_path(fmap, body, (1.0, 0.5), (1.02, 1.0), goal_reach=0.05)
    assert np.allclose(exact[-1], [1.02, 1.0])  # a standable goal stays exact


def test_trajectory_optimisation_moves_a_path_off_a_faint_obstacle():
    """A straight path grazing a low-density ball (a field's fog, below the map's obstacle
    threshold) is pushed away from it, start and goal fixed."""
    model = BallModel()
    fmap = FloorMap(np.zeros((60, 40), bool), (-1.0, -1.0), 0.05)
    body = RobotBody(radius=0.1, height=0.4)
    start, goal = np.array([-0.5, 0.25]), np.array([1.4, 0.25])
    path, info = optimise_trajectory(model, np.stack([start, goal]), body, fmap)
    assert info["refined"] and info["collision_cost_after"] < 0.5 * info["collision_cost_before"]
    assert np.allclose(path[0], start) and np.allclose(path[-1], goal)
    assert np.max(path[:, 1]) > 0.27         # bent away from the ball at y = 0


@pytest.fixture(scope="module")
def room_with_robot():
    spec = mujoco.MjSpec.from_file(str(resolve_scene("room:0")))
    add_robot(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_true_floor_map_blocks_furniture_and_walls(room_with_robot):
    model, data = room_with_robot
    body = RobotBody()
    fmap = true_floor_map(model, data, body)
    assert fmap.blocked[0].all() and fmap.blocked[-1].all()         # walls
    assert fmap.blocked[:, 0].all() and fmap.blocked[:, -1].all()
    centre = model.geom("crate_0")
    cell = fmap.to_cell(data.geom_xpos[centre.id][:2])
    assert fmap.blocked[tuple(cell)]
    free = fmap.free_for(body.radius)
    assert 0.3 < free.mean() < 0.9


def test_a_scripted_drive_into_a_wall_registers_contacts(room_with_robot):
    model, data = room_with_robot
    ids = robot_ids(model)
    floor = (model.geom("floor").id,)
    mujoco.mj_resetData(model, data)
    w = float(model.numeric("nerfbot_room_size").data[0])
    fmap = true_floor_map(model, data, RobotBody())
    free = np.argwhere(fmap.free_for(0.2))
    start = fmap.to_world(free[np.argmax(fmap.to_world(free)[:, 0])])  # the free cell nearest the east wall
    set_robot_pose(data, ids, start[0], start[1], 0.0)
    mujoco.mj_forward(model, data)
    assert robot_contacts(model, data, ids, floor) == []
    command_velocity(data, ids, 0.5, 0.0, 0.0)
    touched = set()
    for _ in range(1500):
        mujoco.mj_step(model, data)
        touched |= set(robot_contacts(model, data, ids, floor))
    names = {model.geom(g).name for g in touched}
    assert "wall_east" in names
    x = robot_pose(data, ids)[0]
    assert x <= w / 2 - 0.18 + 0.01          # the wall stopped it


def test_the_base_follows_a_planned_path_without_contacts(room_with_robot):
    model, data = room_with_robot
    ids = robot_ids(model)
    body = RobotBody()
    fmap = true_floor_map(model, data, body)
    free = np.argwhere(fmap.free_for(body.radius + 0.03))
    rng = np.random.default_rng(3)
    for _ in range(2):
        a, b = (fmap.to_world(free[rng.integers(len(free))]) for _ in range(2))
        path = shortcut(plan_grid_path(fmap, body, a, b, margin=0.03), fmap, body.radius + 0.03)
        mujoco.mj_resetData(model, data)
        set_robot_pose(data, ids, a[0], a[1], 0.0)
        mujoco.mj_forward(model, data)
        log = drive(model, data, ids, path, floor_geoms=(model.geom("floor").id,))
        assert log.reached and not log.contacts, (a, b, log.contacts)
        assert np.linalg.norm(robot_pose(data, ids)[:2] - b) < 0.1


def test_map_agreement_counts_phantoms_misses_and_standable_cells():
    truth = np.zeros((20, 20), bool)
    truth[8:12, 8:12] = True                      # a 4x4 obstacle
    found = truth.copy()
    found[8, 8] = False                            # one cell missed
    found[2, 2] = True                             # one phantom speck
    t = FloorMap(truth, (0.0, 0.0), 0.1)
    same = map_agreement(t, t, 0.15)
    assert same["iou"] == 1.0 and same["phantom"] == 0.0 and same["missed"] == 0.0
    assert same["standable_kept"] == 1.0 and same["standable_wrong"] == 0.0
    a = map_agreement(FloorMap(found, (0.0, 0.0), 0.1), t, 0.15)
    assert a["iou"] == pytest.approx(15 / 17)
    assert a["phantom"] == pytest.approx(1 / 384) and a["missed"] == pytest.approx(1 / 16)
    assert a["standable_kept"] < 1.0               # the speck blocks the cells around it
    # a map on a shifted grid is read at the true map's cell centres; beyond it counts blocked
    shifted = map_agreement(FloorMap(truth[2:], (0.2, 0.0), 0.1), t, 0.15)
    assert shifted["missed"] == 0.0 and shifted["phantom"] == pytest.approx(40 / 384)


def test_sensor_map_of_a_small_capture_finds_the_walls_and_furniture(tmp_path):
    """The depth sensor's readings of 60 inside views (64x64) fused into a TSDF: a map that
    agrees with the true one (the sensor sees surfaces, so obstacles' hidden insides are
    missed: IoU well below 1, phantoms rare)."""
    from sims.capture import capture
    from sims.rigs import default_rig, make_test_rig
    from sims.sensor import DepthSensorModel
    from tasks.navigate import NavTaskConfig, World, sensor_floor_map

    rig = default_rig("room:0", count=60, width=64, height=64, seed=0)
    capture("room:0", rig, make_test_rig(rig, 1), tmp_path / "data", progress=False,
            sensor=DepthSensorModel(seed=0))
    cfg = NavTaskConfig(capture_size=64, progress=False)
    world = World("room:0", cfg)
    try:
        truth = true_floor_map(world.model, world.data, cfg.body, cfg.map_cell)
        agreement = map_agreement(sensor_floor_map(tmp_path / "data", world, cfg), truth,
                                  cfg.robot.radius + cfg.margin)
    finally:
        world.close()
    # measured: IoU 0.44, phantom 0.03, standable kept 0.94 (a fusion that extracts no surface
    # leaves only the room's edges: IoU under 0.2)
    assert agreement["iou"] > 0.35 and agreement["phantom"] < 0.05, agreement
    assert agreement["standable_kept"] > 0.85, agreement


class PaneField(nn.Module):
    """A room-sized field: a faint pane (0.8 / m, as a field holds glass) across x = 0.5 m,
    10 cm thick and floor to ceiling; a dense wall (100 / m) across x = -1 m, 10 cm thick,
    with a faint fringe (0.8 / m) 8 cm deep on both sides, as a trained field blurs a surface;
    and a floor whose density fades out 3 / m below z = 0.12 m, as a trained field's does."""

    def density(self, x, cond=None):
        pane = 0.8 * (torch.abs(x[..., 0] - 0.5) < 0.05).to(x.dtype)
        d = torch.abs(x[..., 0] + 1.0)
        wall = 100.0 * (d < 0.05).to(x.dtype) + 0.8 * ((d >= 0.05) & (d < 0.13)).to(x.dtype)
        fuzz = 3.0 * (x[..., 2] < 0.12).to(x.dtype)
        return pane + wall + fuzz, None


class PaneModel(nn.Module):
    """:class:`PaneField` with the bounds of a room (no occupancy grid)."""

    def __init__(self):
        super().__init__()
        self.register_buffer("aabb", torch.tensor([[-4.0, -4.0, -0.1], [4.0, 4.0, 3.0]]))
        self.field = PaneField()


def test_a_field_map_finds_a_faint_pane_above_the_floors_fuzz_and_off_dense_surfaces():
    from dataclasses import replace

    from tasks.navigate import NavTaskConfig, World, field_floor_map

    cfg = NavTaskConfig(capture_size=32, progress=False, threshold=10.0)
    world = World("room:0", cfg)
    try:
        model = PaneModel()
        plain = field_floor_map(model, world, cfg)
        glass = field_floor_map(model, world, replace(cfg, glass_threshold=0.5,
                                                      glass_halo=0.0))
        halo = field_floor_map(model, world, replace(cfg, glass_threshold=0.5))  # 0.1 m
        low = field_floor_map(model, world, replace(cfg, glass_threshold=0.5,
                                                    glass_clearance=0.05, glass_halo=0.0))
    finally:
        world.close()
    x = plain.to_world(np.stack([np.arange(plain.shape[0]), np.zeros(plain.shape[0], int)],
                                -1))[:, 0]
    on_pane, on_wall = np.abs(x - 0.5) < 0.04, np.abs(x + 1.0) < 0.04
    fringe = (np.abs(x + 1.0) > 0.08) & (np.abs(x + 1.0) < 0.12)
    assert plain.blocked[on_wall].all() and not plain.blocked[np.abs(x + 1.0) > 0.08].any()
    assert not plain.blocked[on_pane].any()        # 0.8 / m is below the threshold
    assert glass.blocked[on_pane].all()            # the band counts the pane at every y
    assert glass.blocked[fringe].all()             # and the wall's fringe
    assert not glass.blocked[(np.abs(x - 0.5) > 0.1) & (np.abs(x + 1.0) > 0.15)].any()
    assert halo.blocked[on_pane].all() and halo.blocked[on_wall].all()
    assert not halo.blocked[fringe].any()          # the fringe lies within 0.1 m of the wall
    assert low.blocked.all()                       # counted from 5 cm, the fuzz blocks it all


def test_estimate_errors_are_taken_where_the_estimates_were_made():
    poses = np.zeros((5, 3))
    estimates = poses.copy()
    estimates[0] = [0.03, 0.04, np.radians(2.0)]           # made at update 0: 5 cm, 2 degrees
    estimates[1] = [1.0, 0.0, 0.0]                         # a prediction, not an estimate
    estimates[2, 2] = np.radians(359.0)                    # made at update 2: 1 degree (wrapped)
    estimates[4, 0] = 0.01                                 # made at update 4: 1 cm
    errors = DriveLog(poses, estimates).estimate_errors(every=2)
    assert errors["estimate_error_m_median"] == pytest.approx(0.01)
    assert errors["estimate_error_m_max"] == pytest.approx(0.05)
    assert errors["estimate_error_deg_median"] == pytest.approx(1.0)
    assert DriveLog(np.zeros((0, 3)), np.zeros((0, 3))).estimate_errors(every=2) == {}


def test_map_agreement_counts_the_transparent_cells_blocked():
    truth = np.zeros((20, 20), bool)
    truth[:, 10] = True                            # a pane across the room
    glass = FloorMap(truth.copy(), (0.0, 0.0), 0.1)
    t = FloorMap(truth, (0.0, 0.0), 0.1)
    half = truth.copy()
    half[10:, 10] = False                          # a map that sees half of it
    a = map_agreement(FloorMap(half, (0.0, 0.0), 0.1), t, 0.15, glass)
    assert a["transparent_blocked"] == pytest.approx(0.5)
    assert "transparent_blocked" not in map_agreement(t, t, 0.15)
    with pytest.raises(ValueError, match="true map's cells"):
        map_agreement(t, t, 0.15, FloorMap(truth[1:], (0.0, 0.0), 0.1))


def test_room_glass_true_map_of_the_transparent_obstacles_is_its_panels():
    model = mujoco.MjSpec.from_file(str(resolve_scene("room_glass:0"))).compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    body = RobotBody()
    everything = true_floor_map(model, data, body)
    glass = true_floor_map(model, data, body, transparent_only=True)
    assert glass.shape == everything.shape
    assert glass.blocked.any() and not (glass.blocked & ~everything.blocked).any()
    assert not glass.blocked[0].any() and not glass.blocked[:, -1].any()      # no walls
    panel = tuple(glass.to_cell(data.geom_xpos[model.geom("partition_a_0").id][:2]))
    assert glass.blocked[panel] and everything.blocked[panel]
    adr = model.numeric_adr[model.numeric("nerfbot_passage").id]
    doorway = tuple(glass.to_cell(model.numeric_data[adr:adr + 4].reshape(2, 2).mean(0)))
    assert not glass.blocked[doorway] and not everything.blocked[doorway]
    plain = mujoco.MjSpec.from_file(str(resolve_scene("room:0"))).compile()
    plain_data = mujoco.MjData(plain)
    mujoco.mj_forward(plain, plain_data)
    assert not true_floor_map(plain, plain_data, body, transparent_only=True).blocked.any()


def test_the_gate_rejects_a_distant_estimate_and_gives_way_after_its_patience():
    cfg = DriveConfig(gate_distance=0.15, gate_angle=10.0, gate_patience=3)
    predicted = np.array([1.0, 2.0, np.radians(179.0)])
    assert within_gate(predicted + [0.1, 0.1, 0.0], predicted, cfg)
    assert within_gate([1.0, 2.0, np.radians(-175.0)], predicted, cfg)          # 6 deg, wrapped
    assert not within_gate(predicted + [0.2, 0.0, 0.0], predicted, cfg)
    assert not within_gate(predicted + [0.0, 0.0, np.radians(15.0)], predicted, cfg)
    assert within_gate(predicted + [5.0, 0.0, 3.0], predicted,
                       DriveConfig(gate_distance=0.0, gate_angle=0.0))


def _far_pair_path(model, data, seed: int):
    """A start and a goal on the room's standable floor more than 1.5 m apart (seeded), and
    the planned path between them on the true map."""
    body = RobotBody()
    fmap = true_floor_map(model, data, body)
    free = np.argwhere(fmap.free_for(body.radius + 0.03))
    rng = np.random.default_rng(seed)
    while True:
        a, b = (fmap.to_world(free[rng.integers(len(free))]) for _ in range(2))
        if np.linalg.norm(a - b) > 1.5:
            break
    return a, b, shortcut(plan_grid_path(fmap, body, a, b, margin=0.03), fmap,
                          body.radius + 0.03)


def test_a_drive_steered_by_estimates_ignores_one_wild_estimate(room_with_robot):
    """A pose source that is exact but for one estimate 1 m off: with the gate the drive
    rejects it and arrives without contact; without the gate the robot steers by it."""
    model, data = room_with_robot
    ids = robot_ids(model)
    a, b, path = _far_pair_path(model, data, seed=5)

    def run(config):
        calls = 0

        def source(m, d, predicted):
            nonlocal calls
            calls += 1
            pose = robot_pose(d, ids)
            return pose + [1.0, 0.0, 0.0] if calls == 2 else pose

        mujoco.mj_resetData(model, data)
        set_robot_pose(data, ids, a[0], a[1], 0.0)
        mujoco.mj_forward(model, data)
        return drive(model, data, ids, path, config, source,
                     floor_geoms=(model.geom("floor").id,))

    gated = run(DriveConfig())
    assert gated.rejected == 1 and gated.reached and not gated.contacts
    assert np.linalg.norm(robot_pose(data, ids)[:2] - b) < 0.1
    ungated = run(DriveConfig(gate_distance=0.0, gate_angle=0.0))
    assert ungated.rejected == 0
    second = DriveConfig().localise_every                 # the update of the wild estimate
    assert ungated.estimates[second, 0] - gated.estimates[second, 0] == pytest.approx(1.0, abs=0.05)


def test_dead_reckoning_follows_the_base_through_a_fast_turn(room_with_robot):
    """A pose source that returns the prediction alone (odometry): starting 180 degrees away
    from the path's heading, the commanded yaw rate exceeds the actuator's range, and the
    prediction, made with what the actuators apply, stays within 3 cm and 3 degrees."""
    model, data = room_with_robot
    ids = robot_ids(model)
    a, b, path = _far_pair_path(model, data, seed=7)
    heading = math.atan2(*(path[1] - path[0])[::-1])
    mujoco.mj_resetData(model, data)
    set_robot_pose(data, ids, a[0], a[1], heading + math.pi)
    mujoco.mj_forward(model, data)
    log = drive(model, data, ids, path, DriveConfig(), lambda m, d, predicted: predicted,
                floor_geoms=(model.geom("floor").id,))
    err = log.estimates - log.poses
    assert np.linalg.norm(err[:, :2], axis=1).max() < 0.03
    assert np.degrees(np.abs((err[:, 2] + np.pi) % (2 * np.pi) - np.pi)).max() < 3.0
