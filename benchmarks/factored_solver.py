"""Factored solver benchmark: time and memory per Bellman sweep of the factored (odIMDP) solver on the
linear systems of the interval-MDP literature, against the joint solver where the joint model fits.
Writes ``benchmarks/results/factored_solver.json`` and ``factored_solver.md``.

    python benchmarks/factored_solver.py                  # d = 4, 5, 6 at 8 intervals per axis (~10 min, 2 cores)
    python benchmarks/factored_solver.py --dims 4 --n 6   # one smaller row

System (Mathiesen, Haesaert, Laurenti, HSCC 2025; issue "factored exact integrals"): ``x' = A x + w``,
``A_ii = 0.7``, ``A_{i,i+1} = -0.1`` (cyclic), ``w ~ N(0, 0.01 I)``, ``X = [-1, 1]^d``, ``n^d``
cells, one mode, safety (stay in X) for ``--horizon`` steps.  The per-axis marginals come from
``robust_imdp.abstraction.marginals.axis_marginals`` (certified) when that module is present, else
from scipy's normal cdf (min at an end of the image interval, max at the clamped midpoint: a
benchmark input, not a certified bound); the JSON says which.  Axis i's image interval depends on
the cell's coordinates i and i + 1 only, so there are n^2 distinct marginals per axis, which the
solver's prefix tree shares (docs/factored.md, "Sharing").

Per dimension, in a fresh process (so the peak memory is that row's): the marginals' time, the
model's size (stored numbers and interval entries per row, MB), the prepared operator (tree nodes
per level, entries read per sweep against the unshared nested reduction), one Bellman sweep (wall
and process CPU time; median of 3 after a warm-up), the safety bracket ``1 - P(leave X within k
steps)`` under both adversaries (time, min / mean p_low), and, where ``FactoredIMDP.to_joint`` fits
``--joint-max-entries``, the joint IMDP's size, its k-step solve by ``solve_reachability`` and the
check that the factored p_low is never below the joint one.  The machine is shared: the load
average is recorded.

Unbounded (``--unbounded NAME ...``; rows under ``"unbounded"`` in the same JSON, the other rows kept): the
synthesis (``synthesis.core.synthesize``: optimistic, robust with ties, both evaluations) of the factored model
the pipeline builds with ``[abstraction] form = "factored"`` and no horizon, timed three ways in one child
process: ``ordered`` (the component-ordered pass, ``solvers.factored.ORDERED = True``), ``whole`` (whole-model
sweeps only, the solver before the pass: ``ORDERED = False``; skipped above ``--whole-max-cells``) and
``joint`` (``FactoredIMDP.to_joint`` solved by the joint engine, where it has at most ``--joint-max-entries``
entries).  Names: ``vehicle:N`` (the 4-D vehicle at N^4, learned drag), ``car`` and ``bas4d`` (the arch
problem files without their horizon), ``three_mode_linear``, ``four_mode_nonlinear`` (the case studies).
Process CPU seconds (every thread) are the comparable numbers on the shared machine; wall and load beside.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SIGMA = 0.1  # noise standard deviation (variance 0.01)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _matrix(d):
    A = 0.7 * np.eye(d)
    for i in range(d):
        A[i, (i + 1) % d] += -0.1
    return A


def _images(d, n):
    """Cells' lower/upper corners and image boxes of A x over each cell (rounded outward by 4 ulps)."""
    A = _matrix(d)
    edges = np.linspace(-1.0, 1.0, n + 1)
    idx = np.indices((n,) * d).reshape(d, -1)
    cl, ch = edges[idx], edges[idx + 1]
    pos, neg = np.clip(A, 0, None), np.clip(A, None, 0)
    ylo = (pos @ cl + neg @ ch).T
    yhi = (pos @ ch + neg @ cl).T
    # the matrix products of d terms err by a few ulps: widen by 4 * d ulps of the magnitude (benchmark input)
    pad = 4 * d * np.spacing(np.abs(ylo) + np.abs(yhi) + 1.0)
    return ylo - pad, yhi + pad


def _marginals_scipy(d, n, ylo, yhi):
    from scipy.special import ndtr

    from robust_imdp.models.factored import AxisMarginals
    edges = np.linspace(-1.0, 1.0, n + 1)
    N = ylo.shape[0]

    def g(a, b, y):
        return ndtr((b - y) / SIGMA) - ndtr((a - y) / SIGMA)

    axes = []
    for i in range(d):
        a_, b_ = ylo[:, i], yhi[:, i]
        L = np.stack([np.minimum(g(l, h, a_), g(l, h, b_)) for l, h in zip(edges[:-1], edges[1:])], -1)
        H = np.stack([g(l, h, np.clip(0.5 * (l + h), a_, b_)) for l, h in zip(edges[:-1], edges[1:])], -1)
        fin_lo, fin_hi = np.minimum(g(-1, 1, a_), g(-1, 1, b_)), g(-1, 1, np.clip(0.0, a_, b_))
        # a relative allowance for ndtr's error (benchmark input, not certified)
        L = np.clip(L * (1 - 1e-12), 0, 1)
        H = np.clip(H * (1 + 1e-12) + 1e-300, 0, 1)
        axes.append(AxisMarginals(n=n, periodic=False, start=np.zeros((1, N), np.int64), lower=L[None], upper=H[None],
                                  out_lower=np.clip((1 - fin_hi) * (1 - 1e-12), 0, 1)[None],
                                  out_upper=np.clip((1 - fin_lo) * (1 + 1e-12), 0, 1)[None],
                                  rest_upper=np.zeros((1, N)), axis=i))
    return tuple(axes)


def _marginals(d, n):
    """(axes, source, seconds)."""
    ylo, yhi = _images(d, n)
    t0 = time.perf_counter()
    try:
        from robust_imdp.abstraction.marginals import axis_marginals
        from robust_imdp.models.geometry import Box, Partition
        from robust_imdp.models.noise import GaussianNoise
    except ImportError:
        return _marginals_scipy(d, n, ylo, yhi), "scipy ndtr (benchmark input, not certified)", \
            time.perf_counter() - t0
    part = Partition(Box([-1.0] * d, [1.0] * d), 2.0 / n)
    axes = axis_marginals(part, ylo[None], yhi[None], GaussianNoise([SIGMA] * d))
    return axes, "abstraction.marginals.axis_marginals (certified)", time.perf_counter() - t0


def _timed(fn, repeat=3):
    """(result, median wall s, median CPU s) of ``repeat`` calls after one warm-up call."""
    out = fn()
    walls, cpus = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return out, float(np.median(walls)), float(np.median(cpus))


def one(d: int, n: int, horizon: int, joint_max: int) -> dict:
    """The row of dimension d (run in its own process)."""
    import numba

    from robust_imdp.models.factored import FactoredIMDP
    from robust_imdp.solvers.factored import factored_bellman, factored_operator, solve_factored_reachability

    row = {"d": d, "n": n, "cells": n ** d, "horizon": horizon, "threads": numba.get_num_threads()}
    axes, source, t_marg = _marginals(d, n)
    model = FactoredIMDP(shape=(n,) * d, axes=axes)
    N = model.n_cells
    row.update(marginals=source, marginals_s=round(t_marg, 2), k=list(model.k),
               entries_per_row=model.entries_per_row, numbers_per_row=model.numbers_per_row,
               rest_upper_max=float(max(ax.rest_upper.max() for ax in model.axes)),
               model_mb=round(model.nbytes / 2**20, 1))
    t0 = time.perf_counter()
    op = factored_operator(model)
    row.update(prepare_s=round(time.perf_counter() - t0, 2), tree_nodes=list(op.groups),
               distinct_marginals=list(op.n_marginals), entries_per_sweep=op.work,
               entries_per_sweep_unshared=op.unshared_work, operator_mb=round(op.nbytes / 2**20, 1))
    w = np.random.default_rng(0).random(model.n_states)
    t0 = time.perf_counter()
    factored_bellman(model, w)  # first call: loads (or compiles) the kernels
    row["first_sweep_s"] = round(time.perf_counter() - t0, 2)
    for adv in ("pessimistic", "optimistic"):
        _, wall, cpu = _timed(lambda: factored_bellman(model, w, adversary=adv))
        row[f"sweep_{adv}_s"] = round(wall, 3)
        row[f"sweep_{adv}_cpu_s"] = round(cpu, 3)
    row["ns_per_entry_cpu"] = round(row["sweep_pessimistic_cpu_s"] / op.work * 1e9, 2)
    # safety = 1 - P(reach outside within k steps); one mode: the controller has no choice.
    # p_low: the adversary maximising the exit (objective "minimize", pessimistic); p_up: minimising it.
    target = [N]
    t0, c0 = time.perf_counter(), time.process_time()
    exit_hi = solve_factored_reachability(model, target, objective="minimize", adversary="pessimistic", horizon=horizon)
    exit_lo = solve_factored_reachability(model, target, objective="minimize", adversary="optimistic", horizon=horizon)
    row["solve_s"] = round(time.perf_counter() - t0, 2)
    row["solve_cpu_s"] = round(time.process_time() - c0, 2)
    row["sweeps"] = 2 * horizon  # one sweep per step and adversary (k steps: a global rounding budget)
    p_low = np.clip(np.nextafter(1.0 - exit_hi.upper[:N], -np.inf), 0, 1)
    p_up = np.clip(np.nextafter(1.0 - exit_lo.lower[:N], np.inf), 0, 1)
    row.update(p_low_min=float(p_low.min()), p_low_mean=float(p_low.mean()), p_low_max=float(p_low.max()),
               p_up_mean=float(p_up.mean()), gap_mean=float((p_up - p_low).mean()),
               bracket_width_max=float(max(exit_hi.precision, exit_lo.precision)))
    row["factored_peak_rss_mb"] = round(_rss_mb(), 0)
    entries = model.joint_entries()
    row["joint_entries"] = entries
    row["joint_numbers_per_row"] = round(2 * (entries - 1) / (N * model.n_modes) + 1, 1)  # lower, upper + floor
    if entries <= joint_max:
        from robust_imdp.solvers.api import solve_reachability
        t0 = time.perf_counter()
        J = model.to_joint(max_entries=joint_max)
        row["joint_build_s"] = round(time.perf_counter() - t0, 2)
        row["joint_mb"] = round(J.memory_bytes / 2**20, 1)
        t0, c0 = time.perf_counter(), time.process_time()
        j_hi = solve_reachability(J, target, objective="minimize", adversary="pessimistic", horizon=horizon)
        row["joint_solve_s"] = round(time.perf_counter() - t0, 2)
        row["joint_solve_cpu_s"] = round(time.process_time() - c0, 2)
        j_low = np.clip(np.nextafter(1.0 - j_hi.upper[:N], -np.inf), 0, 1)
        row.update(joint_p_low_mean=float(j_low.mean()),
                   factored_minus_joint_p_low_min=float((p_low - j_low).min()),
                   factored_minus_joint_p_low_max=float((p_low - j_low).max()),
                   factored_never_below_joint=bool(np.all(p_low >= j_low - 1e-12)))
    else:
        row["joint"] = f"does not fit: {entries:,} entries > --joint-max-entries {joint_max:,}"
    row["peak_rss_mb"] = round(_rss_mb(), 0)
    row["load_end"] = os.getloadavg()
    return row


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def _md(data) -> str:
    rows = data["rows"]
    lines = ["# Factored solver (`benchmarks/factored_solver.py`)", "",
             f"{data['command']}; {data['date']}; commit {data['commit']}; load at start {data['load_start']}; "
             f"numba threads {rows[0]['threads'] if rows else '?'}.", "",
             "Linear system x' = A x + w (A_ii = 0.7, A_{i,i+1} = -0.1 cyclic, w ~ N(0, 0.01 I)), X = [-1, 1]^d, "
             f"one mode, safety for {rows[0]['horizon'] if rows else '?'} steps. Marginals: "
             f"{rows[0]['marginals'] if rows else '?'}.", "",
             "| d | cells | numbers / row (entries) | model MB | distinct marginals / axis | entries read / sweep "
             "(unshared) | sweep s (CPU s) | ns / entry (CPU) | k-step bracket s | peak RSS MB | p_low mean (min) | "
             "joint |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "joint" in r:
            joint = r["joint"]
        else:
            joint = (f"{r['joint_entries']:,} entries, {r['joint_mb']} MB, solve {r['joint_solve_s']} s; p_low mean "
                     f"{r['joint_p_low_mean']:.4f}; factored - joint in [{r['factored_minus_joint_p_low_min']:.2e}, "
                     f"{r['factored_minus_joint_p_low_max']:.2e}]")
        lines.append(
            f"| {r['d']} | {r['cells']:,} | {r['numbers_per_row']} ({r['entries_per_row']}) | {r['model_mb']} | "
            f"{r['distinct_marginals'][0]} | {r['entries_per_sweep']:,} ({r['entries_per_sweep_unshared']:.3g}) | "
            f"{r['sweep_pessimistic_s']} ({r['sweep_pessimistic_cpu_s']}) | {r['ns_per_entry_cpu']} | "
            f"{r['solve_s']} ({r['sweeps']} sweeps) | {r['peak_rss_mb']:.0f} | {r['p_low_mean']:.4f} "
            f"({r['p_low_min']:.4f}) | {joint} |")
    lines += ["", "Columns: numbers / row = stored numbers per (cell, mode), sum_i (2 k_i + 4); entries = sum_i (k_i + 1). "
              "Entries read / sweep: listed entries read by one sweep through the prefix tree of shared marginals, "
              "against a nested reduction per row. Sweep: one application of the operator to every row (median of "
              "3, wall clock, process CPU time in brackets). k-step bracket: both adversaries (p_low and p_up of "
              "safety), one sweep per step each. Joint: `FactoredIMDP.to_joint` solved by "
              "`solve_reachability` (same horizon), where it fits."]
    if data.get("unbounded"):
        u = data["unbounded"]
        lines += _md_unbounded(u["rows"])
        lines += _md_notes(u.get("notes", []))
        lines += ["", f"{u['command']}; {u['date']}; commit {u['commit']}."]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- unbounded synthesis
def _unbounded_problem(name: str, work: Path):
    from robust_imdp.io.files import load_problem

    if name.startswith("vehicle:"):
        from robust_imdp.casestudies.systems import write_problem_files

        p = load_problem(write_problem_files("vehicle_4d", work / "problem", seed=0))
        p = p.replace(cell_size=(p.space_upper - p.space_lower) / int(name[8:]))
    elif name in ("car", "bas4d"):
        p = load_problem(ROOT / "benchmarks" / "arch" / "problems" / {"car": "car_parking.toml",
                                                                       "bas4d": "bas4d.toml"}[name])
    else:
        from robust_imdp.casestudies.systems import write_problem_files

        p = load_problem(write_problem_files(name, work / "problem", seed=0))
    return p.replace(form="factored", horizon=None)


def _capture(problem):
    """The arguments the pipeline passes to ``synthesize`` (the pipeline stops there)."""
    import robust_imdp.synthesis.core as core
    from robust_imdp.pipeline.run import synthesize_from_data

    got = {}

    class _Stop(Exception):
        pass

    def fake(model, labels, atoms, dfa, **kw):
        got.update(model=model, labels=np.asarray(labels), atoms=atoms, dfa=dfa, kw=kw)
        raise _Stop

    import robust_imdp.pipeline.nominal_stage as nominal_stage

    real, real_nominal = core.synthesize, nominal_stage.run_nominal
    core.synthesize = fake
    # the nominal model (a tie key of the pipeline's synthesis) is not built: its solve is not the solver's work
    # (on car parking without a horizon its joint unbounded solve alone ran 2 x 100,000 sweeps)
    nominal_stage.run_nominal = lambda *a, **k: None
    try:
        synthesize_from_data(problem, advice=False, margins=False, check_resources=False)
    except _Stop:
        pass
    finally:
        core.synthesize, nominal_stage.run_nominal = real, real_nominal
    return got


def _synth(model, got) -> dict:
    import warnings

    from robust_imdp.synthesis.core import synthesize

    kw = {k: v for k, v in got["kw"].items() if k != "nominal"}  # the nominal tie key is not the solver's work
    c0, w0 = time.process_time(), time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = synthesize(model, got["labels"], got["atoms"], got["dfa"], **kw)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return {"cpu_s": round(cpu, 2), "wall_s": round(wall, 2), "load": [round(x, 2) for x in os.getloadavg()],
            "sweeps": {x.name: int(x.iterations) for x in r.runs}, "converged": all(bool(x.converged) for x in r.runs),
            "warnings": sorted({str(w.message)[:100] for w in caught}), "p_low": np.asarray(r.p_low, float),
            "p_up": np.asarray(r.p_up, float), "strategy": np.asarray(r.strategy)}


def unbounded_one(name: str, joint_max: int, whole_max_cells: int) -> dict:
    import robust_imdp.solvers.factored as F
    from robust_imdp.warmup import _factored_models, _solver_models

    work = Path(tempfile.mkdtemp(prefix="factored-solver-"))
    got = _capture(_unbounded_problem(name, work))
    m = got["model"]
    _factored_models()  # load the factored and joint kernels from numba's cache before timing
    _solver_models()
    row = {"name": name, "cells": int(m.n_cells), "modes": int(m.n_modes), "shape": list(m.shape), "k": list(m.k),
           "dfa_states": int(got["dfa"].n_states), "threads": int(__import__("numba").get_num_threads()), "runs": {}}
    F.ORDERED = True
    res = {"ordered": _synth(m, got)}
    if m.n_cells <= whole_max_cells:
        F.ORDERED = False
        res["whole"] = _synth(m, got)
        F.ORDERED = True
    try:
        t = time.process_time()
        J = m.to_joint(max_entries=joint_max)
        row["joint_build_cpu_s"] = round(time.process_time() - t, 2)
        row["joint_entries"] = int(J.nnz)
        res["joint"] = _synth(J, got)
    except Exception as exc:  # noqa: BLE001 -- too large: said in the row
        row["joint_skipped"] = f"{type(exc).__name__}: {str(exc)[:120]}"
    o = res["ordered"]
    for key, r in res.items():
        row["runs"][key] = {k: v for k, v in r.items() if k not in ("p_low", "p_up", "strategy")}
        row["runs"][key].update(p_low_mean=float(r["p_low"].mean()), p_up_mean=float(r["p_up"].mean()),
                                mean_gap=float((r["p_up"] - r["p_low"]).mean()))
        if key != "ordered":
            # the two brackets must overlap (both sound); the factored lower is above the joint one up to the
            # unlisted rest (docs/factored.md)
            row["runs"][key].update(
                ordered_low_minus_this_low_min=float((o["p_low"] - r["p_low"]).min()),
                ordered_low_minus_this_low_max=float((o["p_low"] - r["p_low"]).max()),
                brackets_overlap=bool(np.all(o["p_low"] <= r["p_up"] + 1e-9) and np.all(r["p_low"] <= o["p_up"] + 1e-9)),
                same_strategy_share=float(np.mean(o["strategy"] == r["strategy"])))
    return row


def _md_unbounded(rows) -> list:
    lines = ["", "## Unbounded synthesis: component-ordered pass against whole-model sweeps and the joint engine", "",
             "`python benchmarks/factored_solver.py --unbounded ...`: `synthesize` (optimistic, robust with ties, "
             "both evaluations) on the factored model the pipeline builds (form factored, no horizon). CPU = process "
             "CPU seconds of every thread (the machine is shared: 2 cores, load beside); sweeps per run (ordered: "
             "largest count of one component + whole-model sweeps after the pass).", "",
             "| problem | cells x modes (k per axis) | ordered CPU s (wall, load) | sweeps | whole-model CPU s | sweeps | "
             "joint CPU s (entries) | sweeps | p_low mean ordered / whole / joint | ordered - joint p_low "
             "[min, max] | brackets overlap |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]

    def sw(r):
        return "/".join(str(v) for v in r["sweeps"].values()) if r else "—"

    for r in rows:
        o, w, j = (r["runs"].get(k) for k in ("ordered", "whole", "joint"))
        jc = f"{j['cpu_s']} ({r['joint_entries']:,})" if j else r.get("joint_skipped", "—")[:40]
        pl = " / ".join(f"{x['p_low_mean']:.4f}" if x else "—" for x in (o, w, j))
        dj = f"[{j['ordered_low_minus_this_low_min']:.1e}, {j['ordered_low_minus_this_low_max']:.1e}]" if j else "—"
        ov = " ".join(f"{k}: {r['runs'][k]['brackets_overlap']}" for k in ("whole", "joint") if k in r["runs"])
        lines.append(f"| {r['name']} | {r['cells']:,} x {r['modes']} ({','.join(map(str, r['k']))}) | {o['cpu_s']} "
                     f"({o['wall_s']}, {o['load'][0]}) | {sw(o)} | {w['cpu_s'] if w else 'skipped'} | {sw(w)} | "
                     f"{jc} | {sw(j)} | {pl} | {dj} | {ov} |")
    lines += ["", "Sweeps are listed as robust/optimistic/evaluate_pessimistic/evaluate_optimistic. Every run "
              "converged to the precision 1e-8 unless a warning is recorded in the JSON."]
    return lines


def _md_notes(notes) -> list:
    """Measurements made outside ``--unbounded`` (the JSON's ``unbounded.notes``: text with its command)."""
    return ["", "Other measurements (same quantities, other commands):", ""] + [f"- {n}" for n in notes] if notes else []


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dims", type=int, nargs="+", default=[4, 5, 6])
    ap.add_argument("--n", type=int, default=8, help="intervals per axis")
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--joint-max-entries", type=int, default=30_000_000)
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--unbounded", nargs="+", metavar="NAME", help="the unbounded synthesis rows (module docstring)")
    ap.add_argument("--unbounded-one", help=argparse.SUPPRESS)
    ap.add_argument("--whole-max-cells", type=int, default=70_000)
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per unbounded child")
    args = ap.parse_args(argv)
    if args.unbounded_one is not None:
        print(json.dumps(unbounded_one(args.unbounded_one, args.joint_max_entries, args.whole_max_cells)))
        return 0
    if args.unbounded:
        return _run_unbounded(args, argv)
    if args.one is not None:
        print(json.dumps(one(args.one, args.n, args.horizon, args.joint_max_entries)))
        return 0
    load_start = os.getloadavg()
    rows = []
    for d in args.dims:
        cmd = [sys.executable, __file__, "--one", str(d), "--n", str(args.n), "--horizon", str(args.horizon),
               "--joint-max-entries", str(args.joint_max_entries)]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(r.stderr[-3000:], file=sys.stderr)
            return r.returncode
        row = json.loads(r.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(json.dumps(row), flush=True)
    try:
        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True).stdout.strip()
    except OSError:
        commit = None
    data = {"rows": rows, "command": "python benchmarks/factored_solver.py " + " ".join(argv or sys.argv[1:]),
            "commit": commit, "load_start": load_start, "load_end": os.getloadavg(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if not args.no_write:
        RESULTS.mkdir(exist_ok=True)
        _write_atomic(RESULTS / "factored_solver.json", json.dumps(data, indent=1) + "\n")
        _write_atomic(RESULTS / "factored_solver.md", _md(data))
    return 0


def _run_unbounded(args, argv) -> int:
    path = RESULTS / "factored_solver.json"
    data = json.loads(path.read_text()) if path.exists() else {"rows": []}
    old = {r["name"]: r for r in data.get("unbounded", {}).get("rows", [])}
    for name in args.unbounded:
        cmd = [sys.executable, __file__, "--unbounded-one", name, "--joint-max-entries", str(args.joint_max_entries),
               "--whole-max-cells", str(args.whole_max_cells)]
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            print(f"{name}: timed out after {args.timeout} s", file=sys.stderr)
            continue
        if r.returncode != 0:
            print(r.stderr[-3000:], file=sys.stderr)
            continue
        row = json.loads(r.stdout.strip().splitlines()[-1])
        old[name] = row
        print(json.dumps(row), flush=True)
        try:
            commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                                    text=True).stdout.strip()
        except OSError:
            commit = None
        data["unbounded"] = {"rows": list(old.values()), "commit": commit,
                             "notes": data.get("unbounded", {}).get("notes", []),
                             "command": "python benchmarks/factored_solver.py " + " ".join(argv or sys.argv[1:]),
                             "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
        if not args.no_write:
            RESULTS.mkdir(exist_ok=True)
            _write_atomic(path, json.dumps(data, indent=1) + "\n")
            _write_atomic(RESULTS / "factored_solver.md", _md(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
