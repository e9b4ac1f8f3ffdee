"""The tutorial notebooks run end to end (real MuJoCo capture, real training) and give sane numbers.

The notebook is executed once per module with nbclient, at a tiny budget set through its
environment variables (32x32 images, 12 train + 4 test views, 60 training steps of 2^15
samples), in a temporary working folder. Its last code cell writes the key numbers to
``results.json`` in ``NERFBOT_NB_OUT``; the tests below check them.

Training uses a *step* budget (``NERFBOT_NB_STEPS``), not the tutorial's wall-clock budget: a
time budget makes the quality depend on the machine's speed and load (on a shared 2-core
machine, 8 s gave only 4 steps and 10.7 dB while a benchmark ran alongside), while a step budget
is deterministic on CPU. ``NERFBOT_NB_SECONDS`` stays as a generous safety cap.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import nbclient
import nbformat
import numpy as np
import pytest

pytestmark = pytest.mark.slow(620)  # rough single-core seconds (tests/conftest.py)

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
QUICKSTART = NOTEBOOKS / "01_quickstart.ipynb"
GLASS = NOTEBOOKS / "02_glass_grasping.ipynb"
ARTICULATED = NOTEBOOKS / "03_articulated.ipynb"
VARIANTS = NOTEBOOKS / "04_variants.ipynb"
NAVIGATION = NOTEBOOKS / "05_navigation.ipynb"
POSES = NOTEBOOKS / "06_poses_and_few_views.ipynb"
EXPORTS = NOTEBOOKS / "07_exports_and_labels.ipynb"

STEPS = 60
SAMPLES = 1 << 15  # per training step; the tutorials' default (2^17) is the whole 32x32 capture
TINY = {"NERFBOT_NB_SIZE": "32", "NERFBOT_NB_VIEWS": "12", "NERFBOT_NB_TEST_VIEWS": "4",
        "NERFBOT_NB_STEPS": str(STEPS), "NERFBOT_NB_SAMPLES": str(SAMPLES),
        "NERFBOT_NB_SECONDS": "240"}
CELL_TIMEOUT_S = 300

# Test PSNR after 60 steps of 2^15 samples at 32x32, 12 views (seed 0): observed 23.98 dB (the
# curve: 19.7, 20.1, 22.5, 24.0 dB at steps 8, 15, 30, 60; an untrained field scores ~10.5 dB).
# With 2^17 samples per step, the whole capture, it was 22.82 dB (4x the samples). 19 dB leaves
# ~5 dB for platform differences in float arithmetic (thread counts, BLAS, CPU) while still
# failing a broken pipeline: wrong poses, broken rendering, or a field that learnt little.
MIN_PSNR_DB = 19.0
# The queried pixel's z-depth against MuJoCo's depth buffer at the same pose: observed 3.545 m
# vs 3.562 m (-17 mm; +24 to +27 mm with 2^17 samples per step). A field that put the surface at
# the far side of the bounds or in the sky would be off by > 0.5 m (the table top alone is
# 1.2 m x 0.8 m).
MAX_CENTRE_DEPTH_ERROR_M = 0.15
# Accumulated opacity of that ray: observed 0.78 (0.63 with 2^17 samples per step; 0.43 with a
# 30-step budget, 0.31 after 4 steps).
MIN_CENTRE_OPACITY = 0.45


def _stored_clean(nb) -> list[str]:
    """Cells that carry outputs or execution counts (the stored notebook should have none)."""
    return [c.get("id", "?") for c in nb.cells if c.cell_type == "code"
            and (c.get("outputs") or c.get("execution_count") is not None)]


def _execute(path: Path, work: Path, **budget: str):
    """Execute notebook ``path`` at the tiny budget in ``work`` (``budget``: environment values
    that replace :data:`TINY`'s); (executed notebook, results)."""
    out = work / "out"
    nb = nbformat.read(path, as_version=4)
    with pytest.MonkeyPatch.context() as mp:  # the kernel inherits this environment
        for key, value in {**TINY, **budget}.items():
            mp.setenv(key, value)
        mp.setenv("NERFBOT_NB_OUT", str(out))
        mp.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
        # The kernel inherits the thread limits of the pytest worker that starts it (one
        # thread per xdist worker, tests/conftest.py), so kernels and workers share the cores.
        client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                                         resources={"metadata": {"path": str(work)}})
        client.execute()  # raises CellExecutionError (with the cell and traceback) on failure
    nbformat.write(nb, work / "executed.ipynb")  # kept for debugging a failed assertion
    results = json.loads((out / "results.json").read_text())
    return nb, results


@pytest.fixture(scope="module")
def quickstart(tmp_path_factory):
    """The quickstart executed at the tiny budget: (executed notebook, results dict)."""
    return _execute(QUICKSTART, tmp_path_factory.mktemp("nb_quickstart"))


@pytest.fixture(scope="module")
def glass(tmp_path_factory):
    """The glass-grasping tutorial executed at the tiny budget (generated scenes are cached in
    the test's own folder)."""
    work = tmp_path_factory.mktemp("nb_glass")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NERFBOT_CACHE", str(work / "cache"))
        return _execute(GLASS, work)


@pytest.fixture(scope="module")
def articulated(tmp_path_factory):
    """The articulated tutorial at the tiny budget: 8 + 2 configurations x 2 views."""
    with pytest.MonkeyPatch.context() as mp:
        for key, value in {"NERFBOT_NB_CONFIGS": "8", "NERFBOT_NB_TEST_CONFIGS": "2",
                           "NERFBOT_NB_VIEWS_PER_CONFIG": "2"}.items():
            mp.setenv(key, value)
        return _execute(ARTICULATED, tmp_path_factory.mktemp("nb_articulated"))


# The poses tutorial at its tiny budget (SfM at 192 px, fields at 48 px, 60 steps): observed 16
# of 16 views registered, 0.16-0.20 degrees and 0.10-0.17 % median errors (COLMAP's threaded
# mapper varies), test PSNR 19.1-19.2 dB on the recovered poses and 19.17 dB on the true ones
# (an untrained field scores ~11 dB); with three views, sparse depth took the depth MAE from
# 6.1 to 3.5 cm.
POSES_MIN_PSNR_DB = 15.0
POSES_MAX_GAP_DB = 2.0


@pytest.fixture(scope="module")
def poses(tmp_path_factory):
    """The poses tutorial at the tiny budget: SfM on 12 + 4 views at 192 px, fields at 48 px.
    SfM on one thread: with several, how many of the 16 views register depends on the
    threads' timing (10 of 16 once under the full suite's load)."""
    with pytest.MonkeyPatch.context() as mp:
        for key, value in {"NERFBOT_NB_SFM_SIZE": "192", "NERFBOT_NB_DOWNSCALE": "4",
                           "NERFBOT_NB_FEW": "3", "NERFBOT_NB_SFM_THREADS": "1"}.items():
            mp.setenv(key, value)
        return _execute(POSES, tmp_path_factory.mktemp("nb_poses"))


@pytest.fixture(scope="module")
def navigation(tmp_path_factory):
    """The navigation tutorial at a small budget: a room needs more views than a tabletop
    (300 at 64 px) and more steps (1000) before its field maps the obstacles and localises;
    the plain field, whose renders are cheaper, and an estimate every 20 control steps (1 s)
    rather than 10, so that the drive fits the cell timeout and the suite its budget."""
    return _execute(NAVIGATION, tmp_path_factory.mktemp("nb_navigation"), NERFBOT_NB_SIZE="64",
                    NERFBOT_NB_VIEWS="300", NERFBOT_NB_STEPS="1000", NERFBOT_NB_ROOM_OPTIONS="0",
                    NERFBOT_NB_LOCALISE_EVERY="20")


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """The exports-and-labels tutorial at a small budget: objects of a few pixels at 32 px
    get no label in 60 steps, so 48 px, 16 views and 200 steps."""
    return _execute(EXPORTS, tmp_path_factory.mktemp("nb_exports"), NERFBOT_NB_SIZE="48",
                    NERFBOT_NB_VIEWS="16", NERFBOT_NB_STEPS="200")


@pytest.mark.parametrize("path", [QUICKSTART, GLASS, ARTICULATED, VARIANTS, NAVIGATION, POSES,
                                  EXPORTS],
                         ids=lambda p: p.stem)
def test_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert _stored_clean(nb) == [], "clear outputs and execution counts before committing"
    assert nb.metadata["kernelspec"]["name"] == "python3"
    first_code = next(c for c in nb.cells if c.cell_type == "code")
    assert first_code.source.lstrip().startswith("import sims"), "sims must be imported first"


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    """The variants tutorial at the tiny budget: six trainings, two bakes."""
    return _execute(VARIANTS, tmp_path_factory.mktemp("nb_variants"))


def _figures(nb) -> list:
    """PNG figures an executed notebook displayed; fails on any error output."""
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    return [o for o in outputs if o.output_type == "display_data" and "image/png" in o.data]


def test_quickstart_runs_and_shows_plots(quickstart):
    figures = _figures(quickstart[0])
    # training images, camera rig, learning curve, comparison sheet, novel view
    assert len(figures) >= 5, f"expected at least 5 figures, got {len(figures)}"


def test_quickstart_embeds_a_video_browsers_play(quickstart):
    """The orbit video is H.264 / yuv420p (what browsers and Jupyter play), and it is embedded
    in the notebook as an HTML5 video."""
    nb, r = quickstart
    assert (r["video"]["codec"], r["video"]["pix_fmt"], r["video"]["frames"]) == \
        ("h264", "yuv420p", 36)
    html = [o.data["text/html"] for c in nb.cells if c.cell_type == "code" for o in c.outputs
            if o.output_type in ("display_data", "execute_result") and "text/html" in o.data]
    assert any("<video" in h and "data:video/mp4;base64," in h for h in html)


def test_quickstart_image_quality(quickstart):
    _, r = quickstart
    assert (r["size_px"], r["train_views"], r["test_views"]) == (32, 12, 4)
    assert r["steps"] == STEPS, (f"training stopped at {r['steps']} steps: the {r['budget_s']} s "
                                 "safety cap ran out first (machine far too slow or overloaded)")
    assert r["psnr_db"] >= MIN_PSNR_DB, f"test PSNR {r['psnr_db']:.2f} dB < {MIN_PSNR_DB} dB"
    assert 0.0 < r["ssim"] <= 1.0
    assert r["depth_mae_m"] is not None and 0.0 <= r["depth_mae_m"] < 1.0
    curve = r["curve"]
    assert len(curve) == 4, "one learning-curve point at 1/8, 1/4, 1/2 and all of the budget"
    secs = [c["train_seconds"] for c in curve]
    assert secs == sorted(secs) and secs[0] > 0.0
    assert all(math.isfinite(c["psnr_db"]) for c in curve)
    assert curve[-1]["psnr_db"] > curve[0]["psnr_db"], "PSNR should improve over training"


def test_quickstart_depth_query(quickstart):
    _, r = quickstart
    z, t = r["centre_z_depth_m"], r["centre_ray_distance_m"]
    assert math.isfinite(z) and math.isfinite(t)
    assert 0.0 < z <= t + 1e-4, "z-depth is the ray distance times a cosine <= 1"
    # The surface must lie within the scene's distance range from the camera: no nearer than
    # the bounding box, no farther than its farthest corner.
    eye = np.asarray(r["novel_eye_m"])
    lo, hi = np.asarray(r["aabb_m"])
    near = float(np.linalg.norm(eye - np.clip(eye, lo, hi)))
    corners = np.array([[x, y, zz] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for zz in (lo[2], hi[2])])
    far = float(np.linalg.norm(corners - eye, axis=1).max())
    assert near - 1e-3 <= t <= far + 1e-3, f"ray distance {t:.3f} m outside [{near:.3f}, {far:.3f}] m"
    assert r["centre_opacity"] >= MIN_CENTRE_OPACITY, \
        f"opacity {r['centre_opacity']:.2f}: the field should be fairly sure it hit a surface"
    z_true = r["centre_z_depth_mujoco_m"]
    assert math.isfinite(z_true) and r["centre_geom"] != "nothing (sky)"
    assert abs(z - z_true) <= MAX_CENTRE_DEPTH_ERROR_M, \
        f"centre z-depth {z:.3f} m vs MuJoCo {z_true:.3f} m"


def test_glass_tutorial_runs_and_shows_plots(glass):
    figures = _figures(glass[0])
    # capture (RGB / depths / glass mask), threshold sweep, depth modes, grasp sheets
    assert len(figures) >= 4, f"expected at least 4 figures, got {len(figures)}"


def test_glass_tutorial_sensor_misses_glass_and_ground_truth_grasps_it(glass):
    _, r = glass
    assert r["steps"] == STEPS
    assert r["glass_pixels"] > 10
    # The simulated sensor returns the table behind the glass: mostly valid, but far behind.
    # At 32x32 the glass is ~40 pixels; observed 98 % valid and 9 cm behind.
    assert r["sensor_valid_fraction_glass"] > 0.8
    assert r["sensor_median_error_glass_m"] > 0.03
    assert math.isfinite(r["expected_mae_glass_m"])
    # Ground-truth depth is the planner's ceiling: the wine glass is lifted in physics; from the
    # sensor's depth there is nothing to grasp.
    assert r["grasp"]["gt"], r["grasp_reason"]["gt"]
    assert not r["grasp"]["sensor"] and r["grasp_reason"]["sensor"] == "no grasp found"


def test_articulated_tutorial_renders_held_out_configurations_and_estimates_joints(articulated):
    nb, results = articulated
    assert len(_figures(nb)) >= 2  # held-out comparison, door sweep
    assert results["parts"] == [["door_hinge"], ["drawer_slide"]]
    psnr = results["psnr"]
    # observed at the tiny budget (60 steps of 2^15 samples, 32x32, 16 frames): articulated
    # 18.8 dB, ngp 17.6 dB, door error 0.3 degrees, drawer 22 mm (19.5 / 18.0 dB, 0.3 degrees and
    # 0.5 mm with 2^17 samples per step). The margins allow for platform
    # arithmetic; an untrained field is near 11 dB and a joint estimate from a broken field is off
    # by tens of degrees (the door spans 110).
    assert psnr["articulated"] > 17.0 and math.isfinite(psnr["ngp"])
    assert results["joint_errors"]["door_hinge"] < 15.0
    assert results["joint_errors"]["drawer_slide"] < 60.0


def test_variants_tutorial_measures_every_variant(variants):
    nb, r = variants
    assert len(_figures(nb)) >= 2  # the trade-off plot and the renders
    methods = r["methods"]
    assert set(methods) == {"ngp", "plenoxels", "tensorf", "fastnerf", "fastnerf_cache",
                            "plenoctree", "plenoctree_octree", "kilonerf"}
    for name, m in methods.items():
        # an untrained field scores ~10.5 dB here; every variant must have learnt the scene
        assert math.isfinite(m["psnr"]) and m["psnr"] > 15.0, (name, m)
        assert m["render_ms"] > 0 and m["params"] >= 0 and 0 < m["ssim"] <= 1, (name, m)
    # baking keeps what the source learnt
    for src, baked in (("fastnerf", "fastnerf_cache"), ("plenoctree", "plenoctree_octree")):
        assert methods[baked]["psnr"] > methods[src]["psnr"] - 1.5, (src, baked)
    assert r["cache_mb"] > 0 and r["octree_mb"] > 0


def test_poses_tutorial_recovers_the_cameras_and_trains_on_them(poses):
    nb, r = poses
    assert len(_figures(nb)) >= 3   # views, pose errors and cameras, few-view renders
    assert r["registered"] >= 0.8 * r["images"]
    assert r["rotation_deg_median"] < 1.0 and r["translation_percent_median"] < 2.0
    assert r["psnr_recovered_poses"] >= POSES_MIN_PSNR_DB
    assert r["psnr_true_poses"] - r["psnr_recovered_poses"] < POSES_MAX_GAP_DB
    assert r["few_views"] == 3 and r["few_points"] > 10
    for key in ("few_psnr_rgb", "few_psnr_sparse_depth", "few_depth_mae_rgb_m",
                "few_depth_mae_sparse_depth_m"):
        assert math.isfinite(r[key]), key
    assert r["few_depth_mae_sparse_depth_m"] < r["few_depth_mae_rgb_m"]


# The exports tutorial at its small budget (48 px, 16 + 4 views, 200 steps of 2^15 samples):
# observed label mIoU 0.54 with full label maps (background 0.99, table 0.89, objects 0-0.79),
# 0.38 with 20 random clicks per class (``click_choice="random"``); the blue can located 1.7 cm
# from where it stands. A head that learnt nothing labels everything background (mIoU ~0.1)
# and locates nothing.
EXPORTS_MIN_MIOU = 0.35
EXPORTS_MIN_CLICK_MIOU = 0.2
EXPORTS_MAX_LOCATED_ERROR_M = 0.05


def test_exports_tutorial_labels_exports_and_locates(exports):
    nb, r = exports
    assert len(_figures(nb)) >= 3   # classes, label renders, 3D exports
    assert r["label_miou"] >= EXPORTS_MIN_MIOU
    assert r["click_miou"] >= EXPORTS_MIN_CLICK_MIOU
    assert r["cloud_points"] > 100 and r["tsdf_faces"] > 100
    for name, f in r["fscore"].items():
        assert 0.0 < f <= 1.0, name
    assert r["located_points"] > 0 and r["located_error_m"] < EXPORTS_MAX_LOCATED_ERROR_M


# The navigation tutorial at its small budget (64 px, 300 views, 1000 steps): observed test
# PSNR 29.1 dB, map IoU 0.58 with the true floor map, a path 0.99x the true map's; from 10 cm
# and 8 degrees off, the wide estimator reached 3.9, 2.4 and 0.2 cm and at most 1.6 degrees on
# the three views (iNeRF 5.9, 4.0 and 9.1 cm, up to 3.0 degrees); the drive,
# steering by the wide estimator every 1 s (9 estimates), kept its estimates within 2.4 cm
# (median) of the true pose and ended 4.9 cm from the goal, without contact. At this budget the
# field's map can miss a low table's top (BENCHMARKS.md, section 9), and an earlier drive touched
# it, so contacts are reported, not asserted.
NAV_MIN_PSNR_DB = 22.0
NAV_MIN_MAP_IOU = 0.4
NAV_MAX_ESTIMATE_ERROR_M = 0.06


def test_navigation_tutorial_maps_plans_localises_and_drives(navigation):
    nb, r = navigation
    assert len(_figures(nb)) >= 4   # views, maps, localisation renders, the trial sheet
    assert r["psnr"] >= NAV_MIN_PSNR_DB
    assert r["map"]["iou"] >= NAV_MIN_MAP_IOU
    assert r["reference_length"] > 1.0
    assert 0.8 * r["reference_length"] <= r["path_length"] <= 1.3 * r["reference_length"]
    wide = r["localise"]["wide"]["error_m"]
    assert len(wide) == 3 and max(wide) < 0.09 and float(np.median(wide)) < 0.06
    assert max(r["localise"]["wide"]["error_deg"]) < 2.0
    assert r["estimates"] >= 5 and r["estimate_error_m_median"] < NAV_MAX_ESTIMATE_ERROR_M
    assert r["goal_error_m"] < 0.10
