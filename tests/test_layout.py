"""The package's layout: ``import torchrl_dhrl`` loads the components only, and no module imports one that imports
it back."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import networkx as nx
import torchrl_dhrl.envs

import torchrl_dhrl

MACHINERY = ("hydra", "omegaconf", "yaml", "matplotlib")


def _modules() -> dict[str, Path]:
    """Every module of the package (``envs/`` is mapped into it from the top level), by dotted name."""
    found = {}
    for package in (torchrl_dhrl, torchrl_dhrl.envs):
        root = Path(package.__path__[0])
        for path in root.rglob("*.py"):
            if package is torchrl_dhrl and "envs" in path.relative_to(root).parts[:1]:
                continue
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package.__name__, *parts])] = path
    return found


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package modules ``name`` imports anywhere in its code (module level and inside functions)."""
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            targets = [base] + [f"{base}.{alias.name}" for alias in node.names]
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


def test_import_torchrl_dhrl_loads_no_machinery():
    code = (
        "import sys, torchrl_dhrl\n"
        "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in ('hydra', 'omegaconf', 'matplotlib')\n"
        "    or m.startswith(('torchrl_dhrl.diagnostics', 'torchrl_dhrl.recipe')))))\n"
        "print(' '.join(sorted(m for m in sys.modules if m.startswith('torchrl_dhrl'))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    forbidden, loaded = out.split("\n")[:2]
    assert forbidden == ""
    # yaml may come with TorchRL's optional dependencies (ray): no loaded module of ours imports it at import time
    modules = _modules()
    for name in loaded.split():
        if name in modules:
            top_level = set()
            for node in ast.parse(modules[name].read_text()).body:
                if isinstance(node, ast.Import):
                    top_level |= {alias.name.split(".")[0] for alias in node.names}
                elif isinstance(node, ast.ImportFrom) and not node.level:
                    top_level.add((node.module or "").split(".")[0])
            assert not top_level & set(MACHINERY), (name, top_level & set(MACHINERY))


def test_no_import_cycles():
    modules = _modules()
    graph = nx.DiGraph()
    for name, path in modules.items():
        for target in _imports(name, path, modules):
            # a module importing its own package's __init__ for names is a cycle too, but a package importing
            # its submodules is the package's job: only edges out of __init__ into its own subtree are exempt
            graph.add_edge(name, target)
    cycles = [
        cycle
        for cycle in nx.simple_cycles(graph)
        if not any(
            a in modules and modules[a].name == "__init__.py" and b.startswith(a + ".")
            for a, b in zip(cycle, cycle[1:] + cycle[:1], strict=True)
        )
    ]
    assert cycles == []


def test_the_layout_separates_components_diagnostics_and_recipe():
    modules = _modules()
    library = [m for m in modules if not m.startswith(("torchrl_dhrl.diagnostics", "torchrl_dhrl.recipe"))]
    for name in library:  # the components know neither the diagnostics nor the recipe
        imported = _imports(name, modules[name], modules)
        assert not [
            m for m in imported if m.startswith(("torchrl_dhrl.diagnostics", "torchrl_dhrl.recipe"))
        ], name
    for name in [m for m in modules if m.startswith("torchrl_dhrl.diagnostics")]:
        imported = _imports(name, modules[name], modules)
        assert not [m for m in imported if m.startswith("torchrl_dhrl.recipe")], name
