"""The paper's algorithm numbers used in code, comments and docs match the map of docs/algorithm.md.

docs/algorithm.md has one ``### Algorithm N, "Title"`` section per algorithm of the paper's Appendix A; that map
is checked against the paper's numbering, and every ``Algorithm N`` / ``Alg. N`` / ``Algorithms N and M`` written in
a tracked text file must come with algorithm N's title or one of its keywords in its paragraph (up to 5 lines either
side), and with no other algorithm's title on its line.
"""

from __future__ import annotations

import re

from tests._tracked import ROOT, tracked_text_files

# Appendix A of Lee et al. (NeurIPS 2022), in the paper's order
PAPER = {
    1: "Training DHRL",
    2: "Farthest Point Sampling",
    3: "Planning with DHRL",
    4: "Gradual Penalty",
    5: "Frontier-Based Goal-Shifting",
    6: "Overview of DHRL",
}
# words that a mention of each algorithm is expected to come with (case-insensitive)
KEYWORDS = {
    1: ("relabel", "hindsight", "subgoal test", "penalty"),
    2: ("farthest", "FPS"),
    3: ("plan", "waypoint"),
    4: ("gradual",),
    5: ("FGS", "goal shift", "frontier", "min_v"),
    6: ("loop", "warm-up", "warmup", "Env.reset", "episode", "epoch"),
}
HEADING = re.compile(r'^### Algorithm (\d+), "([^"]+)"', re.MULTILINE)
LABEL = re.compile(r"\bAlg(?:orithm)?s?\.?\s+(\d+)((?:\s*(?:,|and)\s*\d+)*)")
SUFFIXES = (".py", ".md", ".yaml", ".yml", ".toml", ".txt", ".rst")
REACH = 5


def _map() -> dict[int, str]:
    return {
        int(n): title for n, title in HEADING.findall((ROOT / "docs" / "algorithm.md").read_text("utf-8"))
    }


def labels_in(text: str):
    """(line number, algorithm number, its line, its paragraph) of every algorithm label of ``text``."""
    lines = text.splitlines()
    for index, line in enumerate(lines):
        for match in LABEL.finditer(line):
            numbers = [int(match.group(1)), *map(int, re.findall(r"\d+", match.group(2)))]
            start = index
            while start > max(index - REACH, 0) and lines[start - 1].strip():
                start -= 1
            end = index + 1
            while end < min(index + REACH + 1, len(lines)) and lines[end].strip():
                end += 1
            paragraph = " ".join(lines[start:end])
            for number in numbers:
                yield index + 1, number, line, paragraph


def mismatch(number: int, line: str, paragraph: str, titles: dict[int, str]) -> str | None:
    """Why the label ``number`` does not fit the text around it, or None."""
    if number not in titles:
        return f"Algorithm {number} is not in docs/algorithm.md's map"
    others = [n for n, title in titles.items() if n != number and title.lower() in line.lower()]
    if others and titles[number].lower() not in line.lower():
        return f"on the line of the title of Algorithm {others[0]} ({titles[others[0]]!r})"
    if not any(word.lower() in paragraph.lower() for word in (titles[number], *KEYWORDS[number])):
        return f"none of {titles[number]!r}'s words ({', '.join(KEYWORDS[number])}) in its paragraph"
    return None


def test_the_map_is_the_papers():
    assert _map() == PAPER


def test_labels_match_the_map():
    titles = _map()
    wrong = []
    # this file is left out: its own examples of wrong labels
    for path in tracked_text_files(exclude="tests/test_algorithm_labels.py", suffixes=SUFFIXES):
        name = path.relative_to(ROOT)
        for number_of_line, number, line, paragraph in labels_in(path.read_text("utf-8", errors="replace")):
            reason = mismatch(number, line, paragraph, titles)
            if reason:
                wrong.append(f"{name}:{number_of_line}: Algorithm {number}: {reason}")
    assert not wrong, "\n".join(wrong)


def test_the_check_catches_a_wrong_label():
    labels = list(
        labels_in(
            "The loop is Appendix A's Algorithm 1, \"Overview of DHRL\"\nthe paper's Algorithms 1 and 4"
        )
    )
    assert [(line, number) for line, number, _, _ in labels] == [(1, 1), (2, 1), (2, 4)]
    assert mismatch(1, *labels[0][2:], PAPER) is not None
    shifts = "DHRL's Algorithm 2 shifts the goal once the graph covers it"
    assert mismatch(2, shifts, shifts, PAPER) is not None
    assert mismatch(2, "(Algorithm 2)", "farthest point sampling\n(Algorithm 2)", PAPER) is None
