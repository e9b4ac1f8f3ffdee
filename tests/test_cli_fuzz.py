"""Property-based fuzz of the `nerfbot` command line: any argument list, whatever its flags and
values, ends in a one-line error with exit code 2 (its paths name nothing usable), never in
another exception, a traceback or a new file.

The flags come from the parser itself, so a flag added later is fuzzed too. Every path points
at a missing file or at a plain file, so no command gets far enough to capture or train.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nerfbot.app.cli import build_parser, main

#: Flags whose value is a path (every command's inputs and outputs).
PATH_DESTS = {"data", "out", "run", "poses", "bench_table", "plot", "scene"}
#: Flags left out: -v re-raises on purpose, --help prints and exits 0.
SKIP_DESTS = {"help", "verbose"}
#: Flags every generated command carries, so that no command starts real work.
REQUIRED_PATHS = {"capture": ("--scene", "--out"), "demo": ("--out",), "train": ("--data",),
                  "bench": ("--data",), "pixelnerf": ("--out",)}
#: Commands given an existing plain file as --out, which they must refuse before any work
#: (with any other --out they would capture a scene family and train).
FILE_OUT = {"demo", "pixelnerf"}

VALUES = st.sampled_from([
    "0", "-1", "1", "2", "3", "7", "-0", "0.5", "1e300", "-1e300", "1e-300", "nan", "inf", "-inf",
    "abc", "", " ", "1,2", "1,2,3", "0,0", "a,b", ",", "a=b", "x=1,y", "key=", "=3",
    "log2_hashmap_size=13", "log2_hashmap_size=-3", "samples_per_batch=0", "time", "door=1",
    "ngp", "auto", "nerf", "test", "train", "nope", "cuda", "cpu", "white", "2,0,0", "🙂", "\x00",
    "9" * 40, "-" * 3, "--", "1e309",
])


#: Values most flags accept, so that generated commands get past the parser as often as not.
PLAUSIBLE = st.sampled_from(["1", "2", "4", "0.5", "16"])


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser(eager=True)  # the capture command's arguments too
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


SUBCOMMANDS = _subcommands()


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli_fuzz")
    (root / "a_file.txt").write_text("not a dataset, a run or a scene\n")
    return root


def _path_value(root: Path):
    return st.sampled_from([str(root / "missing" / "x"), str(root / "a_file.txt"),
                            str(root / "missing.xml"), str(root / "missing.mp4"),
                            "builtin:nope"])


@st.composite
def command_lines(draw, root: Path) -> list[str]:
    name = draw(st.sampled_from(sorted(SUBCOMMANDS)))
    sub = SUBCOMMANDS[name]
    actions = [a for a in sub._actions if a.dest not in SKIP_DESTS]
    argv = [name]
    paths = _path_value(root)
    for action in actions:
        if not action.option_strings:  # a positional: the run folder
            argv.append(draw(paths))
    for flag in REQUIRED_PATHS.get(name, ()):
        value = draw(paths)
        if flag == "--out" and name in FILE_OUT:
            value = str(root / "a_file.txt")  # an existing file: the command must refuse it
        argv += [flag, value]
    optional = [a for a in actions if a.option_strings]
    required = [a for a in optional if a.required]
    chosen = required + draw(st.lists(st.sampled_from(optional), max_size=6))
    for action in chosen:
        flag = action.option_strings[-1] if action.required else \
            draw(st.sampled_from(action.option_strings))
        if flag in REQUIRED_PATHS.get(name, ()):
            continue
        if action.nargs == 0:
            argv.append(flag)
            continue
        count = {None: 1, "?": 1, "+": draw(st.integers(1, 3))}.get(action.nargs, action.nargs)
        if not isinstance(count, int):
            count = 1
        if action.dest in PATH_DESTS:
            values = [draw(paths) for _ in range(count)]
        elif action.choices and draw(st.booleans()):
            values = [str(draw(st.sampled_from(sorted(map(str, action.choices)))))
                      for _ in range(count)]
        else:
            values = [draw(st.one_of(PLAUSIBLE, VALUES)) for _ in range(count)]
        argv += [flag, *values]
    return argv


def _listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@settings(max_examples=150, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_any_command_line_ends_in_a_one_line_error(sandbox, data):
    argv = data.draw(command_lines(sandbox))
    before = _listing(sandbox)
    err = io.StringIO()
    cwd = os.getcwd()
    os.chdir(sandbox)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                code = main(argv)
            except SystemExit as exit_:  # argparse's own errors
                code = exit_.code
    finally:
        os.chdir(cwd)
    text = err.getvalue()
    errors = [line for line in text.splitlines() if "error:" in line]
    assert code == 2, (argv, code, text)
    assert len(errors) == 1 and errors[0].startswith("nerfbot"), (argv, text)
    assert "Traceback" not in text, (argv, text)
    assert _listing(sandbox) == before, (argv, "created or removed files")
