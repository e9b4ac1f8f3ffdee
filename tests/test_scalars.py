"""Per-step training scalars: scalars.csv beside the checkpoint, continued exactly by a resume,
plotted to curve.png; damaged tables are named, and a resume starts them again."""

from __future__ import annotations

import logging
import math
import shutil

import cv2
import pytest

from nerfbot.data import load_dataset
from nerfbot.train.scalars import COLUMNS, SCALARS, read_scalars, step_row, write_scalars
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(5)

TINY = {"samples_per_batch": 4096, "grid_update_every": 4}


def _config(max_steps: int) -> TrainConfig:
    return TrainConfig(method="ngp", max_steps=max_steps, seed=3, progress=False,
                       options=dict(TINY), checkpoint_every_steps=2,
                       checkpoint_every_seconds=float("inf"))


@pytest.fixture(scope="module")
def dataset(tiny_capture):
    return load_dataset(tiny_capture[0])


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("scalars") / "run"
    Trainer(dataset, out, _config(6)).train()
    return out


def test_every_step_has_a_row_and_the_run_a_plot(run):
    rows = read_scalars(run / SCALARS)
    assert [r["step"] for r in rows] == [1, 2, 3, 4, 5, 6]
    for r in rows:
        assert r["psnr"] == pytest.approx(-10 * math.log10(r["loss"]), abs=1e-4)
        assert r["rays"] > 0 and r["samples_per_ray"] > 0 and r["step_ms"] > 0 and r["lr"] > 0
        assert r["occupied"] is None or 0.0 <= r["occupied"] <= 1.0
    assert all(b["seconds"] >= a["seconds"] for a, b in zip(rows, rows[1:]))
    image = cv2.imread(str(run / "curve.png"))
    assert image is not None and image.shape[0] > 100 and image.std() > 1


def test_a_resume_continues_the_table_from_the_checkpoint(run, dataset, tmp_path):
    """Rows written after the checkpoint (a process killed between its table and its next
    checkpoint) are dropped: every step appears once."""
    copy = shutil.copytree(run, tmp_path / "run")
    rows = read_scalars(copy / SCALARS)
    stale = [dict(r, step=r["step"] + 6) for r in rows[:2]]  # steps 7, 8: not in the checkpoint
    write_scalars(copy / SCALARS, rows + stale)
    trainer = Trainer(dataset, copy, _config(10))
    assert trainer.load() and trainer.step == 6
    trainer.train()
    again = read_scalars(copy / SCALARS)
    assert [r["step"] for r in again] == list(range(1, 11))
    assert again[:6] == rows  # the first six rows are the original run's


def test_a_damaged_table_is_named_and_restarted_on_resume(run, dataset, tmp_path, caplog):
    copy = shutil.copytree(run, tmp_path / "run")
    (copy / SCALARS).write_text("step,loss\n1,0.5\n")
    with pytest.raises(ValueError, match=f"{SCALARS}: not a scalars table"):
        read_scalars(copy / SCALARS)
    trainer = Trainer(dataset, copy, _config(8))
    with caplog.at_level(logging.WARNING):
        assert trainer.load()
    assert "start again at step 6" in caplog.text
    trainer.train()
    assert [r["step"] for r in read_scalars(copy / SCALARS)] == [7, 8]
    bad = tmp_path / "bad.csv"
    bad.write_text(",".join(COLUMNS) + "\n1,0.1,x,1,1,1,,1,1\n")
    with pytest.raises(ValueError, match="bad.csv: line 2"):
        read_scalars(bad)


def test_rows_round_trip(tmp_path):
    rows = [step_row(1, 0.25, 0.01, 1024, 8192, None, 1e-2, 0.25),
            step_row(2, 0.5, 0.004, 2048, 8192, 0.3, 1e-2, 0.25)]
    back = read_scalars(write_scalars(tmp_path / SCALARS, rows))
    assert [r["step"] for r in back] == [1, 2] and back[0]["occupied"] is None
    assert back[1]["samples_per_ray"] == pytest.approx(4.0)
    assert back[1]["psnr"] == pytest.approx(-10 * math.log10(0.004), rel=1e-5)
    assert read_scalars(tmp_path / "missing.csv") == []
    assert read_scalars(tmp_path / SCALARS, up_to_step=1) == back[:1]
