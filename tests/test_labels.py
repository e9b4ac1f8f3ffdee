"""Semantic labels: classes from the manifest, label maps, clicks, mean IoU, the label head's
rendering arithmetic, joint and post-hoc training on real captures, labels in renders, exports,
point queries and object location."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import open3d as o3d
import pytest
import torch

from nerfbot.app.cli import main
from nerfbot.data import load_dataset
from nerfbot.data.labels import (BACKGROUND, IGNORE, STRUCTURE, LabelClasses, click_maps,
                                 label_classes, label_map, mean_iou)
from nerfbot.methods import build_model
from nerfbot.models.labels import attach_label_head, label_loss, point_labels, render_labels
from nerfbot.ops.rendering import RenderOutput
from nerfbot.query.export import label_palette
from nerfbot.query.semantic import locate_class
from nerfbot.train.runs import load_model

pytestmark = pytest.mark.slow(135)

MANIFEST = {"geoms": {"0": "floor", "1": "box_a", "2": "leg", "3": "box_b"},
            "objects": ["box_a", "box_b"]}


def test_classes_from_the_manifest_and_label_maps():
    classes = label_classes(MANIFEST)
    assert classes.names == (BACKGROUND, "box_a", "box_b", STRUCTURE)
    assert classes.geom_class == {0: 3, 1: 1, 2: 3, 3: 2}
    assert LabelClasses.from_dict(json.loads(json.dumps(classes.to_dict()))) == classes
    seg = np.array([[-1, 0, 1], [2, 3, 7]])
    mask = np.array([[True, True, True], [True, False, True]])
    np.testing.assert_array_equal(label_map(seg, classes),
                                  [[0, 3, 1], [3, 2, IGNORE]])  # geom 7 is unknown
    np.testing.assert_array_equal(label_map(seg, classes, mask), [[0, 3, 1], [3, IGNORE, IGNORE]])
    rooms = label_classes({"geoms": {"0": "wall", "1": "sofa"}, "obstacles": {"sofa": []}})
    assert rooms.names == (BACKGROUND, "sofa", STRUCTURE)
    with pytest.raises(ValueError, match="no class 'cup'"):
        classes.index("cup")
    with pytest.raises(ValueError, match="scene manifest"):
        label_classes(None, "data/x")


def test_clicks_keep_n_pixels_per_class_seeded():
    rng = np.random.default_rng(0)
    maps = [rng.integers(-1, 3, size=(20, 30)).astype(np.int16) for _ in range(3)]
    maps[1][0, 0] = 3  # class 3: one pixel in all
    clicks = click_maps(maps, 5, seed=1)
    flat = np.concatenate([m.ravel() for m in clicks])
    assert [int((flat == c).sum()) for c in range(4)] == [5, 5, 5, 1]
    original = np.concatenate([m.ravel() for m in maps])
    kept = flat != IGNORE
    np.testing.assert_array_equal(flat[kept], original[kept])  # clicks carry their true class
    again = click_maps(maps, 5, seed=1)
    assert all(np.array_equal(a, b) for a, b in zip(clicks, again))
    with pytest.raises(ValueError):
        click_maps(maps, 0)


def test_mean_iou_by_hand():
    target = np.array([0, 0, 1, 1, 2, IGNORE])
    pred = np.array([0, 1, 1, 1, 2, 0])
    miou, iou = mean_iou(pred, target, 4)
    np.testing.assert_allclose(iou[:3], [1 / 2, 2 / 3, 1.0])
    assert np.isnan(iou[3])  # absent from both: not scored
    assert miou == pytest.approx((1 / 2 + 2 / 3 + 1) / 3)
    assert mean_iou(target, target, 4)[0] == 1.0


def _head_model():
    model = build_model("ngp", [[-1, -1, -1], [1, 1, 1]], options={"log2_hashmap_size": 12})
    attach_label_head(model, label_classes(MANIFEST), seed=0)
    return model


def test_rendered_labels_are_distributions_and_never_move_the_field():
    model = _head_model()
    m, rays = 7, 3
    x = torch.rand(m, 3) * 2 - 1
    sigma, feat = model.field.density(x)
    weights = torch.tensor([0.2, 0.3, 0.1, 0.5, 0.4, 0.0, 0.0], requires_grad=True)
    ray_indices = torch.tensor([0, 0, 0, 1, 1, 1, 1])  # ray 2 has no sample
    opacity = torch.zeros(rays).index_add(0, ray_indices, weights.detach())
    out = RenderOutput(rgb=torch.zeros(rays, 3), opacity=opacity, depth=opacity,
                       z_depth=opacity, median_depth=opacity, weights=weights, num_samples=m,
                       ray_indices=ray_indices, t_starts=torch.zeros(m), t_ends=torch.ones(m),
                       sigmas=sigma, positions=x, features=feat)
    probs = render_labels(model.label_head, out)
    assert probs.shape == (rays, 4)
    np.testing.assert_allclose(probs.sum(1).detach().numpy(), 1.0, atol=1e-6)
    head = model.label_head
    empty = torch.softmax(head.background_logits, 0)
    np.testing.assert_allclose(probs[2].detach().numpy(), empty.detach().numpy(), atol=1e-6)
    assert int(probs[2].argmax()) == 0  # an empty ray shows the background class
    # by hand: logits composited with the weights, the rest transmittance on the background's
    logits = head(x, feat)
    ray0 = (weights[:3, None] * logits[:3]).sum(0) + (1 - 0.6) * head.background_logits
    np.testing.assert_allclose(probs[0].detach().numpy(),
                               torch.softmax(ray0, 0).detach().numpy(), atol=1e-5)
    sub = render_labels(model.label_head, out, slice(1, 3))
    np.testing.assert_allclose(sub.detach().numpy(), probs[1:].detach().numpy(), atol=1e-6)
    loss = label_loss(probs, torch.tensor([1, 2, IGNORE]))
    loss.backward()
    assert weights.grad is None  # the weights enter detached
    assert all(p.grad is None for p in model.field.parameters())  # so do the features
    assert all(p.grad is not None and torch.isfinite(p.grad).all()
               for p in model.label_head.parameters())
    nothing = label_loss(probs, torch.tensor([IGNORE] * 3))
    assert float(nothing.detach()) == 0.0 and nothing.requires_grad
    p = point_labels(model, x)
    np.testing.assert_allclose(p.sum(1).numpy(), 1.0, atol=1e-6)


def test_only_renderers_that_keep_features_take_a_head():
    model = build_model("mipnerf", [[-1, -1, -1], [1, 1, 1]])
    with pytest.raises(ValueError, match="cannot render labels"):
        attach_label_head(model, label_classes(MANIFEST))


@pytest.fixture(scope="module")
def runs(tiny_capture, tmp_path_factory):
    """A tiny tabletop trained 120 steps of 2^15 samples without labels and with
    ``--labels``."""
    data, _ = tiny_capture
    root = tmp_path_factory.mktemp("labels")
    for name, extra in (("plain", []), ("joint", ["--labels"])):
        assert main(["train", "--data", str(data), "--method", "ngp", "--max-steps", "120",
                     "--out", str(root / name), "--no-progress",
                     "--option", "log2_hashmap_size=14",
                     "--option", "samples_per_batch=32768"] + extra) == 0
    return data, root


@pytest.fixture(scope="module")
def labelled(runs, tmp_path_factory):
    """The plain run labelled by ``nerfbot label`` (200 head steps): (its folder, the
    command's JSON report)."""
    _, root = runs
    out = tmp_path_factory.mktemp("labelled") / "run"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        assert main(["label", str(root / "plain"), "--out", str(out), "--steps", "200",
                     "--no-progress"]) == 0
    return out, json.loads(stdout.getvalue())


def test_joint_labels_leave_the_field_unchanged_and_score(runs):
    _, root = runs
    plain = json.loads((root / "plain" / "metrics.json").read_text())
    joint = json.loads((root / "joint" / "metrics.json").read_text())
    assert joint["psnr"] == pytest.approx(plain["psnr"], abs=1e-6)
    assert "label_miou" not in plain
    # 120 steps of 2^15 samples at 32 px (observed: background 0.97, table 0.79, objects of
    # a pixel or two not yet, mIoU 0.20): the head learns the large classes first
    assert joint["label_iou"][BACKGROUND] > 0.9
    assert joint["label_iou"][STRUCTURE] > 0.5
    assert joint["label_miou"] > 0.15


def test_label_command_on_a_frozen_field_renders_and_exports(runs, labelled, tmp_path, capsys):
    data, root = runs
    out, report = labelled
    assert report["label_miou"] > 0.5
    assert json.loads((out / "labels.json").read_text())["classes"][0] == BACKGROUND
    # the field is the source run's: same colours
    src, _ = load_model(root / "plain")
    model, info = load_model(out)
    assert all(torch.equal(a, b) for a, b in zip(src.field.parameters(),
                                                 model.field.parameters()))
    assert main(["label", str(root / "plain"), "--out", str(root / "plain"),
                 "--no-progress"]) == 2
    assert "the run being labelled" in capsys.readouterr().err
    # renders: class images and indices beside rgb and depth
    frames = tmp_path / "frames"
    assert main(["render", str(out), "--path", "test", "--out", str(frames),
                 "--no-progress"]) == 0
    classes = np.load(frames / "labels_0000.npy")
    assert classes.shape == (32, 32) and classes.max() < len(report["classes"])
    assert main(["render", str(root / "plain"), "--path", "test", "--out",
                 str(tmp_path / "v.mp4"), "--what", "labels", "--no-progress"]) == 2
    assert "trained without labels" in capsys.readouterr().err
    # exports coloured by class
    cloud_path = tmp_path / "c.ply"
    assert main(["export", str(out), "pointcloud", "--what", "labels", "--out",
                 str(cloud_path), "--no-progress"]) == 0
    assert "coloured by class" in capsys.readouterr().out
    colours = np.asarray(o3d.io.read_point_cloud(str(cloud_path)).colors)
    palette = label_palette(len(report["classes"])) / 255.0
    distance = np.abs(colours[:, None, :] - palette[None]).max(-1).min(1)
    assert len(colours) and distance.max() < 1e-2  # every point wears a class colour


def test_the_labels_locate_an_object_where_it_is(runs, labelled):
    data, _ = runs
    model, _ = load_model(labelled[0])
    ds = load_dataset(data)
    name = "blue_can"
    gid = next(int(g) for g, n in ds.manifest["geoms"].items() if n == name)
    truth = []  # the object's pixels in the training views, at their true depth
    for i in ds.indices("train"):
        seg, z = ds.segmentations[i], ds.depths[i]
        v, u = np.nonzero(seg == gid)
        if not len(u):
            continue
        fx, fy, cx, cy = ds.intrinsics[i]
        cam = np.stack([(u + 0.5 - cx) / fx * z[v, u], -(v + 0.5 - cy) / fy * z[v, u],
                        -z[v, u], np.ones(len(u))])
        truth.append((ds.c2w[i] @ cam)[:3].T)
    truth = np.concatenate(truth)
    found = locate_class(model, name, threshold=5.0, resolution=96)
    assert len(found.points) > 0
    error = np.linalg.norm(found.centre[:2] - np.median(truth[:, :2], axis=0))
    assert error < 0.05, error  # within 5 cm horizontally
    with pytest.raises(ValueError, match="no class"):
        locate_class(model, "unicorn")


def test_questions_spread_every_click_over_the_first_half():
    from nerfbot.train.labelling import LabelTrainConfig, question_schedule

    config = LabelTrainConfig(steps=1000, clicks=20, click_rounds=8)
    for extra in (1, 7, 8, 173):
        schedule = question_schedule(config, extra)
        assert sum(schedule.values()) == extra
        assert len(schedule) == min(8, extra) and all(n >= 1 for n in schedule.values())
        assert min(schedule) >= 1 and max(schedule) <= 500
        assert max(schedule.values()) - min(schedule.values()) <= 1  # even rounds
    assert question_schedule(config, 0) == {}
    assert sum(question_schedule(LabelTrainConfig(steps=3, clicks=5), 9).values()) == 9
    assert question_schedule(LabelTrainConfig(steps=1, clicks=5), 9) == {0: 9}  # before it
    with pytest.raises(ValueError, match="click_choice"):
        LabelTrainConfig(clicks=5, click_choice="best").validate()
    with pytest.raises(ValueError, match="click_rounds"):
        LabelTrainConfig(clicks=5, click_rounds=0).validate()


def test_the_question_is_the_most_uncertain_free_pixels(runs):
    from nerfbot.data.labels import label_maps
    from nerfbot.data.pixels import PixelBank
    from nerfbot.train.labelling import LabelTrainConfig, train_label_head, uncertain_pixels

    data, root = runs
    ds = load_dataset(data)
    model, _ = load_model(root / "plain")
    train_label_head(model, ds, LabelTrainConfig(steps=40))  # a head that predicts a few classes
    classes = model.label_head.classes
    train = ds.indices("train")
    bank = PixelBank(ds, train, model.aabb.device)
    answers = torch.from_numpy(np.concatenate(
        [m.reshape(-1) for m in label_maps(ds, classes, train)]))
    bank.load_labels(click_maps(label_maps(ds, classes, train), 1, seed=0), sparse=True)
    answers[:100] = IGNORE  # pixels the user cannot answer are never asked for
    free = torch.nonzero((answers >= 0) & (bank.labels < 0)).squeeze(1)
    with torch.no_grad():
        probs = render_labels(model.label_head, model.render_rays(bank.centre_rays(free)))
    entropy = -(probs * probs.clamp_min(1e-12).log()).sum(-1)
    predicted = probs.argmax(-1)
    # every free pixel a candidate: the question takes each predicted class in turn, and from
    # each class its most uncertain pixels
    asked = uncertain_pixels(model, bank, answers, 50, len(bank), torch.Generator().manual_seed(0),
                             chunk=1000)
    assert len(asked) == 50 and len(set(asked.tolist())) == 50
    assert set(asked.tolist()) <= set(free.tolist())
    where = torch.searchsorted(free, asked)
    sizes = torch.bincount(predicted, minlength=len(classes.names))
    taken = torch.bincount(predicted[where], minlength=len(classes.names))
    fair = taken.max()
    assert bool(((taken == sizes) | (taken >= fair - 1)).all()), (taken, sizes)
    assert int((sizes > 0).sum()) > 1  # the head, 40 steps in, predicts several classes
    for c in range(len(classes.names)):
        mine = where[predicted[where] == c]
        if len(mine):
            torch.testing.assert_close(entropy[mine].sort().values,
                                       entropy[predicted == c].topk(len(mine)).values.sort().values)
    before = len(bank.clicks)
    bank.add_clicks(asked, answers[asked])
    assert len(bank.clicks) == before + 50 and torch.equal(bank.labels[asked], answers[asked])
    # a second question never asks again; fewer candidates: a random subset of the free pixels
    again = uncertain_pixels(model, bank, answers, 20, 300, torch.Generator().manual_seed(1))
    assert len(again) == 20 and not set(again.tolist()) & set(asked.tolist())
    assert bool((bank.labels[again] < 0).all() and (answers[again] >= 0).all())


TOY_BOXES = """
    <geom name="red_box" type="box" size="0.12 0.12 0.12" pos="-0.2 0 0.12" material="red"/>
    <geom name="blue_box" type="box" size="0.1 0.1 0.15" pos="0.2 0.1 0.15" material="blue"/>
"""


def test_twenty_asked_clicks_per_class_come_near_full_labels_on_a_toy_scene(tmp_path, toy_mjcf):
    from sims.capture import capture
    from sims.rigs import default_rig, make_test_rig

    scene = tmp_path / "toy.xml"
    scene.write_text(toy_mjcf("toy_labels", TOY_BOXES,
                              custom='<text name="nerfbot_objects" data="red_box blue_box"/>'))
    # close enough that the boxes fill a fifth of each view
    rig = default_rig(scene, count=24, width=48, height=48, seed=0, radius=1.8)
    data = tmp_path / "toy"
    capture(scene, rig, make_test_rig(rig, 4), data, progress=False)
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--method", "ngp", "--max-steps", "200",
                 "--out", str(run), "--no-progress", "--option", "log2_hashmap_size=14",
                 "--option", "samples_per_batch=32768"]) == 0
    scores = {}
    for name, extra in (("full", []), ("clicks", ["--clicks", "20"])):
        out = tmp_path / name
        assert main(["label", str(run), "--out", str(out), "--steps", "150",
                     "--no-progress"] + extra) == 0
        model, _ = load_model(out)
        assert model.label_head.classes.names == (BACKGROUND, "red_box", "blue_box", STRUCTURE)
        from nerfbot.eval.evaluation import evaluate
        scores[name] = evaluate(model, load_dataset(data), "test", with_ssim=False)["label_miou"]
    print(scores)
    # observed with training seeds 0-6 (one thread per process, as the suite runs): full
    # 0.79-0.81, 20 asked clicks (the default) 0.05-0.22 below; which pixels are asked follows
    # float-level changes of the 200-step field. BENCHMARKS.md (section 13) finds asked clicks
    # within 0.03-0.16 mIoU of full label maps on three larger scenes.
    assert scores["full"] > 0.7, scores
    assert scores["clicks"] > scores["full"] - 0.25, scores
