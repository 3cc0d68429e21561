"""Adaptive BO against the better Optuna TPE + pruner, per setting (a check on Kim et al. 2019's benchmarks).

Usage: ``vs_tpe.py BO/trials.jsonl TPE/trials.jsonl`` (docs/results.md, "Stopping
benchmarks of Kim et al. 2019"). Both campaigns ran the same seeds, hence the same exploration
per trial. For every function × noise level: adaptive's mean y_T, each TPE method's, and whether
adaptive's is below the better of the two. Writes a Markdown table and the count.
"""

from __future__ import annotations

import json
import statistics as st
import sys
from collections import defaultdict

from paired import FUNCTION_ORDER, sem  # the sibling script (run as a script, its directory is on the path)

PEERS = ("tpe-wilcoxon", "tpe-halving")


def final_y(paths: list[str]) -> dict[tuple[str, float, str], list[float]]:
    out: dict[tuple[str, float, str], list[float]] = defaultdict(list)
    for path in paths:
        with open(path) as f:
            for rec in map(json.loads, f):
                out[(rec["function"], rec["noise"], rec["method"])].append(rec["y"][-1])
    return out


def cell(values: list[float]) -> str:
    return f"{st.mean(values):.3f} ± {sem(values):.3f}"


def main(bo_path: str, tpe_path: str) -> None:
    y = final_y([bo_path, tpe_path])
    settings = sorted({k[:2] for k in y}, key=lambda k: (FUNCTION_ORDER.index(k[0]), k[1]))
    out = ["| function | σ_z²/σ̃² | adaptive | tpe-wilcoxon | tpe-halving | adaptive below the better TPE |",
           "|---|---|---|---|---|---|"]
    wins = 0
    for fn, noise in settings:
        ada = y[(fn, noise, "adaptive")]
        best_peer = min(st.mean(y[(fn, noise, p)]) for p in PEERS)
        below = st.mean(ada) < best_peer
        wins += below
        out.append(f"| {fn} | {noise:g} | {cell(ada)} | {cell(y[(fn, noise, PEERS[0])])} | "
                   f"{cell(y[(fn, noise, PEERS[1])])} | {'yes' if below else 'no'} |")
    out.append(f"\nadaptive below the better TPE + pruner in {wins} of {len(settings)} settings")
    sys.stdout.write("\n".join(out) + "\n")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
