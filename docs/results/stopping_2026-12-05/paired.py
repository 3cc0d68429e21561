"""Paired by seed: y_final and mean y_t of campaign B minus campaign A, per setting and method."""
import json, math, sys, statistics as st
def load(p):
    return {(r["function"], r["noise"], r["method"], r["seed"]): r for r in map(json.loads, open(p))}
A, B = load(sys.argv[1]), load(sys.argv[2])
la, lb = sys.argv[3], sys.argv[4]
settings = sorted({k[:3] for k in B}, key=lambda k: (["hartmann6", "ackley", "levy", "branin"].index(k[0]), k[1], k[2] != "fixed"))
print(f"| function | σ_z²/σ̃² | method | pairs | y_final, {la} | y_final, {lb} | Δ y_final ({lb} − {la}) | z | Δ mean y_t | evaluations {la} → {lb} | s / trial {la} → {lb} |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
zs = []
for s in settings:
    keys = [k for k in B if k[:3] == s and k in A]
    if len(keys) < 2: continue
    ya = [A[k]["y"][-1] for k in keys]; yb = [B[k]["y"][-1] for k in keys]
    d = [b - a for a, b in zip(ya, yb)]
    da = [st.mean(B[k]["y"]) - st.mean(A[k]["y"]) for k in keys]
    n = len(d); se = st.stdev(d) / math.sqrt(n); z = st.mean(d) / se if se > 0 else 0.0
    sea = st.stdev(da) / math.sqrt(n)
    zs.append(z)
    m = lambda v: st.mean(v); sem = lambda v: st.stdev(v) / math.sqrt(len(v))
    print(f"| {s[0]} | {s[1]:g} | {s[2]} | {n} | {m(ya):.3f} ± {sem(ya):.3f} | {m(yb):.3f} ± {sem(yb):.3f} | {m(d):+.3f} ± {se:.3f} | {z:+.2f} | {m(da):+.3f} ± {sea:.3f} "
          f"| {m([A[k]['evaluations'] for k in keys]):.1f} → {m([B[k]['evaluations'] for k in keys]):.1f} | {m([A[k]['wall_s'] for k in keys]):.2f} → {m([B[k]['wall_s'] for k in keys]):.2f} |")
print(f"\n|z| > 1.96: {sum(abs(z) > 1.96 for z in zs)} of {len(zs)} settings; mean z {st.mean(zs):+.2f}")
