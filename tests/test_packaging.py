"""Packaging checks: the wheel ships the envs as ``torchrl_dhrl.envs`` and the docs' commands agree."""

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(out),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
    )
    wheels = list(out.glob("torchrl_dhrl-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


@pytest.mark.slow
def test_wheel_layout(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert "torchrl_dhrl/__init__.py" in names
    assert "torchrl_dhrl/envs/__init__.py" in names
    # never a bare top-level ``envs`` package in site-packages
    assert not any(n.startswith("envs/") for n in names), [n for n in names if n.startswith("envs/")]
    for sub in ("modules", "objectives", "planner", "data", "training", "diagnostics", "recipe"):
        assert f"torchrl_dhrl/{sub}/__init__.py" in names
    assert "torchrl_dhrl/checks.py" in names


@pytest.mark.slow
def test_non_editable_install_imports_envs(wheel, tmp_path):
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
        check=True,
        capture_output=True,
    )
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]);"
        "import torchrl_dhrl.envs as e, gymnasium as gym;"
        "assert e.__file__.startswith(sys.argv[1]), e.__file__;"
        "env = e.make_env('PointMaze', seed=0); td = env.reset();"
        "assert td['observation'].shape[-1] == 6;"
        "g = gym.make('dhrl/AntMaze-v0'); o, _ = g.reset(seed=0);"
        "assert o['observation'].shape == (29,);"
        "print('ok')"
    )
    # run from a neutral directory so the source tree cannot shadow the installed wheel
    res = subprocess.run(
        [sys.executable, "-c", code, str(target)], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().endswith("ok")


def _readme_commands():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```(?:bash|sh)?\n(.*?)```", text, re.S)
    assert block, "README must start with a code block holding the two set-up commands"
    lines = [
        ln.strip() for ln in block.group(1).splitlines() if ln.strip() and not ln.strip().startswith("#")
    ]
    return lines


def test_readme_has_two_setup_commands_and_ci_runs_the_test_one():
    lines = _readme_commands()
    assert len(lines) == 2, lines
    install, test = lines
    assert "pip install" in install
    ci = (ROOT / ".ci" / "run").read_text()
    # CI runs exactly the README's test command (after its venv activation prefix)
    test_cmd = test.split("&&")[-1].strip()
    assert test_cmd in ci.splitlines(), (test_cmd, ci)


def test_everything_the_readme_calls_public_is_importable_from_the_package():
    """The names the README's table lists for the first five parts (envs, modules, objectives, planner, data),
    with ``LossUpdater`` and ``evaluate``, are attributes of ``torchrl_dhrl`` itself; the 0.1 aliases are gone."""
    import importlib

    import torchrl_dhrl

    text = (ROOT / "README.md").read_text()
    parts = ("envs", "modules", "objectives", "planner", "data")
    listed = {"LossUpdater", "evaluate"}
    for part in parts:
        row = re.search(rf"^\| `torchrl_dhrl\.{part}`[^\n]*", text, re.M)
        assert row, part
        homes = [importlib.import_module(f"torchrl_dhrl.{part}")]
        if part == "envs":
            homes.append(importlib.import_module("torchrl_dhrl.envs.transforms"))
        for token in re.findall(r"`([A-Za-z_]\w*)(?:\(|`)", row.group(0)):
            if any(token in getattr(home, "__all__", ()) for home in homes):
                listed.add(token)
    assert {"make_env", "plot_env", "AngleFeatures", "GraphPlanner", "RelabelReplayBuffer"} <= listed
    missing = sorted(name for name in listed if name not in torchrl_dhrl.__all__)
    assert not missing, missing
    envs = importlib.import_module("torchrl_dhrl.envs")
    for alias in ("MazeEnv", "MazeSimulation", "MazeGoalEnv"):
        assert not hasattr(envs, alias), alias
    assert not hasattr(envs.GoalEnv, "maze") and not hasattr(envs.GymGoalEnv, "maze")
    assert "count_hops" in importlib.import_module("torchrl_dhrl.planner").__all__


def test_the_version_is_the_changelog_s_latest_release():
    """pyproject's version, ``torchrl_dhrl.__version__`` and the CHANGELOG's newest dated release agree, and no doc
    cites a version the CHANGELOG does not release."""
    import torchrl_dhrl

    pyproject = (ROOT / "pyproject.toml").read_text()
    version = re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1)
    released = re.findall(r"^## \[(\d+\.\d+\.\d+)\] - \d{4}-\d{2}-\d{2}$", (ROOT / "CHANGELOG.md").read_text(), re.M)
    assert version == torchrl_dhrl.__version__ == released[0]
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "recipes/config/config.yaml"]:
        # the project's own versions, as the docs cite them ("from 0.4.0", "before 0.4.0", "since 0.2.0")
        for cited in re.findall(r"\b(?:from|before|since|in) (0\.\d+\.\d+)\b", doc.read_text()):
            assert cited in released, f"{doc.name} cites {cited}, which the CHANGELOG does not release"
