"""Local pools grown by kernel weight, family 3-D (issue 20: can pools keep the far-but-correlated points cheaply?).

    python benchmarks/archive/grown_pools.py [--ratios 0.03 0.06 0.125 0.25] [--kappas 0.9 0.7 0.5]

Today a local pool is the 100 nearest points of every cell. Here a cell's pool is its k nearest points
with k the number of points whose kernel value at the cell centre is at least kappa, clipped to
[100, all] and rounded up to 100 / 200 / 400 / 800 / all (each bucket one ``bound_chunk`` call). Per
r/l (8^3 cells, 1,024 points per mode, no sub-boxes): bound time of all modes and outputs, Q_yes, the
slack over the optimal range on the family's sampled cells (first mode and output, median per side),
the mean pool size; against fixed pools of 100 and 400 and all points. An exploration for a follow-up
issue: nothing in the library uses grown pools.

Writes ``benchmarks/results/grown_pools.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: the shared helpers
import family as F  # noqa: E402
from reference import results_record, write_results  # noqa: E402

from robust_imdp.bounds import rkhs  # noqa: E402

BUCKETS = (100, 200, 400, 800)


def pool_sizes(X, lower, upper, lengthscale, kappa: float) -> np.ndarray:
    """Per cell: the bucketed count of points with k(centre, x_i) >= kappa (None-free ints; m = all points)."""
    m = X.shape[0]
    centres = 0.5 * (lower + upper)
    radius = float(np.sqrt(-2.0 * np.log(kappa)))  # k = exp(-|x - c|^2 / (2 l^2)) >= kappa
    counts = np.array([len(v) for v in cKDTree(X / lengthscale).query_ball_point(centres / lengthscale, radius)])
    out = np.full(counts.shape, m)
    for b in reversed(BUCKETS):
        out[counts <= b] = b
    return np.minimum(out, m)


def boxes(sy, sizes) -> dict:
    """Image boxes of every mode, cell and output with the per-cell pool sizes ``sizes`` (m: all points)."""
    part = sy["partition"]
    M, N, d = len(sy["data"]), part.n_cells, sy["dim"]
    lo, up = np.empty((M, N, d)), np.empty((M, N, d))
    t0 = time.perf_counter()
    for u, (X, Y, _) in enumerate(sy["data"]):
        A, b = sy["maps"][u]
        for k in np.unique(sizes):
            cells = np.flatnonzero(sizes == k)
            res = rkhs.bound_chunk(X, Y, A, b, part.cells_lower[cells], part.cells_upper[cells],
                                   lengthscale=sy["lengthscale"], rkhs_bound=sy["B"],
                                   noise_bound=np.full(d, sy["noise_bound"]),
                                   local_points=None if k >= X.shape[0] else int(k))
            lo[u, cells], up[u, cells] = res["lower"], res["upper"]
    return {"lower": lo, "upper": up, "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.03, 0.06, 0.125, 0.25])
    ap.add_argument("--kappas", nargs="+", type=float, default=[0.9, 0.7, 0.5])
    ap.add_argument("--seed", type=int, default=20)
    args = ap.parse_args(argv)
    F.warm_up(args.seed)
    rows = []
    for r in args.ratios:
        sy = F.system(F.middle_3d(r), args.seed)
        sy["dfa"] = F.ltlf_to_dfa(F.FORMULA)
        part, m = sy["partition"], sy["m"]
        cells = F.slack_cells(sy)
        opt = F.optimal_ranges(sy, cells)
        X0 = sy["data"][0][0]
        variants = [("pools 100", np.full(part.n_cells, 100)), ("pools 400", np.full(part.n_cells, 400)),
                    ("all points", np.full(part.n_cells, m))]
        variants += [(f"grown, kappa {k:g}", pool_sizes(X0, part.cells_lower, part.cells_upper, sy["lengthscale"], k))
                     for k in args.kappas]
        for name, sizes in variants:
            ob = boxes(sy, sizes)
            row = {"ratio": r, "variant": name, "mean_pool": float(np.mean(np.minimum(sizes, m))),
                   "bound_seconds": ob["seconds"], "q_yes": F.q_yes(sy, ob["lower"], ob["upper"])["yes"],
                   "slack_upper_median": float(np.median(ob["upper"][0, cells, 0] - opt["opt_up"])),
                   "slack_lower_median": float(np.median(opt["opt_lo"] - ob["lower"][0, cells, 0]))}
            rows.append(row)
            print(json.dumps(row), flush=True)
    data = results_record(rows)
    lines = ["# Local pools grown by kernel weight, family 3-D (`benchmarks/grown_pools.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}; 8^3 cells, 1,024 points "
             "per mode, 3 modes x 3 outputs, no sub-boxes. *grown, kappa*: each cell's pool is the points with "
             "kernel value >= kappa at its centre (at least 100; rounded up to 100/200/400/800/all).", "",
             "| r/l | pools | mean pool | bound s | Q_yes | slack upper / lower |", "|---|---|---|---|---|---|"]
    for w in rows:
        lines.append(f"| {w['ratio']} | {w['variant']} | {w['mean_pool']:.0f} | {w['bound_seconds']:.2f} | {w['q_yes']} | "
                     f"{w['slack_upper_median']:.4f} / {w['slack_lower_median']:.4f} |")
    write_results("grown_pools", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
