"""The tracked text files point at no file outside the repository (notes a user of the package does not have)."""

from __future__ import annotations

from tests._tracked import ROOT, tracked_text_files

OUTSIDE = ("shared/reference", "../shared", "torchrl-notes", "official-implementation.md", "style-anchors")


def test_no_pointer_outside_the_repository():
    found = []
    for path in tracked_text_files(exclude="tests/test_self_contained.py"):
        for number, line in enumerate(path.read_text("utf-8", errors="replace").splitlines(), start=1):
            found += [f"{path.relative_to(ROOT)}:{number}: {word}" for word in OUTSIDE if word in line]
    assert not found, "pointers to files outside the repository:\n" + "\n".join(found)
