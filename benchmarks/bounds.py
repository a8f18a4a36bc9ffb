"""Benchmark of certified GP bounds over a grid (issue 4, item 6).

1024 cells of width 0.125 on [-2, 2]^2, one GP per mode and output (fixed hyperparameters:
lengthscale 1.5, sf2 = 1, lambda = 1 + 2/m, so nothing depends on likelihood fitting), data
from the paper's systems:

* linear: x+ = A_u x + v, three modes, f_u = 0 (the GP learns x+ itself), 200 points/mode;
* nonlinear: x+ = x + g_u(x) + v, four modes, f_u(x) = x (the GP learns g_u), 300 and 1000
  points/mode; v ~ N(0, 0.01^2) truncated at +-0.01.

Reported per case: total time, time per cell, distribution of certified gaps, B&B leaves,
soundness violations against dense samples, the same bounds with the relaxation alone (no
branching) and with sampling-only estimates (100 points per cell, like the authors' code):
how much looser / how often unsound.  Writes ``benchmarks/results/bounds.{json,md}``.

Usage: ``python benchmarks/bounds.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

# one BLAS thread: the machine has 2 cores shared by other jobs (oversubscription is slower)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

from robust_imdp.bounds.gp_cells import bound_image  # noqa: E402
from robust_imdp.bounds.gp import GaussianProcess  # noqa: E402

A_LIN = [
    np.array([[0.4, 0.1], [0.0, 0.5]]),
    np.array([[0.4, 0.5], [0.0, 0.5]]),
    np.array([[0.4, 0.0], [0.5, 0.5]]),
]


def g_nonlinear(x, u):
    s1, s2, c1, c2 = np.sin(x[:, 0]), np.sin(x[:, 1]), np.cos(x[:, 0]), np.cos(x[:, 1])
    if u in (0, 1):
        return np.column_stack([(0.5 if u == 0 else -0.5) + 0.2 * s2, 0.4 * c1])
    return np.column_stack([0.4 * c2, (0.5 if u == 2 else -0.5) + 0.2 * s1])


def noise(rng, n):
    v = rng.normal(0.0, 0.01, (n, 2))
    while np.any(bad := np.abs(v) > 0.01):  # truncated Gaussian by rejection
        v[bad] = rng.normal(0.0, 0.01, bad.sum())
    return v


def make_case(name, m, rng):
    """Return (list over modes of (gps, A, b), description)."""
    modes = []
    if name == "linear":
        for Au in A_LIN:
            x = rng.uniform(-2, 2, (m, 2))
            y = x @ Au.T + noise(rng, m)  # f_u = 0: the GP learns x+ itself
            gps = [GaussianProcess(1.5, 1.0, "chowdhury").fit(x, y[:, i]) for i in range(2)]
            modes.append((gps, np.zeros((2, 2)), np.zeros(2)))
    else:
        for u in range(4):
            x = rng.uniform(-2, 2, (m, 2))
            y = g_nonlinear(x, u) + noise(rng, m)  # residual x+ - f_u(x), f_u(x) = x
            gps = [GaussianProcess(1.5, 1.0, "chowdhury").fit(x, y[:, i]) for i in range(2)]
            modes.append((gps, np.eye(2), np.zeros(2)))
    return modes


def grid(width=0.125):
    g = np.arange(-2.0, 2.0, width)
    lo = np.array([[a, b] for a in g for b in g])
    return lo, lo + width


def image_at(gps, A, b, x):
    mus, sds = zip(*(g.predict(x, return_std=True) for g in gps))
    return x @ A.T + b + np.column_stack(mus), np.column_stack(sds)


def run_case(name, m, tol, local_solver, rng, n_dense, n_sample):
    modes = make_case(name, m, rng)
    lo, hi = grid()
    k = lo.shape[0]
    out = {"case": name, "points_per_mode": m, "modes": len(modes), "cells": k, "tol": tol,
           "local_solver": local_solver}
    t0 = time.perf_counter()
    res = [bound_image(gps, A, b, lo, hi, tol=tol, local_solver=local_solver)
           for gps, A, b in modes]
    out["time_s"] = time.perf_counter() - t0
    out["time_per_cell_ms"] = 1e3 * out["time_s"] / k
    gaps = np.concatenate([np.r_[r.lower_gap.ravel(), r.upper_gap.ravel()] for r in res])
    sgaps = np.concatenate([r.std_upper_gap.ravel() for r in res])
    q = [50, 90, 99, 100]
    out["mean_gap_percentiles_50_90_99_100"] = np.percentile(gaps, q).tolist()
    out["std_gap_percentiles_50_90_99_100"] = np.percentile(sgaps, q).tolist()
    out["leaves"] = int(sum(r.n_leaves for r in res))
    out["budget_exhausted"] = int(sum(r.budget_exhausted.sum() for r in res))
    # relaxation only (root box, no branching)
    t0 = time.perf_counter()
    root = [bound_image(gps, A, b, lo, hi, tol=tol, max_boxes=1, local_solver=None)
            for gps, A, b in modes]
    out["relaxation_only_time_s"] = time.perf_counter() - t0
    loose = np.concatenate([np.r_[(r.lower - r0.lower).ravel(), (r0.upper - r.upper).ravel()]
                            for r, r0 in zip(res, root)])
    sloose = np.concatenate([(r0.std_upper - r.std_upper).ravel() for r, r0 in zip(res, root)])
    out["relaxation_only_extra_width_mean_median_max"] = [float(np.median(loose)), float(loose.max())]
    out["relaxation_only_extra_width_std_median_max"] = [float(np.median(sloose)), float(sloose.max())]
    # dense samples (soundness) and sampling-only estimates (n_sample points per cell)
    viol, under, under_max, s_under = 0, 0, 0.0, 0
    srng = np.random.default_rng(1)
    for (gps, A, b), r in zip(modes, res):
        for c0 in range(0, k, 64):  # 64 cells at a time: (64 * n_dense, 2) points
            sl = slice(c0, c0 + 64)
            nc = lo[sl].shape[0]
            u = srng.uniform(size=(nc, n_dense, 2))
            pts = lo[sl, None, :] + u * (hi - lo)[sl, None, :]
            val, sd = image_at(gps, A, b, pts.reshape(-1, 2))
            val, sd = val.reshape(nc, n_dense, 2), sd.reshape(nc, n_dense, 2)
            viol += int((val.min(1) < r.lower[sl]).sum() + (val.max(1) > r.upper[sl]).sum()
                        + (sd.max(1) > r.std_upper[sl]).sum())
            # sampling-only estimate: first n_sample points; "unsound" where it lies strictly
            # inside the certified achieved extremum (true extremum is beyond the estimate)
            ach_up = r.upper[sl] - r.upper_gap[sl]
            est_up = val[:, :n_sample].max(1)
            miss = ach_up - est_up
            under += int((miss > 0).sum())
            under_max = max(under_max, float(miss.max()))
            ach_sd = r.std_upper[sl] - r.std_upper_gap[sl]
            s_under += int((ach_sd - sd[:, :n_sample].max(1) > 0).sum())
    out["dense_samples_per_cell"] = n_dense
    out["soundness_violations"] = viol
    out["sampling_only_points_per_cell"] = n_sample
    out["sampling_only_upper_below_true_max_count"] = under
    out["sampling_only_upper_below_true_max_worst"] = under_max
    out["sampling_only_std_below_true_max_count"] = s_under
    out["problems"] = 3 * 2 * k * len(modes)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="linear + nonlinear-300 only, fewer samples")
    ap.add_argument("--render", action="store_true", help="only rewrite bounds.md from bounds.json")
    args = ap.parse_args()
    if args.render:
        res_dir = Path(__file__).parent / "results"
        data = json.loads((res_dir / "bounds.json").read_text())
        write_md(res_dir / "bounds.md", data["meta"], data["runs"])
        return
    rng = np.random.default_rng(0)
    n_dense = 200 if args.quick else 1000
    # (case, points per mode, local solver); casadi on the linear case measures whether it pays
    runs = [("linear", 200, None), ("nonlinear", 300, None), ("linear", 200, "casadi")]
    if not args.quick:
        runs += [("nonlinear", 1000, None), ("nonlinear", 300, "casadi")]
    results = []
    for name, m, ls in runs:
        # dense soundness check costs O(m^2) per point for the std: fewer points for m = 1000
        nd = n_dense if m <= 300 else 100
        r = run_case(name, m, 1e-3, ls, np.random.default_rng(0), nd, min(100, nd))
        print(json.dumps(r))
        results.append(r)
    meta = {"machine": platform.platform(), "python": platform.python_version(),
            "note": os.environ.get("BENCH_NOTE", "2-core machine; single run per case"),
            "quick": args.quick, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    out_dir = Path(__file__).parent / "results"
    out_dir.mkdir(exist_ok=True)
    (out_dir / "bounds.json").write_text(json.dumps({"meta": meta, "runs": results}, indent=1))
    write_md(out_dir / "bounds.md", meta, results)


def write_md(path, meta, results):
    lines = [
        "# Certified GP bounds benchmark (`benchmarks/bounds.py`)", "",
        f"{meta['note']}; {meta['date']}; quick={meta['quick']}.", "",
        "1024 cells of width 0.125 on [-2, 2]^2, 2 outputs per mode, tol = 1e-3 (mean and std), "
        "lengthscale 1.5, sf2 = 1, lambda = 1 + 2/m. *gap*: certified bound minus achieved value. "
        "*violations*: dense samples outside the certified bounds (must be 0). *relax-only*: "
        "extra width of the root relaxation without branching, vs the B&B bound. "
        "*sampling-only*: cells x outputs where the max of 100 random samples lies below the "
        "achieved max (i.e. a sampled 'bound' would be unsound), and the worst shortfall.", "",
        "| case | m | modes | local solver | time s | ms/cell | mean gap p50/p99/max | std gap max |"
        " leaves | exhausted | violations (samples/cell) | relax-only extra width mean med/max, std max |"
        " sampling-only unsound: mean-max (worst), std-max |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        g, s = r["mean_gap_percentiles_50_90_99_100"], r["std_gap_percentiles_50_90_99_100"]
        ro = r["relaxation_only_extra_width_mean_median_max"]
        rs = r["relaxation_only_extra_width_std_median_max"]
        tot = r["cells"] * 2 * r["modes"]
        lines.append(
            f"| {r['case']} | {r['points_per_mode']} | {r['modes']} | {r['local_solver']} | "
            f"{r['time_s']:.1f} | {r['time_per_cell_ms']:.1f} | {g[0]:.1e}/{g[2]:.1e}/{g[3]:.1e} | "
            f"{s[3]:.1e} | {r['leaves']} | {r['budget_exhausted']} | {r['soundness_violations']} "
            f"({r['dense_samples_per_cell']}) | {ro[0]:.1e}/{ro[1]:.1e}, {rs[1]:.1e} | "
            f"{r['sampling_only_upper_below_true_max_count']}/{tot} "
            f"({r['sampling_only_upper_below_true_max_worst']:.1e}), "
            f"{r['sampling_only_std_below_true_max_count']}/{tot} |")
    Path(path).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
