"""A 4-D vehicle: known kinematics, periodic heading, only the drag learned (16^4 = 65,536 cells).

    python examples/vehicle_4d.py --out results/vehicle_4d [--cells-per-axis 16] [--n-per-cell 4]

State (p_x, p_y, theta, v) in [0, 4]^2 x [-pi, pi) x [0, 0.8]; modes accelerate / brake / left / right.
Known (the problem file's ``f``): p' = p + v (cos theta, sin theta), theta' = theta + omega_u, the speed
update without drag; the heading is periodic; unknown: the drag -0.25 v|v| on v, learned from 5,000
samples per mode. Reach the band ``goal`` (p_y >= 3) and never touch ``obs``. Writes the result files,
figures (slices) and a Monte-Carlo validation summary into OUT.
"""

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

from robust_imdp.casestudies.systems import true_system, write_problem_files  # noqa: E402
from robust_imdp.io.files import load_problem, save_result  # noqa: E402
from robust_imdp.pipeline.run import synthesize_from_data  # noqa: E402
from robust_imdp.plotting import save_figures  # noqa: E402
from robust_imdp.validate import validate  # noqa: E402

NAME = "vehicle_4d"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("results") / NAME)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cells-per-axis", type=int, default=16, help="grid resolution (default 16: 65,536 cells)")
    ap.add_argument("--n-per-cell", type=int, default=4, help="Monte-Carlo runs per cell (0: no validation)")
    args = ap.parse_args(argv)
    problem = load_problem(write_problem_files(NAME, args.out / "problem", seed=args.seed))
    problem = problem.replace(cell_size=(problem.space_upper - problem.space_lower) / args.cells_per_axis)
    t = time.perf_counter()
    result = synthesize_from_data(problem, abstraction_cache=args.out / "cache")
    print(f"pipeline: {time.perf_counter() - t:.1f} s")
    save_result(result, args.out)
    save_figures(result, args.out)
    print(result.summary())
    if args.n_per_cell > 0:
        rep = validate(result, true_system(NAME), n_per_cell=args.n_per_cell, max_steps=200, rng=args.seed)
        (args.out / "validation.txt").write_text(rep.summary() + "\n")
        print(rep.summary())


if __name__ == "__main__":
    main()
