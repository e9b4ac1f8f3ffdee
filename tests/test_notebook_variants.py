"""notebooks/04_variants.ipynb runs end to end at a tiny budget (tests/notebook_run.py): every
variant trains, bakes keep what their sources learnt."""

from __future__ import annotations

import math
import pytest
from notebook_run import VARIANTS, execute, png_figures

pytestmark = pytest.mark.slow(135)  # rough single-core seconds (tests/conftest.py)


@pytest.fixture(scope="module")
def variants(tmp_path_factory):
    """The variants tutorial at the tiny budget: six trainings, two bakes."""
    return execute(VARIANTS, tmp_path_factory.mktemp("nb_variants"))


def test_variants_tutorial_measures_every_variant(variants):
    nb, r = variants
    assert len(png_figures(nb)) >= 2  # the trade-off plot and the renders
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
