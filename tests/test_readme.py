"""The README's Python blocks are a program: read top to bottom in one namespace, every name
they use is defined in them (checked statically in the default run), and they run as
written (slow: together they compile most of the package)."""

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


def test_readme_blocks_define_every_name_they_use():
    blocks = _blocks()
    assert len(blocks) >= 9
    defined = set(dir(builtins))
    for number, block in enumerate(blocks, start=1):
        tree = ast.parse(block, filename=f"README.md block {number}")
        defined |= _bound(tree)
        used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
        assert used <= defined, f"README block {number} uses undefined names {sorted(used - defined)}"


@pytest.mark.slow
def test_readme_blocks_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the blocks write their files (atlas.npz, figures) here
    namespace: dict = {}
    for number, block in enumerate(_blocks(), start=1):
        exec(compile(block, f"README.md block {number}", "exec"), namespace)  # noqa: S102
