"""Mutated copies of the real cart exports: every read ends in a report or the package's error.

A few hundred seeded copies per export (bytes flipped, inserted, cut or truncated, numbers made
huge, zip members damaged, dropped or swapped) through ``hilbo cart inspect``'s reader, with the
format detected and given; the same functions measure 10,000 copies per export outside the suite
(``scripts/fuzz_files.py``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from cart_exports import EXPORTS, needs_exports
from file_inputs import load_fuzz_script

pytestmark = pytest.mark.timeout(120)

N_COPIES = 100
"""Copies per export (each read twice): a few seconds per export."""


fuzz_files = load_fuzz_script()


@needs_exports
@pytest.mark.parametrize("name", sorted(fuzz_files.EXPORT_FORMATS))
def test_mutated_exports_never_raise_anything_else(name: str, tmp_path: Path,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    assert EXPORTS is not None
    caplog.set_level(logging.ERROR)
    outcome = fuzz_files.run(EXPORTS, N_COPIES, 20261206, tmp_path, names=(name,))[name]
    assert outcome.read + outcome.refused == 2 * N_COPIES
    assert not outcome.tracebacks, "\n".join(outcome.examples.values())
    assert outcome.read > 0 and outcome.refused > 0  # the mutations reach both outcomes


def test_the_mutations_are_seeded_and_damage_the_file() -> None:
    import numpy as np

    data = bytes(range(256)) * 4
    a = [fuzz_files.mutate(data, np.random.default_rng(3)) for _ in range(2)]
    b = fuzz_files.mutate(data, np.random.default_rng(3))
    assert a[0] == a[1] == b
    rng = np.random.default_rng(4)
    assert sum(fuzz_files.mutate(data, rng) != data for _ in range(50)) >= 45
