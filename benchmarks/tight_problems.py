"""The ``tight`` preset on the case studies and the newcomer problems (issue 20): what it gains and costs.

    python benchmarks/tight_problems.py [--only NAME ...] [--merge]

Problems: the shipped case-study files, the newcomer problems (``examples/newcomer``, data from their
generators; ``unicycle3d_16`` and ``di4d_8`` included) and the 3-D case study at 16^3 (all as
``benchmarks/identical.py --full`` writes them), and the issue's newcomer system
(``serial_parts.build_problem(0.25)``). Per problem, one after the other in this process: a run with the
problem as it is and a run of ``problem.tightened()`` (advice off, no cache), Q_yes and the bound stage's
seconds (``Result.timings``).

Writes ``benchmarks/results/tight_problems.json`` and ``.md`` after every problem.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import identical  # noqa: E402
from reference import merged_rows, results_record, write_results  # noqa: E402
from serial_parts import build_problem  # noqa: E402

NAME = "tight_problems"



def problems(work: Path) -> list:
    env = {**os.environ}
    out = [(n, p) for n, p in identical._problems(work, True, env)
           if not n.startswith(("v_", "one_d"))]
    return out + [("newcomer_issue20_cell0.25", None)]


def _bound_s(res) -> float:
    t = res.timings
    return float(sum(v for k, v in t.items() if k.startswith("bound")))


def main(argv=None) -> int:
    from robust_imdp.io.files import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--merge", action="store_true")
    args = ap.parse_args(argv)
    path = ROOT / "benchmarks" / "results" / f"{NAME}.json"
    old = json.loads(path.read_text())["rows"] if args.merge and path.exists() else []
    rows = []
    work = Path(tempfile.mkdtemp())
    for name, file in problems(work):
        if args.only and name not in args.only:
            continue
        p = build_problem(0.25) if file is None else load_problem(file)
        if not p.method.split:
            continue
        row = {"problem": name, "cells": None}
        for label, q in (("as_is", p), ("tight", p.tightened())):
            res = synthesize_from_data(q, progress=False, advice=False)
            row["cells"] = int(res.partition.n_cells)
            row[label] = {"q_yes": int((res.class_names == "yes").sum()), "bound_seconds": _bound_s(res),
                          "timings": {k: float(v) for k, v in res.timings.items()},
                          "split_tol": q.split_tol, "local_points": q.local_points}
        rows.append(row)
        a, t = row["as_is"], row["tight"]
        print(f"{name}: Q_yes {a['q_yes']} -> {t['q_yes']} of {row['cells']}; bound {a['bound_seconds']:.1f} -> "
              f"{t['bound_seconds']:.1f} s", flush=True)
        data = results_record(merged_rows(old, rows, "problem"))
        lines = ["# The `tight` preset on the case studies and newcomer problems (`benchmarks/tight_problems.py`)", "",
                 f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}. Per problem: a run "
                 "as it is and a run of `problem.tightened()`, one after the other (advice off, no cache); bound = "
                 "the bound stage's seconds.", "",
                 "| problem | cells | Q_yes as is / tight | tight settings | bound s as is / tight (ratio) |",
                 "|---|---|---|---|---|"]
        for r in data["rows"]:
            a, t = r["as_is"], r["tight"]
            lp = t["local_points"]
            lines.append(f"| {r['problem']} | {r['cells']} | {a['q_yes']} / {t['q_yes']} | split_tol {t['split_tol']:g}"
                         f", {'local_points unset' if lp is None else f'local_points {lp}'} | {a['bound_seconds']:.1f} / "
                         f"{t['bound_seconds']:.1f} ({t['bound_seconds'] / max(a['bound_seconds'], 1e-9):.1f}x) |")
        write_results(NAME, data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
