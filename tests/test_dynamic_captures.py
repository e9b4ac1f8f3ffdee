"""sims captures over time (dynamic scene: physics rollout, monocular / multi-view rigs) and over
joint configurations (articulated cabinet), on real MuJoCo renders at 32x32 with a few frames."""

from __future__ import annotations

import argparse
import json

import mujoco
import numpy as np
import pytest

import sims  # noqa: F401  (selects the GL backend before mujoco is imported)
from nerfbot.data import load_dataset
from nerfbot.ops.cameras import look_at, spherical_eye
from sims.articulated import capture_articulated, config_schedule
from sims.camera import CaptureCamera
from sims.cli import add_capture_arguments, run_capture
from sims.dynamic import capture_dynamic, held_out_steps
from sims.joints import set_joints
from sims.rollout import joint_motion, rollout
from sims.scene import builtin_scenes, load_capture_model
from sims.sequence import capture_kind, fixed_ring, sequence_rig, spiral_path

SIZE = 32
FREE_OBJECTS = ("ball", "crate", "can")
TABLE_TOP_Z = 0.75


def parse(*argv: str) -> argparse.Namespace:
    return add_capture_arguments(argparse.ArgumentParser()).parse_args(list(argv))


def transforms(out) -> dict:
    return json.loads((out / "transforms.json").read_text())


@pytest.fixture(scope="module")
def mono(tmp_path_factory):
    """Monocular capture of the dynamic scene: 12 time steps, steps 2, 6, 10 held out."""
    rig = sequence_rig("dynamic", "monocular", size=SIZE)
    out = capture_dynamic("dynamic", rig, tmp_path_factory.mktemp("dyn") / "mono", frames=12,
                          test_every=4, progress=False)
    return out, transforms(out)


@pytest.fixture(scope="module")
def multi(tmp_path_factory):
    """Multi-view capture through the CLI (Blender format): 6 time steps x 3 cameras."""
    out = tmp_path_factory.mktemp("dyn") / "multi"
    run_capture(parse("--scene", "dynamic", "--rig", "multiview", "--views-per-frame", "3",
                      "--frames", "6", "--test-every", "4", "--size", str(SIZE),
                      "--format", "blender", "--out", str(out), "--no-progress"))
    return out


@pytest.fixture(scope="module")
def cabinet(tmp_path_factory):
    """Articulated capture through the CLI: 4 train + 4 test configurations x 2 views."""
    out = tmp_path_factory.mktemp("art") / "cabinet"
    run_capture(parse("--scene", "articulated", "--configs", "4", "--test-configs", "4",
                      "--views-per-frame", "2", "--size", str(SIZE), "--out", str(out),
                      "--no-progress"))
    return out, transforms(out)


# ------------------------------------------------------------------------------ scenes, rollout

def test_scenes_declare_their_capture_kind():
    assert {"dynamic", "articulated", "tabletop"} <= set(builtin_scenes())
    kinds = {name: capture_kind(load_capture_model(name)[0])
             for name in ("tabletop", "dynamic", "articulated")}
    assert kinds == {"tabletop": "static", "dynamic": "dynamic", "articulated": "articulated"}
    model = load_capture_model("dynamic")[0]
    head = model.vis.headlight
    assert not np.any(head.diffuse) and not np.any(head.specular)  # view-independent shading


def test_rollout_is_deterministic_and_things_move():
    model, data = load_capture_model("dynamic")
    first = rollout(model, data, 2.5, 11)
    again = rollout(model, mujoco.MjData(model), 2.5, 11)
    assert np.array_equal(first.qpos, again.qpos) and np.array_equal(first.time, again.time)
    assert first.time[0] == 0.0 and first.time[-1] == 1.0 and np.all(np.diff(first.time) > 0)
    assert first.duration_s == pytest.approx(2.5)

    for name in FREE_OBJECTS:
        adr = model.jnt_qposadr[model.joint(f"{name}_free").id]
        path = first.qpos[:, adr:adr + 3]
        assert np.linalg.norm(path[-1] - path[0]) > 0.1, name         # fell / rolled > 10 cm
        x, y, z = path[-1]                                             # ... and stays on the table
        assert abs(x) < 0.5 and abs(y) < 0.35 and TABLE_TOP_Z < z < TABLE_TOP_Z + 0.1, name
    angle = first.qpos[:, model.jnt_qposadr[model.joint("pendulum_hinge").id]]
    assert np.ptp(angle) > 1.5                                         # swings both ways
    assert np.any(np.diff(np.sign(angle)) != 0)
    motion = joint_motion(model, first.qpos)
    assert min(motion.values()) > 0.1


def test_held_out_schedule():
    assert held_out_steps(12, 4) == [2, 6, 10]
    assert held_out_steps(100, 8)[:3] == [4, 12, 20] and len(held_out_steps(100, 8)) == 12
    assert held_out_steps(12, 0) == []
    with pytest.raises(ValueError, match="test_every"):
        held_out_steps(12, 1)


def test_rig_paths_are_smooth_and_fixed():
    rig = sequence_rig("dynamic", "monocular", size=SIZE)
    eyes = np.array([p[:3, 3] for p in spiral_path(rig, 100)])
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1)
    assert steps.max() < 0.5 and steps.min() > 0.01               # moves, smoothly
    assert np.allclose(np.linalg.norm(eyes - rig.target, axis=1), rig.radius)
    ring = fixed_ring(sequence_rig("dynamic", "multiview", views_per_step=4, size=SIZE))
    assert len(ring) == 4 and len({tuple(np.round(p[:3, 3], 6)) for p in ring}) == 4


# ------------------------------------------------------------------------------ dynamic captures

def test_monocular_capture_one_view_per_time_step(mono):
    out, doc = mono
    frames = doc["frames"]
    times = np.array([f["time"] for f in frames])
    assert len(frames) == 12
    assert times[0] == 0.0 and times[-1] == 1.0 and np.all(np.diff(times) > 0)
    test = [i for i, f in enumerate(frames) if f["file_path"] in doc["test_filenames"]]
    assert test == [2, 6, 10] and len(doc["train_filenames"]) == 9
    train_times = {f["time"] for f in frames if f["file_path"] in doc["train_filenames"]}
    assert not train_times & {frames[i]["time"] for i in test}      # held-out times
    eyes = np.array([f["transform_matrix"] for f in frames])[:, :3, 3]
    for i in test:                                                   # new views too
        others = np.delete(eyes, test, axis=0)
        assert np.linalg.norm(others - eyes[i], axis=1).min() > 0.05

    scene = doc["scene"]
    assert scene["time_varying"] is True
    assert scene["moving_joints"] == ["pendulum_hinge", "ball_free", "crate_free", "can_free"]
    assert scene["joint_bodies"] == {"pendulum_hinge": ["pendulum"], "ball_free": ["ball"],
                                     "crate_free": ["crate"], "can_free": ["can"]}
    assert scene["joint_info"]["pendulum_hinge"]["type"] == "hinge"
    assert scene["capture"]["rig"] == "monocular" and scene["capture"]["test_steps"] == [2, 6, 10]

    states = np.load(out / "states.npz")
    assert np.array_equal(states["state_of_frame"], np.arange(12))
    assert np.allclose(states["time"], times)
    lo, hi = np.array(scene["bounds"])
    names = list(states["body_names"])
    centres = states["body_pos"][:, [names.index(n) for n in FREE_OBJECTS]]
    assert np.all(centres >= lo) and np.all(centres <= hi)       # bounds cover the whole rollout


def test_multiview_capture_k_views_per_time_step(multi):
    docs = {s: json.loads((multi / f"transforms_{s}.json").read_text()) for s in ("train", "test")}
    train, test = docs["train"]["frames"], docs["test"]["frames"]
    assert len(train) == 5 * 3 and len(test) == 3
    assert [f["time"] for f in test] == [pytest.approx(2 / 5)] * 3
    for frames in (train, test):
        for i in range(0, len(frames), 3):
            assert len({f["time"] for f in frames[i:i + 3]}) == 1
    poses = np.array([f["transform_matrix"] for f in train + test])
    assert all(np.allclose(poses[j], poses[j + 3 * s]) for j in range(3) for s in range(6))
    assert docs["train"]["scene"]["capture"]["views_per_frame"] == 3

    ds = load_dataset(multi)
    assert ds.times is not None and len(ds.times) == 18 and ds.joints is None
    assert sorted(ds.times[ds.splits["test"]].tolist()) == [pytest.approx(0.4)] * 3
    # Same camera, different times: the objects have moved in the image.
    first, last = ds.images[0].astype(int), ds.images[12].astype(int)
    assert np.abs(first - last).mean() > 2.0


def test_reader_loads_times_back(mono):
    out, doc = mono
    ds = load_dataset(out)
    assert ds.times.dtype == np.float32 and len(ds.times) == 12
    assert np.allclose(ds.times, [f["time"] for f in doc["frames"]])
    assert ds.splits["test"] == [2, 6, 10] and ds.manifest["time_varying"] is True


# ------------------------------------------------------------------------------ articulated

def test_articulated_capture_splits_configurations(cabinet):
    out, doc = cabinet
    scene = doc["scene"]
    assert scene["time_varying"] is False
    assert scene["moving_joints"] == ["door_hinge", "drawer_slide"]
    assert scene["joint_bodies"] == {"door_hinge": ["door"], "drawer_slide": ["drawer"]}
    info = scene["joint_info"]
    assert info["door_hinge"]["type"] == "hinge" and info["drawer_slide"]["type"] == "slide"
    assert info["door_hinge"]["range"] == pytest.approx([0.0, np.radians(110)])
    assert info["drawer_slide"]["range"] == pytest.approx([0.0, 0.25])

    frames = doc["frames"]
    assert len(frames) == (4 + 4) * 2 and all("time" not in f for f in frames)
    test_paths = set(doc["test_filenames"])
    outside = {name: 0 for name in info}
    for f in frames:
        for name, value in f["joints"].items():
            lo, hi = info[name]["range"]
            t_lo, t_hi = scene["joint_train_range"][name]
            assert t_lo == pytest.approx(lo + 0.15 * (hi - lo))
            assert t_hi == pytest.approx(lo + 0.85 * (hi - lo))
            assert lo <= value <= hi
            if f["file_path"] not in test_paths:
                assert t_lo <= value <= t_hi, (name, value)
            elif value < t_lo - 0.1 * (hi - lo) or value > t_hi + 0.1 * (hi - lo):
                outside[name] += 1
    assert all(n >= 1 for n in outside.values()), outside   # every joint extrapolated somewhere
    test_configs = {tuple(f["joints"].values()) for f in frames if f["file_path"] in test_paths}
    train_configs = {tuple(f["joints"].values()) for f in frames
                     if f["file_path"] not in test_paths}
    assert len(test_configs) == 4 and not test_configs & train_configs
    assert sum(bool(t["outside_train_range"]) for t in scene["capture"]["test"]) == 2

    ds = load_dataset(out)
    assert ds.times is None and len(ds.joints) == 16
    assert ds.joints[0] == pytest.approx(frames[0]["joints"])
    assert len(ds.splits["test"]) == 8


def test_schedule_margin_and_validation():
    model = load_capture_model("articulated")[0]
    sched = config_schedule(model, ["door_hinge", "drawer_slide"], 32, 12, seed=5)
    span = sched.limits[:, 1] - sched.limits[:, 0]
    assert np.all(sched.train >= sched.train_range[:, 0])
    assert np.all(sched.train <= sched.train_range[:, 1])
    # Stratified: each tenth of each joint's training range holds some training configuration.
    frac = (sched.train - sched.train_range[:, 0]) / (sched.train_range[:, 1]
                                                      - sched.train_range[:, 0])
    assert all(len(set((frac[:, j] * 10).astype(int))) == 10 for j in range(2))
    for row, out in zip(sched.test, sched.test_outside):
        for j, name in enumerate(sched.joints):
            gap = max(sched.train_range[j, 0] - row[j], row[j] - sched.train_range[j, 1])
            assert (gap >= 0.1 * span[j] - 1e-12) == (name in out)
    assert sum(bool(o) for o in sched.test_outside) == 6
    with pytest.raises(ValueError, match="leaves less than"):
        config_schedule(model, ["door_hinge"], 4, 2, train_range=(0.05, 0.9))


def test_rendered_pixels_change_when_the_door_and_drawer_open():
    model, data = load_capture_model("articulated")
    target = (0.0, 0.05, 1.0)
    front = look_at(spherical_eye(target, 1.6, -90.0, 35.0), target)
    vase, block = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("vase", "block"))
    shots = {}
    with CaptureCamera(model, data, 48, 48, 30.0) as cam:
        for key, values in {"closed": {"door_hinge": 0.0, "drawer_slide": 0.0},
                            "open": {"door_hinge": np.radians(100), "drawer_slide": 0.25}}.items():
            data.qpos[:] = set_joints(model, model.qpos0, values)
            mujoco.mj_forward(model, data)
            shots[key] = cam.render(front)
    closed, opened = shots["closed"], shots["open"]
    assert np.abs(closed.rgb.astype(int) - opened.rgb.astype(int)).mean() > 5.0
    assert not np.isin([vase, block], closed.segmentation).any()   # hidden when closed
    assert np.isin([vase, block], opened.segmentation).all()       # revealed when open


def _quat_rotate(axis, angle):
    q = np.empty(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(axis, dtype=np.float64), float(angle))
    return q


def test_manifest_kinematics_reproduce_mujoco_body_poses(cabinet):
    out, doc = cabinet
    scene = doc["scene"]
    states = np.load(out / "states.npz")
    names = list(states["body_names"])
    for c, values in enumerate(states["joint_values"]):
        for j, joint in enumerate(states["joint_names"]):
            info = scene["joint_info"][str(joint)]
            rest = scene["body_rest_poses"][info["body"]]
            q = values[j] - info["qpos0"]
            pos, quat = np.array(rest["pos"]), np.array(rest["quat"])
            if info["type"] == "hinge":
                rot = _quat_rotate(info["axis"], q)
                moved = np.empty(3)
                mujoco.mju_rotVecQuat(moved, pos - info["anchor"], rot)
                pos = np.asarray(info["anchor"]) + moved
                out_quat = np.empty(4)
                mujoco.mju_mulQuat(out_quat, rot, quat)
                quat = out_quat
            else:
                pos = pos + np.asarray(info["axis"]) * q
            b = names.index(info["body"])
            assert np.allclose(pos, states["body_pos"][c, b], atol=1e-9)
            same = np.allclose(quat, states["body_quat"][c, b], atol=1e-9)
            assert same or np.allclose(-quat, states["body_quat"][c, b], atol=1e-9)


# ------------------------------------------------------------------------------ CLI

def test_cli_defaults_and_errors(tmp_path):
    from sims.cli import check_capture_options, sequence_rig_from_args

    args = parse("--scene", "dynamic", "--out", str(tmp_path / "d"))
    assert check_capture_options(args, "dynamic") == "monocular"
    rig = sequence_rig_from_args(args, "monocular")
    assert (rig.width, rig.height, rig.views_per_step) == (128, 128, 1)
    args = parse("--scene", "articulated", "--out", str(tmp_path / "a"))
    assert check_capture_options(args, "articulated") == "multiview"
    assert check_capture_options(parse("--out", "x"), "static") == "hemisphere"

    bad = [(("--scene", "tabletop", "--rig", "monocular"), "static"),
           (("--scene", "tabletop", "--frames", "5"), "static"),
           (("--scene", "dynamic", "--rig", "hemisphere"), "monocular or multiview"),
           (("--scene", "dynamic", "--configs", "5"), "--configs"),
           (("--scene", "articulated", "--frames", "5"), "--frames"),
           (("--scene", "dynamic", "--views", "5"), "--views"),
           (("--scene", "dynamic", "--rig", "monocular", "--views-per-frame", "3"), "multiview")]
    for argv, message in bad:
        with pytest.raises(ValueError, match=message):
            run_capture(parse(*argv, "--out", str(tmp_path / "x"), "--size", str(SIZE)))
    assert not (tmp_path / "x").exists()
    with pytest.raises(ValueError, match="not dynamic"):
        capture_dynamic("tabletop", sequence_rig("tabletop", size=SIZE), tmp_path / "y",
                        frames=3, progress=False)
    with pytest.raises(ValueError, match="not articulated"):
        capture_articulated("dynamic", sequence_rig("dynamic", "multiview", 2, size=SIZE),
                            tmp_path / "y", configs=2, test_configs=1, progress=False)
    assert not (tmp_path / "y").exists()
