"""A 3-D case study at scale (issue 10): a unicycle with three turning modes on a 64^3 grid.

    python examples/unicycle_3d.py --out results/unicycle_3d [--workers N] [--cells-per-axis 64]

State (p_x, p_y, theta) in [0, 4]^2 x [-pi, pi]; modes turn left / go straight / turn right
(known: theta + omega_u); unknown: the motion 0.15 (cos theta, sin theta) and a cross current
0.04 sin p_y (learned from 10,000 samples per mode, local optimal certificates). Reach ``goal``
and never touch ``obs``. Writes the result files, slices of the classes at a few headings and
a Monte-Carlo validation summary into OUT.
"""

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402

from robust_imdp.casestudies.systems import true_system, write_problem_files  # noqa: E402
from robust_imdp.io.files import load_problem, save_result  # noqa: E402
from robust_imdp.pipeline.run import synthesize_from_data  # noqa: E402
from robust_imdp.validate import validate  # noqa: E402

NAME = "unicycle_3d"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("results") / NAME)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=None, help="local cores (default: all, in process)")
    ap.add_argument("--cells-per-axis", type=int, default=64, help="grid resolution (default 64: 262,144 cells)")
    ap.add_argument("--n-per-cell", type=int, default=4, help="Monte-Carlo runs per cell (0: no validation)")
    args = ap.parse_args(argv)
    problem = load_problem(write_problem_files(NAME, args.out / "problem", seed=args.seed))
    k = args.cells_per_axis
    problem = problem.replace(cell_size=(problem.space_upper - problem.space_lower) / k)
    t = time.perf_counter()
    result = synthesize_from_data(problem, abstraction_cache=args.out / "cache", workers=args.workers)
    print(f"pipeline: {time.perf_counter() - t:.1f} s")
    save_result(result, args.out)
    try:  # figures of 3-D results (slices) come with the plotting module's 3-D support
        from robust_imdp.plotting import save_figures

        save_figures(result, args.out)
    except Exception as exc:  # noqa: BLE001 - figures are optional here
        print(f"no figures: {exc}")
    print(result.summary())
    if args.n_per_cell > 0:
        rep = validate(result, true_system(NAME), n_per_cell=args.n_per_cell, max_steps=200, rng=args.seed)
        (args.out / "validation.txt").write_text(rep.summary() + "\n")
        print(rep.summary())


if __name__ == "__main__":
    main()
