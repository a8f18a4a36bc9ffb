"""Finite-horizon synthesis against the same number of unbounded sweeps.

    python benchmarks/finite_horizon.py [--label NAME] [--repeat 3] [--threads 1 0] [--horizons 10]
                                        [--before SRC]

The problem: car parking (``benchmarks/arch/problems/car_parking.toml`` with ``form = "joint"``: 1,601
states, 9 modes, about 325 successors per row, 4.7 M transitions, a floor on the unlisted states,
known dynamics, ``G !avoid & F target`` within 10 steps). The abstraction and the nominal model are
built once (not timed). Measured, after one untimed call (numba's compilation), best of ``--repeat``:

* ``synthesize_s``: :func:`robust_imdp.synthesis.core.synthesize` with the horizon and the nominal model,
  as the pipeline calls it (the optimistic solve, the nominal solve, the robust solve with its two
  tie-break keys, the strategy's two evaluations); ``sweeps``: how many Bellman sweeps of all rows (full)
  and of a fixed strategy's rows (fixed) it makes, counted in a separate untimed call (a key that reads the
  rows an earlier solve kept and an end of a bracket that is not iterated make none: ``synthesis.core``,
  "k steps");
* ``solve_s``: one k-step product solve without keys (pessimistic: a lower and an upper sweep per step);
* ``sweep_s``: one sweep of the unbounded engine on the same model (``Sweeper.sweep(V, -1, inplace=True)``,
  the Jacobi sweep of :func:`robust_imdp.solvers.ovi._ovi_jacobi`, which solves models with floor rows),
  against the robust k-step lower values; ``insertion_sweep_s``: the same sweep with every row sorted by
  insertion (the kernel before the bucketed one; results identical);
* ratios: ``synthesize_s / (k sweep_s)`` (the issue's target: within 3 x the time of the same number of
  unbounded sweeps) and the same of CPU seconds (``_cpu``: the comparable one on a shared machine),
  ``solve_s / (k sweep_s)``, and ns per transition and step.

``--threads``: numba threads per measurement (0 = all); ``--label`` names the run (rows of other labels in
the results are kept, so a ``PYTHONPATH=<old tree>/src`` run can stand beside); ``--before SRC`` first
measures the package in ``SRC`` (e.g. ``git archive <commit> src | tar -x -C /tmp/old``, then
``/tmp/old/src``) in a child process, labelled ``before``, then this tree, labelled ``--label``, in one run. Wall and CPU seconds are
recorded with the load average: on the shared 2-core machine the one-thread CPU seconds are the
load-independent number. Writes ``benchmarks/results/finite_horizon.{json,md}`` (atomically).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NAME = "finite_horizon"
PROBLEM = ROOT / "benchmarks" / "arch" / "problems" / "car_parking.toml"


def _build():
    """(problem, partition, joint IMDP, nominal IMDP, dfa) of car parking."""
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.io.files import load_problem
    from robust_imdp.models.geometry import Box, Partition
    from robust_imdp.pipeline import run as R
    from robust_imdp.pipeline.nominal_stage import run_nominal
    from robust_imdp.pipeline.runtime import _Log
    from robust_imdp.spec.api import to_dfa

    p = load_problem(PROBLEM)
    if "form" in {f.name for f in dataclasses.fields(p)}:
        p = dataclasses.replace(p, form="joint")
    log = _Log(False)
    part = Partition(Box(p.space_lower, p.space_upper), p.cell_size, R._region_objects(p), names=p.dim_names,
                     periodic=p.periodic)
    ab = R._build_abstraction(p, part, log, None)[0]
    return p, part, abstraction_model(ab), run_nominal(p, part, log), to_dfa(p.formula, part.atoms)


def _best(fn, repeat):
    """(best wall s, CPU s of that call, last result) of ``repeat`` calls."""
    best = None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        w, c = time.perf_counter() - w0, time.process_time() - c0
        if best is None or w < best[0]:
            best = (w, c)
    return best[0], best[1], out


def _count_sweeps(fn):
    """Bellman sweeps of ``fn()``: (all rows, a fixed strategy's rows)."""
    from robust_imdp.solvers import sweep as S

    counts = [0, 0]
    orig = S.Sweeper.sweep

    def counted(self, V, direction, *a, **k):
        counts[1 if self.strategy is not None else 0] += len(self.layers)
        return orig(self, V, direction, *a, **k)

    S.Sweeper.sweep = counted
    try:
        fn()
    finally:
        S.Sweeper.sweep = orig
    return counts


def measure(model, horizon, threads, repeat) -> dict:
    import numba

    from robust_imdp.solvers.common import Control
    from robust_imdp.solvers.product import solve_product
    from robust_imdp.solvers.sweep import Sweeper
    from robust_imdp.synthesis.core import synthesize

    p, part, imdp, nominal, dfa = model
    all_threads = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(all_threads if threads == 0 else min(threads, all_threads))
    kw = dict(threshold=p.threshold, horizon=horizon, outside_state=part.outside_state, semantics=p.semantics)

    def synth():
        return synthesize(imdp, part.labels, part.atoms, dfa, nominal=nominal, **kw)

    letters = np.concatenate([part.labels, np.zeros(imdp.n_states - part.n_cells, dtype=np.int64)])
    syn = synth()  # compile
    sweeps = _count_sweeps(synth)
    syn_w, syn_c, syn = _best(synth, repeat)
    avoid = [part.outside_state] if part.outside_state is not None else None

    def solve():
        return solve_product(imdp, letters, dfa, adversary="pessimistic", horizon=horizon, avoid=avoid,
                             semantics=syn.semantics)

    solve()
    sol_w, sol_c, sol = _best(solve, repeat)
    # the unbounded engine's sweep against realistic values: the k-step lower values of the initial layer
    n = imdp.n_states
    V = np.asarray(sol.lower, dtype=np.float64)[int(np.bincount(sol.initial_state).argmax())][None, :].copy()
    sw = Sweeper(imdp, np.zeros((1, n), dtype=np.int64), np.ones((1, n), dtype=bool), Control.MAXIMISE, False, None)
    sw.sweep(V.copy(), -1, inplace=True)
    swp_w, swp_c, _ = _best(lambda: sw.sweep(V.copy(), -1, inplace=True), max(repeat, 5))
    ins = {}
    if getattr(sw, "_bucket", None) is not None:
        sw._bucket = None  # every row sorted by insertion (the kernel before the bucketed one)
        sw.sweep(V.copy(), -1, inplace=True)
        w, c, _ = _best(lambda: sw.sweep(V.copy(), -1, inplace=True), 2)
        ins = {"insertion_sweep_s": w, "insertion_sweep_cpu_s": c}
    nnz = int(imdp.nnz)
    return {"horizon": horizon, "threads": numba.get_num_threads(), "transitions": nnz, "states": int(n),
            "rows": int(imdp.n_choices), "synthesize_s": syn_w, "synthesize_cpu_s": syn_c,
            "sweeps_full": sweeps[0], "sweeps_fixed": sweeps[1], "solve_s": sol_w, "solve_cpu_s": sol_c,
            "sweep_s": swp_w, "sweep_cpu_s": swp_c, **ins,
            "synthesize_over_k_sweeps": syn_w / (horizon * swp_w), "solve_over_k_sweeps": sol_w / (horizon * swp_w),
            "synthesize_over_k_sweeps_cpu": syn_c / (horizon * swp_c),
            "ns_per_transition_step": syn_w / (nnz * horizon) * 1e9, "sweep_ns_per_transition": swp_w / nnz * 1e9,
            "load": list(os.getloadavg()),
            "p_low_digest": float(np.sum(syn.p_low)), "strategy_digest": int(np.sum(syn.strategy))}


def _md(data: dict) -> list[str]:
    lines = [f"# Finite-horizon synthesis (`benchmarks/finite_horizon.py`)", "",
             "Car parking (`benchmarks/arch/problems/car_parking.toml`, joint form: "
             f"{data['rows'][0]['states']:,} states, {data['rows'][0]['rows']:,} rows, "
             f"{data['rows'][0]['transitions']:,} transitions, floor rows), `G !avoid & F target` within k steps, "
             "known dynamics and the nominal model. Seconds are wall, best of the repeats, on the shared 2-core "
             "machine (load average in the row; CPU seconds beside: with one thread they are the load-independent "
             "number). *k sweeps* = k sweeps of the unbounded engine on the same model (its Jacobi sweep, which "
             "solves floor models); target: synthesis within 3 x that.", "",
             "| label | source | k | threads | synthesize s (CPU) | sweeps full + fixed | k-step solve s | "
             "unbounded sweep s (CPU) | insertion sweep s | synthesize / k sweeps (CPU) | solve / k sweeps | "
             "ns / transition step | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        ins = f"{r['insertion_sweep_s']:.3f}" if "insertion_sweep_s" in r else ""
        lines.append(f"| {r['label']} | {r['source']} | {r['horizon']} | {r['threads']} | {r['synthesize_s']:.2f} "
                     f"({r['synthesize_cpu_s']:.2f}) | {r['sweeps_full']} + {r['sweeps_fixed']} | {r['solve_s']:.3f} | "
                     f"{r['sweep_s']:.4f} ({r['sweep_cpu_s']:.4f}) | {ins} | {r['synthesize_over_k_sweeps']:.1f} "
                     f"({r['synthesize_cpu_s'] / (r['horizon'] * r['sweep_cpu_s']):.1f}) | "
                     f"{r['solve_over_k_sweeps']:.1f} | {r['ns_per_transition_step']:.0f} | {r['load'][0]:.1f} |")
    lines += ["", "Identical results across rows: the p_low sum and strategy sum of every row of one k agree: "
              + ("**yes**" if _identical(data["rows"]) else "**no**") + "."]
    if data.get("notes"):
        lines += ["", data["notes"]]
    return lines


def _identical(rows) -> bool:
    by_k = {}
    for r in rows:
        by_k.setdefault(r["horizon"], set()).add((r["p_low_digest"], r["strategy_digest"]))
    return all(len(v) == 1 for v in by_k.values())


def _write_atomic(data: dict) -> None:
    out = ROOT / "benchmarks" / "results"
    for suffix, text in ((".json", json.dumps(data, indent=1)), (".md", "\n".join(_md(data)) + "\n")):
        tmp = out / f".{NAME}{suffix}.part"
        tmp.write_text(text)
        os.replace(tmp, out / f"{NAME}{suffix}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="after")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 0], help="numba threads per row (0: all)")
    ap.add_argument("--horizons", type=int, nargs="+", default=[10])
    ap.add_argument("--notes", default=None, help="a paragraph under the table")
    ap.add_argument("--before", default=None, help="a src folder measured first (label 'before', child process)")
    args = ap.parse_args(argv)
    if args.before:
        import subprocess

        env = dict(os.environ, PYTHONPATH=str(Path(args.before).resolve()))
        cmd = [sys.executable, __file__, "--label", "before", "--repeat", str(args.repeat), "--threads",
               *map(str, args.threads), "--horizons", *map(str, args.horizons)]
        if args.notes is not None:
            cmd += ["--notes", args.notes]
        subprocess.run(cmd, env=env, check=True)
    import robust_imdp

    source = str(Path(robust_imdp.__file__).resolve().parents[1])
    source = "this tree" if source == str(ROOT / "src") else source
    model = _build()
    path = ROOT / "benchmarks" / "results" / f"{NAME}.json"
    old = json.loads(path.read_text()) if path.exists() else {"rows": []}
    rows = [r for r in old["rows"] if r["label"] != args.label]
    for k in args.horizons:
        for t in args.threads:
            row = {"label": args.label, "source": source, **measure(model, k, t, args.repeat)}
            print(json.dumps(row), flush=True)
            rows.append(row)
            data = {"rows": rows, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                    "cpus": os.cpu_count(), "python": sys.version.split()[0],
                    "notes": args.notes if args.notes is not None else old.get("notes")}
            _write_atomic(data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
