"""Two ``hilbo bench stopping`` campaigns paired by seed: B minus A, per setting and method.

Usage: ``paired.py A/trials.jsonl B/trials.jsonl LABEL_A LABEL_B`` (docs/results.md, "Stopping
benchmarks of Kim et al. 2019"). Both campaigns share every trial's exploration (same seed), so the
difference of a trial's y_T between them is a paired difference. Writes a Markdown table.
"""

from __future__ import annotations

import json
import math
import statistics as st
import sys
from typing import Any

FUNCTION_ORDER = ["hartmann6", "ackley", "levy", "branin"]


def load(path: str) -> dict[tuple[str, float, str, int], dict[str, Any]]:
    with open(path) as f:
        return {(r["function"], r["noise"], r["method"], r["seed"]): r for r in map(json.loads, f)}


def sem(values: list[float]) -> float:
    return st.stdev(values) / math.sqrt(len(values))


def main(path_a: str, path_b: str, la: str, lb: str) -> None:
    a, b = load(path_a), load(path_b)
    settings = sorted({k[:3] for k in b}, key=lambda k: (FUNCTION_ORDER.index(k[0]), k[1], k[2] != "fixed"))
    out = [f"| function | σ_z²/σ̃² | method | pairs | y_final, {la} | y_final, {lb} | "
           f"Δ y_final ({lb} − {la}) | z | Δ mean y_t | evaluations {la} → {lb} | s / trial {la} → {lb} |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    zs = []
    for s in settings:
        keys = [k for k in b if k[:3] == s and k in a]
        if len(keys) < 2:
            continue
        ya = [a[k]["y"][-1] for k in keys]
        yb = [b[k]["y"][-1] for k in keys]
        d = [y2 - y1 for y1, y2 in zip(ya, yb, strict=True)]
        d_avg = [st.mean(b[k]["y"]) - st.mean(a[k]["y"]) for k in keys]
        z = st.mean(d) / sem(d) if sem(d) > 0 else 0.0
        zs.append(z)
        ev_a, ev_b = st.mean(a[k]["evaluations"] for k in keys), st.mean(b[k]["evaluations"] for k in keys)
        s_a, s_b = st.mean(a[k]["wall_s"] for k in keys), st.mean(b[k]["wall_s"] for k in keys)
        out.append(f"| {s[0]} | {s[1]:g} | {s[2]} | {len(keys)} | {st.mean(ya):.3f} ± {sem(ya):.3f} | "
                   f"{st.mean(yb):.3f} ± {sem(yb):.3f} | {st.mean(d):+.3f} ± {sem(d):.3f} | {z:+.2f} | "
                   f"{st.mean(d_avg):+.3f} ± {sem(d_avg):.3f} | {ev_a:.1f} → {ev_b:.1f} | "
                   f"{s_a:.2f} → {s_b:.2f} |")
    beyond = sum(abs(z) > 1.96 for z in zs)
    out.append(f"\n|z| > 1.96: {beyond} of {len(zs)} settings; mean z {st.mean(zs):+.2f}")
    sys.stdout.write("\n".join(out) + "\n")


if __name__ == "__main__":
    main(*sys.argv[1:5])
