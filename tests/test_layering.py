"""The architecture as a test: which part of roughuq may import which (STYLE.md, "The shape of the house").

Data flows one way: ``physics`` and ``multilevel`` are siblings that never import
each other; ``problem`` (the contact problem as a level sampler) joins them;
``study`` (config, store, executors, pipeline), ``report`` and ``cli`` sit
above. The core (``physics``, ``multilevel``, ``problem``) imports no I/O or UI
library.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "rough_uq"
CORE = ("physics", "multilevel", "problem")
#: The parts of roughuq each part may import (besides itself and ``rough_uq.errors``).
ALLOWED = {
    "physics": set(),
    "multilevel": set(),
    "problem": {"physics", "multilevel"},
    "study": {"physics", "multilevel", "problem"},
    "report": {"physics", "multilevel", "problem", "study"},
}
EDGE_LIBRARIES = {"h5py", "click", "rich", "yaml", "pydantic", "matplotlib", "distributed", "dask"}
#: Imported by numba (PyYAML) itself where installed: checked in the source only. (pyFFTW's own import of
#: dask is skipped, :func:`rough_uq.physics.fft._import_pyfftw`.)
IMPORTED_BY_DEPENDENCIES = {"yaml"}


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            if node.module == "rough_uq":
                names.update(f"rough_uq.{alias.name}" for alias in node.names)
    return names


@pytest.mark.parametrize("part", sorted(ALLOWED))
def test_each_part_imports_only_the_parts_below_it(part):
    for path in sorted((PACKAGE / part).rglob("*.py")):
        for name in _imports(path):
            if not name.startswith("rough_uq."):
                continue
            target = name.split(".")[1]
            if target in ("errors", "__version__", part):
                continue
            assert target in ALLOWED[part], f"{path.relative_to(PACKAGE.parent)} imports {name}"


@pytest.mark.parametrize("part", CORE)
def test_the_core_imports_no_io_or_ui_library(part):
    for path in sorted((PACKAGE / part).rglob("*.py")):
        for name in _imports(path):
            assert name.split(".")[0] not in EDGE_LIBRARIES, f"{path.relative_to(PACKAGE.parent)} imports {name}"


def test_importing_the_core_loads_no_io_or_ui_library():
    # Checked in a fresh interpreter: the modules the core imports must not pull them in either.
    # Those of subpackages too (rough_uq.multilevel.drivers and its modules).
    modules = sorted(".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts).removesuffix(".__init__")
                     for part in CORE for path in (PACKAGE / part).rglob("*.py"))
    forbidden = sorted(EDGE_LIBRARIES - IMPORTED_BY_DEPENDENCIES)
    code = f"import sys, {', '.join(modules)}; print(sorted(m for m in {forbidden!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_every_module_lives_in_a_part():
    # The command line: cli.py, and console.py, the console script's entry, which loads before it (Ctrl-C), and
    # __main__.py (python -m rough_uq).
    top = ("__init__.py", "__main__.py", "errors.py", "cli.py", "console.py")
    flat = sorted(p.name for p in PACKAGE.glob("*.py") if p.name not in top)
    assert flat == [], "modules outside the subpackages"
