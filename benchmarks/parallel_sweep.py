"""Value iteration on all cores (issue 10, item 7): Jacobi sweeps on numba's threads.

    python benchmarks/parallel_sweep.py [--repeat 5]

Where the solver sweeps Jacobi-style (products with a DFA, k-step horizons, floor models,
``method="interval"``) a layer with at least ``solve.PAR_MIN_STATES`` active states is updated by
``bellman_layer_parallel`` (prange over blocks of states); Gauss-Seidel sweeps (the default
engine's components) stay serial, since their order is part of the method. Measured here, in one
run, medians of ``--repeat`` alternating runs:

1. one Jacobi sweep of random models (3 actions, 12-20 successors) with 10k, 100k and 1M states:
   the serial kernel against the parallel one on 1 and on all threads; ns per stored entry;
2. a 100-step bounded solve (``horizon=100``: 200 Jacobi sweeps) of a 100k-state model, serial
   (``PAR_MIN_STATES`` raised above the model) against parallel; the results must be identical.

Writes ``benchmarks/results/parallel_sweep.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from solver import loadavg, med, random_model, targets  # noqa: E402

from robust_imdp.solvers import sweep as solve  # noqa: E402  (PAR_MIN_STATES and the layer kernels)
from robust_imdp.solvers.api import solve_reachability  # noqa: E402

OUT = HERE / "results"
PAR_DEFAULT = solve.PAR_MIN_STATES  # restored after the serial runs of bounded_solve


def one_sweep(m, w, kernel, threads):
    """Seconds of one upper Jacobi sweep of every state with ``kernel`` on ``threads`` threads."""
    n = m.n_states
    active = np.ones(n, dtype=bool)
    out_val = np.empty(n)
    out_arg = np.empty(n, dtype=np.int64)
    dummy_i, dummy_f = np.zeros(1, dtype=np.int64), np.zeros(1)
    numba.set_num_threads(threads)
    t0 = time.perf_counter()
    args = (m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, m.floor, w, active, False, False, dummy_i, dummy_f,
            dummy_f, dummy_f, 0, dummy_i, 1, out_val, out_arg, dummy_f, False, False)
    kernel(*args, threads) if kernel is solve.bellman_layer_parallel else kernel(*args)
    return time.perf_counter() - t0, out_val


def sweeps(sizes, repeat, rng, cores):
    rows = []
    for n in sizes:
        m = random_model(n, rng)
        w = rng.random(n)
        cases = {"serial": (solve.bellman_layer, 1), "parallel_1_thread": (solve.bellman_layer_parallel, 1),
                 f"parallel_{cores}_threads": (solve.bellman_layer_parallel, cores)}
        for kernel, threads in cases.values():  # compile / load the cache outside the timing
            one_sweep(m, w, kernel, threads)
        times = {k: [] for k in cases}
        ref = None
        identical = True
        for _ in range(repeat):
            for k, (kernel, threads) in cases.items():
                t, v = one_sweep(m, w, kernel, threads)
                times[k].append(t)
                ref = v if ref is None else ref
                identical &= bool(np.array_equal(v, ref))
        row = {"n_states": n, "nnz": int(m.nnz), "identical": identical}
        for k, ts in times.items():
            row[f"{k}_ns_per_entry"] = med(ts) / m.nnz * 1e9
        row["speedup"] = row["serial_ns_per_entry"] / row[f"parallel_{cores}_threads_ns_per_entry"]
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def bounded_solve(n, repeat, rng, cores):
    m = random_model(n, rng)
    t, z = targets(n, rng)
    numba.set_num_threads(cores)
    runs = {"serial": [], "parallel": []}
    results = {}
    for _ in range(repeat + 1):  # the first round compiles and is not counted
        for mode in ("serial", "parallel"):
            solve.PAR_MIN_STATES = n + 1 if mode == "serial" else PAR_DEFAULT
            t0 = time.perf_counter()
            r = solve_reachability(m, t, avoid=z, adversary="pessimistic", horizon=100)
            runs[mode].append(time.perf_counter() - t0)
            results[mode] = r
    solve.PAR_MIN_STATES = PAR_DEFAULT
    same = all(np.array_equal(getattr(results["serial"], a), getattr(results["parallel"], a))
               for a in ("lower", "upper", "strategy"))
    out = {"n_states": n, "nnz": int(m.nnz), "horizon": 100, "identical": same,
           "serial_s": med(runs["serial"][1:]), "parallel_s": med(runs["parallel"][1:])}
    out["speedup"] = out["serial_s"] / out["parallel_s"]
    print(json.dumps(out), flush=True)
    return out


def write_md(data):
    m = data["meta"]
    cores = m["cores"]
    lines = ["# Parallel Jacobi sweeps (`benchmarks/parallel_sweep.py`)", "",
             f"{m['date']}, {cores} cores, load average {m['load_start']} at the start; medians of {m['repeat']} "
             "alternating runs.", "",
             "## One upper sweep, ns per stored entry", "",
             f"| states | entries | serial kernel | parallel kernel, 1 thread | parallel, {cores} threads | speed-up | "
             "identical values |", "|---|---|---|---|---|---|---|"]
    for r in data["sweeps"]:
        lines.append(f"| {r['n_states']:,} | {r['nnz']:,} | {r['serial_ns_per_entry']:.1f} | "
                     f"{r['parallel_1_thread_ns_per_entry']:.1f} | {r[f'parallel_{cores}_threads_ns_per_entry']:.1f} | "
                     f"{r['speedup']:.2f}x | {r['identical']} |")
    b = data["bounded"]
    lines += ["", "## A 100-step bounded solve (200 Jacobi sweeps)", "",
              f"{b['n_states']:,} states, {b['nnz']:,} entries: serial {b['serial_s']:.2f} s, parallel "
              f"{b['parallel_s']:.2f} s ({b['speedup']:.2f}x); identical lower, upper and strategy: {b['identical']}.", "",
              "Gauss-Seidel sweeps (the default engine's strongly connected components) stay serial.", ""]
    (OUT / "parallel_sweep.md").write_text("\n".join(lines))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    cores = numba.config.NUMBA_NUM_THREADS
    data = {"meta": {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cores": cores,
                     "cpu_count": os.cpu_count(), "load_start": loadavg(), "repeat": args.repeat}}
    data["sweeps"] = sweeps([10_000, 100_000, 1_000_000], args.repeat, rng, cores)
    data["bounded"] = bounded_solve(100_000, args.repeat, rng, cores)
    data["meta"]["load_end"] = loadavg()
    OUT.mkdir(exist_ok=True)
    (OUT / "parallel_sweep.json").write_text(json.dumps(data, indent=1))
    write_md(data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
