"""The tutorial notebooks are stored clean (no outputs, no execution counts) and import sims
first. Each one is executed end to end by its own module, ``tests/test_notebook_*.py``."""

from __future__ import annotations

import nbformat
import pytest
from notebook_run import (ARTICULATED, EXPORTS, GLASS, NAVIGATION, NOTEBOOKS, POSES, QUICKSTART,
                          VARIANTS, stored_clean)


def test_every_notebook_is_executed_by_a_module():
    """Each notebook in notebooks/ is one of tests/notebook_run.py's paths, which the
    test_notebook_* modules execute: a new tutorial needs its constant and its module."""
    assert sorted(NOTEBOOKS.glob("*.ipynb")) == sorted(
        [QUICKSTART, GLASS, ARTICULATED, VARIANTS, NAVIGATION, POSES, EXPORTS])


@pytest.mark.parametrize("path", sorted(NOTEBOOKS.glob("*.ipynb")), ids=lambda p: p.stem)
def test_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert stored_clean(nb) == [], "clear outputs and execution counts before committing"
    assert nb.metadata["kernelspec"]["name"] == "python3"
    first_code = next(c for c in nb.cells if c.cell_type == "code")
    assert first_code.source.lstrip().startswith("import sims"), "sims must be imported first"
