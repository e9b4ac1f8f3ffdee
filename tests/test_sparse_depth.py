"""DS-NeRF sparse depth: the keypoint depth loss, keypoint files, keypoint rays, training."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from nerfbot.data import DatasetError, load_dataset
from nerfbot.data.pixels import PixelBank
from nerfbot.ops.losses import KEYPOINT_WEIGHT_FLOOR, keypoint_depth_loss
from nerfbot.train.config import TrainConfig
from nerfbot.train.trainer import Trainer, batch_loss


def _packed(counts, seed=0):
    """Random packed samples: weights, t_starts, t_ends, ray_indices for rays of ``counts``."""
    g = torch.Generator().manual_seed(seed)
    ray_indices = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    m = int(sum(counts))
    t_starts = torch.zeros(m)
    t_ends = torch.zeros(m)
    k = 0
    for n in counts:
        edges = torch.sort(torch.rand(n + 1, generator=g) * 4.0 + 0.5).values
        t_starts[k:k + n], t_ends[k:k + n] = edges[:-1], edges[1:]
        k += n
    weights = torch.rand(m, generator=g) * 0.2
    return weights, t_starts, t_ends, ray_indices


def _reference(weights, t_starts, t_ends, ray_indices, target, sigma):
    """The DS-NeRF loss written as a plain float64 loop over rays and samples."""
    per_ray = {}
    for w, a, b, r in zip(weights.double().tolist(), t_starts.double().tolist(),
                          t_ends.double().tolist(), ray_indices.tolist()):
        d, s = float(target[r]), float(sigma[r])
        if not math.isfinite(d):
            continue
        mid = 0.5 * (a + b)
        per_ray[r] = per_ray.get(r, 0.0) - math.log(w + KEYPOINT_WEIGHT_FLOOR) * \
            math.exp(-((mid - d) ** 2) / (2 * s * s)) * (b - a)
    valid = [r for r in range(len(target)) if math.isfinite(float(target[r]))]
    return sum(per_ray.get(r, 0.0) for r in valid) / len(valid)


def test_keypoint_depth_loss_matches_a_float64_reference():
    counts = [5, 9, 1, 7, 12]
    weights, t0, t1, idx = _packed(counts)
    target = torch.tensor([1.5, 2.0, float("nan"), 3.0, 4.2])
    sigma = torch.tensor([0.1, 0.3, 0.2, 0.05, 0.5])
    loss = keypoint_depth_loss(weights, t0, t1, idx, target, sigma)
    assert loss.item() == pytest.approx(_reference(weights, t0, t1, idx, target, sigma),
                                        rel=1e-5)


def test_keypoint_depth_loss_is_finite_for_zero_weights_and_rays_without_samples():
    weights, t0, t1, idx = _packed([6, 6])
    # ray 1 and 2 have no samples at all (indices 0 and 3 only); weights all zero
    idx = torch.cat([torch.zeros(6, dtype=torch.long), torch.full((6,), 3, dtype=torch.long)])
    zero = torch.zeros(12, requires_grad=True)
    target = torch.tensor([2.0, 2.0, 2.0, 2.0])
    sigma = torch.full((4,), 0.2)
    loss = keypoint_depth_loss(zero, t0, t1, idx, target, sigma)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(zero.grad).all()
    expected = _reference(zero.detach(), t0, t1, idx, target, sigma)
    assert loss.item() == pytest.approx(expected, rel=1e-5)   # rays 1, 2 count 0 in the mean
    # no ray has a keypoint: zero, still connected to the weights
    none = keypoint_depth_loss(weights.requires_grad_(), t0, t1, idx,
                               torch.full((4,), float("nan")), sigma)
    none.backward()
    assert none.item() == 0.0 and torch.equal(weights.grad, torch.zeros_like(weights))
    empty = keypoint_depth_loss(torch.zeros(0), torch.zeros(0), torch.zeros(0),
                                torch.zeros(0, dtype=torch.long), target, sigma)
    assert empty.item() == 0.0


def test_robust_keypoint_weights_follow_the_rendered_depth():
    """With ``robust`` c each ray's loss is scaled by 1 / (1 + (r / (c sigma))^2), r the
    distance of its expected depth from the keypoint's (float64 reference); a ray without
    weight keeps its loss, and c = 0 is the plain loss."""
    counts = [5, 9, 7, 12]
    weights, t0, t1, idx = _packed(counts, seed=3)
    weights[idx == 2] = 0.0                                    # ray 2: no weight at all
    target = torch.tensor([1.5, 2.0, 3.0, 4.2])
    sigma = torch.tensor([0.1, 0.3, 0.05, 0.5])
    c = 3.0
    expected = 0.0
    for r in range(4):
        m = idx == r
        one = torch.tensor([0])
        per_ray = _reference(weights[m], t0[m], t1[m], one.repeat(int(m.sum())),
                             target[r:r + 1], sigma[r:r + 1])
        w = weights[m].double()
        mid = 0.5 * (t0[m] + t1[m]).double()
        if float(w.sum()) > 0:
            res = float((w * mid).sum() / w.sum()) - float(target[r])
            per_ray /= 1.0 + (res / (c * float(sigma[r]))) ** 2
        expected += per_ray / 4
    robust = keypoint_depth_loss(weights, t0, t1, idx, target, sigma, robust=c)
    assert robust.item() == pytest.approx(expected, rel=1e-5)
    plain = keypoint_depth_loss(weights, t0, t1, idx, target, sigma)
    assert robust.item() < plain.item()
    assert keypoint_depth_loss(weights, t0, t1, idx, target, sigma, robust=0.0).item() == \
        plain.item()


def test_keypoint_depth_loss_pulls_weight_toward_the_keypoint():
    n = 40
    t0 = torch.linspace(0.0, 4.0, n + 1)[:-1]
    t1 = torch.linspace(0.0, 4.0, n + 1)[1:]
    idx = torch.zeros(n, dtype=torch.long)
    weights = torch.full((n,), 0.02, requires_grad=True)
    loss = keypoint_depth_loss(weights, t0, t1, idx, torch.tensor([2.0]), torch.tensor([0.1]))
    loss.backward()
    mid = 0.5 * (t0 + t1)
    near, far = (mid - 2.0).abs() < 0.1, (mid - 2.0).abs() > 1.0
    assert (weights.grad[near] < 0).all()          # more weight at the keypoint lowers the loss
    assert weights.grad[far].abs().max() < 1e-6 * weights.grad[near].abs().min() + 1e-12
    # and a distribution peaked there scores lower than one peaked elsewhere
    at = torch.where(near, 0.45, 1e-3)
    off = torch.where((mid - 3.0).abs() < 0.1, 0.45, 1e-3)
    score = lambda w: keypoint_depth_loss(w, t0, t1, idx, torch.tensor([2.0]),  # noqa: E731
                                          torch.tensor([0.1])).item()
    assert score(at) < score(off)


def _with_keypoints(src, dst, rows_of):
    """Copy the capture ``src`` to ``dst`` with sparse depth files rows_of(frame index, frame)."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "transforms.json").read_text())
    (dst / "sparse_depth").mkdir()
    for i, frame in enumerate(meta["frames"]):
        rows = rows_of(i, frame)
        if rows is None:
            continue
        path = f"sparse_depth/{i:03d}.npy"
        np.save(dst / path, np.asarray(rows, dtype=np.float32))
        frame["sparse_depth_file_path"] = path
    (dst / "transforms.json").write_text(json.dumps(meta))
    return dst


def _true_keypoints(ds, i, step=5):
    """(K, 4) keypoints at pixel centres of frame i where the true depth is finite."""
    depth = ds.depths[i]
    v, u = np.mgrid[0:depth.shape[0]:step, 0:depth.shape[1]:step]
    z = depth[v, u]
    ok = np.isfinite(z)
    return np.stack([u[ok] + 0.5, v[ok] + 0.5, z[ok], np.full(ok.sum(), 0.01)], axis=1)


def test_keypoint_rays_reach_the_true_surface(tiny_capture, tmp_path):
    truth = load_dataset(tiny_capture[0])
    data = _with_keypoints(tiny_capture[0], tmp_path / "kp",
                           lambda i, f: _true_keypoints(truth, i))
    ds = load_dataset(data)
    assert ds.keypoints[0] is not None and ds.keypoints[0].shape[1] == 4
    bank = PixelBank(ds, ds.indices("train"))
    count = bank.load_keypoints()
    assert count == sum(len(ds.keypoints[i]) for i in ds.indices("train"))
    rays, colours, slot, target_t, sigma_t = bank.sample_keypoints(
        64, torch.Generator().manual_seed(0))
    assert colours.shape == (64, 3)
    points = rays.origins + target_t[:, None] * rays.directions
    frames = bank.frames[slot]
    for k in range(64):
        i = int(frames[k])
        w2c = np.linalg.inv(ds.c2w[i])
        p = w2c[:3, :3] @ points[k].double().numpy() + w2c[:3, 3]
        fx, fy, cx, cy = ds.intrinsics[i]
        u, v = fx * p[0] / -p[2] + cx, -fy * p[1] / -p[2] + cy
        assert abs(u - round(u - 0.5) - 0.5) < 1e-3 and abs(v - round(v - 0.5) - 0.5) < 1e-3
        assert truth.depths[i][int(v), int(u)] == pytest.approx(-p[2], rel=1e-4)
        np.testing.assert_allclose(colours[k].numpy() * 255, truth.images[i][int(v), int(u)],
                                   atol=1e-3)
    assert torch.all(sigma_t >= 0.01 - 1e-6)
    # 2 x 2 rays per keypoint pixel: four rays, each with the keypoint's distance along it
    rays, colours, slot, target_t, _ = bank.sample_keypoints(8, torch.Generator(), 2)
    assert len(rays) == 32 and colours.shape == (8, 3) and target_t.shape == (32,)
    z = target_t * rays.z_per_t
    assert torch.allclose(z.reshape(8, 4), z.reshape(8, 4)[:, :1].expand(8, 4))


def test_sparse_depth_files_are_checked(tiny_capture, tmp_path):
    def bad(i, frame):
        return [[5.0, 5.0, -1.0, 0.1]] if i == 2 else None
    data = _with_keypoints(tiny_capture[0], tmp_path / "bad", bad)
    with pytest.raises(DatasetError, match=r"frames\[2\]\.sparse_depth_file_path.*row 0"):
        load_dataset(data)


def test_training_with_sparse_depth_runs_and_needs_keypoints(tiny_capture, tmp_path):
    truth = load_dataset(tiny_capture[0])
    ds = load_dataset(_with_keypoints(tiny_capture[0], tmp_path / "kp",
                                      lambda i, f: _true_keypoints(truth, i)))
    config = TrainConfig(method="ngp", max_steps=12, sparse_depth_weight=0.1,
                         sparse_depth_rays=64, progress=False,
                         options={"log2_hashmap_size": 12, "samples_per_batch": 4096})
    result = Trainer(ds, tmp_path / "run", config).train()
    assert result["steps"] == 12
    with pytest.raises(ValueError, match="sparse depth supervision needs keypoints"):
        Trainer(truth, tmp_path / "run2", config)


def test_the_keypoint_term_is_added_on_the_keypoint_rays_only(tiny_capture, tmp_path):
    truth = load_dataset(tiny_capture[0])
    ds = load_dataset(_with_keypoints(tiny_capture[0], tmp_path / "kp",
                                      lambda i, f: _true_keypoints(truth, i)))
    trainer = Trainer(ds, tmp_path / "run", TrainConfig(
        method="ngp", max_steps=1, sparse_depth_weight=0.1, progress=False,
        options={"log2_hashmap_size": 12}))
    losses = {}
    for weight in (0.0, 0.1):
        loss, out, s = batch_loss(trainer.model, trainer.bank, 512,
                                  torch.Generator().manual_seed(0), 0.1, 32, weight)
        losses[weight] = float(loss)
        assert len(out.rgb) == (512 // (s * s)) * s * s   # random pixels + 32 keypoint pixels
    # same rays, same colour loss: the difference is the keypoint term, positive
    assert losses[0.1] > losses[0.0]
    # the keypoint pixels' colours are left out of the colour loss, which stays the random
    # pixels' mean
    seen = {}
    colour_loss = trainer.model.loss

    def spy(*args, **kwargs):
        seen.update(kwargs)
        return colour_loss(*args, **kwargs)

    trainer.model.loss = spy
    batch_loss(trainer.model, trainer.bank, 512, torch.Generator().manual_seed(0), 0.1, 32, 0.1)
    weights = seen["pixel_weights"]
    assert bool((weights[-32:] == 0).all()) and bool((weights[:-32] > 0).all())
    assert float(weights.sum()) == pytest.approx(len(weights))
    # a batch of few pixels gives the keypoints at most a quarter of them
    _, out, s = batch_loss(trainer.model, trainer.bank, 64, torch.Generator().manual_seed(0),
                           0.1, 32, 0.1)
    assert int((seen["pixel_weights"] == 0).sum()) == 64 // (s * s) // 4


def test_robust_keypoint_weights_start_at_a_quarter_of_the_budget(tiny_capture, tmp_path):
    truth = load_dataset(tiny_capture[0])
    ds = load_dataset(_with_keypoints(tiny_capture[0], tmp_path / "kp",
                                      lambda i, f: _true_keypoints(truth, i)))
    trainer = Trainer(ds, tmp_path / "run", TrainConfig(
        method="ngp", max_steps=1, sparse_depth_weight=0.1, sparse_depth_robust=3.0,
        progress=False, options={"log2_hashmap_size": 12}))

    def loss(progress, robust):
        return float(batch_loss(trainer.model, trainer.bank, 512,
                                torch.Generator().manual_seed(0), progress, 32, 0.1,
                                sparse_depth_robust=robust)[0])

    # before a quarter: DS-NeRF's loss (the same terms; threaded sums differ in the last bits)
    assert loss(0.1, 3.0) == pytest.approx(loss(0.1, 0.0), rel=1e-5)
    # after it the untrained field's depths are far from the keypoints': their terms shrink
    assert loss(0.5, 3.0) < loss(0.5, 0.0)
    with pytest.raises(ValueError, match="sparse_depth_robust"):
        TrainConfig(method="ngp", max_steps=1, sparse_depth_robust=-1.0).validate()


def test_keypoints_leave_the_batch_after_sparse_depth_until(tiny_capture, tmp_path,
                                                            monkeypatch):
    config = TrainConfig(method="ngp", max_steps=8, sparse_depth_weight=0.1,
                         sparse_depth_until=0.5, progress=False,
                         options={"log2_hashmap_size": 12, "samples_per_batch": 4096})
    assert [config.keypoint_pixels(p) for p in (0.0, 0.49, 0.5, 1.0)] == [256, 256, 0, 0]
    assert TrainConfig(method="ngp", max_steps=1).keypoint_pixels(0.0) == 0
    truth = load_dataset(tiny_capture[0])
    ds = load_dataset(_with_keypoints(tiny_capture[0], tmp_path / "kp",
                                      lambda i, f: _true_keypoints(truth, i)))
    drawn = []
    sample_keypoints = PixelBank.sample_keypoints

    def counted(self, n, *args, **kwargs):
        drawn.append(n)
        return sample_keypoints(self, n, *args, **kwargs)

    monkeypatch.setattr(PixelBank, "sample_keypoints", counted)
    assert Trainer(ds, tmp_path / "run", config).train()["steps"] == 8
    assert len(drawn) == 4 and all(n > 0 for n in drawn)   # steps 0-3 of 8
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="sparse_depth_until"):
            TrainConfig(method="ngp", max_steps=1, sparse_depth_until=bad).validate()
