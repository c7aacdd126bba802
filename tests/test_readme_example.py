"""The README's two composition examples (the factory's and the hand-composed one) run verbatim and learn something:
both levels update, a graph is built."""

import re
import runpy
import warnings
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"
MARKER = "<!-- composition example: run verbatim by tests/test_readme_example.py -->"
FACTORY_MARKER = "<!-- factory example: run verbatim by tests/test_readme_example.py -->"


def _example(marker: str = MARKER) -> str:
    text = README.read_text()
    assert marker in text, f"the README lost its example marker {marker}"
    match = re.search(r"```python\n(.*?)```", text[text.index(marker) :], flags=re.S)
    assert match, "no python block after the marker"
    return match.group(1)


def test_readme_factory_example_runs_verbatim_and_builds_the_reference_agent(tmp_path):
    path = tmp_path / "factory_example.py"
    path.write_text(_example(FACTORY_MARKER))
    ns = runpy.run_path(str(path), run_name="__main__")
    low, high = ns["updaters"]
    assert low.num_updates == high.num_updates == 40  # 4 episodes x 10 updates of each level
    for losses in ns["losses"]:
        assert all(torch.isfinite(value).all() for value in losses.values())
    agent = ns["agent"]
    assert agent.planner.has_graph and agent.planner.num_landmarks >= 2
    # the reference's wiring: the actor sees the waypoint relative to the achieved goal, the critics see it as is
    assert agent.low_actor.module.relative_goal
    assert not agent.sqgc_loss.policy_critic.module.relative_goal and not agent.sqgc_loss.graph_critic.module.relative_goal


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
