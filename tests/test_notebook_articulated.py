"""notebooks/03_articulated.ipynb runs end to end at a tiny budget (tests/notebook_run.py):
held-out configurations and joint estimates."""

from __future__ import annotations

import math
import pytest
from notebook_run import ARTICULATED, execute, png_figures

pytestmark = pytest.mark.slow(80)  # rough single-core seconds (tests/conftest.py)


@pytest.fixture(scope="module")
def articulated(tmp_path_factory):
    """The articulated tutorial at the tiny budget: 8 + 2 configurations x 2 views."""
    with pytest.MonkeyPatch.context() as mp:
        for key, value in {"NERFBOT_NB_CONFIGS": "8", "NERFBOT_NB_TEST_CONFIGS": "2",
                           "NERFBOT_NB_VIEWS_PER_CONFIG": "2"}.items():
            mp.setenv(key, value)
        return execute(ARTICULATED, tmp_path_factory.mktemp("nb_articulated"))


def test_articulated_tutorial_renders_held_out_configurations_and_estimates_joints(articulated):
    nb, results = articulated
    assert len(png_figures(nb)) >= 2  # held-out comparison, door sweep
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
