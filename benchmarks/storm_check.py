"""Exchange and agreement benchmark: DRN/stormpy export costs, Storm vs our solver vs the LP.

Random sparse IMDPs (3 actions, 20 successors per row, positive lower bounds so that Storm
accepts unbounded queries).  For each size: seconds to write/read DRN, to build the stormpy
model in memory, Storm's robust/cooperative ``Pmax=? [F "target"]`` at precision 1e-8, our
``solve_reachability`` at 1e-8, and the largest distance of Storm's value from our sound
bracket.  A 30-state model is also solved by the LP (cvxpy + Clarabel).

Writes ``benchmarks/results/storm_check.json`` and ``.md`` (medians over ``--repeat`` runs;
ratios from one run).  stormpy is optional: without it the Storm columns are empty.

Usage: ``python benchmarks/storm_check.py [--sizes 1000 10000 100000] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time

import numpy as np

from robust_imdp.io.formats import read_drn, storm_reachability, to_stormpy, write_drn
from robust_imdp.models.imdp import IMDP

HERE = os.path.dirname(os.path.abspath(__file__))


def random_sparse_imdp(n, a=3, k=20, delta=0.2, rng=0):
    """n states, a actions, k distinct successors per row, [p(1-delta), p(1+delta)] intervals."""
    rng = np.random.default_rng(rng)
    R = n * a
    k = min(k, n)
    col = (np.sort(rng.integers(0, n - k + 1, size=(R, k)), axis=1) + np.arange(k)).ravel()  # distinct, sorted
    w = rng.uniform(0.05, 1.0, size=(R, k))
    p = w / w.sum(axis=1, keepdims=True)
    lo = (p * (1 - delta)).ravel()
    up = np.minimum(1.0, p * (1 + delta)).ravel()
    return IMDP.from_csr(np.arange(0, R + 1, a), np.arange(0, R * k + 1, k), col, lo, up)


def timed(fn, repeat):
    ts, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    try:
        import stormpy  # noqa: F401

        have_storm = True
    except ImportError:
        have_storm = False
    try:
        from robust_imdp.solvers.api import solve_reachability
    except ImportError:
        solve_reachability = None

    rows = []
    for n in args.sizes:
        m = random_sparse_imdp(n, rng=n)
        tgt = np.zeros(n, bool)
        tgt[: max(1, n // 100)] = True
        rep = args.repeat if n <= 10_000 else 1
        row = {"n_states": n, "n_choices": m.n_choices, "nnz": m.nnz}
        with tempfile.TemporaryDirectory() as d:
            path = os.path.join(d, "m.drn")
            row["drn_write_s"], _ = timed(lambda: write_drn(m, path, target=tgt), rep)
            row["drn_mb"] = os.path.getsize(path) / 2**20
            if n <= 10_000:
                row["drn_read_s"], back = timed(lambda: read_drn(path), rep)
                assert np.array_equal(back.upper, m.upper)
        if have_storm:
            row["stormpy_build_s"], model = timed(lambda: to_stormpy(m, tgt), rep)
            row["stormpy_build_ns_per_entry"] = 1e9 * row["stormpy_build_s"] / m.nnz
        for adv in ("pessimistic", "optimistic"):
            if solve_reachability is not None:
                row[f"ours_{adv}_s"], ours = timed(lambda: solve_reachability(m, tgt, adversary=adv, precision=1e-8), rep)
                row[f"ours_{adv}_precision"] = float(ours.precision)
            if have_storm:
                row[f"storm_{adv}_s"], sv = timed(lambda: storm_reachability(model, tgt, adversary=adv, precision=1e-8), rep)
                if solve_reachability is not None:
                    # distance of Storm's value from our sound bracket [lower, upper] (0 = inside)
                    out = np.maximum(ours.lower - sv, sv - ours.upper).clip(min=0)
                    row[f"storm_{adv}_outside_bracket"] = float(out.max())
                    row[f"storm_{adv}_max_abs_diff_lower"] = float(np.abs(ours.lower - sv).max())
                    row[f"ratio_ours_over_storm_{adv}"] = row[f"ours_{adv}_s"] / row[f"storm_{adv}_s"]
        rows.append(row)
        print(json.dumps(row))

    # LP agreement on a small model
    lp_row = {}
    small = random_sparse_imdp(30, a=2, k=5, rng=1)
    stgt = np.zeros(30, bool)
    stgt[0] = True
    from robust_imdp.solvers.lp import solve_reachability_lp

    t = time.perf_counter()
    lp = solve_reachability_lp(small, stgt, adversary="optimistic")
    lp_row["lp_optimistic_30_states_s"] = time.perf_counter() - t
    lp_row["lp_bracket_width"] = float(lp.precision)
    if solve_reachability is not None:
        ours = solve_reachability(small, stgt, adversary="optimistic", precision=1e-10)
        # gap between the two brackets (0 when they overlap)
        gap = np.maximum(ours.lower - lp.upper, lp.lower - ours.upper).clip(min=0)
        lp_row["lp_vs_ours_bracket_gap"] = float(gap.max())
    if have_storm:
        sv = storm_reachability(small, stgt, adversary="optimistic", precision=1e-10)
        lp_row["storm_outside_lp_bracket"] = float(np.maximum(lp.lower - sv, sv - lp.upper).clip(min=0).max())
    print(json.dumps(lp_row))

    result = {"machine": platform.platform(), "note": os.environ.get("BENCH_NOTE", "2-core machine; medians of the stated repetitions"),
              "sizes": rows, "lp_small": lp_row}
    os.makedirs(os.path.join(HERE, "results"), exist_ok=True)
    with open(os.path.join(HERE, "results", "storm_check.json"), "w") as fh:
        json.dump(result, fh, indent=2)
    cols = ["n_states", "nnz", "drn_write_s", "drn_mb", "stormpy_build_ns_per_entry", "ours_pessimistic_s",
            "storm_pessimistic_s", "storm_pessimistic_outside_bracket", "ours_optimistic_s", "storm_optimistic_s",
            "storm_optimistic_outside_bracket"]
    md = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        md.append("| " + " | ".join(f"{r[c]:.3g}" if isinstance(r.get(c), float) else str(r.get(c, "-")) for c in cols) + " |")
    md += ["", "LP (30 states, optimistic): " + ", ".join(f"{k} = {v:.3g}" for k, v in lp_row.items()),
           "", result["note"] + "; ratios from one run."]
    with open(os.path.join(HERE, "results", "storm_check.md"), "w") as fh:
        fh.write("\n".join(md) + "\n")


if __name__ == "__main__":
    main()
