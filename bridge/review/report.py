"""The report (Markdown and self-contained HTML) and CSV tables of ``hilbo review``.

Both report formats are rendered from one list of blocks (headings, paragraphs, lists, tables,
images, code), so they always say the same thing. The HTML inlines every image as a base64
``data:`` URI and its style sheet, and references nothing outside itself; the Markdown refers to
the PNG files next to it.
"""

from __future__ import annotations

import base64
import contextlib
import csv
import html
import io
import json
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from drivers.files import create_private_file

if TYPE_CHECKING:
    from bridge.review.session import EvaluationRow, Session

__all__ = [
    "BREATH_COLUMNS",
    "EVALUATION_FIXED_COLUMNS",
    "evaluation_columns",
    "write_breaths_csv",
    "write_compare_report",
    "write_evaluations_csv",
    "write_report",
]

EVALUATION_FIXED_COLUMNS = ("evaluation", "phase", "mean_w", "var_w2", "sd_w", "breaths", "duration_s",
                            "stopped_early", "reason", "t_start_s", "t_end_s", "log", "source", "index")
"""Columns of ``evaluations.csv`` besides the parameters (which follow ``phase``). ``evaluation``
counts from 1, as the report, the plots and the operator view do; ``index`` is the log's and the
summary's 0-based index of the same evaluation."""

BREATH_COLUMNS = ("breath", "log", "t_s", "time_s", "vo2_ml_min", "vco2_ml_min", "ve_l_min", "rer",
                  "hr_bpm", "watts", "evaluation", "breath_in_evaluation", "mean_w", "sd_w", "index")
"""Columns of ``breaths.csv``: ``t_s`` on the cart's clock, ``time_s`` session time (s); ``breath``,
``evaluation`` and ``breath_in_evaluation`` count from 1 (as the report and the threshold plot),
``index`` is the evaluation's 0-based index in the log."""

_CAPTIONS = {
    "timeline": "Breath-by-breath metabolic power (Brockway) with the {estimator} of each setting and "
                "its ±1 σ band; grey lines mark setting changes (numbers: evaluations), red bands the "
                "pauses; below, the estimate's σ.",
    "best_so_far": "Best estimated cost so far (the lowest raw estimate) against minutes walked; dots are "
                   "the evaluations (±1 σ), crosses the early stops, the dashed line the recommended "
                   "setting's estimate (the GP posterior over every evaluation: it differs from the "
                   "lowest raw estimate, which the winner's curse biases low).",
    "parameters": "Each parameter against evaluation number; crosses mark early stops, the circle the "
                  "recommended setting, the shaded band the exploration bout.",
    "thresholds": "The threshold schedule the session used over breath index (black: {threshold}), the "
                  "standardised exploration traces Algorithm 2 takes its envelope of (grey), and "
                  "z = (μ − μ*)/σ of the optimisation evaluations (orange; crosses: stopped early).",
    "force_tracking": "Desired vs measured force over the gait cycle while the recommended setting (or, if "
                      "it was never applied, the measured setting nearest to it) was measured (controller "
                      "feedback samples).",
}
_TITLES = {"timeline": "Metabolic power and estimate", "best_so_far": "Best so far",
           "parameters": "Parameters", "thresholds": "Threshold schedule",
           "force_tracking": "Force tracking of the recommended setting"}

_CSS = """body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1450px;
margin:1.5em auto;padding:0 1em;color:#222;line-height:1.4}h1{font-size:1.6em}h2{font-size:1.25em;
border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}table{border-collapse:collapse;
font-size:.85em;margin:.6em 0}th,td{border:1px solid #ccc;padding:.2em .5em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}img{max-width:100%;height:auto;
border:1px solid #ddd}figure{margin:1em 0}figcaption{font-size:.85em;color:#555}pre{background:#f6f6f6;
padding:.6em;overflow:auto;font-size:.8em;max-height:30em}"""


# ---------------------------------------------------------------------------------- blocks
@dataclass(frozen=True)
class _Block:
    kind: str  # h1, h2, p, ul, table, img, code
    text: str = ""
    items: tuple[str, ...] = ()
    headers: tuple[str, ...] = ()
    rows: tuple[tuple[str, ...], ...] = ()
    path: Path | None = None


def _h(level: int, text: str) -> _Block:
    return _Block(f"h{level}", text)


def _p(text: str) -> _Block:
    return _Block("p", text)


def _ul(items: Sequence[str]) -> _Block:
    return _Block("ul", items=tuple(items))


def _table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> _Block:
    return _Block("table", headers=tuple(headers), rows=tuple(tuple(str(c) for c in r) for r in rows))


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _markdown(blocks: Sequence[_Block]) -> str:
    out: list[str] = []
    for b in blocks:
        if b.kind.startswith("h"):
            out.append("#" * int(b.kind[1]) + " " + b.text)
        elif b.kind == "p":
            out.append(b.text)
        elif b.kind == "ul":
            out.append("\n".join(f"- {i}" for i in b.items))
        elif b.kind == "table":
            lines = ["| " + " | ".join(_md_cell(h) for h in b.headers) + " |",
                     "|" + "|".join("---" for _ in b.headers) + "|"]
            lines += ["| " + " | ".join(_md_cell(c) for c in r) + " |" for r in b.rows]
            out.append("\n".join(lines))
        elif b.kind == "img" and b.path is not None:
            out.append(f"![{b.text}]({b.path.name})\n\n*{b.items[0] if b.items else ''}*")
        elif b.kind == "code":
            out.append(f"```json\n{b.text}\n```")
    return "\n\n".join(out) + "\n"


def _html(title: str, blocks: Sequence[_Block]) -> str:
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           '<meta name="viewport" content="width=device-width, initial-scale=1">',
           f"<title>{e(title)}</title><style>{_CSS}</style></head><body>"]
    for b in blocks:
        if b.kind.startswith("h"):
            out.append(f"<{b.kind}>{e(b.text)}</{b.kind}>")
        elif b.kind == "p":
            out.append(f"<p>{e(b.text)}</p>")
        elif b.kind == "ul":
            out.append("<ul>" + "".join(f"<li>{e(i)}</li>" for i in b.items) + "</ul>")
        elif b.kind == "table":
            head = "".join(f"<th>{e(h)}</th>" for h in b.headers)
            body = "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in r) + "</tr>" for r in b.rows)
            out.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        elif b.kind == "img" and b.path is not None:
            data = base64.b64encode(b.path.read_bytes()).decode("ascii")
            caption = b.items[0] if b.items else ""
            out.append(f'<figure><img alt="{e(b.text)}" src="data:image/png;base64,{data}">'
                       f"<figcaption>{e(caption)}</figcaption></figure>")
        elif b.kind == "code":
            out.append(f"<details><summary>the whole configuration (JSON)</summary><pre>{e(b.text)}</pre>"
                       "</details>")
    out.append("</body></html>")
    return "\n".join(out) + "\n"


@contextlib.contextmanager
def _create_text(path: Path, mode: int) -> Iterator[TextIO]:
    """``path`` created for UTF-8 text with permission bits ``mode`` (the session's file mode)."""
    with create_private_file(path, mode) as raw, io.TextIOWrapper(raw, encoding="utf-8", newline="") as f:
        yield f


def _write_both(out: Path, stem: str, title: str, blocks: Sequence[_Block], mode: int) -> list[Path]:
    md, page = out / f"{stem}.md", out / f"{stem}.html"
    with _create_text(md, mode) as f:
        f.write(_markdown(blocks))
    with _create_text(page, mode) as f:
        f.write(_html(title, blocks))
    return [md, page]


# ---------------------------------------------------------------------------------- formatting
# Round-off of the unit-cube mapping (6e-16 for a bound at 0): shown as the 0 it is.
_ROUND_OFF = 1e-9


def _num(value: float | None, fmt: str = ".1f") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return format(0.0 if abs(value) < _ROUND_OFF else value, fmt)


def _min(t_s: float | None) -> str:
    return "–" if t_s is None else f"{t_s / 60.0:.2f}"


def _param(value: float) -> str:
    return _num(value, ".6g")


def _file_line(session: Session, k: int) -> str:
    f = session.files[k]
    state = "closed normally" if f.complete else \
        f"CUT OFF by a crash: {f.unreadable_bytes:,} bytes unreadable ({f.stop_reason})"
    chain = f", resumes {f.previous_log}" if f.previous_log else ""
    return (f"{f.path}: {f.size_bytes:,} bytes, {f.messages:,} messages, {state}{chain}; "
            f"session time {f.offset_s / 60:.2f}–{(f.offset_s + f.duration_s) / 60:.2f} min")


def _config_tables(config: Mapping[str, Any]) -> list[_Block]:
    blocks: list[_Block] = []
    for key in ("session", "protocol", "limits", "cart", "can", "watchdog"):
        section = config.get(key)
        if not isinstance(section, Mapping):
            continue
        rows = [(k, json.dumps(v) if not isinstance(v, str) else v) for k, v in section.items()
                if not isinstance(v, Mapping | list) or len(json.dumps(v)) <= 80]
        if rows:
            blocks += [_p(f"[{key}]"), _table(("key", "value"), rows)]
    space = config.get("space")
    if isinstance(space, Mapping):
        definition = space.get("definition") if isinstance(space.get("definition"), Mapping) else {}
        params = definition.get("parameters") or []
        rows = [(p.get("name", ""), _num(p.get("lower"), "g"), _num(p.get("upper"), "g"), p.get("unit", ""),
                 p.get("description", "")) for p in params if isinstance(p, Mapping)]
        if rows:
            blocks += [_p(f"[space] preset {space.get('preset', definition.get('name', '?'))}"),
                       _table(("parameter", "lower", "upper", "unit", "description"), rows)]
        cons = [c.get("text", "") for c in definition.get("constraints") or [] if isinstance(c, Mapping)]
        if cons:
            blocks.append(_p("constraints: " + "; ".join(cons)))
    return blocks


def _recommended_blocks(session: Session) -> list[_Block]:
    rec = session.recommended
    if rec is None:
        return [_p("No evaluation completed: nothing to recommend.")]
    rows = [(n, _param(rec.params[n]), session.param_units.get(n, ""))
            for n in (session.param_names or sorted(rec.params)) if n in rec.params]
    rows += [(n, _param(v), "") for n, v in rec.params.items() if n not in session.param_names
             and session.param_names]
    sd = rec.sd_w
    source = ""
    if rec.index is not None:
        ev = next((e for e in session.evaluations if e.index == rec.index), None)
        if ev is not None:
            source = f" It is evaluation {ev.index + 1} ({ev.phase}, {ev.breaths} breaths, {ev.reason})."
    blocks = [
        _table(("parameter", "value", "unit"), rows),
        _p(f"Estimated cost: {rec.mean_w:.2f} W ± {sd:.2f} W (1 σ; variance {rec.var_w2:.1f} W²; 95 % "
           f"interval {rec.mean_w - 1.96 * sd:.1f}–{rec.mean_w + 1.96 * sd:.1f} W).{source} "
           f"Chosen by {rec.method}."),
    ]
    lowest = min(session.evaluations, key=lambda e: e.mean_w)
    if not math.isclose(lowest.mean_w, rec.mean_w, rel_tol=1e-9):
        blocks.append(_p(
            f"The best so far (the lowest raw estimate, {lowest.mean_w:.1f} ± {lowest.sd_w:.1f} W at "
            f"evaluation {lowest.index + 1}, from {lowest.breaths} breaths, ended by {lowest.reason}) "
            "differs from the recommendation: the recommendation weighs every "
            "evaluation through the GP, and the lowest of many noisy estimates is biased low (the "
            "winner's curse)."))
    return blocks


def _validation_blocks(session: Session) -> list[_Block]:
    """The validation walk's result per condition (``hilbo validate``, bridge/validate.py)."""
    rows = []
    for r in session.validation or ():
        ci = r.get("ci95_w") or [None, None]
        red = r.get("reduction")
        rci = r.get("reduction_ci95") or [None, None]
        setting = str(r.get("setting") or "assistance off")
        rows.append((str(r.get("order", "")), str(r.get("name", "")), setting,
                     _num(r.get("mean_w"), ".1f"), f"{_num(ci[0], '.1f')} to {_num(ci[1], '.1f')}",
                     "–" if red is None else f"{100 * red:.1f}",
                     "–" if red is None else f"{100 * rci[0]:.1f} to {100 * rci[1]:.1f}",
                     str(r.get("breaths", "–"))))
    zero = any(r.get("kind") == "zero_force" for r in session.validation or ())
    return [_p("Each condition measured in this order with the session's estimator, from the level "
               "the previous one left (Kim et al. 2019 §IV.A.3: the optimised setting OPT, a generic "
               "one FIX, walking without assistance"
               + ("; zero-force: the suit actuated with 0 N at every point, whose reduction is the "
                  "suit's own cost against assistance off" if zero else "")
               + "). Reduction: 1 − cost / unassisted cost, its interval by the delta method."),
            _table(("order", "condition", "setting", "estimate (W)", "95 % CI (W)",
                    "reduction vs unassisted (%)", "95 % CI (%)", "breaths"), rows)]


def _pause_minutes(session: Session) -> float:
    end_s = session.breaths[-1].time_s if session.breaths else 0.0
    return sum((end_s if t1 is None else t1) - t0 for t0, t1 in session.pauses) / 60.0


def _caption(name: str, session: Session) -> str:
    floor = session.threshold_floor
    threshold = ("Algorithm 2's A as is" if floor is None
                 else f"max(A_i, {floor:g}), Algorithm 2's A floored by the sound rule; dashed: A "
                      "before the floor")
    if floor is not None and session.boundary_s is not None:
        threshold += (f" (the late level: before {session.boundary_s:g} s in a setting the floor was "
                      f"{floor:g}·sqrt({session.boundary_s:g} s / t), the sequential boundary)")
    return _CAPTIONS[name].format(estimator=session.estimator_label, threshold=threshold)


def _names(session: Session) -> list[str]:
    if session.param_names:
        return list(session.param_names)
    return sorted(session.evaluations[0].params) if session.evaluations else []


def _phase_of(session: Session, e: EvaluationRow) -> tuple[str, bool]:
    """An evaluation's phase for the tables, and whether its setting was applied: in a
    validation walk the condition it measured (unassisted and zero-force walking apply no
    setting; the optimizer records OPT's for them, bridge/validate.py)."""
    cond = session.condition_of(e.index)
    if cond is None:
        return e.phase, True
    return f"validation: {cond.get('name', '?')}", cond.get("kind") in ("recommended", "generic")


def _evaluation_rows(session: Session) -> tuple[tuple[str, ...], list[tuple[str, ...]]]:
    names = _names(session)
    headers = ("#", "phase", *names, "mean (W)", "σ (W)", "breaths", "early stop", "reason",
               "start (min)", "end (min)", "log")
    rows = []
    for e in session.evaluations:
        phase, shown = _phase_of(session, e)
        rows.append((str(e.index + 1), phase,
                     *((_num(e.params.get(n), ".4g") if shown else "–") for n in names),
                     _num(e.mean_w), _num(e.sd_w), str(e.breaths), "yes" if e.stopped_early else "", e.reason,
                     _min(e.t_start_s), _min(e.t_end_s),
                     session.files[e.file].name + ("" if e.source == "observation" else " (snapshot)")))
    return headers, rows


def write_report(session: Session, out: Path, plots: Mapping[str, Path],
                 skipped: Mapping[str, str]) -> list[Path]:
    """Write ``report.md`` and ``report.html``.

    Args:
        session: The session.
        out: Output directory.
        plots: ``{plot name: PNG path}`` drawn.
        skipped: ``{plot name: why}`` for plots not drawn.

    Returns:
        The two paths.
    """
    from bridge.log import hilbo_version

    sess_cfg = session.config.get("session") if isinstance(session.config.get("session"), Mapping) else {}
    space = session.config.get("space") if isinstance(session.config.get("space"), Mapping) else {}
    n_exp = sum(e.phase == "exploration" for e in session.evaluations)
    title = f"Session review: {session.session_id or session.files[0].name}"
    blocks: list[_Block] = [_h(1, title), _ul([_file_line(session, k) for k in range(len(session.files))])]
    blocks.append(_ul([
        f"subject: {sess_cfg.get('subject', '?')}; parameter space: {space.get('preset', '?')} "
        f"({', '.join(session.param_names)})",
        f"walked {session.minutes_walked:.1f} min, {len(session.breaths)} breaths; "
        f"{len(session.pauses)} pause{'' if len(session.pauses) == 1 else 's'}"
        + (f" ({_pause_minutes(session):.1f} min in all)" if session.pauses else ""),
        f"estimator: {session.estimator_label}",
        f"{len(session.evaluations)} evaluations ({n_exp} exploration, {len(session.evaluations) - n_exp} "
        f"optimisation), {session.n_early_stops} stopped early",
        f"reviewed with hilbo {hilbo_version()}",
    ]))
    if session.validation is not None:
        blocks += [_h(2, "Validation walk"), *_validation_blocks(session)]
    if session.validation_plan is not None:
        blocks += [_h(2, "Recommended setting"),
                   _p("A validation walk recommends nothing: it measures fixed conditions, and its OPT "
                      "is the recommendation of the session it validates (its validation_plan event "
                      "names that log).")]
    else:
        blocks += [_h(2, "Recommended setting"), *_recommended_blocks(session)]
    blocks.append(_h(2, "Plots"))
    for name, title_ in _TITLES.items():
        if name in plots:
            blocks.append(_Block("img", text=title_, items=(_caption(name, session),), path=plots[name]))
        elif name in skipped:
            blocks.append(_p(f"{title_}: not drawn: {skipped[name]}."))
    headers, rows = _evaluation_rows(session)
    blocks += [_h(2, "Evaluations"), _table(headers, rows) if rows else _p("No evaluation completed.")]
    blocks.append(_h(2, "Timeline of events and faults"))
    if session.events:
        blocks.append(_table(("time (min)", "log", "level", "kind", "message"),
                             [(_min(e.time_s), session.files[e.file].name, e.level, e.kind, e.message)
                              for e in session.events]))
    else:
        blocks.append(_p("No events recorded."))
    blocks.append(_h(2, "Rejected records and frames"))
    reject_rows = [(src, reason, str(n)) for src, counts in sorted(session.rejects.items())
                   for reason, n in sorted(counts.items())]
    if reject_rows:
        blocks += [_p("Cumulative counts by reason at the end of each log file (summed over the files): "
                      "cart = breath records, can = CAN frames."),
                   _table(("source", "reason", "count"), reject_rows)]
    else:
        blocks.append(_p("None recorded (no /rejects messages: nothing was rejected, or the log predates "
                         "them)."))
    if session.notes:
        blocks += [_h(2, "Notes"), _ul(session.notes)]
    blocks += [_h(2, "Configuration"), *_config_tables(session.config),
               _Block("code", text=json.dumps(session.config, indent=2, sort_keys=False))]
    return _write_both(out, "report", title, blocks, session.file_mode)


# ---------------------------------------------------------------------------------- CSV
def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    return value


def evaluation_columns(session: Session) -> list[str]:
    """Header of ``evaluations.csv``: index, phase, the parameters, then the estimate and times."""
    names = _names(session)
    return [EVALUATION_FIXED_COLUMNS[0], EVALUATION_FIXED_COLUMNS[1], *names, *EVALUATION_FIXED_COLUMNS[2:]]


def write_evaluations_csv(session: Session, path: Path) -> Path:
    """``evaluations.csv``: one row per completed evaluation (W, W², s; times are session times)."""
    cols = evaluation_columns(session)
    names = cols[2:2 + len(cols) - len(EVALUATION_FIXED_COLUMNS)]
    with _create_text(path, session.file_mode) as f:
        w = csv.writer(f)
        w.writerow(cols)
        for e in session.evaluations:
            phase, shown = _phase_of(session, e)
            w.writerow([_cell(v) for v in (
                e.index + 1, phase, *((e.params.get(n) if shown else None) for n in names),
                e.mean_w, e.var_w2, e.sd_w,
                e.breaths, e.duration_s, e.stopped_early, e.reason, e.t_start_s, e.t_end_s,
                session.files[e.file].name, e.source, e.index)])
    return path


def _from_one(index: int | None) -> int | None:
    return None if index is None else index + 1


def write_breaths_csv(session: Session, path: Path) -> Path:
    """``breaths.csv``: one row per breath of the log(s), with the estimate it produced if any."""
    with _create_text(path, session.file_mode) as f:
        w = csv.writer(f)
        w.writerow(BREATH_COLUMNS)
        for k, b in enumerate(session.breaths):
            w.writerow([_cell(v) for v in (
                k + 1, session.files[b.file].name, b.t_s, b.time_s, b.vo2_ml_min, b.vco2_ml_min, b.ve_l_min,
                b.rer, b.hr_bpm, b.watts, _from_one(b.evaluation), _from_one(b.breath), b.mean_w, b.sd_w,
                b.evaluation)])
    return path


# ---------------------------------------------------------------------------------- compare
def _key_numbers(s: Session) -> list[tuple[str, str]]:
    rec = s.recommended
    best_t = None
    pts = s.best_so_far()
    if pts:
        final = pts[-1][1]
        best_t = next(t for t, v in pts if v == final)
    rej = sum(n for counts in s.rejects.values() for n in counts.values())
    sess_cfg = s.config.get("session") if isinstance(s.config.get("session"), Mapping) else {}
    space = s.config.get("space") if isinstance(s.config.get("space"), Mapping) else {}
    proto = s.config.get("protocol") if isinstance(s.config.get("protocol"), Mapping) else {}
    rows = [
        ("log", ", ".join(f.name + ("" if f.complete else " (cut off)") for f in s.files)),
        ("session id", s.session_id or "?"),
        ("subject", str(sess_cfg.get("subject", "?"))),
        ("parameter space", str(space.get("preset", "?"))),
        ("stopping rule", str(proto.get("stopping", "?"))),
        ("minutes walked", f"{s.minutes_walked:.1f}"),
        ("breaths", str(len(s.breaths))),
        ("evaluations", str(len(s.evaluations))),
        ("exploration / optimisation", f"{sum(e.phase == 'exploration' for e in s.evaluations)} / "
                                       f"{sum(e.phase != 'exploration' for e in s.evaluations)}"),
        ("early stops", str(s.n_early_stops)),
        ("lowest estimated cost (W)", _num(min((e.mean_w for e in s.evaluations), default=None))),
        ("best so far reached at (min)", _num(best_t, ".1f")),
        ("recommended cost (W, ± 1 σ)", "–" if rec is None else f"{rec.mean_w:.1f} ± {rec.sd_w:.1f}"),
        ("recommended evaluation", "–" if rec is None or rec.index is None else str(rec.index + 1)),
    ]
    if rec is not None:
        rows += [(f"recommended {n}", _num(rec.params.get(n), ".4g")) for n in s.param_names]
    rows.append(("rejected records/frames", str(rej)))
    return rows


def write_compare_report(sessions: Sequence[Session], out: Path, png: Path) -> list[Path]:
    """Write ``compare.md`` and ``compare.html``: the comparison plot and a table of key numbers.

    Args:
        sessions: The sessions (A, B).
        out: Output directory.
        png: The comparison plot.

    Returns:
        The two paths.
    """
    tags = [chr(ord("A") + k) for k in range(len(sessions))]
    keyed = [dict(_key_numbers(s)) for s in sessions]
    order = list(dict.fromkeys(k for numbers in (_key_numbers(s) for s in sessions) for k, _ in numbers))
    rows = [(k, *(numbers.get(k, "–") for numbers in keyed)) for k in order]
    title = "Session comparison: " + " vs ".join(f"{t} = {s.label}"
                                                 for t, s in zip(tags, sessions, strict=True))
    blocks = [
        _h(1, title),
        _ul([f"{t}: {', '.join(f.path for f in s.files)}" for t, s in zip(tags, sessions, strict=True)]),
        _Block("img", text="comparison", items=(
            "Left: best estimated cost so far against minutes walked (dots: evaluations, crosses: early "
            "stops, dashed: each session's recommended setting). Right: evaluation counts.",), path=png),
        _h(2, "Key numbers"),
        _table(("", *tags), rows),
    ]
    notes = [f"{t}: {n}" for t, s in zip(tags, sessions, strict=True) for n in s.notes]
    if notes:
        blocks += [_h(2, "Notes"), _ul(notes)]
    return _write_both(out, "compare", title, blocks, sessions[0].file_mode & sessions[-1].file_mode)
