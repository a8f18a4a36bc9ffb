"""The advice's larger-local-pools lever against real runs (issue 20): is its estimate right, what does it cost?

    python benchmarks/advice_local_pools.py [--only NAME ...]

Problems: the benchmark family's configurations that the pipeline certifies with local pools (more than
``LOCAL_AUTO`` points per mode): the 3-D middle configuration (1,024 points per mode, 8^3 cells) at r/l
0.03, 0.125 and 0.25, and the dense 2-D one (2,048 points per mode). Per problem: a run with the advice on
(its baseline Q_yes and every lever's estimate), then a run with ``local_points`` = the lever's proposal (the
real Q_yes it estimates, and the bound stage's time against the first run's, one after the other).
``--only`` re-runs some rows and keeps the others.

Writes ``benchmarks/results/advice_local_pools.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))
import family  # noqa: E402
from reference import merged_rows, results_record, write_results  # noqa: E402

SEED = 20  # the family's default seed: the same data as benchmarks/results/family.md
CONFIGS = {
    "d3-rl0.03": family.middle_3d(0.03),
    "d3-rl0.125": family.middle_3d(0.125),
    "d3-rl0.25": family.middle_3d(0.25),
    "d2-rl0.125-dn8": dict(dim=2, ratio=0.125, noise=0.15, density=8),
}


def main(argv=None) -> int:
    from robust_imdp.pipeline.run import synthesize_from_data

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=None)
    args = ap.parse_args(argv)
    family.warm_up(SEED)
    rows = []
    for name, c in family.chosen(CONFIGS, args.only):
        p = family.pipeline_problem(c, SEED)
        plain = synthesize_from_data(p, progress=False, advice=True)
        levers = {lv["name"]: lv for lv in plain.advice.get("levers", [])}
        pool = levers.get("larger local pools", {})
        real = None
        if pool:
            k = int(pool["setting"].split("=")[1].split()[0].rstrip(","))
            res = synthesize_from_data(p.replace(local_points=k), progress=False, advice=False)
            real = {"local_points": k, "q_yes": int(np.sum(res.class_names == "yes")),
                    "share": float(np.mean(res.class_names == "yes")), "bound_seconds": res.timings.get("bound")}
        row = {"problem": name, "key": family.key_of(c), "cells": int(plain.partition.n_cells),
               "winner": plain.advice.get("winner"), "baseline_share": float(np.mean(plain.class_names == "yes")),
               "q_yes": int(np.sum(plain.class_names == "yes")),
               "levers": {k: {"share": v["q_yes_share"], "setting": v["setting"], "note": v["note"]}
                          for k, v in levers.items()},
               "pool_estimate": pool.get("q_yes_share"), "real": real,
               "bound_seconds": plain.timings.get("bound"), "advice_seconds": plain.timings.get("advice")}
        rows.append(row)
        print(json.dumps(row), flush=True)
    old = OUT / "advice_local_pools.json"
    if args.only and old.exists():  # --only: replace those rows of the earlier record, keep the others
        rows = merged_rows(json.loads(old.read_text())["rows"], rows, "problem")
    data = results_record(rows)

    def pct(v):
        return "-" if v is None else f"{100 * v:.1f} %"

    lines = ["# The advice's larger-local-pools lever against real runs (`benchmarks/advice_local_pools.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}. Q_yes as a share of "
             "X (cells; the family's cells are equal); *estimate* = the advice's lever (the pilot cells' median "
             "excess ratio with the proposed pools, applied to every cell); *real* = a run with that "
             "`local_points`; bound seconds of each run, one after the other; advice seconds of the first run "
             "(all five levers).", "",
             "| problem | cells | now: Q_yes, bound s, advice s | other levers (estimates) | pool lever: setting | "
             "estimate | real: Q_yes, bound s | bound time ratio | winner |", "|---|---|---|---|---|---|---|---|---|"]
    for w in rows:
        lv = w["levers"]
        others = "; ".join(f"{k} {pct(v['share'])}" for k, v in lv.items() if k != "larger local pools")
        r = w["real"]
        real_s = "-" if r is None else f"{pct(r['share'])} ({r['q_yes']}), {r['bound_seconds']:.1f}"
        ratio = "-" if r is None else f"{r['bound_seconds'] / w['bound_seconds']:.1f}x"
        lines.append(f"| {w['problem']} | {w['cells']} | {pct(w['baseline_share'])} ({w['q_yes']}), "
                     f"{w['bound_seconds']:.1f}, {w['advice_seconds']:.1f} | {others} | "
                     f"{lv.get('larger local pools', {}).get('setting', '-')} | {pct(w['pool_estimate'])} | "
                     f"{real_s} | {ratio} | {w['winner']} |")
    write_results("advice_local_pools", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
