"""The README's composition example runs verbatim and learns something: both levels update, a graph is built."""

import re
import runpy
import warnings
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"
MARKER = "<!-- composition example: run verbatim by tests/test_readme_example.py -->"


def _example() -> str:
    text = README.read_text()
    assert MARKER in text, "the README lost its composition example marker"
    match = re.search(r"```python\n(.*?)```", text[text.index(MARKER) :], flags=re.S)
    assert match, "no python block after the marker"
    return match.group(1)


def test_readme_composition_example_runs_verbatim(tmp_path, capsys):
    path = tmp_path / "example.py"
    path.write_text(_example())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ns = runpy.run_path(str(path), run_name="__main__")
    # a newcomer's first run prints no FutureWarning of TorchRL's (e.g. the collector's InitTracker notice)
    assert not [w for w in caught if issubclass(w.category, FutureWarning) and "torchrl" in w.filename], [
        str(w.message)[:200] for w in caught
    ]
    # one update of each level happened, with finite losses, and the graph was built from buffer states
    assert ns["low_updater"].num_updates == 1 and ns["high_updater"].num_updates == 1
    for key in ("loss_policy_qvalue", "loss_graph_qvalue"):
        assert torch.isfinite(ns["low_out"][key])
    assert torch.isfinite(ns["high_out"]["loss_qvalue"])
    assert ns["planner"].has_graph and ns["planner"].num_landmarks >= 2
    # samples come out relabelled: the graph critics' goals (100% hindsight) with rewards recomputed for them
    sample = ns["low_rb"].sample()
    expected = ns["reward"](sample["next", "achieved_goal"], sample["graph_goal"])
    torch.testing.assert_close(
        sample["next", "graph_reward"], expected.reshape(sample["next", "graph_reward"].shape)
    )
    assert (sample["graph_goal"] != sample["waypoint"]).any(-1).float().mean() > 0.5
    assert "landmarks" in capsys.readouterr().out
