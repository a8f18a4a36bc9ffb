"""Q_yes against split_tol on the family's worst 2-D configuration (issue 20): can finer sub-boxes reach the optimal boxes?

    python benchmarks/archive/split_tol_sweep.py [--key d2-rl0.5-nz0.15-dn2] [--tols 0.0015 0.00075 0.0004]

Our cell bounds (``family.our_boxes``) at several ``split_tol`` against the per-cell optimal boxes
(``family.optimal_boxes``, the Q_yes ceiling of the family table): Q_yes, the slack of the sampled cells
(``family.slack_cells``, first mode and output, median per side over the optimal range) and the bound time.
Writes ``benchmarks/results/split_tol_sweep.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import family  # noqa: E402
from reference import results_record, write_results  # noqa: E402

SEED = 20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--key", default="d2-rl0.5-nz0.15-dn2")
    ap.add_argument("--tols", nargs="+", type=float, default=[0.0015, 0.00075, 0.0004])
    args = ap.parse_args(argv)
    c = next(c for c in family.configurations("full") if family.key_of(c) == args.key)
    family.warm_up(SEED)
    sy = family.system_with_dfa(c, SEED)
    cells = family.slack_cells(sy)
    opt = family.optimal_ranges(sy, cells)
    ob = family.optimal_boxes(sy)
    ceiling = int(family.q_yes(sy, ob["lower"], ob["upper"])["yes"])
    rows = []
    for tol in args.tols:
        ours = family.our_boxes(sy, tol)
        rows.append({"split_tol": tol, "q_yes": int(family.q_yes(sy, ours["lower"], ours["upper"])["yes"]),
                     "slack_upper": float(np.median(ours["upper"][0, cells, 0] - opt["opt_up"])),
                     "slack_lower": float(np.median(opt["opt_lo"] - ours["lower"][0, cells, 0])),
                     "bound_seconds": ours["seconds"]})
        print(rows[-1], flush=True)
    data = results_record({"key": args.key, "optimal_boxes_q_yes": ceiling, "rows": rows})
    lines = ["# Q_yes against split_tol (`benchmarks/split_tol_sweep.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}. Configuration "
             f"{args.key}; per-cell optimal boxes: Q_yes {ceiling} (target 0.95 of it: {0.95 * ceiling:.1f}).", "",
             "| split_tol | Q_yes | ratio vs optimal boxes | slack upper / lower | bound s |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['split_tol']:g} | {r['q_yes']} | {r['q_yes'] / ceiling:.3f} | {r['slack_upper']:.4f} / "
                     f"{r['slack_lower']:.4f} | {r['bound_seconds']:.1f} |")
    write_results("split_tol_sweep", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
