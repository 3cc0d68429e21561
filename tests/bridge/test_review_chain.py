"""hilbo review of a session's chain of logs: copies given together, a log missing in the middle.

A log and the copy ``hilbo log recover`` made of it, given together, used to be laid end to end
(every breath of that stretch twice, the session time inflated) without a word; the first and
third logs of three gave no note of the missing second. Logs are written as in
test_review_merge.py.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from test_review_merge import N_EXPLORE, drive, estimator, make, session_log, size_at

from bridge.cli.main import main
from bridge.log.reader import read_log, recover
from bridge.log.resume import rebuild_optimizer
from bridge.review.session import load_session


def _n_breaths(path: Path) -> int:
    return len(read_log(path, topics=["/breaths"]).data("/breaths"))


@pytest.fixture(scope="module")
def chain(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A session in three logs, A (cut by a crash) -> B (cut by a crash) -> C, and
    ``B.recovered.mcap``, the copy ``hilbo log recover`` wrote of B."""
    d = tmp_path_factory.mktemp("review-chain")
    full, sizes = d / "full.mcap", []
    with session_log(full) as log:
        opt = make()
        log.log_optimizer_state(opt, reason="start")
        drive(opt, log, sizes)
    a = d / "A.mcap"
    a.write_bytes(full.read_bytes()[:size_at(sizes, "snapshot", N_EXPLORE - 1)])
    b_full, b_sizes = d / "B-full.mcap", []
    opt, _ = rebuild_optimizer(a, estimator_factory=estimator)
    with session_log(b_full, previous=a) as log:
        log.log_optimizer_state(opt, reason="resume")
        drive(opt, log, b_sizes)
    b = d / "B.mcap"
    b.write_bytes(b_full.read_bytes()[:size_at(b_sizes, "snapshot", N_EXPLORE + 1)])
    b_full.unlink()
    c = d / "C.mcap"
    opt, _ = rebuild_optimizer(b, estimator_factory=estimator)
    with session_log(c, previous=b) as log:
        log.log_optimizer_state(opt, reason="resume")
        drive(opt, log, [])
    recovered = d / "B.recovered.mcap"
    recover(b, recovered)
    return {"A": a, "B": b, "B.recovered": recovered, "C": c}


def test_a_log_and_its_recovered_copy_are_reviewed_once_with_a_warning(
        chain: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b, rec, c = chain["A"], chain["B"], chain["B.recovered"], chain["C"]
    out = tmp_path / "review"
    assert main(["review", str(a), str(b), str(rec), str(c), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    # The fuller copy (closed normally, the same breaths) is reviewed; the other is named.
    assert f"hilbo review: warning: {b} and {rec} hold the same part of session sess" in err
    assert f"left out {b}" in err and err.count("warning") == 1
    with open(out / "breaths.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == _n_breaths(a) + _n_breaths(b) + _n_breaths(c)
    assert {r["log"] for r in rows} == {"A.mcap", "B.recovered.mcap", "C.mcap"}
    times = [float(r["time_s"]) for r in rows]
    assert times == sorted(times)

    s = load_session([c, rec, b, a])  # any order
    assert [Path(f.path).name for f in s.files] == ["A.mcap", "B.recovered.mcap", "C.mcap"]
    assert [e.index for e in s.evaluations] == list(range(len(s.evaluations)))
    assert any(f"left out {b}" in n for n in s.notes)
    assert not any("which was not given" in n for n in s.notes)


def test_the_recovered_copy_in_place_of_its_log_links_the_chain(chain: dict[str, Path]) -> None:
    s = load_session([chain["C"], chain["A"], chain["B.recovered"]])
    assert [Path(f.path).name for f in s.files] == ["A.mcap", "B.recovered.mcap", "C.mcap"]
    assert not s.warnings and not any("which was not given" in n for n in s.notes)


def test_a_log_missing_in_the_middle_of_the_chain_is_noted(chain: dict[str, Path]) -> None:
    a, b, c = chain["A"], chain["B"], chain["C"]
    s = load_session([a, c])
    (note,) = [n for n in s.notes if "which was not given" in n]
    assert note.startswith(f"{c} resumes {b}, which was not given: the part of the session between {a}")
    # The last log alone: the note it always had.
    (alone,) = [n for n in load_session([c]).notes if "which was not given" in n]
    assert alone.startswith(f"{c} resumes {b}, which was not given")
    # The whole chain: no note.
    assert not any("which was not given" in n for n in load_session([a, b, c]).notes)
