"""Where the real cart exports are (``shared/data/cart-exports``), for the tests that read them.

``$HILBO_SHARED_DIR`` (the ``shared/`` folder, or the exports folder itself), else a ``shared/``
beside the clone (CI) or above the worktree. Tests that need the files are skipped, with the
reason, when none is found.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

__all__ = ["EXPORTS", "needs_exports"]

REPO = Path(__file__).resolve().parents[2]


def _exports_dir() -> Path | None:
    candidates = []
    if os.environ.get("HILBO_SHARED_DIR"):
        shared = Path(os.environ["HILBO_SHARED_DIR"])
        candidates += [shared / "data" / "cart-exports", shared]
    candidates += [p / "shared" / "data" / "cart-exports" for p in REPO.parents]
    return next((c for c in candidates if (c / "cosmed_test.xlsx").is_file()), None)


EXPORTS = _exports_dir()
"""The exports folder, or None when it is not found."""

needs_exports = pytest.mark.skipif(
    EXPORTS is None, reason="shared/data/cart-exports not found (beside the repo, above it, or "
                            "at $HILBO_SHARED_DIR/data/cart-exports)")
"""Skip a test that reads the real exports when they are not found."""
