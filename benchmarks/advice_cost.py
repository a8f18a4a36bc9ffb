"""What the advice costs: its seconds against the run's, on the newcomer problems and the case studies.

    python benchmarks/advice_cost.py --label before|after [--only NAME ...] [--merge]
    python benchmarks/advice_cost.py --render      # the markdown table again from the JSON record

The advice stage (``synthesis.advice.advise`` through ``pipeline/advice_stage.py``) must take at most 25 % of a
run (docs: README, "Reading the results"). Problems:

* the newcomer problems of ``examples/newcomer`` (data from their generators): ``robot2d_16``, ``robot2d_32``,
  ``unicycle3d_16``, ``di4d_8``;
* the 2-D robot at cell 0.0625 (``robot2d_64``: ``robot2d_16.toml`` with that cell size, 4,096 cells);
* ``robot2d_dense``: a 2-D robot through the Python API on X = [0, 5]^2 (modes east / north / stay, an obstacle
  in the middle, a goal in the corner), 1,500 points per mode, Gaussian noise of sigma 0.08 (unbounded: every
  row of the IMDP lists about 500 cells), cell 0.0625 (6,400 cells). Dense rows are where the advice's 2x finer
  grid costs most (2^d times the cells, each with up to 2^d times the successors);
* the three shipped case studies (``examples/problems/*.toml``, 32 x 32 cells).

Per problem, in this process, one after the other: ``synthesize_from_data(problem, advice="auto")`` without a
cache; the advice's seconds, the run's, their ratio, Q_yes, and which levers were estimated (or why not). With
``--label before`` the script is meant to run on the tree before a change (``PYTHONPATH=<old>/src``); rows of
both labels are kept side by side.

Writes ``benchmarks/results/advice_cost.json`` and ``.md`` after every problem.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from reference import results_record, write_results  # noqa: E402

NAME = "advice_cost"
NEWCOMER = ("robot2d_16", "robot2d_32", "unicycle3d_16", "di4d_8")
CASE_STUDIES = ("three_mode_linear", "four_mode_nonlinear", "four_mode_nonlinear_two_goals")
ORDER = ("robot2d_16", "robot2d_32", "robot2d_64", "robot2d_dense", "unicycle3d_16", "di4d_8") + CASE_STUDIES
#: The advice's share of a run that the budget is meant to keep (README, "Reading the results").
TARGET = 0.25


def dense_robot(cell: float = 0.0625, per_mode: int = 1500, sigma: float = 0.08):
    """The 2-D robot with Gaussian noise (see the module docstring), seeded."""
    import numpy as np

    from robust_imdp import GaussianNoise, Problem

    rng = np.random.default_rng(0)
    steps = {"east": (0.3, 0.0), "north": (0.0, 0.3), "stay": (0.0, 0.0)}
    xs, us, xn = [], [], []
    for name, s in steps.items():
        x = rng.uniform(0, 5, (per_mode, 2))
        drift = np.stack([0.1 * np.sin(x[:, 1]), -0.08 * np.cos(x[:, 0])], axis=1)
        xs.append(x)
        us += [name] * per_mode
        xn.append(x + np.array(s) + drift + rng.normal(0, sigma, x.shape))
    return Problem.from_arrays(
        np.vstack(xs), np.array(us), np.vstack(xn), lower=[0, 0], upper=[5, 5], cell_size=cell,
        regions={"goal": ([4, 4], [5, 5]), "obstacle": ([1.5, 1.5], [3.5, 3.5])}, formula="G !obstacle & F goal",
        threshold=0.9, modes={k: (np.eye(2), list(v)) for k, v in steps.items()},
        noise=GaussianNoise([sigma, sigma]), rkhs_bound=0.4, lengthscale=1.0, misspecification=0.001)


def problems(work: Path, names) -> dict:
    """name -> a callable returning the Problem (data written under ``work`` first)."""
    from robust_imdp.io.files import load_problem

    nc = work / "newcomer"
    nc.mkdir(parents=True, exist_ok=True)
    for f in (ROOT / "examples" / "newcomer").glob("*.toml"):
        shutil.copy(f, nc / f.name)
    text = (nc / "robot2d_16.toml").read_text()
    (nc / "robot2d_64.toml").write_text(text.replace("cell_size = [0.25, 0.25]", "cell_size = [0.0625, 0.0625]"))
    gens = {"robot2d_16": ("robot2d_data.py", []), "robot2d_32": ("robot2d_data.py", []),
            "robot2d_64": ("robot2d_data.py", []), "unicycle3d_16": ("unicycle3d_data.py", ["plain", "uni.csv"]),
            "di4d_8": ("di4d_data.py", [])}
    done = set()
    for n in names:
        if n in gens and gens[n][0] not in done:
            gen, args = gens[n]
            subprocess.run([sys.executable, str(ROOT / "examples" / "newcomer" / gen), *args], cwd=nc, check=True)
            done.add(gen)
    out = {}
    for n in names:
        if n == "robot2d_dense":
            out[n] = dense_robot
        elif n in CASE_STUDIES:
            out[n] = lambda n=n: load_problem(ROOT / "examples" / "problems" / f"{n}.toml")
        else:
            out[n] = lambda n=n: load_problem(nc / f"{n}.toml")
    return out


def _levers(advice: dict) -> list:
    return [{"name": lv["name"], "estimated": lv.get("gain") is not None, "gain": lv.get("gain"),
             "note": lv.get("note", "")} for lv in advice.get("levers", [])]


def measure(make) -> dict:
    import warnings

    from robust_imdp.pipeline.run import synthesize_from_data

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = synthesize_from_data(make(), progress=False, advice="auto")
    t = {k: float(v) for k, v in res.timings.items()}
    adv = res.advice or {}
    return {"cells": int(res.partition.n_cells), "q_yes": int((res.class_names == "yes").sum()),
            "total_s": t["total"], "advice_s": t.get("advice", 0.0),
            "ratio": t.get("advice", 0.0) / t["total"], "timings": t, "winner": adv.get("winner"),
            "levers": _levers(adv), "note": adv.get("note", ""), "load": os.getloadavg()[0]}


def _table(rows: list) -> list:
    by = {}
    for r in rows:
        by.setdefault(r["problem"], {})[r["label"]] = r
    lines = ["| problem | cells | run s before / after | advice s before / after | advice share before / after "
             "| levers estimated after (not estimated: why) |", "|---|---|---|---|---|---|"]

    def f(r, k, fmt):
        return "-" if r is None else fmt.format(r[k])

    for name in [n for n in ORDER if n in by] + [n for n in by if n not in ORDER]:
        b, a = by[name].get("before"), by[name].get("after")
        est = "-"
        if a is not None:
            ok = [lv["name"] for lv in a["levers"] if lv["estimated"]]
            no = [f"{lv['name']}: {lv['note']}" for lv in a["levers"] if not lv["estimated"]]
            est = ", ".join(ok) + (f" (not: {'; '.join(no)})" if no else "") if (ok or no) else (a["note"] or "-")
        cells = (a or b)["cells"]
        share = f"{f(b, 'ratio', '{:.1%}')} / {f(a, 'ratio', '{:.1%}')}".replace("%", " %")
        if a is not None and a["ratio"] > TARGET:
            share += " **over 25 %**"
        lines.append(f"| {name} | {cells:,} | {f(b, 'total_s', '{:.1f}')} / {f(a, 'total_s', '{:.1f}')} | "
                     f"{f(b, 'advice_s', '{:.1f}')} / {f(a, 'advice_s', '{:.1f}')} | {share} | "
                     f"{est.replace('|', '/')} |")
    return lines


def _lines(data: dict) -> list:
    return ["# The advice's cost (`benchmarks/advice_cost.py`)", "",
            f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f} (2 cores shared with "
            "other jobs: times are inflated, the shares less so; each row's own load is in the JSON). Per problem, "
            "one run with `advice=\"auto\"` and no cache; before = the tree before the advice's budget (its rows' "
            f"`source`), after = with it. Target: advice / run <= {100 * TARGET:.0f} %.", ""] + _table(data["rows"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", choices=("before", "after"))
    ap.add_argument("--render", action="store_true", help="write the markdown table from the JSON record only")
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--merge", action="store_true", help="keep the rows of the problems not run now")
    args = ap.parse_args(argv)
    path = ROOT / "benchmarks" / "results" / f"{NAME}.json"
    if args.render:
        data = json.loads(path.read_text())
        write_results(NAME, data, _lines(data))
        return 0
    if args.label is None:
        ap.error("--label is required (or --render)")
    names = [n for n in ORDER if not args.only or n in args.only]
    rows = json.loads(path.read_text())["rows"] if path.exists() else []
    if not args.merge:
        rows = [r for r in rows if r["label"] != args.label]
    work = Path(tempfile.mkdtemp())
    makers = problems(work, names)
    import robust_imdp

    for name in names:
        row = {"problem": name, "label": args.label, "source": str(Path(robust_imdp.__file__).parent),
               **measure(makers[name])}
        rows = [r for r in rows if not (r["problem"] == name and r["label"] == args.label)] + [row]
        print(f"{name} ({args.label}): advice {row['advice_s']:.1f} s of {row['total_s']:.1f} s "
              f"({row['ratio']:.0%}), Q_yes {row['q_yes']} of {row['cells']}", flush=True)
        data = results_record(rows)
        write_results(NAME, data, _lines(data))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
