"""Benchmark of the abstraction stage alone (bounds given as arrays).

Grids 32x32, 64x64, 128x128 on [-2, 2]^2 and 16x16x16 on [-2, 2]^3, 4 modes. Image boxes are
exact (monotone nonlinear maps evaluated at the cell corners), std bound 0.01 everywhere with
a Gaussian-tail stand-in error model (no GP import: this times ``abstract`` only).
Noise: the paper's truncated Gaussian (sigma = bound = 0.01) and, to show the cost of
unbounded noise, a Gaussian with sigma = 0.01.

Writes benchmarks/results/abstraction.json and .md: median wall time over repeats, peak
traced memory (tracemalloc, separate run), non-zeros per row.

Usage: python benchmarks/abstraction.py [--quick] [--repeats N]
"""

from __future__ import annotations

import os
import argparse
import json
import platform
import statistics
import time
import tracemalloc
from pathlib import Path

import numpy as np

from robust_imdp.abstraction.rows import CellBounds, abstract
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise

OUT = Path(__file__).parent / "results"


class TailModel:
    """Stand-in error model: P[sup |g - mu| <= eps] >= 1 - 2 exp(-(eps/s)^2/2)."""

    def prob_within(self, eps, std_upper):
        eps, s = np.broadcast_arrays(np.asarray(eps, float), np.asarray(std_upper, float))
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(s > 0, eps / s, np.inf)
        p = 1.0 - 2.0 * np.exp(-0.5 * r * r)
        return np.clip(np.where(p < 1, np.nextafter(p - 1e-15, -np.inf), 1.0), 0.0, 1.0)

    def eps_for_prob(self, p, std_upper):
        return np.asarray(std_upper, float) * np.sqrt(2.0 * np.log(2.0 / (1.0 - np.asarray(p, float))))


def problem(n_per_dim: int, d: int, n_modes: int = 4):
    P = Partition(Box([-2.0] * d, [2.0] * d), 4.0 / n_per_dim)
    L, U = P.cells_lower, P.cells_upper
    # f(x)_i = 0.8 x_i + 0.05 x_{i+1}^3 (+ shift): increasing in every variable -> exact box
    lo = 0.8 * L + 0.05 * np.roll(L, -1, axis=1) ** 3
    hi = 0.8 * U + 0.05 * np.roll(U, -1, axis=1) ** 3
    shifts = 0.3 * np.eye(d)[np.arange(n_modes) % d] * np.where(np.arange(n_modes) >= d, -1, 1)[:, None]
    image_lo = np.stack([lo + s for s in shifts])
    image_hi = np.stack([hi + s for s in shifts])
    cb = CellBounds(image_lo, image_hi, np.full(image_lo.shape, 0.01))
    models = [[TailModel()] * d for _ in range(n_modes)]
    return P, cb, models


def run_case(n, d, noise_name, rule, repeats):
    P, cb, models = problem(n, d)
    noise = (TruncatedGaussianNoise([0.01] * d, [0.01] * d) if noise_name == "truncated"
             else GaussianNoise([0.01] * d))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        ab = abstract(P, cb, noise, models, eps_rule=rule)
        times.append(time.perf_counter() - t0)
    tracemalloc.start()
    abstract(P, cb, noise, models, eps_rule=rule)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    nnz_row = ab.nnz_per_row[: P.n_cells * 4]
    return {
        "grid": "x".join([str(n)] * d), "n_cells": P.n_cells, "n_modes": 4, "noise": noise_name, "eps_rule": rule,
        "median_s": statistics.median(times), "repeats": repeats, "peak_traced_MB": peak / 2**20,
        "nnz": int(ab.imdp.nnz), "nnz_per_row_mean": float(nnz_row.mean()), "nnz_per_row_max": int(nnz_row.max()),
        "floor_median": float(np.median(ab.imdp.floor[: P.n_cells * 4])),
    }


def rule_comparison(n: int = 32):
    """Tightness: synthesis classes (yes/no/maybe) of "!obs U goal" under each rule (2-D, 4 modes)."""
    from robust_imdp.spec.dfa import ltlf_to_dfa
    from robust_imdp.models.geometry import Region
    from robust_imdp.synthesis.core import synthesize

    base, cb, models = problem(n, 2)
    regions = [Region("goal", (Box([0.5, 0.5], [1.5, 1.5]),)), Region("obs", (Box([-1.0, -0.25], [0.0, 0.25]),))]
    P = Partition(base.space, base.cell_size, regions)
    assert P.shape == base.shape  # region boundaries lie on the grid: same cells, same bounds
    dfa = ltlf_to_dfa("!obs U goal")
    out = []
    for noise_name, noise in (("truncated", TruncatedGaussianNoise([0.01] * 2, [0.01] * 2)),
                              ("gaussian", GaussianNoise([0.01] * 2))):
        for rule, combine in (("paper", "product"), ("optimized", "product"), ("optimized", "union")):
            ab = abstract(P, cb, noise, models, eps_rule=rule, combine=combine)
            syn = synthesize(ab.imdp, P.labels, P.atoms, dfa, threshold=0.9, outside_state=P.outside_state)
            cls = np.asarray(syn.classes).astype(str)
            out.append({"grid": f"{n}x{n}", "noise": noise_name, "eps_rule": rule, "combine": combine,
                        "yes": int(np.sum(cls == "yes")), "no": int(np.sum(cls == "no")),
                        "maybe": int(np.sum(cls == "maybe")), "mean_error": float(np.mean(syn.error))})
            print(json.dumps(out[-1]))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="only the 32x32 grid")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    grids = [(32, 2)] if args.quick else [(32, 2), (64, 2), (128, 2), (16, 3)]
    rows = []
    for n, d in grids:
        for noise_name, rule in (("truncated", "optimized"), ("truncated", "paper"), ("gaussian", "optimized")):
            reps = args.repeats if n ** d <= 4096 else 1
            r = run_case(n, d, noise_name, rule, reps)
            rows.append(r)
            print(json.dumps(r))
    classes = rule_comparison()
    meta = {"python": platform.python_version(), "numpy": np.__version__, "machine": platform.machine(),
            "note": os.environ.get("BENCH_NOTE", "2-core machine; median of the stated runs")}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "abstraction.json").write_text(json.dumps({"meta": meta, "results": rows, "classes": classes}, indent=2))
    lines = ["# Abstraction benchmark", "", meta["note"] + ".", "",
             "| grid | cells | modes | noise | rule | median s | runs | peak MB | nnz | nnz/row mean | max | floor (median) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['grid']} | {r['n_cells']} | {r['n_modes']} | {r['noise']} | {r['eps_rule']} | "
                     f"{r['median_s']:.3f} | {r['repeats']} | {r['peak_traced_MB']:.0f} | {r['nnz']} | "
                     f"{r['nnz_per_row_mean']:.1f} | {r['nnz_per_row_max']} | {r['floor_median']:.2e} |")
    lines += ["", "## Tightness: classes of `!obs U goal` (threshold 0.9), 32x32, 4 modes", "",
              "| noise | rule | combine | yes | no | maybe | mean error |", "|---|---|---|---|---|---|---|"]
    for r in classes:
        lines.append(f"| {r['noise']} | {r['eps_rule']} | {r['combine']} | {r['yes']} | {r['no']} | {r['maybe']} | "
                     f"{r['mean_error']:.4f} |")
    lines += ["", "Targets (issue 5): 1024 cells x 4 modes <= 1 s; 128x128 x 4 modes <= 30 s and <= 2 GB."]
    (OUT / "abstraction.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
