"""Solver benchmark (issue 2, item 7): random sparse IMDPs, time per Bellman iteration, time to
precision 1e-8, memory, numba vs numpy inner loop, and Storm on the same models when stormpy
is installed.  Writes ``benchmarks/results/solver.json`` and ``solver.md``.

    python benchmarks/solver.py            # 10k, 100k, 1M states (about 5 minutes)
    python benchmarks/solver.py --quick    # 10k and 100k only

Models: n states, 3 actions, 20 distinct successors per row, intervals [0.8 p, 1.2 p] around a
random distribution p (positive lower bounds, as Storm's unbounded queries require), 1% of the
states are targets.  The floor variant lists 20 successors carrying 95% of the mass and gives
every other state the floor 0.1 / n (the GP abstraction's shape); Storm cannot take floors
without densifying (n^2 entries), so it is not run there.

Reported medians; ratios come from one run on the same machine.  Absolute times depend on the
machine and its load; the results' note (``BENCH_NOTE``) records the conditions of the run.
"""

from __future__ import annotations

import os
import argparse
import json
import platform
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from robust_imdp.imdp import IMDP
from robust_imdp.solve import _Sweeper, solve_reachability

RESULTS = Path(__file__).resolve().parent / "results"
K = 20  # successors per row
A = 3  # actions per state


def random_model(n: int, rng, floor: bool) -> IMDP:
    """Random IMDP with n states, A actions, K distinct successors per row (vectorised)."""
    R = n * A
    col = np.sort(rng.integers(0, n - K + 1, size=(R, K)), axis=1) + np.arange(K)  # distinct, sorted
    p = rng.random((R, K)) + 0.05
    p /= p.sum(axis=1, keepdims=True)
    fl = None
    if floor:
        p *= 0.95  # 5% of the mass must go to unlisted states (capacity 0.1 / n each, 0.1 in total)
        fl = np.full(R, 0.1 / n)
    lower = (0.8 * p).ravel()
    upper = np.minimum(1.2 * p, 1.0).ravel()
    del p
    return IMDP.from_csr(np.arange(0, R + 1, A), np.arange(0, R * K + 1, K), col.ravel(), lower, upper, floor=fl)


def median_time(fn, repeat):
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def numpy_bellman(m: IMDP, w: np.ndarray) -> np.ndarray:
    """Reference numpy formulation of one pessimistic max Bellman step (no floor): a global
    lexsort of the entries by (row, value), capacities accumulated per row, max per state."""
    rl = np.diff(m.row_ptr)
    entry_row = np.repeat(np.arange(m.n_choices), rl)
    v = w[m.col]
    order = np.lexsort((v, entry_row))  # ascending values inside each row: the adversary minimises
    vs = v[order]
    cap = (m.upper - m.lower)[order]
    rem = 1.0 - np.add.reduceat(m.lower, m.row_ptr[:-1])
    cs = np.cumsum(cap)
    before = cs - cap - np.repeat(cs[m.row_ptr[:-1]] - cap[m.row_ptr[:-1]], rl)  # exclusive, per row
    take = np.clip(np.repeat(rem, rl) - before, 0.0, cap)
    rowv = np.add.reduceat(m.lower * v, m.row_ptr[:-1]) + np.add.reduceat(take * vs, m.row_ptr[:-1])
    return np.maximum.reduceat(rowv, m.state_ptr[:-1])


def numba_sweep(m: IMDP, w: np.ndarray, adv_max=False):
    n = m.n_states
    sw = _Sweeper(m, np.zeros((1, n), np.int64), np.ones((1, n), bool), 0, adv_max, None)
    return lambda: sw.sweep(w[None, :], -1)


def storm_case(m: IMDP, target, avoid, ours, args):
    try:
        from robust_imdp.formats import storm_reachability, to_stormpy  # the stormpy bridge (lazy)
        import stormpy  # noqa: F401
    except ImportError as e:  # optional dependency
        return {"skipped": f"stormpy bridge unavailable: {e}"}
    out = {}
    t0 = time.perf_counter()
    model = to_stormpy(m, target, avoid=avoid)
    out["build_s"] = time.perf_counter() - t0
    for adv, key in (("pessimistic", "robust"), ("optimistic", "cooperative")):
        # per-iteration cost from two bounded queries (F<=1 and F<=1+steps)
        steps = args.storm_steps
        rep = 3 if m.nnz <= 1_000_000 else 1
        t1 = median_time(lambda: storm_reachability(model, target, avoid=avoid, adversary=adv, horizon=1), rep)
        t2 = median_time(lambda: storm_reachability(model, target, avoid=avoid, adversary=adv, horizon=1 + steps), rep)
        per_it = max(t2 - t1, 0.0) / steps
        t0 = time.perf_counter()
        vals = storm_reachability(model, target, avoid=avoid, adversary=adv, precision=1e-8)
        t_prec = time.perf_counter() - t0
        r = ours[adv]
        out[key] = {
            "per_iteration_s": per_it,
            "ns_per_entry": per_it / m.nnz * 1e9,
            "time_to_1e-8_s": t_prec,
            "max_abs_diff_to_our_lower": float(np.max(np.abs(vals - r.lower))),
            "storm_outside_our_bracket_by": float(max(np.max(r.lower - vals), np.max(vals - r.upper), 0.0)),
        }
    return out


def run_case(n: int, floor: bool, rng, args) -> dict:
    t0 = time.perf_counter()
    m = random_model(n, rng, floor)
    gen = time.perf_counter() - t0
    special = rng.choice(n, 2 * max(1, n // 20), replace=False)
    target = np.zeros(n, bool)
    target[special[: special.size // 2]] = True
    avoid = np.zeros(n, bool)
    avoid[special[special.size // 2:]] = True
    w = rng.random(n)
    row = {"n_states": n, "floor": floor, "nnz": m.nnz, "generate_s": gen,
           "model_bytes_per_entry": m.memory_bytes / m.nnz}
    f = numba_sweep(m, w)
    f()  # compile / warm up
    t_it = median_time(f, args.repeat)
    row["numba_iteration_s"] = t_it
    row["numba_ns_per_entry"] = t_it / m.nnz * 1e9
    if not floor and n <= args.numpy_max:
        t_np = median_time(lambda: numpy_bellman(m, w), max(1, args.repeat // 2))
        row["numpy_iteration_s"] = t_np
        row["numpy_ns_per_entry"] = t_np / m.nnz * 1e9
    ours = {}
    if n > args.precision_max:
        print(json.dumps(row, default=float), flush=True)
        return row  # time to precision skipped (see --precision-max)
    for adv in ("pessimistic", "optimistic"):
        tracemalloc.start()
        t0 = time.perf_counter()
        r = solve_reachability(m, target, avoid=avoid, adversary=adv, precision=1e-8)
        el = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        ours[adv] = r
        row[adv] = {"time_to_1e-8_s": el, "iterations": r.iterations, "converged": r.converged,
                    "precision": r.precision, "solver_peak_bytes_per_entry": peak / m.nnz,
                    "total_bytes_per_entry": (peak + m.memory_bytes) / m.nnz}
    if not floor and args.storm and n <= args.storm_max:
        row["storm"] = storm_case(m, target, avoid, ours, args)
        st = row["storm"]
        if "robust" in st:
            st["ratio_ours_over_storm_per_iteration"] = t_it / st["robust"]["per_iteration_s"] \
                if st["robust"]["per_iteration_s"] > 0 else None
    print(json.dumps(row, default=float), flush=True)
    return row


def markdown(rows) -> str:
    lines = ["| states | floor | entries | ours ns/entry/it (numba) | numpy ns/entry/it | Storm ns/entry/it | ratio ours/Storm "
             "| ours time to 1e-8 (robust / coop) | iterations | Storm time to 1e-8 (robust / coop) | max abs diff vs Storm "
             "| bytes/entry (model + solver) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        st = r.get("storm", {})
        rob, coop = st.get("robust", {}), st.get("cooperative", {})
        pes, opt = r.get("pessimistic", {}), r.get("optimistic", {})
        fmt = lambda x, f="{:.1f}": f.format(x) if isinstance(x, (int, float)) else "—"  # noqa: E731
        diff = max(rob.get("max_abs_diff_to_our_lower", float("nan")), coop.get("max_abs_diff_to_our_lower", float("nan"))) \
            if rob else None
        lines.append(
            f"| {r['n_states']:,} | {'yes' if r['floor'] else 'no'} | {r['nnz']:,} | {fmt(r['numba_ns_per_entry'])} "
            f"| {fmt(r.get('numpy_ns_per_entry'))} | {fmt(rob.get('ns_per_entry'))} "
            f"| {fmt(st.get('ratio_ours_over_storm_per_iteration'), '{:.2f}')} "
            f"| {fmt(pes.get('time_to_1e-8_s'), '{:.2f}')} s / {fmt(opt.get('time_to_1e-8_s'), '{:.2f}')} s "
            f"| {pes.get('iterations', '—')} / {opt.get('iterations', '—')} "
            f"| {fmt(rob.get('time_to_1e-8_s'), '{:.2f}')} s / {fmt(coop.get('time_to_1e-8_s'), '{:.2f}')} s "
            f"| {fmt(diff, '{:.1e}')} | {fmt(pes.get('total_bytes_per_entry'))} |")
    return "\n".join(lines)


def notes(rows) -> list[str]:
    """Short findings derived from the rows (choice of the inner loop, targets of issue 2)."""
    out = []
    np_rows = [r for r in rows if "numpy_ns_per_entry" in r]
    if np_rows:
        sp = [r["numpy_ns_per_entry"] / r["numba_ns_per_entry"] for r in np_rows]
        out.append(f"* Inner loop: numba, because the numpy formulation (global lexsort by row and value, "
                   f"capacities by cumsum) is {min(sp):.0f}-{max(sp):.0f}x slower per entry here and needs several "
                   "nnz-sized temporaries; it also cannot do the floor blocks without densifying.")
    big = [r for r in rows if r["n_states"] == max(x["n_states"] for x in rows) and not r["floor"]]
    if big:
        out.append(f"* Largest model: {big[0]['numba_ns_per_entry']:.1f} ns per stored entry per Bellman sweep "
                   "(issue target <= 22, aim 10; the issue quotes Storm at ~22 here; Storm is not run at 1M because building its model from Python costs ~1 us per entry).")
    mem = [r["pessimistic"]["total_bytes_per_entry"] for r in rows if "pessimistic" in r]
    if mem:
        out.append(f"* Memory: {max(mem):.1f} bytes per stored entry at the peak of a solve (model "
                   f"{rows[0]['model_bytes_per_entry']:.1f}: col int64 + lower + upper; the rest is the transient "
                   "end-component graph, int32 CSR built in numba).  Target <= 40.")
    st = [r for r in rows if "storm" in r and "robust" in r["storm"]]
    if st:
        worst = max(max(r["storm"]["robust"]["storm_outside_our_bracket_by"],
                        r["storm"]["cooperative"]["storm_outside_our_bracket_by"]) for r in st)
        out.append(f"* Storm stops on a residual: its values lie up to {worst:.1e} outside our *proven* bracket "
                   "(requested precision 1e-8), which is why our time to 1e-8 (two-sided, certified) is longer "
                   "than Storm's.")
    out.append("* Floor rows cost O(listed) via global order + double-double prefix sums; the per-sweep argsort of n "
               "values and the random access into the prefix sums make floor sweeps slower per entry, and floor "
               "models use Jacobi sweeps (Gauss-Seidel would invalidate the sweep's order).")
    return out


def render(data) -> str:
    meta, rows = data["meta"], data["rows"]
    md = ["# Solver benchmark", "", f"`python benchmarks/solver.py`; {meta['actions']} actions, {meta['successors']} "
          "successors per row, 5% targets, 5% avoid; medians. ns/entry/it: one Bellman sweep (sound rounding "
          "included) per stored entry. Time to 1e-8: our interval iteration runs a lower *and* an upper sweep per "
          "iteration (plus the graph pre-computations) and stops on a proven bracket; Storm stops on a residual. "
          f"{meta['note']}; total run {meta['total_s']:.0f} s.", "", markdown(rows), "", *notes(rows), ""]
    return "\n".join(md)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="10k and 100k states only")
    ap.add_argument("--sizes", type=int, nargs="*", default=None)
    ap.add_argument("--repeat", type=int, default=5, help="timing repetitions (median)")
    ap.add_argument("--no-storm", dest="storm", action="store_false")
    ap.add_argument("--storm-max", type=int, default=100_000, help="largest model given to Storm "
                    "(building a stormpy model from Python costs ~1 us per entry)")
    ap.add_argument("--storm-steps", type=int, default=20)
    ap.add_argument("--numpy-max", type=int, default=100_000)
    ap.add_argument("--precision-max", type=int, default=100_000, help="largest model solved to 1e-8 "
                    "(1M states takes ~10 minutes on a loaded 2-core machine)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--render", action="store_true", help="only re-render solver.md from solver.json")
    args = ap.parse_args(argv)
    if args.render:
        (RESULTS / "solver.md").write_text(render(json.loads((RESULTS / "solver.json").read_text())))
        return
    sizes = args.sizes or ([10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000])
    rng = np.random.default_rng(args.seed)
    rows = []
    t0 = time.perf_counter()
    for n in sizes:
        for floor in (False, True):
            rows.append(run_case(n, floor, rng, args))
    meta = {"python": sys.version.split()[0], "numpy": np.__version__, "machine": platform.machine(),
            "note": os.environ.get("BENCH_NOTE", "2-core machine; medians of the stated repetitions"),
            "total_s": time.perf_counter() - t0, "actions": A, "successors": K, "seed": args.seed}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "solver.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1, default=float))
    md = render({"meta": meta, "rows": rows})
    (RESULTS / "solver.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
