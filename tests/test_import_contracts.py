"""The layer rule of shared/DESIGN.md is import-linter's contracts in pyproject.toml, which
`make test` checks with `lint-imports`; this test runs them too and checks what they cover."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _contracts() -> list[dict]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]


def test_the_contracts_hold() -> None:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    assert exe is not None, "import-linter is a dev dependency"
    done = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert f"Contracts: {len(_contracts())} kept, 0 broken." in done.stdout


def test_the_contracts_state_the_design_rule() -> None:
    by_source = {tuple(c.get("source_modules", ())): c for c in _contracts() if c["type"] == "forbidden"}
    core = set(by_source[("hilbo_core",)]["forbidden_modules"])
    assert {"drivers", "virtual_hw", "bridge", "asyncio", "socket", "time", "can", "mcap"} <= core
    assert set(by_source[("drivers",)]["forbidden_modules"]) == {"virtual_hw", "bridge"}
    assert set(by_source[("virtual_hw",)]["forbidden_modules"]) == {"bridge"}
    bridge = by_source[("bridge",)]
    # The one exception: bridge.sim wires the virtual devices in.
    assert bridge["forbidden_modules"] == ["virtual_hw"]
    assert bridge["ignore_imports"] == ["bridge.sim.** -> virtual_hw.**"]


def test_no_package_of_ours_may_hold_an_import_cycle() -> None:
    acyclic = [c for c in _contracts() if c["type"] == "acyclic_siblings"]
    assert len(acyclic) == 1
    assert set(acyclic[0]["ancestors"]) == {"hilbo_core", "drivers", "virtual_hw", "bridge"}
    assert "depth" not in acyclic[0] and "skip_descendants" not in acyclic[0]  # every level
