"""Paired regret of `hilbo bench hil` runs: method A of run X against method B of run Y, per subject.

    python docs/results/hil/paired.py RUN_X/sessions.jsonl METHOD_A RUN_Y/sessions.jsonl METHOD_B

Prints, at 20, 30 and 60 min and at the end: the median regret of each (W and % of the available
reduction, i.e. baseline - optimum), the paired mean difference A - B with its SE, and the share
of subjects where A is lower. The regret at minute m is that of the recommendation in force then
(the last trace entry at or before m; before the first, the unassisted baseline's).
"""

from __future__ import annotations

import json
import math
import statistics
import sys


def load(path: str, method: str) -> dict[tuple[str, int], dict]:
    out = {}
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            r = json.loads(line)
            if r["method"] == method:
                out[(r["space"], r["seed"])] = r
    return out


def regret_at(r: dict, minute: float | None) -> float:
    if minute is None:
        return r["final_regret_w"]
    t = 60.0 * minute
    value = r["baseline_cost_w"] - r["optimum_cost_w"]  # nothing recommended yet
    for t_s, regret in r["trace"]:
        if t_s <= t:
            value = regret
    return value


def out(line: str) -> None:
    sys.stdout.write(line + "\n")


def main() -> None:
    xa, ma, yb, mb = sys.argv[1:5]
    a, b = load(xa, ma), load(yb, mb)
    keys = sorted(set(a) & set(b))
    out(f"{ma} ({xa}) vs {mb} ({yb}): {len(keys)} paired subjects")
    out("| minute | median A (W) | median A (%) | median B (W) | median B (%) | A - B mean ± SE (W) "
        "| A lower |")
    out("|---|---|---|---|---|---|---|")
    for minute in (20, 30, 60, None):
        ra = [regret_at(a[k], minute) for k in keys]
        rb = [regret_at(b[k], minute) for k in keys]
        red = [a[k]["baseline_cost_w"] - a[k]["optimum_cost_w"] for k in keys]
        d = [x - y for x, y in zip(ra, rb, strict=True)]
        se = statistics.stdev(d) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
        pa = statistics.median(100 * x / r for x, r in zip(ra, red, strict=True))
        pb = statistics.median(100 * x / r for x, r in zip(rb, red, strict=True))
        lower = sum(x < y for x, y in zip(ra, rb, strict=True)) / len(d)
        label = "final" if minute is None else str(minute)
        out(f"| {label} | {statistics.median(ra):.1f} | {pa:.1f} | {statistics.median(rb):.1f} | {pb:.1f} | "
              f"{statistics.mean(d):+.1f} ± {se:.1f} | {100 * lower:.0f} % |")


if __name__ == "__main__":
    main()
