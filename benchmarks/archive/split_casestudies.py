"""Case studies under certification sub-boxes: Q_yes and bound time per ``split_tol`` setting.

Runs ``synthesize_from_data`` (advice off, no cache, default scheduler: in process, numba threads on
all cores) on the shipped problem files with ``rkhs.bound_chunk``'s ``split_tol`` forced to each
value given (the problem file has no such key, so the setting is injected by wrapping
``rkhs.bound_chunk``, which the bound stage imports at call time). Repeats ``--reps`` times and
reports the median bound time. ``PYTHONPATH=<other tree>/src`` measures another tree the same way.

Usage: ``python benchmarks/archive/split_casestudies.py [--tol none 0.0015 ...] [--reps 2] [--out NAME]``;
prints one JSON line per (problem, tol) and writes ``benchmarks/results/NAME.json`` if ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

HERE = Path(__file__).resolve().parents[1]  # benchmarks/
PROBLEMS = ("three_mode_linear", "four_mode_nonlinear")


def run(name: str, tol, reps: int) -> dict:
    from robust_imdp.bounds import rkhs
    from robust_imdp.io.files import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data

    orig = rkhs.bound_chunk

    def wrapped(*a, **k):
        k["split_tol"] = tol
        return orig(*a, **k)

    rkhs.bound_chunk = wrapped
    try:
        problem = load_problem(HERE.parent / "examples" / "problems" / f"{name}.toml")
        bound, total, yes = [], [], set()
        for _ in range(reps):
            t0 = time.perf_counter()
            res = synthesize_from_data(problem, progress=False, advice=False)
            total.append(time.perf_counter() - t0)
            bound.append(float(res.timings["bound"]))
            yes.add(res.counts()["yes"])
    finally:
        rkhs.bound_chunk = orig
    return {"problem": name, "split_tol": tol, "q_yes": sorted(yes), "bound_s": bound,
            "bound_median_s": statistics.median(bound), "total_s": total, "load": os.getloadavg()[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tol", nargs="+", default=["none"])
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    for name in args.problems:
        for t in args.tol:
            row = run(name, None if t == "none" else float(t), args.reps)
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.out:
        (HERE / "results" / f"{args.out}.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
