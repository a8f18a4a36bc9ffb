"""Sub-boxes per cell (``rkhs_model.MAX_SUB``) on the family's 3-D configurations at r/l 0.25 and 0.5 (issue 20).

The rule ``s = ceil(sqrt(B rho(t_max) / split_tol))`` asks for 6 pieces per axis at r/l 0.25 and 11 at
0.5 in 3-D; ``MAX_SUB`` caps ``s^d``. For each cap (pieces per axis 4, 5, 6, 8) and local pools of 100
points or all points, this bounds the family's sampled cells (first mode, all outputs) with
``split_tol = rkhs.SPLIT_TOL`` and reports the bound time of those cells and the slack over the optimal
range (median per side, first output). Times of one row are comparable within the run only.

    python benchmarks/archive/sub_cap.py [--ratios 0.25 0.5] [--caps 4 5 6 8]

Writes ``benchmarks/results/sub_cap.json`` and ``.md``.
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

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: the shared helpers
import family as F  # noqa: E402
from reference import results_record, write_results  # noqa: E402

from robust_imdp.bounds import rkhs, rkhs_model  # noqa: E402



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.25, 0.5])
    ap.add_argument("--caps", nargs="+", type=int, default=[4, 5, 6, 8], help="pieces per axis")
    ap.add_argument("--seed", type=int, default=20)
    args = ap.parse_args(argv)
    shipped = rkhs_model.MAX_SUB
    F.warm_up(args.seed)
    rows = []
    try:
        for r in args.ratios:
            c = F.middle_3d(r)
            sy = F.system(c, args.seed)
            part = sy["partition"]
            cells = F.slack_cells(sy)
            opt = F.optimal_ranges(sy, cells)
            X, Y, _ = sy["data"][0]
            A, b = sy["maps"][0]
            for local in (F.LOCAL_POINTS, None):
                for cap in args.caps:
                    rkhs_model.MAX_SUB = cap ** 3
                    t0 = time.perf_counter()
                    res = rkhs.bound_chunk(X, Y, A, b, part.cells_lower[cells], part.cells_upper[cells],
                                           lengthscale=sy["lengthscale"], rkhs_bound=sy["B"],
                                           noise_bound=np.full(3, sy["noise_bound"]), local_points=local,
                                           split_tol=rkhs.SPLIT_TOL)
                    row = {"key": F.key_of(c), "ratio": r, "local_points": local, "pieces_cap": cap,
                           "bound_seconds": time.perf_counter() - t0,
                           "slack_upper_median": float(np.median(res["upper"][:, 0] - opt["opt_up"])),
                           "slack_lower_median": float(np.median(opt["opt_lo"] - res["lower"][:, 0]))}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    finally:
        rkhs_model.MAX_SUB = shipped
    data = results_record(rows, max_sub_shipped=shipped)
    lines = ["# Sub-boxes per cell, family 3-D (`benchmarks/sub_cap.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}; the family's "
             f"{F.SLACK_CELLS[3]} sampled cells of each 3-D configuration, first mode (3 outputs bounded), "
             f"`split_tol = {rkhs.SPLIT_TOL}`; shipped `MAX_SUB = {shipped}`. Target: slack <= 0.002 at r/l 0.25, "
             "<= 0.005 at 0.5.", "",
             "| r/l | points | pieces per axis (cap) | bound s (sampled cells) | slack upper / lower |",
             "|---|---|---|---|---|"]
    for w in rows:
        lines.append(f"| {w['ratio']} | {'all' if w['local_points'] is None else w['local_points']} | "
                     f"{w['pieces_cap']} | {w['bound_seconds']:.2f} | {w['slack_upper_median']:.4f} / "
                     f"{w['slack_lower_median']:.4f} |")
    write_results("sub_cap", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
