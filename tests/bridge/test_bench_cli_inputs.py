"""What every ``hilbo bench`` command refuses before it works: an unwritable ``--out``, a
malformed scheduler address, a list given with commas; and a benchmark cut by a signal."""

from __future__ import annotations

from pathlib import Path

import pytest

from bridge.bench.cli import bench_main
from bridge.bench.common import raise_if_interrupted


@pytest.mark.parametrize("bench", [["estimator", "--n", "1"], ["pairs", "--n", "1"],
                                   ["tutor", "--reps", "1"], ["watchdog", "--n", "1"],
                                   ["perf", "--sessions", "0"]])
def test_an_out_that_is_a_file_is_refused_before_any_work(
        bench: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    assert bench_main([*bench, "--out", str(blocker / "sub")]) == 1
    err = capsys.readouterr().err
    assert "--out" in err and f"{blocker} is a file" in err and "Traceback" not in err
    assert blocker.read_text() == "x"


@pytest.mark.parametrize("address", ["notanaddress", "tcp://host", "host:port", "host:0", "tcp://h:99999"])
def test_a_malformed_scheduler_address_is_a_usage_error(
        address: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        bench_main(["stopping", "--trials", "1", "--scheduler", address])
    assert exc.value.code == 2
    assert ("expected a Dask scheduler address HOST:PORT or tcp://HOST:PORT (port 1-65535), "
            f"got {address!r}") in capsys.readouterr().err


def test_tutor_figures_take_commas_and_name_an_unknown_one(capsys: pytest.CaptureFixture[str],
                                                           tmp_path: Path) -> None:
    assert bench_main(["tutor", "--figures", "fig7,fig8", "--out", str(tmp_path)]) == 2
    assert "unknown figure 'fig8'; choose from ['fig7', 'fig9']" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_a_session_ended_by_a_signal_ends_the_benchmark() -> None:
    raise_if_interrupted({"end_reason": "budget"})  # any other end: the benchmark goes on
    with pytest.raises(KeyboardInterrupt):
        raise_if_interrupted({"end_reason": "interrupted"})
