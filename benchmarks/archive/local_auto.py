"""Local pools (100 points) against all points on the family's 3-D configurations (issue 20).

Measures what ``pipeline.LOCAL_AUTO`` decides for a mode with 1,024 points (the family's 3-D
configurations, ``benchmarks/family.py``): per r/l, both without and with sub-box certification,
the bound time of all modes and outputs, the slack over the optimal range (median per side over
the family's sampled cells, first mode and output) and Q_yes. Ratios are measured in one run.

    python benchmarks/archive/local_auto.py [--ratios 0.03 0.06 ...] [--split-ratios ...]

Writes ``benchmarks/results/local_auto.json`` and ``.md`` (``--name`` another name).
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

from robust_imdp.bounds import rkhs  # noqa: E402



def measure(sy: dict, cells, opt: dict, local, tol) -> dict:
    ob = F.our_boxes(sy, tol, local)
    lo, up = ob["lower"], ob["upper"]
    return {"local_points": local, "split_tol": tol, "bound_seconds": ob["seconds"], "q_yes": F.q_yes(sy, lo, up)["yes"],
            "slack_upper_median": float(np.median(up[0, cells, 0] - opt["opt_up"])),
            "slack_lower_median": float(np.median(opt["opt_lo"] - lo[0, cells, 0]))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ratios", nargs="*", type=float, default=[0.03, 0.06, 0.125, 0.25, 0.5])
    ap.add_argument("--split-ratios", nargs="*", type=float, default=[0.03, 0.06, 0.125])
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--name", default="local_auto", help="results file name (without .json / .md)")
    args = ap.parse_args(argv)
    F.warm_up(args.seed)
    rows = []
    t_all = time.perf_counter()
    for r in sorted(set(args.ratios) | set(args.split_ratios)):
        c = F.middle_3d(r)
        sy = F.system(c, args.seed)
        sy["dfa"] = F.ltlf_to_dfa(F.FORMULA)
        cells = F.slack_cells(sy)
        opt = F.optimal_ranges(sy, cells)
        for tol in ([None] if r in args.ratios else []) + ([rkhs.SPLIT_TOL] if r in args.split_ratios else []):
            for local in (F.LOCAL_POINTS, None):
                row = {"key": F.key_of(c), "ratio": r, "points_per_mode": sy["m"], **measure(sy, cells, opt, local, tol)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    data = results_record(rows, seconds=time.perf_counter() - t_all)
    lines = ["# Local pools against all points, family 3-D (`benchmarks/local_auto.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}; "
             "1,024 points per mode, 8^3 cells, 3 modes x 3 outputs.", "",
             "| r/l | split | local 100: bound s / slack up, lo / Q_yes | all points: bound s / slack up, lo / Q_yes "
             "| time ratio |", "|---|---|---|---|---|"]
    for i in range(0, len(rows), 2):
        a, b = rows[i], rows[i + 1]
        lines.append(f"| {a['ratio']} | {'yes' if a['split_tol'] else 'no'} | {a['bound_seconds']:.1f} / "
                     f"{a['slack_upper_median']:.4f}, {a['slack_lower_median']:.4f} / {a['q_yes']} | "
                     f"{b['bound_seconds']:.1f} / {b['slack_upper_median']:.4f}, {b['slack_lower_median']:.4f} / "
                     f"{b['q_yes']} | {b['bound_seconds'] / a['bound_seconds']:.2f} |")
    write_results(args.name, data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
