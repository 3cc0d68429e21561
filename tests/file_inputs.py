"""Helpers of the bad-file tests: inputs that are not regular files, and the fuzzing script.

Used by tests/drivers/test_cart_bad_files.py, tests/drivers/test_cart_fuzz_exports.py,
tests/bridge/test_log_bad_files.py and tests/bridge/test_config_bad_files.py.
"""

from __future__ import annotations

import importlib.util
import os
import stat
import sys
from pathlib import Path
from types import ModuleType

import pytest

__all__ = ["NOT_REGULAR", "load_fuzz_script", "not_regular_file"]

REPO = Path(__file__).resolve().parents[1]

NOT_REGULAR = ("fifo", "directory", "dev_zero")
"""The kinds :func:`not_regular_file` makes (a fixture's params)."""


def not_regular_file(kind: str, tmp_path: Path, name: str = "input") -> tuple[Path, str]:
    """A path of ``kind`` (a FIFO no one writes, a directory, ``/dev/zero``) and the words an
    error about it uses; skips the test when this machine has no ``/dev/zero``."""
    if kind == "fifo":
        path = tmp_path / name
        os.mkfifo(path)
        return path, "a FIFO"
    if kind == "directory":
        path = tmp_path / f"{name}.d"
        path.mkdir()
        return path, "a directory"
    if not Path("/dev/zero").exists() or not stat.S_ISCHR(os.stat("/dev/zero").st_mode):
        pytest.skip("no /dev/zero here")
    return Path("/dev/zero"), "a character device"


def load_fuzz_script() -> ModuleType:
    """``scripts/fuzz_files.py`` as a module (its mutations and outcome counting)."""
    path = REPO / "scripts" / "fuzz_files.py"
    spec = importlib.util.spec_from_file_location("fuzz_files_under_test", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up here
    spec.loader.exec_module(module)
    return module
