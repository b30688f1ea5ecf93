"""Imports point one way: cli -> workflows -> models -> _kernels; io -> models; report -> models.

The source of every module of the package is parsed (ast, imports inside functions included)
and each import of another part of cfm_fem is checked against `ALLOWED`. A new upward import
fails with the file, line and import named.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "cfm_fem"

#: Parts of the package (first name below ``cfm_fem``) and the parts each may import.
#: ``simulation`` (a recordings simulator) is at the level of ``models``.
ALLOWED = {
    "cli": {"workflows", "models", "simulation", "io", "report", "_kernels"},
    "__main__": {"cli"},
    "workflows": {"models", "simulation", "io", "report", "_kernels"},
    "report": {"models", "simulation", "io"},
    "io": {"models", "simulation"},
    "models": {"_kernels"},
    "testing": {"models", "simulation", "_kernels"},
    "_kernels": set(),
    "simulation": set(),
    "errors": set(),
    "units": set(),
    "threads": set(),
    "_numba_cache": set(),
}
#: Shared utilities every part may import (``""`` is the package root, for ``__version__``).
SHARED = {"errors", "units", "threads", "_numba_cache", ""}
#: Parts restricted further: they may import only these shared utilities.
SHARED_ONLY = {"simulation": {"errors"}}
#: The public API (``cfm_fem/__init__.py`` and the functions of ``cfm_fem/api.py``) may import
#: anything.
UNRESTRICTED = {"__init__", "api"}


def part_of(path: Path, root: Path = PACKAGE) -> str:
    """First name below the package of a source file: ``cfm_fem/io/vtk.py`` -> ``io``."""
    rel = path.relative_to(root).with_suffix("")
    return rel.parts[0]


def imported_modules(source: str, path: Path, root: Path = PACKAGE):
    """(line, dotted module) of every import in ``source`` that names cfm_fem or a submodule.

    ``from . import x`` yields ``cfm_fem.<package>.x`` so that importing a module by name counts.
    """
    package = ["cfm_fem", *path.relative_to(root).parent.parts]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "cfm_fem" or alias.name.startswith("cfm_fem."):
                    yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if module != "cfm_fem" and not module.startswith("cfm_fem."):
                continue
            if module == "cfm_fem":
                for alias in node.names:  # from cfm_fem import x: x may be a part
                    yield node.lineno, f"cfm_fem.{alias.name}"
            else:
                yield node.lineno, module


def violations(path: Path, source: str, root: Path = PACKAGE) -> list[str]:
    """The imports of one source file that break the layering, as readable lines."""
    me = part_of(path, root)
    if me in UNRESTRICTED:
        return []
    rel = path.relative_to(root.parent)
    if me not in ALLOWED:
        return [f"{rel}: part {me!r} of cfm_fem is not classified; add it to ALLOWED"]
    found = []
    for line, module in imported_modules(source, path, root):
        target = module.split(".")[1] if "." in module else ""
        if target == "__version__":
            target = ""
        if target == me:
            continue
        if me in SHARED_ONLY:
            ok = target in SHARED_ONLY[me]
            rule = f"{me} may import only {sorted(SHARED_ONLY[me])}"
        else:
            ok = target in SHARED or target in ALLOWED[me]
            rule = f"{me} may import {sorted(ALLOWED[me] | (SHARED - {''}))}"
        if not ok:
            found.append(f"{rel}:{line}: imports {module} ({rule})")
    return found


def test_imports_point_one_way():
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        bad += violations(path, path.read_text(encoding="utf-8"))
    assert not bad, "upward or sideways imports:\n" + "\n".join(bad)


def test_nothing_imports_the_cli():
    bad = []
    for path in sorted(PACKAGE.rglob("*.py")):
        me = part_of(path)
        if me in ("cli", "__main__"):
            continue
        for line, module in imported_modules(path.read_text(encoding="utf-8"), path):
            if module == "cfm_fem.cli" or module.startswith("cfm_fem.cli."):
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: imports {module}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(
    ("where", "source", "expected"),
    [
        (
            "io/fake.py",
            "from ..workflows.coupled import run_coupled\n",
            "imports cfm_fem.workflows",
        ),
        ("models/fake.py", "def f():\n    from ..io import read_field\n", ":2: imports cfm_fem.io"),
        ("_kernels/fake.py", "from cfm_fem.models import field\n", "imports cfm_fem.models"),
        ("report/fake.py", "from .. import workflows\n", "imports cfm_fem.workflows"),
        ("simulation/fake.py", "from ..units import LENGTH_TO_MM\n", "imports cfm_fem.units"),
        ("simulation/fake.py", "from ..models.field import FieldMap\n", "imports cfm_fem.models"),
        ("models/fake.py", "from ..simulation import simulate\n", "imports cfm_fem.simulation"),
        ("newpart/fake.py", "x = 1\n", "part 'newpart' of cfm_fem is not classified"),
    ],
)
def test_an_upward_import_is_named(where, source, expected):
    found = violations(PACKAGE / where, source)
    assert len(found) == 1 and expected in found[0], found


@pytest.mark.parametrize(
    ("where", "source"),
    [
        ("io/fake.py", "from ..models.field import FieldMap\nfrom ..errors import CfmInputError\n"),
        ("workflows/fake.py", "from .. import _kernels\nfrom ..io.vtk import write_vtu\n"),
        ("simulation/fake.py", "from ..errors import CfmInputError\n"),
        ("__init__.py", "from .cli import main\n"),
        ("cli/fake.py", "from .. import __version__\n"),
        ("cli/fake.py", "from ..simulation import simulate\n"),
    ],
)
def test_allowed_imports_pass(where, source):
    assert violations(PACKAGE / where, source) == []


def _package_graph(folder: Path) -> dict:
    """Module -> the sibling modules it imports (``from .x import``, inside functions too)."""
    graph = {}
    for path in folder.glob("*.py"):
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
                deps.add(node.module.split(".")[0])
        graph[path.stem] = deps & {p.stem for p in folder.glob("*.py")}
    return graph


def _cycle(graph: dict) -> list:
    """One import cycle of ``graph`` as a list of modules, or []."""
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == "open":
                return stack[stack.index(d) :] + [d]
            if d not in state:
                found = visit(d)
                if found:
                    return found
        state[m] = "done"
        stack.pop()
        return []

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return []


@pytest.mark.parametrize("package", ["workflows/diagnose", "workflows/sweep", "models/quality"])
def test_no_import_cycle_within_a_package(package):
    cycle = _cycle(_package_graph(PACKAGE / package))
    assert not cycle, f"{package}: {' -> '.join(cycle)}"


def test_an_import_cycle_is_found():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) == []
