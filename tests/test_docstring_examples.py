"""Every **Example** block of a public docstring runs as written, in a fresh namespace
with the imports a reader has (`jax`, `jnp`, `np`, `helixrod`; float64).  Two examples once
used names defined nowhere (`fit_stiffness`, `linearity_check`), one unpacked two branch
points into one name (`follow_branch`), and one showed an atlas that was mostly
unresolved (`stability_atlas`)."""

import inspect
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import helixrod
from helixrod import dna, plot

_BLOCK = re.compile(r"\*\*Example\*\*[^\n]*\n+\s*```python\n(.*?)```", re.S)


def _documented():
    """(name, source) of every example block of the public objects and their methods."""
    seen, found = set(), []
    for module in (helixrod, dna, plot):
        for name in sorted(n for n in dir(module) if not n.startswith("_")):
            obj = getattr(module, name)
            members = [(name, obj)]
            if inspect.isclass(obj):
                members += [(f"{name}.{m}", getattr(obj, m)) for m in sorted(vars(obj)) if not m.startswith("_")]
            members.append((module.__name__, module))
            for label, member in members:
                doc = inspect.getdoc(member) or ""
                for i, block in enumerate(_BLOCK.findall(doc)):
                    source = inspect.cleandoc(block)
                    if source not in seen:
                        seen.add(source)
                        found.append((f"{label}[{i}]", source))
    return found


EXAMPLES = _documented()


def test_the_examples_are_found():
    names = {name.split("[")[0] for name, _ in EXAMPLES}
    assert {"fit_stiffness", "linearity_check", "follow_branch", "stability_atlas", "solve_static"} <= names, names


@pytest.mark.heavy  # ~15 examples, each compiling its programs
@pytest.mark.parametrize("name, source", EXAMPLES, ids=[name for name, _ in EXAMPLES])
def test_example_runs_as_written(name, source, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # an example that writes a figure writes it here
    namespace = dict(jax=jax, jnp=jnp, np=np, helixrod=helixrod, hr=helixrod, dna=dna)
    exec(compile(source, f"<example of {name}>", "exec"), namespace)
