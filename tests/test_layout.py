"""Dependencies inside nrt point one way (docs/extending.md, "Layout").

Every module of the package is parsed with :mod:`ast` (nothing is imported), and each of its
``import nrt...`` statements, at module level, inside functions and under
``TYPE_CHECKING`` alike, must name a module of the same layer or a lower one. A new
module outside every layer fails too, so that it gets a place in the order.

The tests mirror the package: each folder under ``tests/`` is named after a package of nrt
(``tests/benchmarks/`` after ``benchmarks/``) and is a package of ``tests``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

TESTS = Path(__file__).resolve().parent
PACKAGE = TESTS.parent / "nrt"

LAYERS: list[tuple[str, ...]] = [
    ("nrt.errors", "nrt.files", "nrt.compile"),
    ("nrt.physics", "nrt.cameras"),
    ("nrt.mitsuba",),
    ("nrt.weights", "nrt.metrics", "nrt.run_dirs", "nrt.tensorboard", "nrt.distributed"),
    ("nrt.data",),
    ("nrt.modules.encodings",),
    ("nrt.modules.fields",),
    ("nrt.modules.renderers",),
    ("nrt.losses",),
    ("nrt.stages",),
    ("nrt.evaluation",),
    ("nrt.callbacks",),
    ("nrt.cli",),
]
"""Lowest first: a module may import its own layer and the layers before it. Mitsuba sits
just above the physics (it needs the camera conventions) and below the data, which it renders.
The compiler check and the C++ extensions' builder sit at the bottom: the physics has fused
kernels.
Evaluation sits below the callbacks: the periodic re-render callback runs nrt-eval's
evaluation."""

PACKAGES_ONLY = {"nrt", "nrt.modules"}
"""Namespaces that hold layers (their ``__init__`` imports nothing)."""


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(name: str) -> int | None:
    """Index in :data:`LAYERS` of the longest prefix naming ``name``'s home."""
    best, best_len = None, -1
    for i, homes in enumerate(LAYERS):
        for home in homes:
            if (name == home or name.startswith(home + ".")) and len(home) > best_len:
                best, best_len = i, len(home)
    return best


def nrt_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import of an ``nrt`` module in the file; ``from nrt
    import x`` counts as ``nrt.x``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == "nrt"]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] != "nrt":
                continue
            if layer_of(node.module) is None:  # from nrt[.modules] import <submodule>
                found += [(node.lineno, f"{node.module}.{a.name}") for a in node.names]
            else:
                found.append((node.lineno, node.module))
    return found


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_layers_cover_every_module():
    outside = [module_name(p) for p in MODULES
               if module_name(p) not in PACKAGES_ONLY and layer_of(module_name(p)) is None]
    assert not outside, f"modules in no layer of tests/test_layout.py: {outside}"
    assert all(not nrt_imports(PACKAGE.parent / (n.replace(".", "/") + "/__init__.py"))
               for n in PACKAGES_ONLY)


def test_no_relative_imports():
    relative = [f"{module_name(p)}:{n.lineno}" for p in MODULES
                for n in ast.walk(ast.parse(p.read_text()))
                if isinstance(n, ast.ImportFrom) and n.level > 0]
    assert not relative, f"relative imports escape the layer check: {relative}"


@pytest.mark.parametrize("path", MODULES, ids=module_name)
def test_imports_point_down(path: Path):
    name = module_name(path)
    if name in PACKAGES_ONLY:
        return
    own = layer_of(name)
    upward = [f"line {line}: {target} (layer {layer_of(target)} > {own})"
              for line, target in nrt_imports(path)
              if layer_of(target) is None or layer_of(target) > own]
    assert not upward, f"{name} (layer {own}: {LAYERS[own]}) imports upward: {upward}"


def test_the_check_sees_a_backward_import(tmp_path: Path):
    """The parser finds lazy imports inside functions, the kind that ran backwards before."""
    source = tmp_path / "m.py"
    source.write_text("def f():\n    from nrt.evaluation.rerender import x\n"
                      "    import nrt.callbacks\n")
    assert nrt_imports(source) == [(2, "nrt.evaluation.rerender"), (3, "nrt.callbacks")]
    assert layer_of("nrt.evaluation.rerender") > layer_of("nrt.stages.dpt")


def mirrors_the_code(folder: Path) -> bool:
    """``tests/<folder>/`` is named after ``nrt/<folder>/``, or ``tests/benchmarks/`` after
    ``benchmarks/``."""
    if folder.parts[0] == "benchmarks":
        return (TESTS.parent / folder).is_dir()
    return (PACKAGE / folder).is_dir()


def test_test_folders_mirror_the_package():
    """Every folder of tests is named after a package of the code, and every one, ``tests/``
    included, has an ``__init__.py``."""
    folders = sorted({p.parent.relative_to(TESTS) for p in TESTS.rglob("*.py")} - {Path(".")})
    stray = [str(f) for f in folders if not mirrors_the_code(f)]
    assert not stray, f"test folders named after no package of nrt: {stray}"
    loose = [str(f) for f in [Path("."), *folders] if not (TESTS / f / "__init__.py").is_file()]
    assert not loose, f"test folders without __init__.py: {loose}"
