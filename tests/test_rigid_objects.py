"""The ``rigid`` method: tracks of the moving bodies from a capture's segmentation, parts carried
along them, and a toy rollout whose moving objects it renders at held-out times."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.data import load_dataset
from nerfbot.data.conditioning import Conditioning, dataset_conditioning
from nerfbot.data.tracks import estimate_tracks, solve_track
from nerfbot.fields.rigid import RigidField, RigidFieldConfig, RigidPart
from nerfbot.ops.lie import so3_exp
from toy_rollout import capture_toy_rollout

AABB = [[-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]]


def _rays_at(points: np.ndarray, eyes: np.ndarray):
    d = points - eyes
    return eyes, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_a_track_is_triangulated_from_many_cameras_and_from_one_moving_camera():
    steps = np.linspace(0.0, 1.0, 21)
    truth = np.stack([0.5 * steps - 0.2, 0.1 * np.sin(3 * steps), 0.5 - 0.3 * steps ** 2], 1)
    rng = np.random.default_rng(0)
    # four cameras per step: each step triangulated, smoothing or not
    step_of_ray = np.repeat(np.arange(21), 4)
    eyes = rng.normal(size=(84, 3))
    eyes = 2.0 * eyes / np.linalg.norm(eyes, axis=1, keepdims=True)
    o, d = _rays_at(truth[step_of_ray], eyes)
    np.testing.assert_allclose(solve_track(steps, step_of_ray, o, d, smoothness=0.0), truth,
                               atol=1e-4)  # the anchor pulls by about 2e-5
    assert np.abs(solve_track(steps, step_of_ray, o, d) - truth).max() < 0.01
    # one camera per step, jumping between views: no step is triangulated alone, the
    # smoothness over steps resolves the depth along each ray
    one = np.arange(21)
    eyes1 = eyes[::4]
    o1, d1 = _rays_at(truth, eyes1)
    alone = solve_track(steps, one, o1, d1, smoothness=0.0)
    assert np.linalg.norm(alone - truth, axis=1).max() > 0.05
    smooth = solve_track(steps, one, o1, d1)
    assert np.median(np.linalg.norm(smooth - truth, axis=1)) < 0.02
    # steps that no ray sees are filled in between their neighbours
    seen = one[one != 10]
    filled = solve_track(steps, seen, o1[seen], d1[seen])
    assert np.linalg.norm(filled[10] - truth[10]) < 0.03


def _track(name="box", extent=0.1):
    return {"name": name, "geoms": [0], "times": [0.0, 0.5, 1.0],
            "centres": [[-0.4, 0.0, 0.5], [0.0, 0.0, 0.5], [0.4, 0.2, 0.5]], "extent": extent}


def test_a_part_moves_with_its_track_and_passes_gradients_to_its_poses():
    part = RigidPart(_track(), RigidFieldConfig(), geo_feat_dim=3, seed=0)
    t = torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0, 1.5])
    rot, centre = part.pose(t)
    torch.testing.assert_close(centre, torch.tensor(
        [[-0.4, 0.0, 0.5], [-0.2, 0.0, 0.5], [0.0, 0.0, 0.5], [0.2, 0.1, 0.5],
         [0.4, 0.2, 0.5], [0.4, 0.2, 0.5]]))
    torch.testing.assert_close(rot, torch.eye(3).expand(6, 3, 3))
    with torch.no_grad():
        part.rotations[1] = torch.tensor([0.0, 0.0, 0.5 * np.pi])
    # a quarter turn about z at t = 0.5: the body's +x points along the world's +y
    y = part.local(torch.tensor([[0.0, 0.1, 0.5]]), torch.tensor([0.5]))
    torch.testing.assert_close(y, torch.tensor([[1.0, 0.0, 0.0]]), atol=1e-6, rtol=0)
    # halfway to it, an eighth of a turn: the shortest turn between the steps' rotations
    rot = part.pose(torch.tensor([0.25]))[0][0]
    c = s = float(np.sqrt(0.5))
    torch.testing.assert_close(rot, torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
                               atol=1e-6, rtol=0)
    # the photometric gradient reaches the poses through the grid's interpolation
    with torch.no_grad():
        for g in part.grids:
            g.normal_()
    x = torch.tensor([[0.03, 0.02, 0.51], [-0.19, 0.01, 0.48]])
    sigma, _ = part(part.local(x, torch.tensor([0.5, 0.25])))
    sigma.sum().backward()
    for p in (part.centres, part.rotations):
        assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
    # t = 0.25 lies between the first two steps and t = 0.5 on the second: the last gets nothing
    assert (part.centres.grad[:2].abs().sum(1) > 0).all() and not part.centres.grad[2].any()


def test_rotation_increments_give_the_same_poses_and_train_earlier_turns_from_later_steps():
    """``rotation_increments``: a track's rotations become the first step's and the turns
    between steps, whose prefix products are the same poses; the image of the last step then
    trains every turn before it, where absolute rotations train that step's (and the step
    before it, through the interpolation's turn) alone."""
    times = np.linspace(0.0, 1.0, 7)
    rotations = np.stack([0.3 * times, np.zeros(7), 2.5 * times], 1)  # about a tilted axis
    track = {"name": "ball", "times": times.tolist(), "extent": 0.1,
             "centres": np.zeros((7, 3)).tolist(), "rotations": rotations.tolist()}
    absolute = RigidPart(track, RigidFieldConfig(), geo_feat_dim=3, seed=0)
    chained = RigidPart(track, RigidFieldConfig(rotation_increments=True), geo_feat_dim=3, seed=0)
    t = torch.tensor([0.0, 0.1, 0.5, 0.77, 1.0])
    torch.testing.assert_close(chained.step_rotations(), absolute.step_rotations(), atol=1e-6,
                               rtol=0)
    torch.testing.assert_close(chained.pose(t)[0], absolute.pose(t)[0], atol=1e-6, rtol=0)
    for part in (absolute, chained):
        with torch.no_grad():
            for g in part.grids:
                g.normal_()
        sigma, _ = part(part.local(torch.tensor([[0.03, 0.02, 0.01]]), torch.tensor([1.0])))
        sigma.sum().backward()
    # t = 1 is the last step, reached from the one before it by the turn between the two
    assert (absolute.rotations.grad[:-2] == 0).all() and absolute.rotations.grad[-1].any()
    assert (chained.rotations.grad.abs().sum(1) > 0).all()


def test_a_time_curriculum_grows_the_trained_steps_and_carries_each_bodys_turn_on():
    """``time_curriculum``: the latest training time moves from the first step to the last over
    that share of the budget; a step whose frames join starts from its body's last turn
    carried on once more, so a body spinning at a constant rate is followed before its frames
    train it."""
    times = np.linspace(0.0, 1.0, 5)
    track = {"name": "ball", "times": times.tolist(), "extent": 0.1,
             "centres": np.zeros((5, 3)).tolist()}
    cond = Conditioning("time", ("time",), ((0.0, 1.0),), object_tracks=[track])
    assert RigidField(AABB, cond).training_time_limit(0.0) is None  # off by default
    for increments in (False, True):
        field = RigidField(AABB, cond, rconfig=RigidFieldConfig(
            time_curriculum=0.5, rotation_increments=increments))
        part = field.parts[0]
        assert [field.training_time_limit(p) for p in (0.0, 0.125, 0.25)] == [0.0, 0.25, 0.5]
        assert field.training_time_limit(0.5) is None and field.training_time_limit(0.9) is None
        field.before_step(0, 0.125)  # steps 0 and 1: step 1 starts at step 0's rotation
        assert int(field.steps_joined[0]) == 2 and not part.rotations.any()
        spin = torch.tensor([0.1, -0.2, 0.3])  # step 1's rotation, as training found it
        with torch.no_grad():
            part.rotations[1] = spin
        field.before_step(1, 0.26)  # step 2 has joined, 3 and 4 not yet
        assert int(field.steps_joined[0]) == 3 and not part.rotations[3:].any()
        field.before_step(2, 0.5)  # every step
        assert int(field.steps_joined[0]) == 5
        expected = so3_exp(torch.outer(torch.arange(5.0), spin))  # a constant angular velocity
        torch.testing.assert_close(part.step_rotations(), expected, atol=1e-5, rtol=0)
        # a step that has joined is not restarted: training owns it
        with torch.no_grad():
            part.rotations[4] = 0.0
        field.before_step(3, 0.7)
        assert not part.rotations[4].any()
        # a share of the last turn: half of it, or none (the step before's rotation)
        for share, turns in ((0.5, 1.5), (0.0, 1.0)):
            with torch.no_grad():
                part.rotations[2:] = 0.0
                part.rotations[1] = spin
            part.carry_on_rotation(2, share)
            torch.testing.assert_close(part.step_rotations()[2], so3_exp(turns * spin[None])[0],
                                       atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="time_curriculum"):
        RigidFieldConfig(time_curriculum=1.5)


def test_the_rigid_field_is_the_scene_away_from_its_parts_and_needs_tracks():
    cond = Conditioning("time", ("time",), ((0.0, 1.0),), object_tracks=[_track()])
    field = RigidField(AABB, cond)
    torch.manual_seed(0)
    x = torch.rand(4000, 3) * torch.tensor([2.0, 2.0, 1.0]) - torch.tensor([1.0, 1.0, 0.0])
    t = torch.rand(4000, 1)
    y = field.parts[0].local(x, t[:, 0])
    outside = ~(y.abs() < 1).all(-1)
    sigma, feat = field.density(x, t)
    sigma_s, feat_s = field.scene.density(x, t)
    torch.testing.assert_close(sigma[outside], sigma_s[outside])
    torch.testing.assert_close(feat[outside], feat_s[outside])
    # inside the part's cube its density adds to the scene's; occupancy sees the part at the
    # step whose centre is nearest, so the cube around every step's centre counts
    centre = torch.tensor([[0.0, 0.0, 0.5]])
    mid = torch.tensor([[0.5]])
    assert float(field.density(centre, mid)[0]) > float(field.scene.density(centre, mid)[0])
    occ = field.occupancy_density(torch.tensor([[-0.4, 0.0, 0.5], [0.4, 0.2, 0.5]]))
    assert (occ > field.scene.static.density(torch.tensor([[-0.4, 0.0, 0.5],
                                                           [0.4, 0.2, 0.5]]))[0]).all()
    # around the parts, a static ngp field instead of kplanes
    from nerfbot.fields.ngp import NGPField
    still = RigidField(AABB, cond, rconfig=RigidFieldConfig(moving_scene=False))
    assert isinstance(still.scene, NGPField)
    sigma2, _ = still.density(centre, mid)
    assert float(sigma2[0]) > float(still.scene.density(centre)[0])
    with pytest.raises(ValueError, match="moving_bodies"):
        RigidField(AABB, Conditioning("time", ("time",), ((0.0, 1.0),)))
    with pytest.raises(ValueError, match="part_resolution"):
        RigidFieldConfig(part_resolution=0)


@pytest.mark.slow(20)
def test_the_segmentation_tracks_the_dynamic_scenes_bodies(tmp_path):
    """A 4-camera rollout of the built-in dynamic scene: the tracks from its training masks
    follow MuJoCo's body positions (the free bodies' origins are their centres)."""
    from sims.dynamic import STATE_FILE, capture_dynamic
    from sims.sequence import sequence_rig

    rig = sequence_rig("dynamic", "multiview", 4, size=64)
    data = capture_dynamic("dynamic", rig, tmp_path / "data", frames=16, test_every=4,
                           progress=False)
    ds = load_dataset(data)
    tracks = {t["name"]: t for t in dataset_conditioning(ds).object_tracks}
    assert sorted(tracks) == ["ball", "can", "crate", "pendulum"]
    states = np.load(data / STATE_FILE)
    names = list(states["body_names"])
    train_times = np.unique(ds.times[ds.indices("train")])
    for name in ("ball", "can", "crate"):
        track = tracks[name]
        np.testing.assert_allclose(track["times"], train_times)
        steps = [int(np.argmin(np.abs(states["time"] - s))) for s in track["times"]]
        err = np.linalg.norm(np.array(track["centres"]) - states["body_pos"][steps,
                                                                              names.index(name)],
                             axis=1)
        # measured: medians 0.4-1.0 cm, at most 4.6 cm early in the fall, while the bodies
        # touch (64 x 64 images, 4 cameras)
        assert np.median(err) < 0.015 and err.max() < 0.06, (name, err)
        assert 0.05 < track["extent"] < 0.25
    # held-out frames never enter: masks of the ball over every held-out pixel change nothing
    ball = tracks["ball"]["geoms"][0]
    for i in ds.indices("test"):
        ds.segmentations[i] = np.full_like(ds.segmentations[i], ball)
    again = {t["name"]: t for t in estimate_tracks(ds)}
    assert all(again[n]["centres"] == tracks[n]["centres"] for n in tracks)


@pytest.mark.slow(90)
def test_rigid_moves_the_toy_rollouts_objects_between_captured_steps(tmp_path, toy_mjcf):
    """The toy rollout of ``test_dynamic_fields`` (a cube and a ball sliding at 0.6 m/s, 8
    cameras, 12 steps, every 4th held out), where ``kplanes`` scores 15.8 dB on the objects at
    the held-out steps after 1000 steps: it cross-fades between the training steps. The parts
    carry the objects there."""
    from nerfbot.eval.evaluation import evaluate
    from nerfbot.train.trainer import TrainConfig, Trainer
    ds = load_dataset(capture_toy_rollout(tmp_path, toy_mjcf))
    options = {"samples_per_batch": 8192, "grid_resolution": 32, "log2_hashmap_size": 15,
               "planes_time_res": 11}
    trainer = Trainer(ds, tmp_path / "rigid", TrainConfig(
        method="rigid", max_steps=400, seed=0, progress=False, options=options))
    trainer.train()
    trainer.model.eval()
    scores = {split: evaluate(trainer.model, ds, split, with_ssim=False)["psnr_objects"]
              for split in ("train", "test")}
    print(scores)
    # measured: 24.9 dB in the training frames, 24.4 at the held-out steps
    assert scores["test"] > 21.0
    assert scores["test"] > scores["train"] - 2.0


@pytest.mark.slow(10)
def test_training_with_a_time_curriculum_draws_rays_only_up_to_the_limit(tmp_path, toy_mjcf):
    from nerfbot.train.trainer import TrainConfig, Trainer
    ds = load_dataset(capture_toy_rollout(tmp_path, toy_mjcf))
    options = {"samples_per_batch": 2048, "grid_resolution": 32, "log2_hashmap_size": 12,
               "planes_time_res": 11, "time_curriculum": 0.5}
    trainer = Trainer(ds, tmp_path / "rigid", TrainConfig(
        method="rigid", max_steps=12, seed=0, progress=False, options=options))
    bank = trainer.bank
    times = bank.conds[:, 0]
    assert (times[1:] >= times[:-1]).all()  # the bank holds the frames in order of time
    seen = []
    trainer.train(on_step=lambda t: seen.append(
        (bank.time_limit, float(times[bank.last_slots].max()))))
    limits = [limit for limit, _ in seen]
    assert limits[0] == float(times[0]) and limits[6:] == [None] * 6
    assert all(a < b for a, b in zip(limits[:6], limits[1:6]))
    assert all(latest <= limit for limit, latest in seen[:6])
    assert seen[-1][1] > limits[5]  # then the later frames train too
    assert int(trainer.model.field.steps_joined[0]) == len(trainer.model.field.parts[0].times)
