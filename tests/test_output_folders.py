"""Nothing the user made is deleted or overwritten, and run folders are relocatable.

Every command that writes an ``--out`` refuses a folder nerfbot did not make (exit code 2, the
folder byte-for-byte unchanged), replaces a folder it made only with ``--overwrite``, and a run
moved together with its dataset finds that dataset again, never another one.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from nerfbot.app.cli import main
from nerfbot.data.outputs import MARKER, check_output_folder, folder_kind, read_marker

pytestmark = pytest.mark.slow(20)  # rough single-core seconds (tests/conftest.py)

TINY = ["--no-progress", "--option", "samples_per_batch=4096"]
#: A capture small enough to render in a second.
SMALL_CAPTURE = ["--scene", "tabletop", "--views", "2", "--test-views", "1", "--size", "16",
                 "--no-progress"]


def snapshot(folder: Path) -> dict:
    """Every entry under ``folder``: relative path -> sha256 of a file's bytes ("dir" for a
    folder)."""
    found = {}
    for path in sorted(Path(folder).rglob("*")):
        rel = str(path.relative_to(folder))
        found[rel] = "dir" if path.is_dir() else hashlib.sha256(path.read_bytes()).hexdigest()
    return found


def _user_dataset(folder: Path, tiny: Path) -> None:
    """A user's own dataset: a plain nerfstudio transforms.json (no sims manifest) and images."""
    doc = json.loads((tiny / "transforms.json").read_text())
    doc.pop("scene")
    folder.mkdir(parents=True)
    (folder / "transforms.json").write_text(json.dumps(doc))
    shutil.copytree(tiny / "images", folder / "images")


def _foreign_folder(kind: str, tmp_path: Path, tiny: Path) -> Path:
    folder = tmp_path / f"theirs_{kind}"
    if kind == "notes":
        folder.mkdir()
        (folder / "notes.txt").write_text("my notes\n")
    elif kind == "config":
        folder.mkdir()
        (folder / "config.json").write_text(json.dumps({"lr": 0.1, "data": "elsewhere"}))
        (folder / "metrics.json").write_text(json.dumps({"psnr": 99.0}))
    else:
        _user_dataset(folder, tiny)
    return folder


def _modified_dataset(src: Path, dst: Path) -> None:
    """A copy of the dataset at ``src`` whose first camera moved by 1 cm: another dataset."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst)
    doc = json.loads((dst / "transforms.json").read_text())
    doc["frames"][0]["transform_matrix"][0][3] += 0.01
    (dst / "transforms.json").write_text(json.dumps(doc))


@pytest.fixture(scope="module")
def moved_run(tiny_capture, tmp_path_factory):
    """(root, run, data): a run trained from ``root/a`` with relative paths (``--data data
    --out run``), then ``root/a`` renamed to ``root/b``: the stored absolute path is gone."""
    root = tmp_path_factory.mktemp("moved")
    shutil.copytree(tiny_capture[0], root / "a" / "data")
    cwd = os.getcwd()
    os.chdir(root / "a")
    try:
        assert main(["train", "--data", "data", "--max-steps", "3", "--out", "run", *TINY]) == 0
    finally:
        os.chdir(cwd)
    os.rename(root / "a", root / "b")
    return root, root / "b" / "run", root / "b" / "data"


def _eval(run, capsys, *extra) -> tuple[int, dict | str]:
    capsys.readouterr()
    code = main(["eval", str(run), "--json", "--supersample", "1", *extra])
    out = capsys.readouterr()
    return code, (json.loads(out.out) if code == 0 else out.err)


# -- the rule ----------------------------------------------------------------------------------
def test_rule_states_and_markers(tmp_path, moved_run):
    _, run, data = moved_run
    assert check_output_folder(tmp_path / "new", "run").state == "new"
    (tmp_path / "empty").mkdir()
    assert check_output_folder(tmp_path / "empty", "run").state == "empty"
    assert read_marker(run) == "run" and read_marker(data) == "dataset"
    assert check_output_folder(run, "run", resume=True).state == "resume"
    assert check_output_folder(run, "run", overwrite=True).state == "replace"
    with pytest.raises(FileExistsError, match="--resume to continue it or --overwrite"):
        check_output_folder(run, "run")
    with pytest.raises(FileExistsError, match="a training run, not a baked run"):
        check_output_folder(run, "baked_run", overwrite=True)
    (tmp_path / "file").write_text("x")
    with pytest.raises(FileExistsError, match="a file is in the way"):
        check_output_folder(tmp_path / "file", "render")


def test_folders_made_before_the_marker(tmp_path, moved_run, tiny_capture):
    """A run (config.json with a spec + checkpoint.pt) and a sims capture (transforms.json with
    the scene manifest) are recognised without a marker; a user's dataset is not."""
    _, run, data = moved_run
    old_run, old_data = tmp_path / "run", tmp_path / "data"
    shutil.copytree(run, old_run)
    shutil.copytree(data, old_data)
    (old_run / MARKER).unlink()
    (old_data / MARKER).unlink()
    assert folder_kind(old_run) == "run" and folder_kind(old_data) == "dataset"
    _user_dataset(tmp_path / "user", tiny_capture[0])
    assert folder_kind(tmp_path / "user") is None


def test_files_the_user_added_block_overwrite_not_resume(tmp_path, moved_run):
    _, run, _ = moved_run
    mine = tmp_path / "run"
    shutil.copytree(run, mine)
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match=r"notes\.txt.*--overwrite would delete them"):
        check_output_folder(mine, "run", overwrite=True)
    assert check_output_folder(mine, "run", resume=True).state == "resume"


# -- capture -----------------------------------------------------------------------------------
@pytest.mark.parametrize("theirs", ["notes", "config", "user_dataset"])
def test_capture_refuses_a_folder_it_did_not_make(theirs, tmp_path, tiny_capture, capsys):
    folder = _foreign_folder(theirs, tmp_path, tiny_capture[0])
    before = snapshot(folder)
    for flags in ([], ["--overwrite"]):
        capsys.readouterr()
        assert main(["capture", *SMALL_CAPTURE, "--out", str(folder), *flags]) == 2
        err = capsys.readouterr().err
        assert str(folder) in err and "not made by nerfbot" in err and len(err.splitlines()) == 1
        assert snapshot(folder) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [folder.name]  # no partial folder


def test_capture_overwrite_replaces_only_its_own_dataset(tmp_path, capsys):
    out = tmp_path / "ds"
    assert main(["capture", *SMALL_CAPTURE, "--out", str(out)]) == 0
    assert read_marker(out) == "dataset"
    before = snapshot(out)
    capsys.readouterr()
    assert main(["capture", *SMALL_CAPTURE, "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err and snapshot(out) == before

    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    assert main(["capture", *SMALL_CAPTURE, "--out", str(out), "--overwrite"]) == 2
    assert "notes.txt" in capsys.readouterr().err and snapshot(out) == before

    (out / "notes.txt").unlink()
    assert main(["capture", *SMALL_CAPTURE[:2], "--views", "3", "--test-views", "1",
                 "--size", "16", "--no-progress", "--out", str(out), "--overwrite"]) == 0
    doc = json.loads((out / "transforms.json").read_text())
    assert len(doc["train_filenames"]) == 3 and read_marker(out) == "dataset"


# -- train -------------------------------------------------------------------------------------
@pytest.mark.parametrize("theirs", ["notes", "config", "user_dataset"])
def test_train_refuses_a_folder_it_did_not_make(theirs, tmp_path, tiny_capture, capsys):
    folder = _foreign_folder(theirs, tmp_path, tiny_capture[0])
    before = snapshot(folder)
    for flags in ([], ["--overwrite"], ["--resume"]):
        capsys.readouterr()
        assert main(["train", "--data", str(tiny_capture[0]), "--max-steps", "1",
                     "--out", str(folder), *TINY, *flags]) == 2
        assert str(folder) in capsys.readouterr().err
        assert snapshot(folder) == before


def test_a_failed_train_leaves_no_folder(tmp_path, tiny_capture, capsys):
    """An unknown option is refused before the folder is made; a bad value fails while the
    model is built, and the folder (and the parents it made) is removed."""
    for option, out in (("no_such_option=1", tmp_path / "r1"),
                        ('log2_hashmap_size="abc"', tmp_path / "new" / "deep" / "r2")):
        assert main(["train", "--data", str(tiny_capture[0]), "--max-steps", "1",
                     "--out", str(out), "--no-progress", "--option", option]) != 0
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "empty").mkdir()  # an empty folder of the user's stays, empty
    assert main(["train", "--data", str(tiny_capture[0]), "--max-steps", "1",
                 "--out", str(tmp_path / "empty"), "--no-progress",
                 "--option", 'log2_hashmap_size="abc"']) != 0
    assert list((tmp_path / "empty").iterdir()) == []


def test_train_overwrite_starts_an_old_run_over(tmp_path, moved_run, capsys):
    _, run, data = moved_run
    old = tmp_path / "run"
    shutil.copytree(run, old)
    (old / "auto.json").write_text(json.dumps({"query_defaults": {"depth_mode": "median"}}))
    before = snapshot(old)
    train = ["train", "--data", str(data), "--max-steps", "2", "--out", str(old), *TINY]
    assert main(train) == 2 and snapshot(old) == before
    assert main([*train, "--resume", "--overwrite"]) == 2 and snapshot(old) == before
    assert main([*train, "--overwrite"]) == 0
    assert json.loads((old / "metrics.json").read_text())["steps"] == 2
    assert not (old / "auto.json").exists()  # nothing of the old run is left to mislead
    config = json.loads((old / "config.json").read_text())
    assert config["data"] == str(data) and config["data_relative"] == os.path.relpath(data, old)
    assert read_marker(old) == "run"


# -- bake --------------------------------------------------------------------------------------
def test_bake_refuses_the_run_itself_and_other_folders(tmp_path, moved_run, tiny_capture, capsys):
    _, run, _ = moved_run
    other_run = tmp_path / "other_run"
    shutil.copytree(run, other_run)
    folders = [run, other_run] + [_foreign_folder(k, tmp_path, tiny_capture[0])
                                  for k in ("notes", "config", "user_dataset")]
    before = {f: snapshot(f) for f in folders}
    for out in folders:
        for flags in ([], ["--overwrite"]):
            capsys.readouterr()
            assert main(["bake", str(run), "--cache", "16,8", "--out", str(out),
                         "--no-progress", *flags]) == 2
            err = capsys.readouterr().err
            assert str(out) in err
            if out == run:
                assert "the run being baked" in err
    assert {f: snapshot(f) for f in folders} == before


def test_write_baked_run_is_relocatable_and_guarded(tmp_path, moved_run):
    from nerfbot.train.baked_runs import write_baked_run
    from nerfbot.data.identity import dataset_identity
    from nerfbot.data.run_dataset import resolve_run_dataset
    from nerfbot.train.runs import load_model

    _, run, data = moved_run
    model, info = load_model(run)
    found, ds = resolve_run_dataset(run)
    spec = {**info["spec"], "dataset": dataset_identity(ds)}
    out = tmp_path / "baked"
    write_baked_run(model, spec, info, out, data=found)
    config = json.loads((out / "config.json").read_text())
    assert config["data"] == str(data) and config["data_relative"] == os.path.relpath(data, out)
    assert read_marker(out) == "baked_run" and resolve_run_dataset(out)[0] == data
    before = snapshot(out)
    with pytest.raises(FileExistsError, match="--overwrite"):
        write_baked_run(model, spec, info, out, data=found)
    assert snapshot(out) == before
    write_baked_run(model, spec, info, out, data=found, overwrite=True)
    assert read_marker(out) == "baked_run"


# -- render, bench, demo -----------------------------------------------------------------------
def test_render_refuses_what_it_did_not_make(tmp_path, moved_run, capsys):
    _, run, _ = moved_run
    orbit = ["render", str(run), "--path", "orbit", "--frames", "2", "--size", "16",
             "--no-progress"]
    notes = _foreign_folder("notes", tmp_path, Path())
    before = snapshot(notes)
    assert main([*orbit, "--out", str(notes), "--overwrite"]) == 2 and snapshot(notes) == before

    images = tmp_path / "images"
    assert main([*orbit, "--out", str(images)]) == 0 and read_marker(images) == "render"
    assert main([*orbit, "--out", str(images)]) == 2
    assert main([*orbit, "--frames", "1", "--out", str(images), "--overwrite"]) == 0
    assert sorted(p.name for p in images.glob("rgb_*")) == ["rgb_0000.png"]  # none stale

    video = tmp_path / "orbit.mp4"
    video.write_bytes(b"someone's video")
    assert main([*orbit, "--out", str(video)]) == 2
    assert video.read_bytes() == b"someone's video"
    assert main([*orbit, "--out", str(video), "--overwrite"]) == 0
    assert video.read_bytes() != b"someone's video"


def test_bench_and_demo_refuse_a_folder_they_did_not_make(tmp_path, tiny_capture, capsys):
    folder = _foreign_folder("notes", tmp_path, tiny_capture[0])
    before = snapshot(folder)
    capsys.readouterr()
    assert main(["bench", "--data", str(tiny_capture[0]), "--budgets", "1", "--budget-kind",
                 "steps", "--out", str(folder), "--no-progress"]) == 2
    assert "not made by nerfbot" in capsys.readouterr().err
    assert main(["demo", "--out", str(folder), "--seconds", "1", "--overwrite",
                 "--no-progress"]) == 2
    assert "not made by nerfbot" in capsys.readouterr().err
    assert snapshot(folder) == before


# -- relocatable runs ----------------------------------------------------------------------------
def test_a_moved_run_evaluates_its_own_dataset_from_anywhere(moved_run, tmp_path, monkeypatch,
                                                             capsys):
    """The run and its dataset moved together (relative layout kept): eval from another working
    directory finds the dataset next to the run, also when another dataset now sits at the
    stored absolute path."""
    root, run, data = moved_run
    config = json.loads((run / "config.json").read_text())
    assert config["data"] == str(root / "a" / "data") and config["data_relative"] == "../data"
    monkeypatch.chdir(tmp_path)
    code, found = _eval(run, capsys)
    assert code == 0 and found["data"] == str(data)

    _modified_dataset(data, root / "a" / "data")  # another dataset at the old absolute path
    try:
        code, again = _eval(run, capsys)
        assert code == 0 and again["data"] == str(data) and again["psnr"] == found["psnr"]
    finally:
        shutil.rmtree(root / "a")


def test_a_replaced_dataset_is_an_error_not_a_score(moved_run, tmp_path, capsys):
    """A run whose dataset was replaced by another one stops with a one-line error naming the
    file and field; --data still evaluates on any dataset."""
    _, run, data = moved_run
    copy = tmp_path / "b"
    shutil.copytree(run.parent, copy)
    _modified_dataset(data, copy / "data")
    code, err = _eval(copy / "run", capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert f"{copy / 'run' / 'config.json'}: data: the dataset at {copy / 'data'} is not the " \
           "one this run was trained on (other camera poses or intrinsics); pass --data DIR" in err
    assert main(["render", str(copy / "run"), "--path", "test", "--out",
                 str(tmp_path / "r"), "--no-progress"]) == 2
    assert not (tmp_path / "r").exists()
    code, out = _eval(copy / "run", capsys, "--data", str(copy / "data"))
    assert code == 0 and out["data"] == str(copy / "data")


def test_missing_dataset_and_config_errors(moved_run, tmp_path, capsys):
    _, run, _ = moved_run
    alone = tmp_path / "alone"
    shutil.copytree(run, alone)  # the run without its dataset
    code, err = _eval(alone, capsys)
    assert code == 2 and "config.json: data: no dataset at" in err and "--data DIR" in err

    config = json.loads((alone / "config.json").read_text())
    config.pop("data")
    (alone / "config.json").write_text(json.dumps(config))
    code, err = _eval(alone, capsys)
    assert code == 2 and f"{alone / 'config.json'}: data:" in err

    config.update(data="data")  # a relative path of an older nerfbot, relative to nowhere known
    config.pop("data_relative")
    (alone / "config.json").write_text(json.dumps(config))
    code, err = _eval(alone, capsys)
    assert code == 2 and "data: 'data' is relative" in err

    (alone / "config.json").write_text("{not json")
    code, err = _eval(alone, capsys)
    assert code == 2 and f"{alone / 'config.json'}: not readable JSON" in err
