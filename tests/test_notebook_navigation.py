"""notebooks/05_navigation.ipynb runs end to end at a small budget (tests/notebook_run.py): map,
plan, localise and drive in a room."""

from __future__ import annotations

import pytest
from notebook_run import NAVIGATION, execute, png_figures

pytestmark = pytest.mark.slow(450)  # rough single-core seconds (tests/conftest.py)


@pytest.fixture(scope="module")
def navigation(tmp_path_factory):
    """The navigation tutorial at a small budget: a room needs more views than a tabletop
    (300 at 64 px) and more steps (1000) before its field maps the obstacles and localises;
    the plain field, whose renders are cheaper; both estimators on two views rather than three;
    during the drive, an iNeRF estimate (about half the time of a wide one) every 25 control
    steps (1.25 s) rather than a wide one every 10, so that the suite keeps its budget."""
    return execute(NAVIGATION, tmp_path_factory.mktemp("nb_navigation"), NERFBOT_NB_SIZE="64",
                   NERFBOT_NB_VIEWS="300", NERFBOT_NB_STEPS="1000", NERFBOT_NB_ROOM_OPTIONS="0",
                   NERFBOT_NB_LOCALISE_VIEWS="2", NERFBOT_NB_LOCALISE_EVERY="25",
                   NERFBOT_NB_TRACKER="inerf")


# The navigation tutorial at its small budget (64 px, 300 views, 1000 steps): observed test
# PSNR 28.9 dB, map IoU 0.57 with the true floor map, a path 0.99x the true map's; from 10 cm
# and 8 degrees off, the wide estimator reached 6.4 and 2.4 cm on the two views (on another
# machine's field 3.3 and 17.4 cm); the drive, steering by iNeRF every 1.25 s (7 estimates),
# kept its estimates within 1.8 cm (median) of the true pose and ended 3.8 cm from the goal,
# without contact. With 700 steps the map's IoU fell to 0.35. At this budget the field's map
# can miss a low table's top (BENCHMARKS.md, section 9), and an earlier drive touched it, so
# contacts are reported, not asserted.
NAV_MIN_PSNR_DB = 22.0
NAV_MIN_MAP_IOU = 0.4
NAV_MAX_ESTIMATE_ERROR_M = 0.06


def test_navigation_tutorial_maps_plans_localises_and_drives(navigation):
    nb, r = navigation
    assert len(png_figures(nb)) >= 4   # views, maps, localisation renders, the trial sheet
    assert r["psnr"] >= NAV_MIN_PSNR_DB
    assert r["map"]["iou"] >= NAV_MIN_MAP_IOU
    assert r["reference_length"] > 1.0
    assert 0.8 * r["reference_length"] <= r["path_length"] <= 1.3 * r["reference_length"]
    # Section 4 at this budget: in fields this brief the colours' optimum lies 5-10 cm off the
    # truth in some robot views whatever the start, so two views cannot show 2 cm. On 10 views
    # each of room:0 and room:1 from 10 cm and 8 degrees, the wide estimator landed within 5 cm
    # on 70 % (median 1.9 cm, at most 11.9 cm and 6.8 degrees) and iNeRF on 45 % (at most
    # 18.8 cm); tests/test_localise.py holds both to their accuracy where the truth is the
    # optimum.
    wide, plain = r["localise"]["wide"], r["localise"]["iNeRF"]
    assert len(wide["error_m"]) == 2 and len(plain["error_m"]) == 2
    assert max(wide["error_m"]) < 0.25 and max(wide["error_deg"]) < 10.0, wide
    assert sum(wide["error_m"]) / 2 < 0.10, wide
    assert max(plain["error_m"]) < 0.4 and max(plain["error_deg"]) < 20.0, plain
    assert r["estimates"] >= 5 and r["estimate_error_m_median"] < NAV_MAX_ESTIMATE_ERROR_M
    assert r["goal_error_m"] < 0.10
