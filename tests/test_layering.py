"""The layer rule of shared/DESIGN.md, checked on the source of every package.

Imports point one way: bridge -> drivers, hilbo_core; virtual_hw -> drivers, hilbo_core;
drivers -> hilbo_core; hilbo_core -> nothing of ours, and no I/O, asyncio or clocks.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OURS = {"hilbo_core", "drivers", "virtual_hw", "bridge"}
ALLOWED_OURS = {
    "hilbo_core": {"hilbo_core"},
    "drivers": {"drivers", "hilbo_core"},
    "virtual_hw": {"virtual_hw", "drivers", "hilbo_core"},
    "bridge": {"bridge", "drivers", "hilbo_core", "virtual_hw"},
}
# hilbo_core is pure: numerical libraries only, and no stdlib module that does I/O or
# reads a clock (filterpy-style core; models are passed in as callables).
CORE_THIRD_PARTY = {"numpy", "scipy", "filterpy"}
CORE_FORBIDDEN_STDLIB = {
    "asyncio", "socket", "selectors", "time", "datetime", "threading", "multiprocessing",
    "subprocess", "os", "io", "pathlib", "shutil", "tempfile", "signal", "sqlite3", "urllib",
    "http",
}


def imported_roots(source: str) -> set[str]:
    """Top-level module names a source file imports (absolute imports only)."""
    roots: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            roots.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def violations(package: str, source: str) -> list[str]:
    """Why a source file of ``package`` breaks the layer rule (empty when it doesn't)."""
    bad = []
    for root in sorted(imported_roots(source)):
        if root in OURS and root not in ALLOWED_OURS[package]:
            bad.append(f"{package} imports {root}")
        if package == "hilbo_core" and root not in OURS:
            if root in CORE_FORBIDDEN_STDLIB:
                bad.append(f"hilbo_core imports {root} (I/O, asyncio or clock)")
            elif root not in sys.stdlib_module_names and root not in CORE_THIRD_PARTY:
                bad.append(f"hilbo_core imports third-party {root}")
    return bad


@pytest.mark.parametrize("package", sorted(OURS))
def test_package_respects_layer_rule(package: str) -> None:
    files = sorted((ROOT / package).rglob("*.py"))
    assert files, f"package {package} has no Python files"
    problems = [f"{f.relative_to(ROOT)}: {v}" for f in files for v in violations(package, f.read_text())]
    assert problems == []


@pytest.mark.parametrize(
    ("package", "source", "expected"),
    [
        ("hilbo_core", "import asyncio", ["hilbo_core imports asyncio (I/O, asyncio or clock)"]),
        ("hilbo_core", "from drivers.cart import x", ["hilbo_core imports drivers"]),
        ("hilbo_core", "import can", ["hilbo_core imports third-party can"]),
        ("hilbo_core", "import time", ["hilbo_core imports time (I/O, asyncio or clock)"]),
        ("drivers", "from bridge import cli", ["drivers imports bridge"]),
        ("virtual_hw", "import bridge.cli", ["virtual_hw imports bridge"]),
        ("hilbo_core", "import numpy as np\nfrom scipy import stats\nimport math", []),
        ("bridge", "import virtual_hw, drivers, hilbo_core, asyncio", []),
    ],
)
def test_checker_catches_violations(package: str, source: str, expected: list[str]) -> None:
    assert violations(package, source) == expected
