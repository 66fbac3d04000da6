"""The README's Python blocks are programs: every name a block uses is defined in it or in
an earlier block of its section (checked statically in the default run), and each section
runs as written, top to bottom in one namespace (together they compile most of the package).

A block that defines every name it uses (its own imports and data) begins a new section --
the helix blocks, the DNA blocks, the finite-rod blocks -- and each section runs in a fresh
namespace, so the heavy tier's workers can share them out.  All three run in the heavy
tier: the helix section in about 4 minutes, the DNA section in 5-8 and the finite-rod
section in about 10 (measured 593 s on one core with another process on the other; its
shape fit compiled for about 15 minutes until the fit's Jacobian was traced once per
step, `with_materialised_jacobian`, and the shooting Jacobian stopped integrating the
flows again, `shooting_jacobian`)."""

import ast
import builtins
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks():
    return re.findall(r"^```python\n(.*?)^```", README.read_text(encoding="utf-8"), re.S | re.M)


def _bound(tree) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and isinstance(node.ctx, (ast.Store, ast.Del)):
            names.add(node.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
    return names


def _used(tree) -> set[str]:
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}


def _sections() -> list[list[tuple[int, str]]]:
    """The blocks (numbered from 1) in sections: a new section at each block that uses only
    names it defines."""
    sections = []
    for number, block in enumerate(_blocks(), start=1):
        tree = ast.parse(block, filename=f"README.md block {number}")
        if not sections or _used(tree) <= _bound(tree) | set(dir(builtins)):
            sections.append([])
        sections[-1].append((number, block))
    return sections


def test_readme_blocks_define_every_name_they_use():
    sections = _sections()
    assert sum(map(len, sections)) >= 9 and len(sections) >= 3
    for section in sections:
        defined = set(dir(builtins))  # a section sees nothing of the sections before it
        for number, block in section:
            tree = ast.parse(block, filename=f"README.md block {number}")
            defined |= _bound(tree)
            used = _used(tree)
            assert used <= defined, f"README block {number} uses undefined names {sorted(used - defined)}"


@pytest.mark.heavy
@pytest.mark.parametrize("section", range(len(_sections())), ids=lambda i: f"section{i + 1}")
@pytest.mark.timeout(2400)  # a section compiles for minutes; on a loaded machine past the default 900 s
def test_readme_blocks_run(section, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the blocks write their files (atlas.npz, figures) here
    namespace: dict = {}
    for number, block in _sections()[section]:
        exec(compile(block, f"README.md block {number}", "exec"), namespace)  # noqa: S102
