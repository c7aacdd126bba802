"""The demo entry point: a random rollout of every environment, drawn (the mazes, the arms)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402
from torchrl_dhrl.envs.demo import main as demo_main  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def test_demo_writes_png(tmp_path, capsys):
    path = demo_main(["--out", str(tmp_path), "--steps", "5", "--num-envs", "2"])
    assert path == tmp_path / "mazes.png" and path.stat().st_size > 10_000
    assert str(path) in capsys.readouterr().out
    image = plt.imread(path)
    assert image.ndim == 3 and image.shape[1] > 2 * image.shape[0]  # five maps side by side


def test_demo_writes_arm_picture(tmp_path):
    demo_main(["--out", str(tmp_path), "--steps", "3", "--num-envs", "1"])
    image = plt.imread(tmp_path / "arms.png")
    assert image.ndim == 3 and image.shape[0] > image.shape[1]  # two arms (rows) x two views
