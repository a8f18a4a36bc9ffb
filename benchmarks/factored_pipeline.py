"""The factored form end to end (docs/factored.md, "In the pipeline"): ``synthesize_from_data`` with
``[abstraction].form`` factored and joint on the field's benchmarks, the 4-D vehicle and our own problems.

    python benchmarks/factored_pipeline.py [--suite car bas4d linear6 linear7 vehicle problems preflight] [--merge]

Suites (every run is a child process of its own, so its peak RSS -- ``resource.getrusage`` of the child, read
after the pipeline and before the Monte Carlo -- is its own; the load average is recorded before and after):

* ``car``: car parking (benchmarks/arch/problems/car_parking.toml at threshold 0.5, the issue's comparison),
  factored (the default form) and joint; Monte Carlo of the true system under each controller (``validate``,
  ``--mc`` runs per cell). Target: Q_yes >= 315 (the joint exact IMDP), above it through the product set.
* ``bas4d``: BAS-4D (bas4d.toml: 1,225 cells, 4 inputs, ``G safe`` for 10 steps), factored and joint: interval
  entries per (cell, mode) as the issue counts them (``sum_i (k_i + 1)``, target <= 30; the stored numbers
  ``sum_i (2 k_i + 4)`` beside), p_low >= the joint exact IMDP's on every cell; Monte Carlo.
* ``linear6`` / ``linear7``: linear 6-D at 8^6 / 7-D at 8^7 (linear6d.toml / linear7d.toml, safety, 10 steps,
  known): end to end against 5 min / 4 GB and 30 min / 16 GB; Monte Carlo on ``--mc-cells`` cells.
* ``vehicle``: the 4-D vehicle at 24^4 (examples/vehicle_4d.py's problem: learned drag, periodic heading,
  unbounded ``G !obs & F goal``) in the factored form, against the recorded joint row of
  benchmarks/results/vehicle_4d.json (Thm 1, 8.4 GB, Q_yes 99,326). Target: peak / 4 or better, Q_yes not lower.
* ``problems``: every problem of benchmarks/identical.py (the case studies, their variants, the newcomer robots,
  ``robust-imdp example``'s case studies): Thm 1 joint, exact with the default form (``auto``), exact factored:
  Q_yes lost against Thm 1 and against joint, mean p_low, times.
* ``preflight``: the pre-flight estimate of both forms (``estimate_resources``) against the peak RSS of the runs
  above (and of small extra runs), within 25 %.

Advice and assumption margins are off in every run (``advice=False, margins=False``): the rows measure the
abstraction and the synthesis. ``--src`` runs the children on another source tree (``PYTHONPATH``).
Writes ``benchmarks/results/factored_pipeline.json`` and ``.md`` after every suite (``--merge`` keeps the other
suites' rows of the last run).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
NAME = "factored_pipeline"
ARCH = ROOT / "benchmarks" / "arch" / "problems"
SUITES = ("car", "bas4d", "linear6", "linear7", "vehicle", "problems", "preflight")
#: the recorded joint row of the 4-D vehicle at 24^4 (benchmarks/results/vehicle_4d.json, Thm 1)
VEHICLE_JOINT = {"source": "benchmarks/results/vehicle_4d.json (learned, 24^4, Thm 1 joint)", "peak_mb": 8379.0,
                 "yes": 99326, "total_s": 777.7}


# --------------------------------------------------------------------------- the child
def _peak_mb() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, kids) / 1024.0  # Linux: KiB


class _Stamped:
    """A text stream that prefixes every line with the seconds since it was made (where a timed-out run spent
    its time)."""

    def __init__(self, stream):
        self.stream, self.t0, self.fresh = stream, time.perf_counter(), True

    def write(self, text):
        for part in text.splitlines(keepends=True):
            if self.fresh:
                self.stream.write(f"[{time.perf_counter() - self.t0:8.1f} s] ")
            self.stream.write(part)
            self.fresh = part.endswith("\n")
        self.stream.flush()
        return len(text)

    def flush(self):
        self.stream.flush()


def _rss_lines(stream, every: float) -> None:
    """A daemon thread writing the process's resident memory (and its peak so far) to ``stream`` every ``every``
    seconds: which stage holds the memory."""
    import threading

    def loop():
        while True:
            time.sleep(every)
            try:
                rss = int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
            except (OSError, ValueError):
                return
            stream.write(f"rss {rss:,.0f} MB (peak so far {_peak_mb():,.0f} MB)\n")

    threading.Thread(target=loop, daemon=True).start()


def _problem(spec: dict, work: Path):
    """The problem a child runs: an arch problem file, the vehicle case study, or a problem file given by path."""
    from robust_imdp.io.files import load_problem

    src = spec["source"]
    if src.startswith("arch:"):
        p = load_problem(ARCH / src[5:])
    elif src.startswith("vehicle:"):
        from robust_imdp.casestudies.systems import write_problem_files

        p = load_problem(write_problem_files("vehicle_4d", work / "problem", seed=0))
        p = p.replace(cell_size=(p.space_upper - p.space_lower) / int(src[8:]))
    elif src.startswith("linear:"):  # linear:D:N: the cyclic linear system of linear6d.toml in D dimensions, N per axis
        from robust_imdp import GaussianNoise, Problem

        d, n = (int(v) for v in src[7:].split(":"))
        a = 0.7 * np.eye(d)
        a[np.arange(d), (np.arange(d) + 1) % d] = -0.1
        p = Problem.from_arrays(None, None, None, lower=[-1.0] * d, upper=[1.0] * d, cell_size=2.0 / n,
                                regions={"safe": ([-1.0] * d, [1.0] * d)}, formula="G safe", threshold=0.9,
                                horizon=10, modes={"autonomous": (a, np.zeros(d))}, noise=GaussianNoise([0.1] * d),
                                rkhs_bound=0.0)
    else:
        p = load_problem(src[5:])
    changes = dict(spec.get("replace", {}))
    if "cell_size" in changes:
        changes["cell_size"] = np.asarray(changes["cell_size"], float)
    return p.replace(**changes) if changes else p


def _true_system(spec: dict, problem):
    sys_name = spec.get("system")
    if sys_name is None:
        return None
    if sys_name == "vehicle_4d":
        from robust_imdp.casestudies.systems import true_system

        return true_system("vehicle_4d")
    sys.path.insert(0, str(ROOT / "benchmarks" / "arch"))
    import run as arch_run  # noqa: E402  (benchmarks/arch/run.py: the true systems in numpy)

    return arch_run.true_system(sys_name, problem)


def child(spec: dict, out: Path) -> None:
    """Run one spec; write its row (JSON) and its p_low / p_up / classes (npz) under ``out``."""
    import warnings

    from robust_imdp.abstraction.factored import is_factored
    from robust_imdp.pipeline.preflight import estimate_resources
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.spec.api import to_dfa

    work = Path(tempfile.mkdtemp(prefix="factored-bench-"))
    if spec.get("progress"):
        sys.stderr = _Stamped(sys.stderr)  # the pipeline's progress lines with the seconds since the child started
        _rss_lines(sys.stderr, float(spec.get("rss_every", 10.0)))
    load0 = os.getloadavg()
    problem = _problem(spec, work)
    dfa = to_dfa(problem.formula)
    form, why = problem.form_choice()
    est = {f: estimate_resources(problem, dfa.n_states, form=f)["bytes"] / 1e6 for f in ("joint", "factored")} \
        if problem.factored_reason() is None else {"joint": estimate_resources(problem, dfa.n_states, form="joint")[
            "bytes"] / 1e6}
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = synthesize_from_data(problem, progress=bool(spec.get("progress")), advice=False, margins=False,
                                   check_resources=False, abstraction_cache=spec.get("cache"))
    wall = time.perf_counter() - t0
    peak = _peak_mb()
    thr = float(problem.threshold)
    p_low, p_up = np.asarray(res.p_low, float), np.asarray(res.p_up, float)
    row = {"name": spec["name"], "form": "factored" if is_factored(res.abstraction) else "joint",
           "form_choice": form, "form_reason": why, "transitions": problem.transitions,
           "cells": int(res.n_cells), "modes": len(problem.mode_names), "threshold": thr, "horizon": problem.horizon,
           "semantics": res.semantics, "yes": int(res.counts["yes"]), "no": int(res.counts["no"]),
           "maybe": int(res.counts["maybe"]), "mean_p_low": float(p_low.mean()), "min_p_low": float(p_low.min()),
           "mean_gap": float((p_up - p_low).mean()), "wall_s": wall, "timings": dict(res.timings), "peak_mb": peak,
           "estimate_mb": est, "load_before": list(load0), "from_cache": bool(res.from_cache),
           "warnings": sorted({f"{w.category.__name__}: {str(w.message)[:120]}" for w in caught
                               if "Convergence" in w.category.__name__})}
    if is_factored(res.abstraction):
        m = res.abstraction.model
        row.update(numbers_per_row=int(m.numbers_per_row), entries_per_row=int(m.entries_per_row),
                   listed_per_axis=list(m.k), model_mb=m.nbytes / 1e6)
    else:
        mem = getattr(res.abstraction.imdp, "memory_bytes", None)  # a property (int) of IMDP
        mem = mem() if callable(mem) else mem
        row.update(successors_per_row=float(np.mean(res.abstraction.nnz_per_row)),
                   imdp_mb=None if mem is None else float(mem) / 1e6)
    np.savez(out / f"{spec['key']}.npz", p_low=p_low, p_up=p_up, classes=np.asarray(res.classes).astype("U5"))
    system = _true_system(spec, problem)
    if system is not None:
        from robust_imdp.validate import validate

        cells = None
        if spec.get("mc_cells"):
            cells = np.sort(np.random.default_rng(5).choice(res.n_cells, min(res.n_cells, spec["mc_cells"]),
                                                            replace=False))
        t1 = time.perf_counter()
        rep = validate(res, system, n_per_cell=int(spec["mc"]), rng=11, cells=cells)
        row["mc"] = {"runs_per_cell": int(spec["mc"]), "cells": int(len(rep.cells)), "flagged": int(len(rep.outside)),
                     "allowed": int(rep.allowed_outside), "passed": bool(rep.passed),
                     "empirical_mean": float(np.mean(rep.empirical)),
                     "p_low_mean": float(np.mean(np.asarray(rep.p_low))), "seconds": time.perf_counter() - t1}
    row["load_after"] = list(os.getloadavg())
    (out / f"{spec['key']}.json").write_text(json.dumps(row))
    shutil.rmtree(work, ignore_errors=True)


# --------------------------------------------------------------------------- the parent
def _run_child(spec: dict, out: Path, src: str | None, timeout: float) -> dict:
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    cmd = ["nice", "-n", "5", sys.executable, __file__, "--child", json.dumps(spec), "--out", str(out)]
    log = out / f"{spec['key']}.log"  # the child's output (the pipeline's progress lines where spec asks for them)
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        p = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            rc = p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, 9)  # the child's own process group (start_new_session): nothing else
            p.wait()
            lines = log.read_text(errors="replace").strip().splitlines()
            return {"name": spec["name"], "error": f"timeout after {timeout:.0f} s", "form": spec.get("form"),
                    "log_tail": lines[-40:], "child_s": time.perf_counter() - t0}
    f = out / f"{spec['key']}.json"
    if rc != 0 or not f.exists():
        tail = log.read_text(errors="replace").strip().splitlines()[-3:]
        return {"name": spec["name"], "error": " | ".join(tail), "form": spec.get("form")}
    row = json.loads(f.read_text())
    row["child_s"] = time.perf_counter() - t0
    if spec.get("progress"):
        row["log_tail"] = log.read_text(errors="replace").strip().splitlines()[-60:]
    print(f"  {spec['name']}: {row['form']} Q_yes {row['yes']} Q_no {row['no']} mean p_low {row['mean_p_low']:.4f} "
          f"wall {row['wall_s']:.1f} s peak {row['peak_mb']:.0f} MB" + (f" MC {row['mc']['flagged']}/"
                                                                       f"{row['mc']['allowed']}" if "mc" in row else ""),
          flush=True)
    return row


def _pair(out: Path, a: dict, b: dict, thr: float) -> dict:
    """Per-cell comparison of run ``a`` against run ``b`` on the same cells: min / max of p_low(a) - p_low(b), the
    Q_yes cells of b that a loses and those it gains."""
    if "error" in a or "error" in b or a["cells"] != b["cells"]:
        return {}
    x, y = np.load(out / f"{a['key']}.npz"), np.load(out / f"{b['key']}.npz")
    d = x["p_low"] - y["p_low"]
    ya, yb = x["p_low"] >= thr, y["p_low"] >= thr
    return {"min_diff": float(d.min()), "max_diff": float(d.max()), "lost": int(np.sum(yb & ~ya)),
            "gained": int(np.sum(ya & ~yb)), "cells_below": int(np.sum(d < 0))}


def _spec(name, key, source, form, *, replace=None, system=None, mc=0, mc_cells=None, cache=None, progress=False):
    r = dict(replace or {})
    if form is not None:
        r["form"] = form
    return {"name": name, "key": key, "source": source, "form": form, "replace": r, "system": system, "mc": mc,
            "mc_cells": mc_cells, "cache": cache, "progress": progress}


def suite_car(args, out):
    rows = {}
    for form in ("factored", "joint"):
        s = _spec(f"car_parking/{form}", f"car_{form}", "arch:car_parking.toml", form, replace={"threshold": 0.5},
                  system="car_parking", mc=args.mc)
        rows[form] = dict(_run_child(s, out, args.src, args.timeout), key=s["key"])
    cmp = _pair(out, rows["factored"], rows["joint"], 0.5)
    return [{"suite": "car", "name": "car_parking_40x40", "runs": rows, "factored_vs_joint": cmp, "target_yes": 315}]


def suite_bas4d(args, out):
    rows = {}
    for form in ("factored", "joint"):
        s = _spec(f"bas4d/{form}", f"bas4d_{form}", "arch:bas4d.toml", form, system="bas4d", mc=args.mc)
        rows[form] = dict(_run_child(s, out, args.src, args.timeout), key=s["key"])
    cmp = _pair(out, rows["factored"], rows["joint"], rows["factored"].get("threshold", 0.9))
    return [{"suite": "bas4d", "name": "bas4d", "runs": rows, "factored_vs_joint": cmp, "target_entries": 30}]


def _linear(args, out, d, target_s, target_gb):
    s = _spec(f"linear{d}d/factored", f"linear{d}", f"arch:linear{d}d.toml", None, system=f"linear{d}d",
              mc=args.mc_linear, mc_cells=args.mc_cells, progress=True)
    row = dict(_run_child(s, out, args.src, args.timeout_linear), key=s["key"])
    return [{"suite": f"linear{d}", "name": f"linear{d}d", "runs": {"factored": row}, "target_s": target_s,
             "target_gb": target_gb}]


def suite_linear6(args, out):
    return _linear(args, out, 6, 300, 4)


def suite_linear7(args, out):
    return _linear(args, out, 7, 1800, 16)


def suite_vehicle(args, out):
    s = _spec("vehicle_4d_24/factored", "vehicle24", "vehicle:24", "factored", system="vehicle_4d", mc=4,
              mc_cells=1000, progress=True)
    row = dict(_run_child(s, out, args.src, args.timeout_linear), key=s["key"])
    return [{"suite": "vehicle", "name": "vehicle_4d_24^4", "runs": {"factored": row}, "joint_recorded": VEHICLE_JOINT}]


def suite_problems(args, out):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import identical

    work = Path(tempfile.mkdtemp(prefix="factored-problems-"))
    env = dict(os.environ)
    if args.src:
        env["PYTHONPATH"] = args.src + os.pathsep + env.get("PYTHONPATH", "")
    rows = []
    for name, file in identical._problems(work, args.full, env):
        if args.only and name not in args.only:
            continue
        runs = {}
        cache = str(work / f"cache-{name}")
        for label, form, tr in (("thm1", "joint", "thm1"), ("auto", None, "exact"), ("factored", "factored", "exact"),
                                ("joint", "joint", "exact")):
            s = _spec(f"{name}/{label}", f"p_{name}_{label}", f"file:{file}", form, replace={"transitions": tr},
                      cache=cache)
            runs[label] = dict(_run_child(s, out, args.src, args.timeout), key=s["key"])
        thr = runs["thm1"].get("threshold", 0.5)
        rows.append({"suite": "problems", "name": name, "runs": runs,
                     "auto_vs_thm1": _pair(out, runs["auto"], runs["thm1"], thr),
                     "factored_vs_joint": _pair(out, runs["factored"], runs["joint"], thr),
                     "factored_vs_thm1": _pair(out, runs["factored"], runs["thm1"], thr)})
    shutil.rmtree(work, ignore_errors=True)
    return rows


def suite_preflight(args, out):
    """Extra runs for the pre-flight's accuracy (both forms where they fit): car parking and BAS-4D at other grids,
    linear 4-D / 5-D at 8 per axis (the peak RSS of the runs of the other suites is compared too)."""
    rows = []
    extra = [("car_parking_20x20", "arch:car_parking.toml", {"cell_size": [1.0, 1.0], "threshold": 0.5}),
             ("bas4d_coarse", "arch:bas4d.toml", {"cell_size": [0.5, 0.5, 1.75, 1.75]})]
    for name, src, rep in extra:
        runs = {}
        for form in ("factored", "joint"):
            s = _spec(f"{name}/{form}", f"pf_{name}_{form}", src, form, replace=rep)
            runs[form] = dict(_run_child(s, out, args.src, args.timeout), key=s["key"])
        rows.append({"suite": "preflight", "name": name, "runs": runs})
    for d in (4, 5):
        s = _spec(f"linear{d}d/factored", f"pf_linear{d}", f"linear:{d}:8", None)
        rows.append({"suite": "preflight", "name": f"linear{d}d_8", "runs": {"factored": dict(
            _run_child(s, out, args.src, args.timeout), key=s["key"])}})
    return rows


# --------------------------------------------------------------------------- results
def _fmt(v, digits=1):
    return "-" if v is None else (f"{v:,.{digits}f}" if isinstance(v, float) else f"{v:,}")


def render(data: dict) -> str:
    lines = ["# The factored form end to end (`benchmarks/factored_pipeline.py`)", "",
             f"{data['when']}; {data['commit']}; commands: {'; '.join(data['commands'])}.", "",
             "Every run is a child process (`synthesize_from_data`, advice and margins off); peak = its peak RSS. "
             "Load: the 1-minute load average before / after the run (2 cores, shared).", ""]
    rows = data["rows"]
    lines += ["## Against the targets", "",
              "| benchmark | target | measured | met |", "|---|---|---|---|"]
    for r in rows:
        lines += _target_lines(r)
    lines += ["", "## Runs", "",
              "| benchmark | form | cells x modes | Q_yes / Q_no / Q_? | mean p_low | per row | wall s (bound / "
              "abstract / synthesize) | peak MB | pre-flight MB (this form) | load | Monte Carlo |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for label, run in r["runs"].items():
            lines.append(_run_line(r["name"], label, run))
    probs = [r for r in rows if r["suite"] == "problems"]
    if probs:
        lines += ["", "## Our problems: Q_yes lost", "",
                  "| problem | Q_yes thm1 / auto (form) / factored / joint | auto vs thm1 lost / gained | factored vs "
                  "joint lost / gained, min p_low diff | factored vs thm1 lost | synthesize s auto / factored / joint |",
                  "|---|---|---|---|---|---|"]
        for r in probs:
            ru = r["runs"]
            if any("error" in v for v in ru.values()):
                lines.append(f"| {r['name']} | error: {'; '.join(v.get('error', '')[:80] for v in ru.values())} "
                             "| | | | |")
                continue
            a, f, j = r["auto_vs_thm1"], r["factored_vs_joint"], r["factored_vs_thm1"]
            lines.append(f"| {r['name']} | {ru['thm1']['yes']} / {ru['auto']['yes']} ({ru['auto']['form']}) / "
                         f"{ru['factored']['yes']} / {ru['joint']['yes']} | {a.get('lost', '-')} / "
                         f"{a.get('gained', '-')} | {f.get('lost', '-')} / {f.get('gained', '-')}, "
                         f"{f.get('min_diff', float('nan')):.2g} | {j.get('lost', '-')} | "
                         f"{ru['auto']['timings'].get('synthesize', 0):.1f} / "
                         f"{ru['factored']['timings'].get('synthesize', 0):.1f} / "
                         f"{ru['joint']['timings'].get('synthesize', 0):.1f} |")
        lost = sum(r["auto_vs_thm1"].get("lost", 0) for r in probs)
        lines += ["", f"**Q_yes cells lost by the default (exact, auto) against Thm 1 over all problems: {lost}**; "
                  f"by factored against joint exact: {sum(r['factored_vs_joint'].get('lost', 0) for r in probs)}."]
    pf = [(r["name"], label, run) for r in rows for label, run in r["runs"].items()
          if "error" not in run and "estimate_mb" in run and run["form"] in run["estimate_mb"]]
    if pf:
        lines += ["", "## Pre-flight", "",
                  "The pre-flight's estimate of the run's form (the code of the run) against its peak RSS, both in MB "
                  "of 10^6 bytes (the runs' `peak_mb` is ru_maxrss in MiB; target: within 25 %).", "",
                  "| run | form | estimate MB | peak MB | estimate / peak |", "|---|---|---|---|---|"]
        for name, label, run in pf:
            e = run["estimate_mb"][run["form"]]
            peak = run["peak_mb"] * 1.048576  # MiB -> MB
            lines.append(f"| {name} ({label}) | {run['form']} | {e:,.0f} | {peak:,.0f} | {e / peak:.2f} |")
    return "\n".join(lines) + "\n"


def _run_line(name, label, run):
    if "error" in run:
        return f"| {name} | {label} | error: {run['error'][:150]} | | | | | | | | |"
    per = (f"{run['entries_per_row']} entries ({run['numbers_per_row']} numbers)" if run["form"] == "factored"
           else f"{run.get('successors_per_row', 0):.1f} successors")
    t = run["timings"]
    mc = run.get("mc")
    mc_text = "-" if mc is None else (f"{mc['flagged']} of {mc['cells']} cells flagged (allowed {mc['allowed']}; "
                                      f"{mc['runs_per_cell']} runs each): {'passed' if mc['passed'] else 'FAILED'}")
    est = run.get("estimate_mb", {}).get(run["form"])
    return (f"| {name} | {run['form']} | {run['cells']:,} x {run['modes']} | {run['yes']:,} / {run['no']:,} / "
            f"{run['maybe']:,} | {run['mean_p_low']:.4f} | {per} | {run['wall_s']:.1f} ({t.get('bound', 0):.1f} / "
            f"{t.get('abstract', 0):.1f} / {t.get('synthesize', 0):.1f}) | {run['peak_mb']:,.0f} | {_fmt(est, 0)} | "
            f"{run['load_before'][0]:.1f} / {run['load_after'][0]:.1f} | {mc_text} |")


def _target_lines(r):
    s, ru = r["suite"], r["runs"]
    f = ru.get("factored", {})
    if "error" in f:
        return [f"| {r['name']} | - | error: {f['error'][:120]} | no |"]
    if s == "car":
        ok = f["yes"] >= 315 and f.get("mc", {}).get("passed", False)
        return [f"| car parking | Q_yes >= 315, above via the product set; MC contained | Q_yes {f['yes']} (joint exact "
                f"{ru['joint'].get('yes', '-')}), MC {'passed' if f.get('mc', {}).get('passed') else 'failed'} | "
                f"{'yes' if ok else 'no'} |"]
    if s == "bas4d":
        c = r.get("factored_vs_joint", {})
        ok = f["entries_per_row"] <= 30 and c.get("cells_below", 1) == 0
        return [f"| BAS-4D | <= 30 entries per (cell, mode); p_low >= joint exact on every cell | {f['entries_per_row']} "
                f"entries ({f['numbers_per_row']} stored numbers); min p_low(factored) - p_low(joint) = "
                f"{c.get('min_diff', float('nan')):.3g} ({c.get('cells_below', '-')} cells below) | "
                f"{'yes' if ok else 'no'} |"]
    if s.startswith("linear"):
        ok = f["wall_s"] <= r["target_s"] and f["peak_mb"] <= 1000 * r["target_gb"]
        return [f"| {r['name']} | <= {r['target_s'] / 60:.0f} min, <= {r['target_gb']} GB | {f['wall_s']:.0f} s "
                f"({f['child_s']:.0f} s with the interpreter), peak {f['peak_mb'] / 1000:.2f} GB | "
                f"{'yes' if ok else 'no'} |"]
    if s == "vehicle":
        j = r["joint_recorded"]
        ok = f["peak_mb"] <= j["peak_mb"] / 4 and f["yes"] >= j["yes"]
        return [f"| 4-D vehicle 24^4 | peak <= {j['peak_mb'] / 4:,.0f} MB (8.4 GB / 4), Q_yes >= {j['yes']:,} | peak "
                f"{f['peak_mb']:,.0f} MB, Q_yes {f['yes']:,}, {f['wall_s']:.0f} s | {'yes' if ok else 'no'} |"]
    return []


def _commit() -> str:
    try:
        c = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "src"], capture_output=True, text=True)
        return f"commit {c.stdout.strip()}" + (" + uncommitted changes in src/" if dirty.stdout.strip() else "")
    except OSError:
        return "commit unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", nargs="+", default=["car", "bas4d", "linear6", "problems", "preflight"],
                    choices=SUITES)
    ap.add_argument("--merge", action="store_true", help="keep the other suites' rows of the last run")
    ap.add_argument("--only", nargs="*", help="problems suite: only these problems")
    ap.add_argument("--full", action="store_true", help="problems suite: identical.py's --full problems too")
    ap.add_argument("--mc", type=int, default=100, help="Monte-Carlo runs per cell (car, BAS-4D)")
    ap.add_argument("--mc-linear", type=int, default=20, help="Monte-Carlo runs per cell (linear)")
    ap.add_argument("--mc-cells", type=int, default=2000, help="Monte-Carlo cells (linear, vehicle)")
    ap.add_argument("--timeout", type=float, default=1800)
    ap.add_argument("--timeout-linear", type=float, default=5400)
    ap.add_argument("--src", help="PYTHONPATH of the children (another source tree)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(json.loads(args.child), Path(args.out))
        return 0
    out = Path(tempfile.mkdtemp(prefix="factored-pipeline-"))
    path = RESULTS / f"{NAME}.json"
    data = {"rows": [], "commands": []}
    if args.merge and path.exists():
        data = json.loads(path.read_text())
        data["rows"] = [r for r in data["rows"] if r["suite"] not in args.suite]
    data["commands"] = data.get("commands", []) + [f"python benchmarks/factored_pipeline.py {' '.join(argv or sys.argv[1:])}"]
    for suite in args.suite:
        print(f"suite {suite}", flush=True)
        new = globals()[f"suite_{suite}"](args, out)
        data["rows"] = [r for r in data["rows"] if not (r["suite"] == suite and r["name"] in {n["name"] for n in new})]
        data["rows"] += new
        data["when"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        data["commit"] = _commit()
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(data, indent=1))
        os.replace(tmp, path)
        md = RESULTS / f"{NAME}.md"
        tmp = md.with_suffix(".md.tmp")
        tmp.write_text(render(data))
        os.replace(tmp, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
