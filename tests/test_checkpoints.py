"""Checkpoints: refused pickles, damaged files and the previous checkpoint, resume spec checks,
the hash-grid table check, and a training process killed while writing a checkpoint."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from nerfbot.app.cli import main
from nerfbot.data import load_dataset
from nerfbot.methods import build_model
from nerfbot.models.base import resize_like_state_dict
from nerfbot.ops.encodings import HashEncoding
from nerfbot.train.checkpoints import (CHECKPOINT, FORMAT, VERSION, CheckpointError,
                                       read_checkpoint, save_checkpoint, stale_temporaries,
                                       write_durable)
from nerfbot.train.runs import load_model
from nerfbot.train.trainer import TrainConfig, Trainer

pytestmark = pytest.mark.slow(80)  # rough single-core seconds (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[1]
TINY = {"samples_per_batch": 4096, "grid_update_every": 4}
TINY_FLAGS = ["--option", "samples_per_batch=4096", "--option", "grid_update_every=4"]
PREV = "checkpoint.prev.pt"


class _Malicious:
    """Unpickling this would create ``marker`` (a stand-in for any code a crafted file runs)."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def _tree_digest(folder: Path) -> dict:
    """sha256 of every file under ``folder`` (hidden ones too), by relative path."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _copy_run(run: Path, dest: Path) -> Path:
    shutil.copytree(run, dest)
    return dest


def _cli(*argv: str, timeout: float = 600) -> subprocess.CompletedProcess:
    """``python -m nerfbot.app.cli ARGV`` in a fresh process."""
    return subprocess.run([sys.executable, "-m", "nerfbot.app.cli", *argv], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout, env=_env())


def _env() -> dict:
    env = dict(os.environ)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[var] = "1"  # the same arithmetic in every process of a comparison
    return env


@pytest.fixture(scope="module")
def dataset(tiny_capture):
    return load_dataset(tiny_capture[0])


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory):
    """A 4-step ngp run checkpointed every 2 steps: checkpoint.pt (step 4), checkpoint.prev.pt
    (step 2)."""
    out = tmp_path_factory.mktemp("ckpt") / "run"
    cfg = TrainConfig(method="ngp", max_steps=4, seed=1, progress=False, options=TINY,
                      checkpoint_every_steps=2, checkpoint_every_seconds=float("inf"))
    Trainer(dataset, out, cfg).train()
    return out


@pytest.fixture(scope="module")
def cli_run(tiny_capture, tmp_path_factory):
    """The same kind of run, made by ``nerfbot train``."""
    out = tmp_path_factory.mktemp("ckpt_cli") / "run"
    code = main(["train", "--data", str(tiny_capture[0]), "--method", "ngp", "--max-steps", "4",
                 "--checkpoint-every-steps", "2", "--out", str(out), "--no-progress",
                 *TINY_FLAGS])
    assert code == 0
    return out


def _resume_config(max_steps: int = 6, **changes) -> TrainConfig:
    kw = dict(method="ngp", max_steps=max_steps, seed=1, progress=False, options=dict(TINY))
    return TrainConfig(**{**kw, **changes})


# ----------------------------------------------------------------------------- format

def test_checkpoints_hold_plain_data_tagged_with_the_format(run):
    ckpt = torch.load(run / CHECKPOINT, map_location="cpu", weights_only=True)
    assert ckpt["format"] == FORMAT and ckpt["version"] == VERSION and ckpt["step"] == 4
    assert read_checkpoint(run / PREV)["step"] == 2
    assert ckpt["spec"]["dataset"]["num_frames"] == 20
    assert not stale_temporaries(run / CHECKPOINT)


def test_numpy_values_are_stored_as_plain_python(tmp_path):
    ckpt = {"spec": {"method": "ngp", "aabb": np.zeros((2, 3)), "background": "learned",
                     "options": {"log2_hashmap_size": np.int64(15)}, "seed": 0},
            "model": {"w": torch.ones(2)}, "step": 3, "train_seconds": 1.5,
            "curve": [{"psnr": np.float64(20.5), "step": np.int32(3)}],
            "config": {"eval_at_seconds": (np.float32(1.0),)}}
    save_checkpoint(ckpt, tmp_path / CHECKPOINT)
    back = read_checkpoint(tmp_path / CHECKPOINT)
    assert back["spec"]["aabb"] == [[0.0] * 3] * 2
    assert type(back["spec"]["options"]["log2_hashmap_size"]) is int
    assert type(back["curve"][0]["psnr"]) is float and back["curve"][0]["step"] == 3
    assert back["config"]["eval_at_seconds"] == (1.0,)
    with pytest.raises(TypeError, match=r"config\['bad'\]"):
        save_checkpoint({**ckpt, "config": {"bad": object()}}, tmp_path / "other.pt")


# ----------------------------------------------------------------------------- refused pickles

@pytest.mark.parametrize("writer", ["pickle", "torch"])
def test_a_malicious_checkpoint_is_refused_and_never_run(run, dataset, tmp_path, writer):
    """A pickle whose loading would create a file (a raw pickle and one in torch's zip
    format): load_model and Trainer.load refuse it with a CheckpointError naming the file, even
    with a good previous checkpoint beside it, and the file is never created."""
    folder = _copy_run(run, tmp_path / "run")
    marker = tmp_path / "MARKER"
    payload = {"spec": _Malicious(marker), "model": {}}
    if writer == "pickle":
        (folder / CHECKPOINT).write_bytes(pickle.dumps(payload))
    else:
        torch.save(payload, folder / CHECKPOINT)
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt is refused: it is not tensors-only"):
        load_model(folder)
    with pytest.raises(CheckpointError, match="refused"):
        Trainer(dataset, folder, _resume_config()).load()
    assert not marker.exists()


def test_the_cli_refuses_a_malicious_checkpoint(run, tiny_capture, tmp_path):
    """``nerfbot eval RUN`` and ``nerfbot train --resume`` in real processes: exit code 2, one
    line on stderr naming the file, and the crafted file's code never runs."""
    folder = _copy_run(run, tmp_path / "run")
    marker = tmp_path / "MARKER"
    (folder / CHECKPOINT).write_bytes(pickle.dumps({"spec": _Malicious(marker)}))
    for argv, command in (
            (["eval", str(folder), "--data", str(tiny_capture[0])], "eval"),
            (["train", "--data", str(tiny_capture[0]), "--out", str(folder), "--resume",
              "--max-steps", "6", "--seed", "1", "--no-progress", *TINY_FLAGS], "train")):
        result = _cli(*argv)
        assert result.returncode == 2, result.stderr
        lines = [ln for ln in result.stderr.splitlines() if " error: " in ln]
        assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
        assert lines[0].startswith(f"nerfbot {command}: error: {folder / CHECKPOINT} is refused")
        assert not marker.exists()


# ----------------------------------------------------------------------------- damaged files

def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(bytes(range(256)) * 16)
    else:
        path.unlink()


@pytest.mark.parametrize("how,message", [("truncated", "is truncated or corrupt"),
                                         ("empty", "is empty"),
                                         ("garbage", "is truncated or corrupt"),
                                         ("missing", "does not exist")],
                         ids=["truncated", "empty", "garbage", "missing"])
def test_a_damaged_checkpoint_falls_back_to_the_previous_one(run, dataset, tmp_path, caplog,
                                                              how, message):
    folder = _copy_run(run, tmp_path / "run")
    _damage(folder / CHECKPOINT, how)
    with caplog.at_level(logging.WARNING, logger="nerfbot.train.checkpoints"):
        model, info = load_model(folder)
    assert info["step"] == 2
    warning = " ".join(r.getMessage() for r in caplog.records)
    assert str(folder / CHECKPOINT) in warning and str(folder / PREV) in warning
    assert message in warning
    trainer = Trainer(dataset, folder, _resume_config())
    assert trainer.load() and trainer.step == 2
    if how != "missing":
        with pytest.raises(CheckpointError) as err:
            read_checkpoint(folder / CHECKPOINT)
        assert str(err.value).startswith(f"{folder / CHECKPOINT} {message}")
        assert "\n" not in str(err.value)


def test_damaged_checkpoints_without_a_good_previous_one_are_errors(run, tmp_path):
    folder = _copy_run(run, tmp_path / "run")
    _damage(folder / CHECKPOINT, "truncated")
    _damage(folder / PREV, "empty")
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt is truncated or corrupt .*"
                                              r"checkpoint\.prev\.pt is empty"):
        load_model(folder)
    (folder / PREV).unlink()
    with pytest.raises(CheckpointError, match=r"^\S*checkpoint\.pt is truncated or corrupt"):
        load_model(folder)
    (folder / CHECKPOINT).unlink()
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_model(folder)


@pytest.mark.parametrize("content,message", [
    ({"weights": torch.ones(3)}, "is not a nerfbot checkpoint"),
    (torch.ones(3), "is not a nerfbot checkpoint"),
    ({"format": "someone-else", "spec": {}, "model": {}}, "is not a nerfbot checkpoint"),
    ({"format": FORMAT, "version": VERSION + 1}, "written by a newer nerfbot"),
], ids=["dict_of_tensors", "bare_tensor", "other_format", "newer_version"])
def test_foreign_checkpoints_are_refused_not_replaced(run, tmp_path, content, message):
    """Files that read fine but are not nerfbot checkpoints are errors even when a good
    previous checkpoint exists: only damage falls back to it."""
    folder = _copy_run(run, tmp_path / "run")
    torch.save(content, folder / CHECKPOINT)
    with pytest.raises(CheckpointError, match=re.escape(f"{folder / CHECKPOINT}") + ".*" + message):
        load_model(folder)


def test_a_checkpoint_missing_a_key_is_named(run, dataset, tmp_path):
    folder = _copy_run(run, tmp_path / "run")
    ckpt = read_checkpoint(folder / CHECKPOINT)
    del ckpt["optimizer"]
    torch.save(ckpt, folder / CHECKPOINT)
    load_model(folder)  # evaluation needs no optimiser
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt: checkpoint has no 'optimizer'"):
        Trainer(dataset, folder, _resume_config()).load()


# ----------------------------------------------------------------------------- durable writes

def test_a_failed_write_leaves_the_checkpoint_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / CHECKPOINT
    write_durable({"a": torch.zeros(2)}, path)
    write_durable({"a": torch.ones(2)}, path)
    assert torch.equal(torch.load(tmp_path / PREV)["a"], torch.zeros(2))
    real_save = torch.save

    def disk_full(obj, f):
        real_save(obj, f)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    with pytest.raises(OSError, match="No space"):
        write_durable({"a": torch.full((2,), 2.0)}, path)
    assert torch.equal(torch.load(path)["a"], torch.ones(2))
    assert torch.equal(torch.load(tmp_path / PREV)["a"], torch.zeros(2))
    assert {p.name for p in tmp_path.iterdir()} == {CHECKPOINT, PREV}


def test_a_complete_checkpoint_exists_at_every_rename(tmp_path, monkeypatch):
    """Every rename of a durable write happens with a complete, synced checkpoint in place."""
    import nerfbot.train.checkpoints as ck

    path = tmp_path / CHECKPOINT
    synced, seen = set(), []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        synced.add(os.path.realpath(f"/proc/self/fd/{fd}"))
        real_fsync(fd)

    def replace(src, dst):
        assert os.path.realpath(src) in synced or Path(src).name.startswith(f".{PREV}")
        good = [p.name for p in (path, tmp_path / PREV) if p.exists() and "n" in torch.load(p)]
        seen.append((Path(dst).name, good))
        real_replace(src, dst)

    monkeypatch.setattr(ck.os, "fsync", fsync)
    monkeypatch.setattr(ck.os, "replace", replace)
    for n in range(3):
        write_durable({"n": n}, path)
    assert [dst for dst, _ in seen] == [CHECKPOINT, PREV, CHECKPOINT, PREV, CHECKPOINT]
    assert all(good for _, good in seen[1:])  # after the first write, never without one
    assert torch.load(path)["n"] == 2 and torch.load(tmp_path / PREV)["n"] == 1


def test_stale_temporaries_are_removed_on_resume(run, dataset, tmp_path):
    folder = _copy_run(run, tmp_path / "run")
    for name in (f".{CHECKPOINT}.tmp999999", f".{PREV}.tmp999999"):
        (folder / name).write_bytes(b"partial")
    assert len(stale_temporaries(folder / CHECKPOINT)) == 2
    assert Trainer(dataset, folder, _resume_config()).load()
    assert not stale_temporaries(folder / CHECKPOINT)


# ----------------------------------------------------------------------------- resume spec

@pytest.fixture(scope="module")
def other_dataset(tiny_capture, tmp_path_factory):
    """The tiny capture with one camera moved 1 cm: another dataset with the same files."""
    folder = tmp_path_factory.mktemp("other") / "tabletop"
    shutil.copytree(tiny_capture[0], folder)
    doc = json.loads((folder / "transforms.json").read_text())
    doc["frames"][0]["transform_matrix"][0][3] += 0.01
    (folder / "transforms.json").write_text(json.dumps(doc))
    return folder


@pytest.mark.parametrize("change,expected", [
    (["--option", "log2_hashmap_size=13"],
     "option log2_hashmap_size=13, but the run was made without it"),
    ("other_dataset", "another dataset"),
    (["--aabb", "-0.6", "-0.6", "0.0", "0.6", "0.6", "0.5"], "bounds --aabb -0.6 -0.6 0 0.6"),
    (["--seed", "5"], "seed 5, but the run was made with 0"),
], ids=["log2_hashmap_size", "dataset", "aabb", "seed"])
def test_resume_with_another_spec_is_refused_and_changes_nothing(
        cli_run, tiny_capture, other_dataset, tmp_path, capsys, change, expected):
    folder = _copy_run(cli_run, tmp_path / "run")
    before = _tree_digest(folder)
    data = other_dataset if change == "other_dataset" else tiny_capture[0]
    extra = [] if change == "other_dataset" else change
    capsys.readouterr()
    code = main(["train", "--data", str(data), "--method", "ngp", "--max-steps", "6", "--out",
                 str(folder), "--resume", "--no-progress", *TINY_FLAGS, *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith(f"nerfbot train: error: {folder}: --resume with ") and "\n" not in err
    assert expected in err and "train into a new --out" in err
    assert _tree_digest(folder) == before


def test_resume_accepts_new_budgets_and_names_every_difference(run, dataset):
    trainer = Trainer(dataset, run, _resume_config(max_steps=40, eval_at_steps=(5,),
                                                   checkpoint_every_steps=7))
    assert trainer.load() and trainer.step == 4  # budgets and cadence may change
    changed = _resume_config(seed=2, background="white",
                             options={**TINY, "log2_hashmap_size": 13, "grid_update_every": 8})
    with pytest.raises(ValueError) as err:
        Trainer(dataset, run, changed).load()
    text = str(err.value)
    assert text.startswith(f"{run}: --resume with ")
    for part in ("option grid_update_every=8, but the run was made with 4",
                 "option log2_hashmap_size=13, but the run was made without it",
                 "background white, but the run was made with learned",
                 "seed 2, but the run was made with 1"):
        assert part in text
    with pytest.raises(ValueError, match="method 'nerf', but the run was made with 'ngp'"):
        Trainer(dataset, run, _resume_config(method="nerf", options={})).load()


def test_older_checkpoints_without_a_dataset_identity_still_resume(run, dataset, tmp_path):
    folder = _copy_run(run, tmp_path / "run")
    ckpt = read_checkpoint(folder / CHECKPOINT)
    for key in ("format", "version"):
        del ckpt[key]
    del ckpt["spec"]["dataset"]
    torch.save(ckpt, folder / CHECKPOINT)
    trainer = Trainer(dataset, folder, _resume_config())
    assert trainer.load() and trainer.step == 4
    assert trainer.spec["dataset"]["num_frames"] == 20  # stored from now on


# ----------------------------------------------------------------------------- hash grid

def test_the_hash_grid_refuses_a_table_that_does_not_fit_its_levels():
    small = HashEncoding(n_levels=4, log2_size=10, min_res=4, max_res=64, seed=0)
    big = HashEncoding(n_levels=4, log2_size=12, min_res=4, max_res=64, seed=0)
    rows = int(big.offsets[-1])
    x = torch.rand(64, 3)
    with pytest.raises(ValueError, match=f"hash table is {small.table.shape[0]} x 2 .* need "
                                         f"{rows} x 2"):
        big.load_state_dict(small.state_dict())
    resize_like_state_dict(big, small.state_dict())  # what a loader does before loading
    with pytest.raises(ValueError, match=f"need {rows} x 2"):
        big.load_state_dict(small.state_dict())
    with pytest.raises(ValueError, match=f"need {rows} x 2"):
        big(x)  # resized but never loaded: the kernels are not reached either
    assert small(x).shape == (64, 8)


def test_a_checkpoint_whose_table_does_not_fit_its_spec_is_refused(run, tmp_path):
    """A crafted checkpoint: spec says log2_hashmap_size 13, the table has the default rows."""
    folder = _copy_run(run, tmp_path / "run")
    ckpt = read_checkpoint(folder / CHECKPOINT)
    ckpt["spec"]["options"]["log2_hashmap_size"] = 13
    torch.save(ckpt, folder / CHECKPOINT)
    with pytest.raises(CheckpointError, match=r"checkpoint\.pt: the model tensors do not fit "
                                              r"method 'ngp': .*encoding\.table: hash table is"):
        load_model(folder)
    model = build_model("ngp", ckpt["spec"]["aabb"], options={"log2_hashmap_size": 13})
    resize_like_state_dict(model, ckpt["model"])  # the table now has the checkpoint's rows
    with pytest.raises(ValueError, match="hash table is"):
        model.field.encoding(torch.rand(8, 3))


def test_checkpoint_cadence_is_validated():
    with pytest.raises(ValueError, match="checkpoint_every_steps"):
        TrainConfig(max_steps=1, checkpoint_every_steps=0).validate()
    with pytest.raises(ValueError, match="checkpoint_every_seconds"):
        TrainConfig(max_steps=1, checkpoint_every_seconds=float("nan")).validate()


# ----------------------------------------------------------------------------- kill -9

KILL_STEPS, KILL_EVERY = 18, 3


def _train_argv(data: Path, out: Path) -> list[str]:
    return ["train", "--data", str(data), "--method", "ngp", "--max-steps", str(KILL_STEPS),
            "--checkpoint-every-steps", str(KILL_EVERY), "--checkpoint-every-seconds", "inf",
            "--seed", "3", "--no-progress", "--out", str(out), *TINY_FLAGS]


def _kill_during_a_checkpoint_write(argv: list[str], run: Path, log: Path) -> str:
    """Start ``nerfbot ARGV`` and SIGKILL it the moment a temporary checkpoint appears in
    ``run`` after two complete checkpoints exist (``checkpoint.prev.pt`` with no write under
    way). "landed": the temporary is still there after the kill; "missed": the write finished
    first; "finished": the run ended without such a write."""
    with open(log, "a") as err:
        proc = subprocess.Popen([sys.executable, "-m", "nerfbot.app.cli", *argv], cwd=ROOT,
                                env=_env(), stdout=subprocess.DEVNULL, stderr=err)
    tmp = run / f".{CHECKPOINT}.tmp{proc.pid}"
    armed = False
    try:
        while proc.poll() is None:
            writing = tmp.exists()
            armed = armed or (not writing and (run / PREV).exists())
            if armed and writing:
                os.kill(proc.pid, signal.SIGKILL)
                assert proc.wait() == -signal.SIGKILL
                return "landed" if tmp.exists() else "missed"
            time.sleep(0.001)  # polling only; nothing asserts on time
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, log.read_text()
    return "finished"


def test_kill_9_during_a_checkpoint_write_resumes_to_the_same_parameters(tiny_capture, tmp_path):
    """A real training process killed while it writes a checkpoint (SIGKILL, a temporary file
    on disk) resumes from the last complete checkpoint (at most one checkpoint interval lost),
    leaves no temporary behind, and ends bit-identical to an uninterrupted run."""
    data = tiny_capture[0]
    straight = _cli(*_train_argv(data, tmp_path / "straight"))
    assert straight.returncode == 0, straight.stderr

    run, log = tmp_path / "killed", tmp_path / "killed.log"
    argv, outcome, attempts = _train_argv(data, run), "missed", 0
    while outcome == "missed" and attempts < 4:  # a kill may miss a write; try the next one
        outcome = _kill_during_a_checkpoint_write(argv, run, log)
        argv, attempts = _train_argv(data, run) + ["--resume"], attempts + 1
    assert outcome == "landed", f"no kill landed during a checkpoint write:\n{log.read_text()}"
    assert stale_temporaries(run / CHECKPOINT), "the kill left a partial checkpoint"
    last = read_checkpoint(run / CHECKPOINT)["step"]  # complete, as is the previous one
    # the previous checkpoint is the one before, or already this one (killed between renames)
    assert read_checkpoint(run / PREV)["step"] in (last - KILL_EVERY, last)
    killed_at = last + KILL_EVERY  # the step whose checkpoint was being written

    resumed = _cli(*_train_argv(data, run), "--resume")
    assert resumed.returncode == 0, resumed.stderr
    found = re.search(r"resumed \S+ at step (\d+)", resumed.stderr)
    assert found, resumed.stderr
    assert int(found.group(1)) == last >= killed_at - KILL_EVERY
    assert not stale_temporaries(run / CHECKPOINT)

    a = read_checkpoint(tmp_path / "straight" / CHECKPOINT)
    b = read_checkpoint(run / CHECKPOINT)
    assert a["step"] == b["step"] == KILL_STEPS
    assert a["model"].keys() == b["model"].keys()
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), f"{k} differs after kill and resume"
    for k, state in a["optimizer"]["state"].items():
        assert torch.equal(state["exp_avg"], b["optimizer"]["state"][k]["exp_avg"])
    assert torch.equal(a["generator"], b["generator"])


# ----------------------------------------------------------------------------- saved configs

def test_config_retrains_a_run_exactly_and_refuses_other_flags(cli_run, tmp_path, capsys):
    """``train --config RUN/config.json`` makes the same run again (same metrics, to the last
    digit, for a step budget); a run flag that differs from the file is refused."""
    again = tmp_path / "again"
    assert main(["train", "--config", str(cli_run / "config.json"), "--out", str(again),
                 "--no-progress"]) == 0
    first = json.loads((cli_run / "metrics.json").read_text())
    second = json.loads((again / "metrics.json").read_text())
    assert second["steps"] == first["steps"] == 4
    assert second["psnr"] == first["psnr"] and second["depth_mae_m"] == first["depth_mae_m"]
    saved = json.loads((again / "config.json").read_text())
    assert saved["train"]["options"] == json.loads(
        (cli_run / "config.json").read_text())["train"]["options"]
    capsys.readouterr()
    assert main(["train", "--config", str(cli_run / "config.json"), "--out",
                 str(tmp_path / "other"), "--seed", "3", "--option", "grid_update_every=8",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--config: --option" in err and "--seed 3 (the run's: 0)" in err
    assert not (tmp_path / "other").exists()
    assert main(["train", "--config", str(tmp_path / "none.json"), "--out",
                 str(tmp_path / "x"), "--no-progress"]) == 2
    assert "none.json: no such file" in capsys.readouterr().err


def test_resume_takes_the_saved_configuration(cli_run, tmp_path, capsys):
    """``train --out RUN --resume`` needs no other flag: data, method and options are the
    run's; a training weight that differs from the run's is refused, and nothing changes."""
    folder = _copy_run(cli_run, tmp_path / "run")
    assert main(["train", "--out", str(folder), "--resume", "--max-steps", "6",
                 "--no-progress"]) == 0
    assert json.loads((folder / "metrics.json").read_text())["steps"] == 6
    before = _tree_digest(folder)
    capsys.readouterr()
    assert main(["train", "--out", str(folder), "--resume", "--max-steps", "8",
                 "--depth-weight", "0.5", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--resume with --depth-weight 0.5 (the run's: 0.0)" in err
    assert _tree_digest(folder) == before
    assert main(["train", "--out", str(tmp_path / "new"), "--max-steps", "2",
                 "--no-progress"]) == 2
    assert "--data DIR is needed" in capsys.readouterr().err
