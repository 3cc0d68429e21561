"""The hour's answer from a ``hilbo bench hil`` run: regret as % of the available reduction at
minutes 20/30/40/60, the share of subjects below CMA-ES with a two-sided sign test (ties left
out), the first proposal's minute, the reported estimate's z, sessions above 50 % at 60 min, by
landscape family of the realistic wearer.

Usage: python docs/results/hil/hour_answer_stats.py RUN/sessions.jsonl[.gz] [REFERENCE_METHOD]
"""

from __future__ import annotations

import gzip
import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

from scipy.stats import binomtest

from hilbo_core.presets import preset
from virtual_hw.wearer import make_wearer

MINUTES = (20, 30, 40, 60)


def regret_pct_at(session: dict, minute: float) -> float:
    """The regret of the recommendation held at ``minute`` of walking, % of the reduction."""
    t_s = 60.0 * minute
    regret_w = None
    for t, r in session["trace"]:
        if t <= t_s + 1e-9:
            regret_w = r
    if regret_w is None:  # nothing recommended yet: the first recommendation's regret
        regret_w = session["trace"][0][1]
    return 100.0 * regret_w / (session["baseline_cost_w"] - session["optimum_cost_w"])


def main(path: str, reference: str = "cmaes") -> None:
    raw = Path(path).read_bytes()
    text = (gzip.decompress(raw) if path.endswith(".gz") else raw).decode()
    rows = [json.loads(line) for line in text.splitlines() if line.strip()]
    by = defaultdict(dict)
    for r in rows:
        by[r["method"]][(r["space"], r["seed"])] = r
    ref = by[reference]
    family = {}
    for space, seed in ref:
        w = make_wearer("realistic", preset(space), seed=seed)
        family[(space, seed)] = getattr(w, "family", None)
    for method, sessions in by.items():
        for fam in (None, *sorted({f.value for f in family.values() if f is not None})):
            keys = [k for k in sessions if fam is None or getattr(family.get(k), "value", None) == fam]
            if not keys:
                continue
            label = "all" if fam is None else fam
            cells = []
            for m in MINUTES:
                med = statistics.median(regret_pct_at(sessions[k], m) for k in keys)
                cell = f"{med:.1f} %"
                if method != reference:
                    pairs = [(regret_pct_at(sessions[k], m), regret_pct_at(ref[k], m))
                             for k in keys if k in ref]
                    lower = sum(a < b for a, b in pairs)
                    higher = sum(a > b for a, b in pairs)
                    p = binomtest(lower, lower + higher).pvalue if lower + higher else 1.0
                    cell += f" ({100 * lower / len(pairs):.0f} % below, p {p:.2g})"
                cells.append(cell)
            first = [sessions[k]["t_first_proposal_s"] / 60 for k in keys
                     if sessions[k].get("t_first_proposal_s")]
            z = [sessions[k]["reported_z"] for k in keys if sessions[k].get("reported_z") is not None]
            over = sum(regret_pct_at(sessions[k], 60) > 50 for k in keys)
            line = f"{method:>8} {label:>7} n={len(keys):3d} | " + " | ".join(cells)
            if first:
                line += f" | first proposal {statistics.median(first):.1f} min"
            if z:
                line += f" | reported z {statistics.median(z):+.2f}"
            sys.stdout.write(line + f" | >50 % at 60: {over}\n")


if __name__ == "__main__":
    main(*sys.argv[1:])
