"""The README's set-up commands and CI stay in step."""

from __future__ import annotations

import re
from pathlib import Path

from nerfbot.methods import METHODS

ROOT = Path(__file__).resolve().parent.parent


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Set-up", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.+?)\n```", section)


def test_readme_has_two_setup_commands_demo_and_tests():
    cmds = _readme_commands()
    assert len(cmds) == 2, cmds
    demo, tests = cmds
    assert "pip install torch==2.13.0" in demo and demo.rstrip().endswith("nerfbot demo")
    assert '".[test]"' in tests and "pytest" in tests


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert _readme_commands()[1] in ci


def test_console_script_and_packages_declared():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["nerfbot"] == "nerfbot.app.cli:main"
    for dep in ("torch", "mujoco", "pycolmap", "open3d", "opencv-contrib-python-headless",
                "trimesh", "numpy", "tqdm"):
        assert any(d.startswith(dep) for d in project["dependencies"]), dep
    test_extra = project["optional-dependencies"]["test"]
    for dep in ("pytest", "hypothesis", "scipy", "nbclient", "nbformat", "ipykernel"):
        assert any(d.startswith(dep) for d in test_extra), dep


def _readme_section(title: str) -> str:
    return (ROOT / "README.md").read_text().split(f"## {title}", 1)[1].split("\n## ", 1)[0]


def test_readme_layout_lists_every_folder():
    """The layout block names every nerfbot subpackage and top-level module, and the project's
    top-level folders; everything it names exists."""
    block = re.search(r"```\n(.+?)\n```", _readme_section("Layout"), re.S).group(1)
    listed = {line.split()[0] for line in block.splitlines() if line.strip()}
    nerfbot = ROOT / "nerfbot"
    expected = {f"nerfbot/{p.name}/" for p in nerfbot.iterdir()
                if p.is_dir() and (p / "__init__.py").exists()}
    expected |= {f"nerfbot/{p.name}" for p in nerfbot.glob("*.py") if p.name != "__init__.py"}
    expected |= {"sims/", "tasks/", "docs/", "notebooks/", "tests/"}
    assert listed == expected, (f"README layout: missing {sorted(expected - listed)}, "
                                f"stale {sorted(listed - expected)}")


def test_readme_method_table_names_each_variants_files():
    """One row per registered method; its files exist and include the module of every config
    the registry builds it with (its field, its renderer, its bake recipe)."""
    rows = {}
    for line in _readme_section("Methods").splitlines():
        match = re.match(r"\| `(\w+)` \|", line)
        if match:
            rows[match.group(1)] = line.rstrip().rstrip("|").rsplit("|", 1)[1]
    assert set(rows) == set(METHODS)
    for method, cell in rows.items():
        files = set(re.findall(r"`([\w/]+\.py)`", cell))
        assert files, f"README: no files for {method}"
        for name in files:
            assert (ROOT / "nerfbot" / name).is_file(), f"README: {method}: no nerfbot/{name}"
        spec = METHODS[method]
        configs = spec.configs + (spec.baked_from.configs if spec.baked_from else ())
        for config in configs:
            module = type(config).__module__.removeprefix("nerfbot.").replace(".", "/") + ".py"
            if module.startswith(("fields/", "models/", "bake/")):
                assert module in files, f"README: {method} is built with {module}, not listed"
