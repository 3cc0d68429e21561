"""hilbo review on real session logs: those of ``hilbo sim`` (the bridge over the virtual devices)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import csv
import io
import json
import re
import struct
from pathlib import Path

import pytest

from bridge.cli.main import main
from bridge.log.reader import read_log
from bridge.review.command import default_review_dir, review_session
from bridge.review.plots import PLOT_FILES, PLOT_SIZES_PX
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim

pytestmark = pytest.mark.slow

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from the IHDR chunk, which must come first."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def sims(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """Two small simulated sessions (seeds 2 and 3): {seed: directory with session.mcap, summary.json}.

    8 walked minutes, proposals in a thread: pushes count as walking time, and at --speed max the
    worker process's start beside CPU burners once ate a 5-minute session's exploration bout (no
    threshold plot), before the session's clock waited for the worker.
    """
    out = {}
    for seed in (2, 3):
        d = tmp_path_factory.mktemp(f"sim{seed}")
        asyncio.run(run_virtual_sim(VirtualSimConfig(minutes=8.0, seed=seed, n_explore=3, max_breaths=10,
                                                     warmup_s=20.0, proposal_worker="thread"), d))
        out[seed] = d
    return out


@pytest.fixture(scope="module")
def reviewed(sims: dict[int, Path], tmp_path_factory: pytest.TempPathFactory):
    """``hilbo review`` of the seed-2 session through the CLI: (exit code, stdout, out dir, sim dir)."""
    out = tmp_path_factory.mktemp("review") / "r"
    buf = io.StringIO()  # capsys is per test; this runs once per module
    with contextlib.redirect_stdout(buf):
        code = main(["review", str(sims[2] / "session.mcap"), "--out", str(out)])
    return code, buf.getvalue(), out, sims[2]


def recommended_from_report(md: str) -> tuple[dict[str, float], float]:
    section = md.split("## Recommended setting", 1)[1].split("\n## ", 1)[0]
    params = {m[1]: float(m[2]) for m in re.finditer(r"^\| (\w+) \| ([-\d.e+]+) \|", section, re.M)}
    mean = float(re.search(r"Estimated cost: ([\d.]+) W", section)[1])
    return params, mean


def test_every_file_is_written_and_printed_one_per_line(reviewed) -> None:
    code, stdout, out, _ = reviewed
    assert code == 0
    expected = [*(out / f for f in PLOT_FILES.values()), out / "report.md", out / "report.html",
                out / "evaluations.csv", out / "breaths.csv"]
    assert stdout.splitlines() == [str(p) for p in expected]
    for p in expected:
        assert p.is_file() and p.stat().st_size > 0, p


def test_plots_are_pngs_of_the_stated_size(reviewed) -> None:
    _, _, out, _ = reviewed
    for name, file in PLOT_FILES.items():
        assert png_size(out / file) == PLOT_SIZES_PX[name], name


def test_csv_rows_match_the_log(reviewed) -> None:
    _, _, out, sim = reviewed
    log = read_log(sim / "session.mcap")
    summary = json.loads((sim / "summary.json").read_text())
    with open(out / "evaluations.csv", newline="") as f:
        evs = list(csv.DictReader(f))
    with open(out / "breaths.csv", newline="") as f:
        breaths = list(csv.DictReader(f))
    assert len(evs) == len(log.data("/observations")) == summary["n_evaluations"]
    assert len(breaths) == len(log.data("/breaths")) == summary["n_breaths"]
    for row, e in zip(evs, summary["evaluations"], strict=True):
        assert int(row["evaluation"]) == e["index"] + 1 and int(row["index"]) == e["index"]
        assert float(row["mean_w"]) == e["mean"] and int(row["breaths"]) == e["breaths"]
        assert float(row["F_p"]) == e["params"]["F_p"]
        assert (row["stopped_early"] == "true") == e["stopped_early"]
        assert float(row["t_end_s"]) == pytest.approx(e["t_end"], abs=1e-6)
        assert float(row["t_start_s"]) == pytest.approx(e["t_start"], abs=1e-6)
    # The breaths the optimizer used carry the estimate they produced.
    used = [b for b in breaths if b["evaluation"] != ""]
    assert len(used) == len(log.data("/estimator"))


def test_the_report_recommends_what_the_session_did(reviewed) -> None:
    _, _, out, sim = reviewed
    summary = json.loads((sim / "summary.json").read_text())
    params, mean = recommended_from_report((out / "report.md").read_text())
    assert params == pytest.approx(summary["best_params"], rel=1e-5)
    assert mean == pytest.approx(summary["best_mean"], abs=0.006)
    # The default (fast) protocol measured it in full in the session's last minutes.
    conf = summary["confirmation"]
    assert conf["n_evaluations"] >= 1 and conf["mean_w"] == pytest.approx(summary["best_mean"])
    assert f"recommended, confirmed at {conf['mean_w']:.1f} ± {conf['sd_w']:.1f} W" in \
        (out / "report.md").read_text()


def test_the_report_has_every_section(reviewed) -> None:
    _, _, out, sim = reviewed
    md = (out / "report.md").read_text()
    for heading in ("## Recommended setting", "## Plots", "## Evaluations",
                    "## Timeline of events and faults", "## Rejected records and frames", "## Configuration"):
        assert heading in md
    log = read_log(sim / "session.mcap")
    assert log.session_id in md
    for kind in {e["kind"] for e in log.data("/events")}:
        assert f"| {kind} |" in md
    last = {r["source"]: r["counts"] for r in log.data("/rejects")}
    for source, counts in last.items():
        for reason, n in counts.items():
            assert f"| {source} | {reason} | {n} |" in md
    evaluations = md.split("## Evaluations", 1)[1].split("\n## ", 1)[0]
    assert len(re.findall(r"^\| \d+ \|", evaluations, re.M)) == len(log.data("/observations"))


def test_the_html_is_self_contained(reviewed) -> None:
    _, _, out, _ = reviewed
    page = (out / "report.html").read_text()
    assert page.startswith("<!DOCTYPE html>")
    images = re.findall(r'<img [^>]*src="([^"]+)"', page)
    assert len(images) == len(PLOT_FILES)
    for src in images:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == PNG_MAGIC
    assert not re.search(r'(href|src)="(?!data:)', page)
    assert "<link" not in page and "<script" not in page


def test_a_log_cut_off_at_60_percent_still_reviews(sims: dict[int, Path], tmp_path: Path) -> None:
    data = (sims[2] / "session.mcap").read_bytes()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    log = read_log(cut)
    assert log.truncated and 0 < len(log.data("/observations"))
    result = review_session([cut])
    assert result.out_dir == default_review_dir(cut) == tmp_path / "crashed-review"
    for p in result.files:
        assert p.is_file()
    with open(result.out_dir / "evaluations.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == len(log.data("/observations"))
    with open(result.out_dir / "breaths.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == len(log.data("/breaths"))
    md = (result.out_dir / "report.md").read_text()
    assert "CUT OFF by a crash" in md and "| log_cut_off |" in md
    # Before its confirmation, the recommendation is said as the optimizer chose it (where the
    # cut leaves an optimizer to ask; the cut's place varies with the simulated session).
    how = re.search(r"Chosen by (.*)\.$", md, flags=re.M)
    assert how is not None
    other = ("the lowest estimated mean", "the session: recommended, confirmed at")
    assert how.group(1).startswith(other) or (
        how.group(1).startswith("HILOptimizer.best() of ")
        and "(lowest GP posterior mean + 1 SD over the whole feasible set, from all " in how.group(1)), how
    assert "The best so far (the lowest raw estimate, " not in md or " breaths, ended by " in md


def test_compare_puts_two_sessions_side_by_side(sims: dict[int, Path], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    a, b = sims[2] / "session.mcap", sims[3] / "session.mcap"
    code = main(["review", "--compare", str(a), str(b), "--out", str(tmp_path / "cmp")])
    stdout, err = capsys.readouterr()
    assert code == 0 and err == ""
    files = [Path(line) for line in stdout.splitlines()]
    assert [f.name for f in files] == ["compare.png", "compare.md", "compare.html"]
    assert png_size(files[0]) == PLOT_SIZES_PX["compare"]
    md = files[1].read_text()
    table = md.split("## Key numbers", 1)[1]
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (sims[2], sims[3]))
    assert f"| evaluations | {sa['n_evaluations']} | {sb['n_evaluations']} |" in table
    assert f"| early stops | {sa['n_early_stops']} | {sb['n_early_stops']} |" in table
    walked = (sa["walking"]["session_s"] / 60, sb["walking"]["session_s"] / 60)
    assert f"| minutes walked | {walked[0]:.1f} | {walked[1]:.1f} |" in table
    assert f"| session id | {sa['session_id']} | {sb['session_id']} |" in table
    row = re.search(r"^\| recommended cost \(W, ± 1 σ\) \| ([\d.]+) ± [\d.]+ \| ([\d.]+) ± [\d.]+ \|",
                    table, re.M)
    assert float(row[1]) == pytest.approx(sa["best_mean"], abs=0.06)
    assert float(row[2]) == pytest.approx(sb["best_mean"], abs=0.06)
    assert "data:image/png;base64," in files[2].read_text()
