"""The advice's sub-box lever against real sub-box runs (issue 20): is its estimate right, and where does it win?

    python benchmarks/advice_sub_boxes.py [--only NAME ...]

Problems: the issue's newcomer system (``serial_parts.build_problem``: the three-mode linear system at
lengthscale 1, B = 6, on cells of 0.25), the newcomer's 16 x 16 robot
(``examples/newcomer/robot2d_16.toml`` with its data generator), and the first case study
(``three_mode_linear``, cells of 0.125) and the shipped two-goal problem of the second
(``four_mode_nonlinear_two_goals.toml``). ``--only`` re-runs some rows and keeps the others. Per problem: a run with the advice on (its baseline Q_yes and
every lever's estimate), then a run with ``split_tol = rkhs.SPLIT_TOL`` (the real Q_yes the sub-box
lever estimates, and the bound stage's time against the first run's, measured one after the other).

Writes ``benchmarks/results/advice_sub_boxes.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))
from reference import merged_rows, results_record, write_results  # noqa: E402
from serial_parts import build_problem  # noqa: E402



def _problems(names) -> dict:
    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem

    out = {}
    want = set(names) if names else None

    def add(name, make):
        if want is None or name in want:
            out[name] = make

    add("newcomer_issue20_cell0.25", lambda: build_problem(0.25))

    def robot():
        d = Path(tempfile.mkdtemp())
        subprocess.run([sys.executable, str(ROOT / "examples" / "newcomer" / "robot2d_data.py")], cwd=d, check=True,
                       stdout=subprocess.DEVNULL)
        (d / "robot2d_16.toml").write_text((ROOT / "examples" / "newcomer" / "robot2d_16.toml").read_text())
        return load_problem(d / "robot2d_16.toml")

    add("robot2d_16", robot)
    add("three_mode_linear", lambda: load_problem(write_problem_files("three_mode_linear", Path(tempfile.mkdtemp()))))
    add("four_mode_nonlinear_two_goals",
        lambda: load_problem(ROOT / "examples" / "problems" / "four_mode_nonlinear_two_goals.toml"))
    return out


def _share(res) -> float:
    vol = np.prod(res.partition.cells_upper - res.partition.cells_lower, axis=1)
    return float(vol[res.class_names == "yes"].sum() / vol.sum())


def main(argv=None) -> int:
    from robust_imdp.bounds import rkhs
    from robust_imdp.pipeline.run import synthesize_from_data

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=None)
    ap.add_argument("--no-default-tol", action="store_true", help="skip the runs at rkhs.SPLIT_TOL (up to 27x)")
    args = ap.parse_args(argv)
    rows = []
    for name, make in _problems(args.only).items():
        p = make()
        plain = synthesize_from_data(p, progress=False, advice=True)
        levers = {lv["name"]: lv for lv in plain.advice.get("levers", [])}
        sub = levers.get("sub-boxes", {})
        tol = float(sub["setting"].split(",")[0].split("=")[1]) if sub else None
        runs = {}
        for label, t in (("lever", tol), ("split_tol", rkhs.SPLIT_TOL)):
            if t is None or (label == "split_tol" and args.no_default_tol):
                continue
            res = synthesize_from_data(p.replace(split_tol=t), progress=False, advice=False)
            runs[label] = {"split_tol": t, "share": _share(res), "q_yes": int(np.sum(res.class_names == "yes")),
                           "bound_seconds": res.timings.get("bound")}
        row = {"problem": name, "cells": int(plain.partition.n_cells), "winner": plain.advice.get("winner"),
               "baseline_share": _share(plain), "q_yes": int(np.sum(plain.class_names == "yes")),
               "levers": {k: {"share": v["q_yes_share"], "setting": v["setting"], "note": v["note"]}
                          for k, v in levers.items()},
               "sub_estimate": sub.get("q_yes_share"), "real": runs,
               "bound_seconds": plain.timings.get("bound"), "advice_seconds": plain.timings.get("advice")}
        rows.append(row)
        print(json.dumps(row), flush=True)
    old = OUT / "advice_sub_boxes.json"
    if args.only and old.exists():  # --only: replace those rows of the earlier record, keep the others
        rows = merged_rows(json.loads(old.read_text())["rows"], rows, "problem")
    data = results_record(rows)

    def pct(v):
        return "-" if v is None else f"{100 * v:.1f} %"

    lines = ["# The advice's sub-box lever against real sub-box runs (`benchmarks/advice_sub_boxes.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}. Q_yes as a share of "
             "X (cells); *estimate* = the advice's sub-box lever (its `split_tol` halves the cells with the "
             "largest Taylor term once per axis); *real* = runs with that `split_tol` and with "
             f"`rkhs.SPLIT_TOL = {rkhs.SPLIT_TOL}`; bound seconds of each run, one after the other; advice "
             "seconds of the first run (all four levers).", "",
             "| problem | cells | now: Q_yes, bound s, advice s | finer grid / more data (estimates) | "
             "sub-boxes lever: setting | estimate | real at the lever's split_tol: Q_yes, bound s | "
             "real at SPLIT_TOL: Q_yes, bound s | winner |", "|---|---|---|---|---|---|---|---|---|"]

    def real(w, k):
        r = w["real"].get(k)
        return "-" if r is None else f"{pct(r['share'])} ({r['q_yes']}), {r['bound_seconds']:.1f}"

    for w in rows:
        lv = w["levers"]
        est3 = " / ".join(pct(lv.get(k, {}).get("share")) for k in ("finer grid", "more data"))
        lines.append(f"| {w['problem']} | {w['cells']} | {pct(w['baseline_share'])} ({w['q_yes']}), "
                     f"{w['bound_seconds']:.1f}, {w['advice_seconds']:.1f} | {est3} | "
                     f"{lv.get('sub-boxes', {}).get('setting', '-')} | {pct(w['sub_estimate'])} | "
                     f"{real(w, 'lever')} | {real(w, 'split_tol')} | {w['winner']} |")
    write_results("advice_sub_boxes", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
