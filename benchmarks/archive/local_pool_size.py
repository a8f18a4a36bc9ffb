"""Local pool size against data density on the family's 3-D systems (issue 20: when do local pools lose cells?).

    python benchmarks/archive/local_pool_size.py [--ratios 0.03 0.06] [--densities 2 4 8] [--pools 100 200 400]

For each r/l and data density (points per cell; 8^3 cells, so 1,024 / 2,048 / 4,096 points per mode),
the bound time of all modes and outputs and Q_yes with local pools of each size and with all points,
and the median over the cell centres of the distance to the 100th-nearest point in lengthscales (the
proxy an adaptive all-points rule would read). Ratios are measured in one run.

Writes ``benchmarks/results/local_pool_size.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: the shared helpers
import family as F  # noqa: E402
from reference import results_record, write_results  # noqa: E402



def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.03, 0.06])
    ap.add_argument("--densities", nargs="+", type=float, default=[2, 4, 8])
    ap.add_argument("--pools", nargs="+", type=int, default=[100, 200, 400])
    ap.add_argument("--seed", type=int, default=20)
    args = ap.parse_args(argv)
    F.warm_up(args.seed)
    rows = []
    for r in args.ratios:
        for dens in args.densities:
            sy = F.system(F.middle_3d(r, dens), args.seed)
            sy["dfa"] = F.ltlf_to_dfa(F.FORMULA)
            part, l = sy["partition"], sy["lengthscale"]
            centres = 0.5 * (part.cells_lower + part.cells_upper)
            dist, _ = cKDTree(sy["data"][0][0] / l).query(centres / l, k=100)
            row = {"ratio": r, "density": dens, "points_per_mode": sy["m"],
                   "nn100_over_l_median": float(np.median(dist[:, -1])), "runs": []}
            for local in [*args.pools, None]:
                ob = F.our_boxes(sy, None, local)
                row["runs"].append({"local_points": local, "bound_seconds": ob["seconds"],
                                    "q_yes": F.q_yes(sy, ob["lower"], ob["upper"])["yes"]})
            rows.append(row)
            print(json.dumps(row), flush=True)
    data = results_record(rows)
    names = [str(p) for p in args.pools] + ["all"]
    lines = ["# Local pool size against data density, family 3-D (`benchmarks/local_pool_size.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}; 8^3 cells, 3 modes x "
             "3 outputs, no sub-boxes. Per pool size: Q_yes and bound seconds (all modes and outputs); "
             "*nn100 / l*: median over cell centres of the distance to the 100th-nearest point, in lengthscales.", "",
             "| r/l | points per mode | nn100 / l | " + " | ".join(f"pool {n}: Q_yes, s" for n in names) + " |",
             "|---|---|---|" + "---|" * len(names)]
    for w in rows:
        cells = " | ".join(f"{x['q_yes']}, {x['bound_seconds']:.2f}" for x in w["runs"])
        lines.append(f"| {w['ratio']} | {w['points_per_mode']} | {w['nn100_over_l_median']:.3f} | {cells} |")
    write_results("local_pool_size", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
