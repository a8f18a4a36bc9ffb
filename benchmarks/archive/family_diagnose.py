"""Where a family configuration loses Q_yes: the bound's slack, the local pools, or the target itself.

For each configuration of ``benchmarks/family.py`` (same seeded system and data) it computes Q_yes of

* ``reference``: the known-dynamics boxes (sound outer boxes of the true f_u + g);
* ``widened``: the reference widened per side by the *median* optimal excess of the sampled cells
  (the family's target denominator);
* ``optimal``: per cell, mode and output the max / min of the pointwise optimal bound (Scharnhorst
  et al.; our certified active-set optimum on degenerate cells, ALL data) over a grid of points in
  the cell. This is what the data allow cell by cell, an inner approximation of the optimal range
  (so a ceiling of what any certified method could reach, up to the grid); not a sound box;
* ``ours`` with ``split_tol`` None and ``rkhs.SPLIT_TOL`` (and, where the family uses local pools,
  the same with all points, ``local_points=None``).

Usage: ``python benchmarks/archive/family_diagnose.py KEY [KEY ...] [--grid N]``; writes
``benchmarks/results/family_diagnose.json`` (merged per key) and prints one line per configuration.
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

from robust_imdp.bounds import rkhs  # noqa: E402
from robust_imdp.spec.dfa import ltlf_to_dfa  # noqa: E402

OUT = F.OUT / "family_diagnose.json"


def run(key: str, seed: int, grid: int | None, splits: dict) -> dict:
    c = next(c for c in F.configurations("full") if F.key_of(c) == key)
    sy = F.system(c, seed)
    sy["dfa"] = ltlf_to_dfa(F.FORMULA)
    d = sy["dim"]
    g = grid or {1: 11, 2: 6, 3: 3}[d]
    t0 = time.perf_counter()
    tb = F.true_boxes(sy)
    out = {"key": key, "grid": g}
    out["reference"] = F.q_yes(sy, tb["outer_lo"], tb["outer_up"])["yes"]
    # the family's widening: median optimal excess of its sampled cells (same rng draws as run_config)
    cells = F.slack_cells(sy)
    opt_s = F.optimal_ranges(sy, cells)
    w_lo = max(0.0, F._median(opt_s["true_lo"] - opt_s["opt_lo"]))
    w_up = max(0.0, F._median(opt_s["opt_up"] - opt_s["true_up"]))
    out["widened"] = F.q_yes(sy, tb["outer_lo"] - w_lo, tb["outer_up"] + w_up)["yes"]
    t1 = time.perf_counter()
    ob = F.optimal_boxes(sy, g)
    out["optimal_seconds"] = time.perf_counter() - t1
    out["optimal"] = F.q_yes(sy, ob["lower"], ob["upper"])["yes"]
    exc = np.concatenate([(ob["upper"] - tb["inner_up"]).ravel(), (tb["inner_lo"] - ob["lower"]).ravel()])
    out["optimal_excess_quantiles"] = [float(v) for v in np.quantile(exc, [0.1, 0.5, 0.9, 0.99])]
    for name, tol in splits.items():
        for local in ([F.LOCAL_POINTS, None] if sy["m"] > F.LOCAL_AUTO else [None]):
            t2 = time.perf_counter()
            lo_all, up_all = [], []
            for u, (X, Y, _) in enumerate(sy["data"]):
                A, b = sy["maps"][u]
                res = rkhs.bound_chunk(X, Y, A, b, sy["partition"].cells_lower, sy["partition"].cells_upper,
                                       lengthscale=sy["lengthscale"], rkhs_bound=sy["B"],
                                       noise_bound=np.full(d, sy["noise_bound"]), local_points=local, split_tol=tol)
                lo_all.append(res["lower"])
                up_all.append(res["upper"])
            lo, up = np.stack(lo_all), np.stack(up_all)
            tag = name + ("" if local is None else f"-local{local}")
            out[f"ours_{tag}"] = F.q_yes(sy, lo, up)["yes"]
            out[f"ours_{tag}_seconds"] = time.perf_counter() - t2
            # slack over the optimal boxes, per side, median over all cells / modes / outputs
            out[f"slack_{tag}"] = [F._median(up - ob["upper"]), F._median(ob["lower"] - lo)]
    out["seconds"] = time.perf_counter() - t0
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("keys", nargs="+")
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--grid", type=int, default=None)
    ap.add_argument("--split-tol", type=float, nargs="*", default=None,
                    help="split tolerances to run besides none (default: rkhs.SPLIT_TOL)")
    args = ap.parse_args(argv)
    splits = {"none": None}
    for t in (args.split_tol if args.split_tol is not None else [rkhs.SPLIT_TOL]):
        splits[f"split{t:g}"] = t
    data = json.loads(OUT.read_text()) if OUT.exists() else {}
    for key in args.keys:
        row = run(key, args.seed, args.grid, splits)
        data[key] = row
        print(json.dumps(row), flush=True)
        OUT.write_text(json.dumps(data, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
