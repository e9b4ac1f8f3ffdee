"""The README's set-up commands and CI stay in step."""

from __future__ import annotations

import re
from pathlib import Path

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
    assert project["scripts"]["nerfbot"] == "nerfbot.cli:main"
    for dep in ("torch", "mujoco", "pycolmap", "open3d", "opencv-contrib-python-headless",
                "trimesh", "numpy", "tqdm"):
        assert any(d.startswith(dep) for d in project["dependencies"]), dep
    test_extra = project["optional-dependencies"]["test"]
    for dep in ("pytest", "hypothesis", "scipy", "nbclient", "nbformat", "ipykernel"):
        assert any(d.startswith(dep) for d in test_extra), dep
