"""pixelNeRF: projection of world points onto source features, pooling over views, errors, saving
and loading, training across scenes of a family that renders an unseen one, and fine-tuning on
that scene's source views."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nerfbot.fields.pixelnerf import PixelNeRFField, PixelNeRFFieldConfig, SourceViews, project
from nerfbot.models.pixelnerf import PixelNeRFModelConfig
from nerfbot.ops.cameras import look_at, pixel_rays
from nerfbot.train.pixelnerf import (FinetuneConfig, PixelTrainConfig, build_pixelnerf,
                                     condition_on, finetune_on, train_pixelnerf)
from nerfbot.train.runs import load_model

pytestmark = pytest.mark.slow(40)  # rough single-core seconds (tests/conftest.py)

AABB = [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]
W, H = 40, 30
K = (36.0, 36.0, 20.0, 15.0)  # fx, fy, cx, cy


def _sources(eyes, seed=0) -> SourceViews:
    gen = torch.Generator().manual_seed(seed)
    images = [torch.rand(H, W, 3, generator=gen) for _ in eyes]
    poses = np.stack([look_at(np.asarray(e, float), np.zeros(3)) for e in eyes])
    return SourceViews.from_frames(images, poses, [K] * len(eyes))


def test_projection_puts_a_known_point_on_its_feature_pixel():
    sources = _sources([(2.0, 0.3, 0.5), (-0.4, 1.8, 0.9)])
    c2w = torch.linalg.inv(sources.w2c.double()).float()
    # points on the rays through known image points of view 0, at known depths
    u = torch.tensor([3.2, 20.0, 35.7, 11.1])
    v = torch.tensor([2.5, 15.0, 27.3, 20.9])
    rays = pixel_rays(c2w[0], *K, u, v)
    t = torch.tensor([0.7, 1.5, 2.0, 2.6])
    points = rays.origins + rays.directions * t[:, None]
    xc, uv, front = project(points, sources)
    torch.testing.assert_close(uv[0], torch.stack([u, v], -1), atol=1e-4, rtol=0)
    torch.testing.assert_close(-xc[0, :, 2], t * rays.z_per_t, atol=1e-5, rtol=0)  # z-depth
    assert bool(front.all())
    # the feature read at a point is the encoder map's value under its projection: a map
    # holding each feature pixel's own column and row gives them back (bilinear, half size)
    field = PixelNeRFField(AABB).eval()
    field.set_sources(sources)
    h, w = field.features().shape[-2:]
    assert (h, w) == (H // 2, W // 2)
    cols = torch.arange(w, dtype=torch.float32).expand(h, w)
    rows = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w)
    coords = torch.zeros(2, field.encoder.out_channels, h, w)
    coords[:, 0], coords[:, 1] = cols, rows
    field._features = coords  # the eval-mode cache of the encoder's output
    feats, _ = field.sample_features(points)
    inner = (u > 1) & (u < W - 1) & (v > 1) & (v < H - 1)  # away from the zero padding
    torch.testing.assert_close(feats[0, inner, 0], (u[inner] / 2 - 0.5), atol=1e-4, rtol=0)
    torch.testing.assert_close(feats[0, inner, 1], (v[inner] / 2 - 0.5), atol=1e-4, rtol=0)
    # a point behind a camera reads nothing from it
    behind = c2w[0, :3, 3] + 0.5 * c2w[0, :3, 2]  # half a metre behind view 0 (it looks along -z)
    feats, _ = field.sample_features(behind[None])
    assert float(feats[0].abs().max()) == 0.0


def test_the_views_are_pooled_in_any_order_and_density_is_zero_outside_the_bounds():
    field = PixelNeRFField(AABB, PixelNeRFFieldConfig(width=32)).eval()
    a = _sources([(2.0, 0.3, 0.5), (-0.4, 1.8, 0.9)])
    b = SourceViews(a.images.flip(0), a.w2c.flip(0), a.intrinsics.flip(0))
    x = torch.cat([torch.rand(50, 3) - 0.5, torch.tensor([[0.9, 0.0, 0.0]])])
    with torch.no_grad():
        field.set_sources(a)
        sa, fa = field.density(x)
        field.set_sources(b)
        sb, fb = field.density(x)
    torch.testing.assert_close(sa, sb, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(fa, fb, atol=1e-5, rtol=1e-5)
    assert bool(torch.isfinite(sa).all()) and float(sa[-1]) == 0.0 and fa.shape == (51, 32)


def test_bad_sources_are_refused_with_a_clear_message():
    field = PixelNeRFField(AABB)
    with pytest.raises(RuntimeError, match="set the source views"):
        field.density(torch.zeros(1, 3))
    with pytest.raises(ValueError, match="one .H, W, 3. size"):
        SourceViews.from_frames([np.zeros((4, 4, 3)), np.zeros((5, 4, 3))], np.stack([np.eye(4)] * 2),
                                [K, K])
    with pytest.raises(ValueError, match="at least one source view"):
        SourceViews.from_frames([], np.zeros((0, 4, 4)), [])
    with pytest.raises(ValueError, match="as many poses"):
        SourceViews.from_frames([np.zeros((4, 4, 3))], np.stack([np.eye(4)] * 2), [K])
    with pytest.raises(ValueError, match="fewest"):
        PixelTrainConfig(sources=(0, 2)).validate()
    with pytest.raises(ValueError, match="pooled_after"):
        PixelNeRFField(AABB, PixelNeRFFieldConfig(pooled_after=6))


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """Four workspace scenes at 32 px: three to train on, one unseen."""
    from sims.family import capture_family

    root = tmp_path_factory.mktemp("family")
    return capture_family("workspace", range(4), root, views=10, test_views=3, size=32,
                          progress=False)


#: A pixelNeRF small enough to train in seconds on one core (the defaults take about 20x as
#: long per step)
TINY_FIELD = PixelNeRFFieldConfig(position_scale=0.8, width=32, blocks=2, pooled_after=1,
                                  encoder_channels=(8, 16, 16, 16))
TINY_MODEL = PixelNeRFModelConfig(coarse_samples=16, fine_samples=8, rays_per_batch=128)
PIXEL_STEPS = 300


@pytest.fixture(scope="module")
def trained(family, tmp_path_factory):
    """The tiny pixelNeRF trained across the first three scenes, saved as a run."""
    from nerfbot.data import load_dataset

    datasets = [load_dataset(p) for p in family[:3]]
    model = build_pixelnerf(datasets[0].aabb, TINY_FIELD, TINY_MODEL)
    run = tmp_path_factory.mktemp("pixelnerf") / "run"
    summary = train_pixelnerf(model, datasets, PixelTrainConfig(steps=PIXEL_STEPS, lr=1e-3,
                                                                progress=False), run)
    return model, run, summary


def test_pixelnerf_renders_an_unseen_scene_from_its_own_views(family, trained):
    from nerfbot.data import load_dataset
    from nerfbot.eval.evaluation import evaluate

    model, run, summary = trained
    assert summary["steps"] == PIXEL_STEPS
    first, last = summary["curve"][0]["loss"], summary["curve"][-1]["loss"]
    unseen, other = load_dataset(family[3]), load_dataset(family[0])
    sources = unseen.indices("train")[:2]
    own = evaluate(condition_on(model, unseen, sources), unseen, "test", with_ssim=False)
    # the same source poses with another scene's images: only what the field reads from the
    # source images differs
    condition_on(model, other, other.indices("train")[:2])
    model.set_scene(SourceViews(model.field.sources.images,
                                torch.linalg.inv(torch.as_tensor(unseen.c2w[sources])).float(),
                                model.field.sources.intrinsics), unseen.aabb)
    foreign = evaluate(model, unseen, "test", with_ssim=False)
    # observed: loss 0.079 -> 0.035; 15.2 dB from the scene's own views, 13.1 from another's
    assert last < 0.7 * first
    assert own["psnr"] > 14.0 and own["psnr"] > foreign["psnr"] + 1.0, (own, foreign)


def test_a_pixelnerf_run_loads_and_the_cli_scores_an_unseen_scene(family, trained, capsys):
    import json

    from nerfbot.app.cli import main
    from nerfbot.data import load_dataset

    model, run, _ = trained
    loaded, info = load_model(run)
    assert info["spec"]["method"] == "pixelnerf" and len(info["spec"]["scenes"]) == 3
    unseen = load_dataset(family[3])
    x = torch.rand(64, 3) * torch.as_tensor(unseen.aabb[1] - unseen.aabb[0]).float() \
        + torch.as_tensor(unseen.aabb[0]).float()
    with torch.no_grad():
        a = condition_on(model, unseen, [0, 1]).field.density(x)[0]
        b = condition_on(loaded, unseen, [0, 1]).field.density(x)[0]
    torch.testing.assert_close(a, b)
    capsys.readouterr()
    assert main(["eval", str(run), "--data", str(family[3]), "--sources", "0,1", "--json"]) == 0
    scores = json.loads(capsys.readouterr().out)
    assert scores["method"] == "pixelnerf" and scores["psnr"] > 14.0
    assert main(["eval", str(run), "--data", str(family[3])]) == 2
    assert "--sources" in capsys.readouterr().err
    assert main(["eval", str(run), "--data", str(family[3]), "--sources", "0,99"]) == 2
    assert "no frame 99" in capsys.readouterr().err


def test_fine_tuning_on_the_source_views_improves_the_unseen_scene(family, trained, capsys):
    import json

    from nerfbot.app.cli import main
    from nerfbot.data import load_dataset
    from nerfbot.eval.evaluation import evaluate

    _, run, _ = trained
    model, _ = load_model(run)  # a copy: fine-tuning changes the weights
    unseen = load_dataset(family[3])
    sources = list(unseen.indices("train")[:2])
    before = evaluate(condition_on(model, unseen, sources), unseen, "test", with_ssim=False)
    summary = finetune_on(model, unseen, sources, FinetuneConfig(steps=50, lr=1e-3,
                                                                 progress=False))
    after = evaluate(model, unseen, "test", with_ssim=False)
    # observed: 15.2 -> 16.1 dB; the model stays conditioned on the sources, in eval mode
    assert summary["steps"] == 50 and not model.training
    assert after["psnr"] > before["psnr"] + 0.4, (before, after)
    with pytest.raises(ValueError, match="needs a budget"):
        FinetuneConfig(steps=None).validate()
    capsys.readouterr()
    assert main(["eval", str(run), "--data", str(family[3]), "--sources", "0,1",
                 "--finetune-seconds", "0.5", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["psnr"] > 14.0
    with pytest.raises(SystemExit) as exit_:
        main(["eval", str(run), "--data", str(family[3]), "--sources", "0,1",
              "--finetune-seconds", "0"])
    assert exit_.value.code == 2 and "positive number" in capsys.readouterr().err


def test_the_pixelnerf_command_captures_a_family_and_trains(tmp_path, capsys):
    import json

    from nerfbot.app.cli import main

    out, captures = tmp_path / "run", tmp_path / "captures"
    assert main(["pixelnerf", "--family", "bins", "--seeds", "0-1", "--views", "4",
                 "--test-views", "1", "--size", "16", "--steps", "3", "--captures",
                 str(captures), "--out", str(out), "--no-progress"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["steps"] == 3 and report["scenes"] == 2
    assert sorted(p.name for p in captures.iterdir()) == ["bins-0", "bins-1"]
    assert load_model(out)[1]["step"] == 3
    assert main(["pixelnerf", "--family", "bins", "--seeds", "0", "--views", "4", "--size",
                 "16", "--steps", "3", "--captures", str(captures), "--out", str(out),
                 "--no-progress"]) == 2  # a run is there: never overwritten unasked
    assert "already" in capsys.readouterr().err
    assert main(["pixelnerf", "--family", "nowhere", "--out", str(tmp_path / "x")]) == 2
    assert "not a scene family" in capsys.readouterr().err
