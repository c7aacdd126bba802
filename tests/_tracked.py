"""The repository's tracked files, for the tests that read every text file (labels, outside pointers)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tracked_text_files(*, exclude: str, suffixes: tuple[str, ...] | None = None) -> list[Path]:
    """Tracked text files (no NUL byte in their first 8 KiB), ``exclude`` (the calling test, whose own examples would
    match) left out and, when given, only names ending in one of ``suffixes``; skips outside a git checkout."""
    try:
        listed = subprocess.run(
            ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    names = [n for n in listed.splitlines() if n != exclude and (suffixes is None or n.endswith(suffixes))]
    paths = [ROOT / name for name in names]
    return [path for path in paths if path.is_file() and b"\0" not in path.read_bytes()[:8192]]
