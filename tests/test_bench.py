"""``nerfbot bench``: the sweep on a tiny real capture (outputs, counts, medians, resume, errors),
the Pareto front, executors (local, Ray), and the meshes behind the Chamfer distance: true
MuJoCo geometry and marching cubes on a field."""

from __future__ import annotations

import csv
import json
import math
import sys

import mujoco
import numpy as np
import pytest
import torch
import trimesh
from torch import nn

from nerfbot.app.cli import main
from nerfbot.bench import executors
from nerfbot.bench.executors import EXECUTORS, LocalExecutor, RayExecutor, make_executor
from nerfbot.bench.sweep import BenchConfig, BenchError, pareto_front, parse_option_sweep, run_bench
from nerfbot.query.meshing import (compare_meshes, default_density_threshold, field_mesh,
                                   surface_distance, visible_mask)
from sims.geometry import capture_geometry, scene_meshes

pytestmark = pytest.mark.slow(155)  # rough single-core seconds (tests/conftest.py)

# Cheap ngp: a small hash table and small batches, so a step takes milliseconds.
CHEAP = ["--option", "samples_per_batch=4096", "--option", "log2_hashmap_size=12"]
COLUMNS = {"scene", "size", "image_size", "method", "budget_kind", "budget", "options", "repeats",
           "psnr", "ssim", "depth_mae_m", "depth_rmse_m", "chamfer_mm", "train_seconds",
           "steps", "steps_per_second", "render_ms_per_image", "render_fps", "peak_rss_mb",
           "speedup_vs_baseline", "train_time_ratio", "pareto_train_time", "pareto_render_fps"}


def _csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# -- the Pareto front ----------------------------------------------------------------------------
def test_pareto_front_hand_made():
    # (train seconds, PSNR): lower time and higher PSNR are better.
    t = [10, 20, 30, 15, 40, 20, None, 5]
    p = [20, 25, 30, 19, 29, 25, 40, float("nan")]
    # 0: on (nothing faster is as good); 1 and 5: identical, both on; 2: on (best PSNR);
    # 3: dominated by 0; 4: dominated by 2; 6 and 7: missing values, never on.
    assert pareto_front(t, p, x_lower_is_better=True) == [True, True, True, False, False, True,
                                                          False, False]
    # (FPS, PSNR): higher FPS is better.
    fps, psnr = [1.0, 2.0, 3.0, 1.5], [30, 28, 20, 27]  # the last is beaten by (2.0, 28)
    assert pareto_front(fps, psnr, x_lower_is_better=False) == [True, True, True, False]
    assert pareto_front([], []) == []


def test_parse_option_sweep():
    assert parse_option_sweep("log2_hashmap_size=15,17,19") == ("log2_hashmap_size", [15, 17, 19])
    assert parse_option_sweep("mlp_precision=bf16,fp32") == ("mlp_precision", ["bf16", "fp32"])
    with pytest.raises(ValueError):
        parse_option_sweep("render_steps")


# -- true geometry -------------------------------------------------------------------------------
PRIMITIVES = """
<mujoco>
  <asset><mesh name="tet" vertex="0 0 0  0.1 0 0  0 0.1 0  0 0 0.1"/></asset>
  <worldbody>
    <geom name="box" type="box" size="0.1 0.2 0.3" pos="1 2 3" euler="0 0 30"/>
    <geom name="ball" type="sphere" size="0.25" pos="-1 0 0.5"/>
    <geom name="can" type="cylinder" size="0.05 0.1" pos="0 1 0" euler="90 0 0"/>
    <geom name="pill" type="capsule" size="0.05 0.1" pos="0 -1 0"/>
    <geom name="egg" type="ellipsoid" size="0.1 0.2 0.3" pos="2 0 0"/>
    <geom name="tet" type="mesh" mesh="tet" pos="0 0 2"/>
    <geom name="floor" type="plane" size="0 0 1"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def primitives():
    model = mujoco.MjModel.from_xml_string(PRIMITIVES)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_scene_meshes_match_analytic_area_and_volume(primitives):
    model, data = primitives
    box = scene_meshes(model, data, ["box"])
    assert box.volume == pytest.approx(0.2 * 0.4 * 0.6, rel=1e-9)
    assert box.area == pytest.approx(2 * (0.2 * 0.4 + 0.2 * 0.6 + 0.4 * 0.6), rel=1e-9)
    assert np.allclose(box.vertices.mean(0), [1, 2, 3])
    # rotated 30 degrees about z: the x extent is 0.2 cos30 + 0.4 sin30
    assert np.ptp(box.vertices[:, 0]) == pytest.approx(0.2 * math.cos(math.pi / 6) + 0.4 * 0.5)

    ball = scene_meshes(model, data, ["ball"])
    assert ball.volume == pytest.approx(4 / 3 * math.pi * 0.25 ** 3, rel=3e-3)
    assert ball.area == pytest.approx(4 * math.pi * 0.25 ** 2, rel=3e-3)
    assert np.allclose(ball.bounds.mean(0), [-1, 0, 0.5], atol=1e-9)

    can = scene_meshes(model, data, ["can"])  # axis along world y after euler 90 about x
    assert can.volume == pytest.approx(math.pi * 0.05 ** 2 * 0.2, rel=3e-3)
    assert np.ptp(can.vertices[:, 1]) == pytest.approx(0.2)
    pill = scene_meshes(model, data, ["pill"])
    assert pill.volume == pytest.approx(math.pi * 0.05 ** 2 * 0.2 + 4 / 3 * math.pi * 0.05 ** 3,
                                        rel=3e-3)
    egg = scene_meshes(model, data, ["egg"])
    assert egg.volume == pytest.approx(4 / 3 * math.pi * 0.1 * 0.2 * 0.3, rel=3e-3)
    tet = scene_meshes(model, data, ["tet"])
    assert abs(tet.volume) == pytest.approx(0.1 ** 3 / 6, rel=1e-6)
    # MuJoCo re-centres mesh vertices (and moves the geom frame to match): the placed mesh is
    # where the MJCF put it
    assert np.allclose(tet.bounds, [[0, 0, 2], [0.1, 0.1, 2.1]], atol=1e-6)

    every = scene_meshes(model, data)  # the infinite floor is skipped
    assert every.area == pytest.approx(sum(m.area for m in (box, ball, can, pill, egg, tet)))
    with pytest.raises(ValueError, match="nosuch"):
        scene_meshes(model, data, ["nosuch"])


def test_capture_geometry_of_a_tabletop_capture(tiny_capture):
    manifest = json.loads((tiny_capture[0] / "transforms.json").read_text())["scene"]
    mesh, bounds = capture_geometry(manifest)
    assert np.allclose(mesh.bounds, bounds, atol=1e-6)
    assert capture_geometry(None) is None
    assert capture_geometry({**manifest, "source": "/nonexistent/scene.xml"}) is None


# -- marching cubes, visibility, Chamfer -----------------------------------------------------------
class _SphereField(nn.Module):
    """Density 100 / m inside a sphere, 0 outside, with a smooth 1 cm wall: 50 / m at radius."""

    def __init__(self, centre, radius):
        super().__init__()
        self.centre, self.radius = torch.tensor(centre), radius

    def density(self, x, cond=None):
        r = (x - self.centre).norm(dim=-1)
        return 100.0 * torch.sigmoid((self.radius - r) / 0.01), None


class _Model(nn.Module):
    def __init__(self, field, aabb):
        super().__init__()
        self.field = field
        self.register_buffer("aabb", torch.tensor(aabb, dtype=torch.float32))


@pytest.mark.parametrize("backend", ["auto", "open3d"])
def test_field_mesh_of_analytic_sphere(backend):
    centre, radius = [0.1, -0.05, 0.2], 0.3
    model = _Model(_SphereField(centre, radius), [[-0.5, -0.5, -0.3], [0.5, 0.5, 0.6]])
    mesh = field_mesh(model, resolution=64, threshold=50.0, backend=backend)  # voxel 15.6 mm
    truth = trimesh.creation.icosphere(5, radius=radius)
    truth.apply_translation(centre)
    cmp = compare_meshes(mesh, truth, count=20000)
    assert cmp["chamfer_mm"] < 1.0, cmp
    assert cmp["pred_points"] == cmp["gt_points"] == 20000
    assert abs(mesh.volume) == pytest.approx(4 / 3 * math.pi * radius ** 3, rel=0.02)
    # a threshold above every density gives an empty mesh and an undefined distance
    empty = field_mesh(model, resolution=16, threshold=1e3, backend=backend)
    assert len(empty.faces) == 0
    assert math.isnan(compare_meshes(empty, truth, count=100)["chamfer_mm"])


def test_field_mesh_cut_by_bounds_and_default_threshold():
    model = _Model(_SphereField([0.0, 0.0, 0.0], 0.3), [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    half = field_mesh(model, resolution=32, threshold=50.0, bounds=[[-0.5, -0.5, 0.0], [0.5, 0.5, 0.5]])
    assert half.bounds[0, 2] >= -1e-9  # only the upper half-ball, closed by the padding
    # default: one step of diagonal / 256 is 50 % opaque
    step = math.sqrt(3.0) * 1.0 / 256
    assert default_density_threshold(model.aabb.numpy()) == pytest.approx(math.log(2) / step)


def test_visible_mask_and_surface_distance():
    box = trimesh.creation.box(extents=[1, 1, 1])
    eye = np.eye(4)
    eye[2, 3] = 5.0  # at z = 5, looking down -z (OpenGL)
    cams = (eye[None], np.array([[100.0, 100.0, 50.0, 50.0]]), np.array([[100, 100]]))
    pts = np.array([[0.1, 0.2, 0.5],    # top face: seen
                    [0.1, 0.2, -0.5],   # bottom face: hidden by the box itself
                    [0.5, 0.0, 0.0]])   # side face: grazing, behind the top edge -> hidden
    assert visible_mask(pts, box, *cams).tolist() == [True, False, False]
    far = np.eye(4)
    far[:3, 3] = [100.0, 0, 5.0]  # the box is outside this camera's image
    assert not visible_mask(pts[:1], box, far[None], cams[1], cams[2]).any()
    assert surface_distance(np.array([[0, 0, 1.5], [0, 0, 0]]), box) == pytest.approx([1.0, 0.5])


def test_downscale_dataset_scales_images_intrinsics_and_depth(tiny_capture):
    from nerfbot.bench.point import downscale_dataset
    from nerfbot.data import load_dataset

    ds = load_dataset(tiny_capture[0])
    small = downscale_dataset(ds, 16)
    assert small.images[0].shape == (16, 16, 3) and small.depths[0].shape == (16, 16)
    assert small.segmentations[0].shape == (16, 16)
    assert small.segmentations[0].dtype == ds.segmentations[0].dtype
    assert np.allclose(small.intrinsics, ds.intrinsics * 0.5) and (small.sizes == 16).all()
    # nearest-pixel depth: every value is one of the original depths (no blending across edges)
    assert np.isin(small.depths[0][np.isfinite(small.depths[0])], ds.depths[0]).all()
    assert downscale_dataset(ds, 64).images[0].shape == (32, 32, 3)  # never upscaled


# -- executors -------------------------------------------------------------------------------------
def test_executor_registry_and_missing_ray(monkeypatch):
    assert set(EXECUTORS) == {"local", "ray"}
    assert isinstance(make_executor("local"), LocalExecutor)
    with pytest.raises(BenchError, match="dask"):
        make_executor("dask")
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now raises ImportError
    with pytest.raises(BenchError, match=r"pip install 'nerfbot\[ray\]'"):
        make_executor("ray", address=None)
    assert EXECUTORS["ray"] is RayExecutor


# -- the sweep -------------------------------------------------------------------------------------
def _bench_args(data, out, *extra):
    return ["bench", "--data", str(data), "--methods", "ngp", "--budget-kind", "steps",
            "--out", str(out), "--mesh-resolution", "12", "--chamfer-points", "2000",
            "--mesh-threshold", "0.05", "--no-progress", *CHEAP, *extra]


@pytest.fixture(scope="module")
def swept(tiny_capture, tmp_path_factory):
    """A real local sweep: 1 method x 2 budgets x 2 repeats at 16 px (a downscaled capture)."""
    out = tmp_path_factory.mktemp("bench") / "out"
    code = main(_bench_args(tiny_capture[0], out, "--budgets", "2,3", "--repeats", "2",
                            "--sizes", "16"))
    assert code == 0
    return out


def test_sweep_writes_tables_plots_with_medians(swept):
    for name in ("bench.csv", "bench_runs.csv", "bench.json", "bench.md",
                 "psnr_vs_train_time.png", "psnr_vs_render_fps.png"):
        assert (swept / name).stat().st_size > 0, name
    rows, runs = _csv(swept / "bench.csv"), _csv(swept / "bench_runs.csv")
    assert len(rows) == 2 and len(runs) == 4  # methods x budgets, x repeats
    assert COLUMNS <= rows[0].keys()
    assert [r["budget"] for r in rows] == ["2", "3"] and all(r["repeats"] == "2" for r in rows)
    assert all(r["image_size"] == "16x16" for r in rows)  # --sizes 16 downscaled the 32 px capture
    doc = json.loads((swept / "bench.json").read_text())
    assert len(doc["runs"]) == 4 and not doc["failures"] and len(doc["summary"]) == 2
    for row in doc["summary"]:
        mine = [r for r in runs if r["budget"] == str(row["budget"])]
        assert len(mine) == 2
        for key in ("psnr", "render_ms_per_image", "train_seconds", "peak_rss_mb", "chamfer_mm"):
            assert row[key] == pytest.approx(np.median([float(r[key]) for r in mine])), key
        assert row["steps"] == row["budget"]
        assert 5 < row["psnr"] < 60 and row["peak_rss_mb"] > 50 and row["render_fps"] > 0
        assert row["depth_mae_m"] > 0 and row["chamfer_mm"] > 0 and row["mesh_faces"] > 0
    base = doc["summary"][0]
    assert base["baseline"] and base["speedup_vs_baseline"] == 1.0 and base["train_time_ratio"] == 1.0
    other = doc["summary"][1]
    assert other["speedup_vs_baseline"] == pytest.approx(other["render_fps"] / base["render_fps"])
    md = (swept / "bench.md").read_text()
    assert "## tabletop" in md and md.count("| ngp") == 2 and "PSNR" in md and "Chamfer" in md
    assert (swept / "psnr_vs_train_time.png").read_bytes()[:4] == b"\x89PNG"


def test_rerun_resumes_without_running_points(swept, tiny_capture, capsys):
    before = json.loads((swept / "bench.json").read_text())["runs"]
    capsys.readouterr()
    code = main(_bench_args(tiny_capture[0], swept, "--budgets", "2,3", "--repeats", "2",
                            "--sizes", "16"))
    assert code == 0
    assert "0 point(s) run, 4 already measured" in capsys.readouterr().out
    assert json.loads((swept / "bench.json").read_text())["runs"] == before


class _FakeExecutor:
    """Records the points it is given; point results are made up (or failures)."""

    calls: list = []
    fail: set = set()

    def __init__(self, **_):
        pass

    def run(self, points, run_root):
        for p in points:
            _FakeExecutor.calls.append(p["key"])
            if p["budget"] in _FakeExecutor.fail:
                yield p, executors.failure(p, "boom")
                continue
            yield p, {"key": p["key"], "status": "ok", "psnr": 10.0 + p["budget"] + p["repeat"],
                      "train_seconds": float(p["budget"]), "render_ms_per_image": 10.0,
                      "render_fps": 100.0, "steps": p["budget"], "image_size": "32x32"}


def test_resume_skips_done_points_force_reruns_failures_retry(tiny_capture, tmp_path, monkeypatch):
    monkeypatch.setitem(EXECUTORS, "fake", _FakeExecutor)
    monkeypatch.setattr(_FakeExecutor, "calls", [])
    monkeypatch.setattr(_FakeExecutor, "fail", {3})

    def cfg(budgets, **kw):
        return BenchConfig(data=[str(tiny_capture[0])], methods=["ngp"], budgets=budgets,
                           out=tmp_path, budget_kind="steps", repeats=3, executor="fake",
                           chamfer=False, progress=False, **kw)

    first = run_bench(cfg([1, 2, 3]))
    assert len(_FakeExecutor.calls) == 9 and len(first.failures) == 3 and len(first.rows) == 2
    assert first.rows[0]["psnr"] == 12.0  # median of 11, 12, 13
    _FakeExecutor.calls.clear()
    _FakeExecutor.fail = set()
    second = run_bench(cfg([1, 2, 3, 4]))  # budgets 1, 2 are done; 3 failed before; 4 is new
    assert len(_FakeExecutor.calls) == 6 and second.skipped == 6 and not second.failures
    assert [r["budget"] for r in second.rows] == [1, 2, 3, 4]
    _FakeExecutor.calls.clear()
    run_bench(cfg([1]))
    assert _FakeExecutor.calls == []
    run_bench(cfg([1], force=True))
    assert len(_FakeExecutor.calls) == 3
    with pytest.raises(BenchError, match="other settings"):  # resumed with other measurements
        run_bench(cfg([1], eval_images=1))


def test_points_run_repeat_by_repeat(tiny_capture, tmp_path, monkeypatch):
    """One repeat of every configuration runs before the next repeat (the machine's drift is
    spread over the configurations instead of biasing those run in a slow spell)."""
    monkeypatch.setitem(EXECUTORS, "fake", _FakeExecutor)
    monkeypatch.setattr(_FakeExecutor, "calls", [])
    monkeypatch.setattr(_FakeExecutor, "fail", set())
    run_bench(BenchConfig(data=[str(tiny_capture[0])], methods=["ngp"], budgets=[1, 2],
                          out=tmp_path, budget_kind="steps", repeats=3, executor="fake",
                          chamfer=False, progress=False))
    order = [(json.loads(k)["repeat"], json.loads(json.loads(k)["config"])["budget"])
             for k in _FakeExecutor.calls]
    assert order == [(0, 1), (0, 2), (1, 1), (1, 2), (2, 1), (2, 2)]


def test_bad_method_dataset_option_name_it(tiny_capture, tmp_path, capsys):
    def err(*args):
        capsys.readouterr()
        code = main(["bench", "--budgets", "2", "--budget-kind", "steps", "--out",
                     str(tmp_path / "o"), "--no-progress", *args])
        return code, capsys.readouterr().err

    code, msg = err("--data", str(tiny_capture[0]), "--methods", "ngp,nerfacto")
    assert code == 2 and "nerfacto" in msg and "plenoxels" in msg  # lists the known methods
    code, msg = err("--data", str(tmp_path / "no_such_dataset"), "--methods", "ngp")
    assert code == 2 and "no_such_dataset" in msg and "tabletop" in msg  # lists the built-ins
    bad = tmp_path / "broken"
    bad.mkdir()
    (bad / "transforms.json").write_text("{}")
    code, msg = err("--data", str(bad), "--methods", "ngp")
    assert code == 2 and "broken" in msg
    code, msg = err("--data", str(tiny_capture[0]), "--methods", "ngp", "--option",
                    "warp_factor=1,2")
    assert code == 2 and "warp_factor" in msg
    assert not (tmp_path / "o" / "bench.json").exists()  # nothing ran


def test_ray_executor_gives_the_same_table(tiny_capture, swept, tmp_path):
    # ray is in the test extra, so this runs wherever the tests do (a real local Ray)
    out = tmp_path / "ray"
    code = main(_bench_args(tiny_capture[0], out, "--budgets", "2", "--sizes", "16",
                            "--executor", "ray"))
    assert code == 0
    rows, local = _csv(out / "bench.csv"), _csv(swept / "bench.csv")
    assert len(rows) == 1 and list(rows[0].keys()) == list(local[0].keys())
    assert {k: rows[0][k] for k in ("scene", "method", "budget", "image_size", "steps")} == \
        {k: local[0][k] for k in ("scene", "method", "budget", "image_size", "steps")}
    assert float(rows[0]["psnr"]) > 5 and float(rows[0]["peak_rss_mb"]) > 50


def test_auto_is_a_bench_method_compared_with_the_best_other_configuration(tiny_capture, tmp_path):
    """`--methods auto,ngp`: the auto point trains what the manifest picks and the table says
    how far it is from the best other configuration."""
    out = tmp_path / "auto"
    assert main(["bench", "--data", str(tiny_capture[0]), "--methods", "auto,ngp",
                 "--budget-kind", "steps", "--budgets", "3", "--option", "sh_degree=0,4",
                 "--sizes", "16", "--out", str(out), "--no-chamfer", "--no-progress",
                 *CHEAP]) == 0
    doc = json.loads((out / "bench.json").read_text())
    rows = doc["summary"]
    assert [r["method"] for r in rows] == ["auto:ngp", "ngp", "ngp"]  # auto is never swept
    auto = rows[0]
    best = max(rows[1:], key=lambda r: r["psnr"])
    assert auto["psnr_gap_to_best"] == pytest.approx(best["psnr"] - auto["psnr"])
    assert auto["best_train_seconds"] == best["train_seconds"]
    # the tabletop is specular, but its shiny surfaces are a small share of the pixels
    assert json.loads(auto["options"])["sh_degree"] == 0
    assert "behind the best other configuration" in (out / "bench.md").read_text()


def test_baked_method_trains_its_source_bakes_and_compares(tiny_capture, tmp_path):
    """`--methods fastnerf_cache`: the point trains `fastnerf` on the budget (with the source's
    options), bakes the cache with the point's own options, and reports both renderers."""
    out = tmp_path / "baked"
    assert main(["bench", "--data", str(tiny_capture[0]), "--methods", "fastnerf_cache",
                 "--budget-kind", "steps", "--budgets", "30", "--option", "np=32",
                 "--option", "components=4", "--out", str(out), "--no-chamfer",
                 "--no-progress", *CHEAP]) == 0
    doc = json.loads((out / "bench.json").read_text())
    assert not doc["failures"]
    (row,), (run,) = doc["summary"], doc["runs"]
    assert row["method"] == "fastnerf_cache" and row["source_method"] == "fastnerf"
    assert row["steps"] == 30 and run["bake_np"] == 32
    assert row["source_psnr"] > 10 and row["psnr"] > 10
    assert row["psnr_change_vs_source"] == pytest.approx(row["psnr"] - row["source_psnr"])
    assert row["render_speedup_vs_source"] == pytest.approx(
        row["source_render_ms_per_image"] / row["render_ms_per_image"], rel=1e-6)
    assert 0 < row["size_mb"] and row["bake_seconds"] > 0
    assert "baked in" in (out / "bench.md").read_text()


def test_a_baked_method_cannot_be_trained(tiny_capture):
    from nerfbot.train.trainer import TrainConfig

    with pytest.raises(ValueError, match="fastnerf_cache.*--method fastnerf.*nerfbot bake"):
        TrainConfig(method="fastnerf_cache", max_steps=1).validate()
