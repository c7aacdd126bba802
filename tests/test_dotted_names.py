"""Every dotted ``torchrl_dhrl.<...>`` name that the docs, docstrings and comments write resolves.

A name resolves when its longest importable module prefix imports and the rest is reached from it by ``getattr``.
Names inside Sphinx roles (``:class:`~torchrl_dhrl.x.Y```) and backticks count; a leading ``~``, a trailing ``()``
and punctuation are not part of the name. Scanned: ``README.md``, ``docs/*.md``, ``benchmarks/README.md``; the
docstrings (and other bare string statements) and comments of the Python files of ``torchrl_dhrl/``, ``envs/``,
``recipes/`` and ``benchmarks/``; the comments of ``recipes/config/**/*.yaml``.
"""

from __future__ import annotations

import ast
import importlib
import io
import re
import tokenize
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# a dotted name of the package: not the tail of a path or of a longer name
DOTTED = re.compile(r"(?<![\w/.])~?(torchrl_dhrl(?:\.[A-Za-z_]\w*)+)")
DOCS = [
    "README.md",
    "benchmarks/README.md",
    *sorted(p.relative_to(ROOT).as_posix() for p in ROOT.glob("docs/*.md")),
]
PYTHON_DIRS = ["torchrl_dhrl", "envs", "recipes", "benchmarks"]


def _python_text_lines(path: Path):
    """(line number, text) of the comments and of the bare string statements (docstrings) of a Python file."""
    source = path.read_text(encoding="utf-8")
    lines = source.splitlines()
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            yield token.start[0], token.string
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Expr)
            and isinstance(node.value, ast.Constant)
            and isinstance(node.value.value, str)
        ):
            for number in range(node.lineno, node.end_lineno + 1):
                yield number, lines[number - 1]


def _yaml_comment_lines(path: Path):
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if "#" in line:
            yield number, line[line.index("#") :]


def _text_lines(path: Path):
    yield from enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)


def _sources():
    for name in DOCS:
        yield name, _text_lines(ROOT / name)
    for folder in PYTHON_DIRS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            yield path.relative_to(ROOT).as_posix(), _python_text_lines(path)
    for path in sorted((ROOT / "recipes" / "config").rglob("*.yaml")):
        yield path.relative_to(ROOT).as_posix(), _yaml_comment_lines(path)


def collect_names() -> list[tuple[str, int, str]]:
    """(file, line, name) of every dotted package name written in the scanned text."""
    found = set()
    for file, lines in _sources():
        for number, text in lines:
            for match in DOTTED.finditer(text):
                found.add((file, number, match.group(1)))
    return sorted(found)


@cache
def resolves(name: str) -> bool:
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError as error:
            # only the module being tried may be missing: a broken import inside it is a failure of its own
            if error.name is None or not ".".join(parts[:cut]).startswith(error.name):
                raise
            continue
        for attribute in parts[cut:]:
            if not hasattr(obj, attribute):
                return False
            obj = getattr(obj, attribute)
        return True
    return False


def test_the_scan_finds_names():
    names = collect_names()
    files = {file for file, _, _ in names}
    assert len(names) > 50
    assert {"README.md", "docs/algorithm.md"} <= files and any(f.startswith("torchrl_dhrl/") for f in files)


def test_every_dotted_name_resolves():
    unresolved = [f"{file}:{line}: {name}" for file, line, name in collect_names() if not resolves(name)]
    assert not unresolved, f"{len(unresolved)} dotted names do not resolve:\n" + "\n".join(unresolved)


def test_the_resolver():
    assert resolves("torchrl_dhrl.planner.GraphPlanner.build")
    assert resolves("torchrl_dhrl.envs")
    assert not resolves("torchrl_dhrl.planner.NoSuchName")
    assert not resolves("torchrl_dhrl.no_such_module.name")
    assert DOTTED.findall(":class:`~torchrl_dhrl.planner.GraphPlanner`, torchrl_dhrl.recipe.train().") == [
        "torchrl_dhrl.planner.GraphPlanner",
        "torchrl_dhrl.recipe.train",
    ]
    assert DOTTED.findall("src/torchrl_dhrl.planner and torchrl_dhrl/planner/fgs.py") == []
