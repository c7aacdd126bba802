"""The reproductions of docs/upstream.md still show the TorchRL gaps they document (update the doc when not)."""

import re
from pathlib import Path

import pytest

BLOCKS = re.findall(
    r"```python\n(.*?)```",
    (Path(__file__).resolve().parents[1] / "docs" / "upstream.md").read_text(),
    flags=re.S,
)


def test_her_replay_buffer_refuses_multi_dimensional_storage():
    with pytest.raises(NotImplementedError, match="1D storages"):
        exec(BLOCKS[0], {})


def test_collector_state_dict_misses_the_running_episode(capsys):
    exec(BLOCKS[1], {})
    out = capsys.readouterr().out
    assert "source continues at step [4, 5, 6, 7]" in out
    assert "restored collector at step [0, 5, 6, 7]" in out
