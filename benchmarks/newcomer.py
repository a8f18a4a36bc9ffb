"""The newcomer problems as a new user runs them: ``robust-imdp run`` on each, the README's newcomer table.

    python benchmarks/newcomer.py [--only robot2d_16 robot2d_32 unicycle3d_16 di4d_8]

Problems: ``examples/newcomer/*.toml``, unchanged, with data from their generators (written by
``advice_cost.problems`` into a scratch folder, as ``examples/newcomer/README.md`` says). Per problem, one
``robust-imdp run PROBLEM --out DIR`` in a child process (defaults: figures, advice, margins), one after the
other: from its ``result.json`` the classes (Q_yes / Q_no / Q_? by the file's threshold), the Q_no cells where
no controller can meet the threshold (``p_up_star < threshold``), the stage times (``timings``: the assumption
check and the bound stage) and the advice's winning lever (``diagnostics.advice``); the run's wall time and its
peak RSS (``os.wait4`` of the child, helpers included); the load average before and after.

Writes ``benchmarks/results/newcomer.json`` and ``.md`` (``--only`` replaces those rows, keeps the others),
beside the old files and renamed into place.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from advice_cost import problems  # noqa: E402
from reference import merged_rows, results_record  # noqa: E402

NAMES = ("robot2d_16", "robot2d_32", "unicycle3d_16", "di4d_8")


def _cli() -> str:
    exe = Path(sys.executable).with_name("robust-imdp")
    return str(exe) if exe.exists() else "robust-imdp"


def run_one(name: str, folder: Path) -> dict:
    """``robust-imdp run`` on ``folder/NAME.toml``: its result's classes, times and peak memory."""
    out = folder / f"out_{name}"
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with open(folder / f"{name}.log", "w") as log:
        proc = subprocess.Popen([_cli(), "run", f"{name}.toml", "--out", str(out)], cwd=folder, stdout=log,
                                stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    row = {"name": name, "wall_seconds": time.perf_counter() - t0, "peak_mb": usage.ru_maxrss / 1024.0,
           "exit": os.waitstatus_to_exitcode(status), "load_before": load0, "load_after": os.getloadavg()[0]}
    if row["exit"] != 0 or not (out / "result.json").exists():
        row["error"] = (folder / f"{name}.log").read_text().strip().splitlines()[-1:]
        return row
    res = json.loads((out / "result.json").read_text())
    t = float(res["threshold"])
    p_low, p_up, p_up_star = (np.asarray(res[k], dtype=float) for k in ("p_low", "p_up", "p_up_star"))
    no = p_up < t
    row.update(cells=int(p_low.size), q_yes=int(np.sum(p_low >= t)), q_no=int(np.sum(no)),
               q_maybe=int(np.sum(~no & (p_low < t))), q_no_no_controller=int(np.sum(no & (p_up_star < t))),
               timings={k: float(v) for k, v in res.get("timings", {}).items()},
               advice=res.get("diagnostics", {}).get("advice", {}))
    return row


def _advice_text(advice: dict) -> str:
    if not advice:
        return "-"
    win = advice.get("winner")
    if not win:
        return "none moves 0.5 %"
    lever = next((lv for lv in advice.get("levers", []) if lv.get("name") == win), {})
    share = lever.get("q_yes_share")
    return f"{win}: {advice.get('baseline_share', 0):.0%} -> {share:.0%} of X" if share is not None else str(win)


def render(data: dict) -> str:
    lines = ["# Newcomer problems (`benchmarks/newcomer.py`)", "",
             f"{data['date']}, commit {data['commit']}; load average {data['load'][0]:.1f} at the end. Reproduce: "
             "`python benchmarks/run.py newcomer`. One `robust-imdp run` per problem, defaults; *time* is the "
             "command's wall time, *check* and *bound* its stage times, *peak* the child's peak RSS.", "",
             "| problem | cells | Q_yes / Q_no / Q_? | Q_no where no controller can | advice | run time (check, bound) | "
             "peak RSS | load |", "|---|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        if "cells" not in r:
            lines.append(f"| {r['name']} | | failed: {r.get('error')} | | | {r['wall_seconds']:.0f} s | | |")
            continue
        tm = r["timings"]
        check = tm.get("check", tm.get("learn", 0.0))
        lines.append(f"| {r['name']} | {r['cells']} | {r['q_yes']} / {r['q_no']} / {r['q_maybe']} | "
                     f"{r['q_no_no_controller']} of {r['q_no']} | {_advice_text(r['advice'])} | "
                     f"{r['wall_seconds']:.0f} s ({check:.1f} s, {tm.get('bound', 0.0):.1f} s) | "
                     f"{r['peak_mb'] / 1024:.2f} GB | {r['load_before']:.1f}-{r['load_after']:.1f} |")
    return "\n".join(lines) + "\n"


def _replace(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", choices=NAMES, default=list(NAMES))
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    path = args.out / "newcomer.json"
    old = json.loads(path.read_text())["rows"] if path.exists() else []
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        problems(Path(tmp), args.only)  # copies the problem files and writes their data
        for name in args.only:
            rows.append(run_one(name, Path(tmp) / "newcomer"))
            print(json.dumps({k: v for k, v in rows[-1].items() if k != "advice"}), flush=True)
            data = results_record(merged_rows(old, rows, "name"))
            _replace(path, json.dumps(data, indent=1))
            _replace(args.out / "newcomer.md", render(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
