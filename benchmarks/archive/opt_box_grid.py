"""How much of the family's Q_yes gap to the per-cell optimal boxes is the boxes' own grid? (issue 20)

    python benchmarks/archive/opt_box_grid.py [--only KEY ...]

The family's *optimal boxes* are the max / min of the pointwise optimal bound over a grid of points in
every cell (``family.optimal_boxes``, ``OPT_BOX_GRID`` per axis): an inner approximation of each cell's
optimal range, so their Q_yes is optimistic, by more where the function bends more between grid points
(large r/l). This script recomputes them on a grid of twice the points per axis minus one (every old point
kept) and sets our split Q_yes (``split_tol = SPLIT_TOL``, the pipeline's rule for the points) against
both. Writes ``benchmarks/results/opt_box_grid.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import family  # noqa: E402
from reference import results_record, write_results  # noqa: E402

SEED = 20
CONFIGS = {"d2-rl0.5-nz0.15-dn2": dict(dim=2, ratio=0.5, noise=0.15, density=2),
           "d2-rl0.25-nz0.15-dn2": dict(dim=2, ratio=0.25, noise=0.15, density=2),
           "d3-rl0.25-nz0.15-dn2": family.middle_3d(0.25)}


def main(argv=None) -> int:
    from robust_imdp.bounds import rkhs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=None)
    args = ap.parse_args(argv)
    family.warm_up(SEED)
    rows = []
    for key, c in family.chosen(CONFIGS, args.only):
        sy = family.system_with_dfa(c, SEED)
        g0 = family.OPT_BOX_GRID[sy["dim"]]
        row = {"key": key, "grids": {}}
        for g in (g0, 2 * g0 - 1):
            ob = family.optimal_boxes(sy, g)
            row["grids"][str(g)] = {"q_yes": int(family.q_yes(sy, ob["lower"], ob["upper"])["yes"]),
                                    "seconds": ob["seconds"]}
        ours = family.our_boxes(sy, rkhs.SPLIT_TOL)
        row["ours_split"] = int(family.q_yes(sy, ours["lower"], ours["upper"])["yes"])
        row["ours_seconds"] = ours["seconds"]
        rows.append(row)
        print(row, flush=True)
    data = results_record(rows)
    lines = ["# The optimal boxes' grid and the family's Q_yes gap (`benchmarks/opt_box_grid.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}. Q_yes of the per-cell "
             "optimal boxes on two grids (points per axis; the finer grid holds every point of the coarser), and "
             "ours with `split_tol = SPLIT_TOL`; *ratio* = ours / optimal boxes.", "",
             "| config | optimal boxes, grid: Q_yes (s) | ours split | ratio per grid |", "|---|---|---|---|"]
    for r in rows:
        gs = r["grids"]
        lines.append(f"| {r['key']} | " + "; ".join(f"{g}: {v['q_yes']} ({v['seconds']:.0f} s)" for g, v in gs.items())
                     + f" | {r['ours_split']} | "
                     + "; ".join(f"{g}: {r['ours_split'] / v['q_yes']:.3f}" for g, v in gs.items()) + " |")
    write_results("opt_box_grid", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
