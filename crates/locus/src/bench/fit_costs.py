#!/usr/bin/env python3
"""What each kind of work costs a farm worker, fitted to callgrind counts.

`forward_cost.py` writes, for every worker of a run, its render-phase
instructions and its report's counts (BVH steps, path vertices, camera
samples started, queries received, queries forwarded). This script fits
instructions = sum over kinds of (cost per item x items) by least squares
over every worker of every run directory given, and prints each kind's
cost in instructions and in BVH steps, how well the fit holds, and, per
worker, the scheduler's predicted share of the work against the share it
took. The partition's cost model (`crates/scheduler/src/cost.rs`,
`partition/refine.rs`) prices the same kinds in preview BVH steps; this is
what to calibrate it against.

    python3 crates/locus/src/bench/fit_costs.py bench-out/fd-*

Each directory is a `forward_cost.py --out DIR` run of any scene, worker
count and partitioner; a run needs at least as many workers in all as
there are kinds.
"""

import json
import os
import sys

# (name, what it counts in a worker's report)
KINDS = [
    ("BVH step", lambda st: st["trace"]["bvh_nodes"] + st["trace"]["tri_tests"]),
    ("path vertex", lambda st: st["trace"]["shadow_rays"]),
    ("camera sample", lambda st: st["trace"]["samples"]),
    ("query in", lambda st: st["queries_in"]),
    ("query forwarded", lambda st: st["forwarded_out"]),
]


def solve(a, b):
    """x with a x = b (Gaussian elimination with partial pivoting)."""
    n = len(a)
    m = [row[:] + [v] for row, v in zip(a, b)]
    for c in range(n):
        p = max(range(c, n), key=lambda r: abs(m[r][c]))
        if abs(m[p][c]) < 1e-300:
            raise SystemExit("the runs do not tell the kinds apart (singular fit)")
        m[c], m[p] = m[p], m[c]
        for r in range(n):
            if r != c:
                f = m[r][c] / m[c][c]
                m[r] = [x - f * y for x, y in zip(m[r], m[c])]
    return [m[i][n] / m[i][i] for i in range(n)]


def rows_of(d):
    """(run, worker, instructions, counts, measured share, predicted share)."""
    fc = json.load(open(os.path.join(d, "forward-cost.json")))
    report = json.load(open(os.path.join(d, "farm.json")))["farm"]
    total = sum(w[3] for w in fc["workers"])
    out = []
    for w in fc["workers"]:
        if len(w) < 5 or not w[4]:
            raise SystemExit(f"{d}: worker {w[0]} has no counts: run forward_cost.py again "
                             "(an older one kept none, and a worker whose report row does not "
                             "carry its --listen address gets none)")
        name, render, st = w[0], w[3], w[4]
        pred = next(r["predicted_cost_share"] for r in report["workers"] if r["stats"] == st)
        out.append((os.path.basename(d.rstrip("/")), name, render,
                    [f(st) for _, f in KINDS], render / total, pred))
    return out


def main():
    dirs = sys.argv[1:]
    if not dirs:
        print(__doc__)
        return 2
    rows = [r for d in dirs for r in rows_of(d)]
    k = len(KINDS)
    if len(rows) < k:
        raise SystemExit(f"{len(rows)} workers in all: the fit needs at least {k}")
    ata = [[sum(r[3][i] * r[3][j] for r in rows) for j in range(k)] for i in range(k)]
    atb = [sum(r[3][i] * r[2] for r in rows) for i in range(k)]
    cost = solve(ata, atb)
    fit = [sum(c * x for c, x in zip(cost, r[3])) for r in rows]
    rel = [(f - r[2]) / r[2] for f, r in zip(fit, rows)]
    print(f"{len(rows)} workers of {len(dirs)} runs")
    print("| kind | instructions | BVH steps |")
    print("|---|---:|---:|")
    for (name, _), c in zip(KINDS, cost):
        print(f"| {name} | {c:.0f} | {c / cost[0]:.1f} |")
    rms = (sum(e * e for e in rel) / len(rel)) ** 0.5
    print(f"fit error per worker: rms {rms:.1%}, most {max(abs(e) for e in rel):.1%}")
    err = [r[4] - r[5] for r in rows]
    print(f"the scheduler's predicted share against the measured: rms {(sum(e * e for e in err) / len(err)) ** 0.5:.3f}")
    print("| run | worker | M instructions | fitted | measured share | predicted share |")
    print("|---|---|---:|---:|---:|---:|")
    for r, f in zip(rows, fit):
        print(f"| {r[0]} | {r[1]} | {r[2] / 1e6:.1f} | {f / 1e6:.1f} | {r[4]:.3f} | {r[5]:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
