"""pyproject.toml declares exactly the third-party packages that nrt/, tests/ and
benchmarks/ import: the package for the code, the ``test`` extra for what only tests use."""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

tomllib = pytest.importorskip("tomllib")

ROOT = Path(__file__).resolve().parents[1]

NOT_IMPORTED = {"torchvision", "ruff", "pytest-xdist", "ninja"}
"""Declared but never imported: lpips imports torchvision (declared beside torch so that
pip installs a matching pair); ruff is the linter the tests' README command runs;
pytest-xdist is the plugin behind the README's ``pytest -n 2``; ninja is the build tool
torch runs for the fused hash grid's C++ extension."""

DISTRIBUTIONS = {"OpenEXR": "openexr"}
"""Modules whose distribution importlib.metadata does not map (single extension files)."""


def _name(requirement: str) -> str:
    return re.split(r"[<>=!~;\[ ]", requirement, maxsplit=1)[0].lower().replace("_", "-")


def _imports(folders: list[str]) -> set[str]:
    """Top-level modules imported anywhere in ``folders`` (inside functions too)."""
    local = {"nrt", "benchmarks", "tests"}  # the repository's own packages
    found = set()
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    found |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    found.add(node.module.split(".")[0])
    return {m for m in found if m not in sys.stdlib_module_names and m not in local}


def _distributions(modules: set[str]) -> set[str]:
    table = importlib.metadata.packages_distributions()
    return {_name(DISTRIBUTIONS.get(m) or table.get(m, [m])[0]) for m in modules}


def test_imports_and_declared_dependencies_agree():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    main = {_name(r) for r in project["dependencies"]}
    test = {_name(r) for r in project["optional-dependencies"]["test"]}
    code = _distributions(_imports(["nrt", "benchmarks"]))
    tests_only = _distributions(_imports(["tests"])) - code
    assert code <= main, f"imported but not declared: {sorted(code - main)}"
    assert tests_only <= main | test, f"tests import undeclared {sorted(tests_only - test)}"
    unused = (main | test) - code - tests_only - NOT_IMPORTED
    assert not unused, f"declared but never imported: {sorted(unused)}"
