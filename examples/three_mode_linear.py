"""The paper's first case study end to end: data -> guarantees -> figures -> Monte-Carlo check.

    python examples/three_mode_linear.py --out results/three_mode_linear

x+ = A_u x + v with three unknown linear modes, truncated Gaussian noise (sigma = 0.01),
200 samples per mode (fixed seed), X = [-2, 2]^2, grid 0.125, "G !obs & F des", threshold 0.95
(Jackson et al., HSCC 2021, Sec. 6.1). Writes into OUT: the problem file and data (problem/),
result.json / result.npz, partition / classes / p_low / error / trajectories PNGs, and
validation.txt.
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
from robust_imdp.plotting import save_figures  # noqa: E402
from robust_imdp.validate import simulate, validate  # noqa: E402

NAME = "three_mode_linear"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("results") / NAME)
    ap.add_argument("--seed", type=int, default=0, help="seed of the data and the simulations")
    ap.add_argument("--n-per-cell", type=int, default=50, help="Monte-Carlo runs per cell")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()

    problem_file = write_problem_files(NAME, args.out / "problem", seed=args.seed)
    problem = load_problem(problem_file)
    result = synthesize_from_data(problem, abstraction_cache=args.out / "cache")
    print(result.summary())

    system = true_system(NAME)
    report = validate(result, system, n_per_cell=args.n_per_cell, max_steps=100, rng=args.seed)
    print(report.summary())
    rng = np.random.default_rng(args.seed + 1)
    x0 = rng.uniform(-2.0, 2.0, size=(25, 2))
    runs = simulate(result, system, x0, max_steps=100, rng=rng, record=True)

    save_figures(result, args.out, trajectories=runs)
    (args.out / "validation.txt").write_text(report.summary() + "\n")
    save_result(result, args.out)  # result.json last: its presence means the run completed
    print(f"wrote {args.out}/result.json, figures and validation.txt "
          f"({time.perf_counter() - t0:.1f} s end to end)")


if __name__ == "__main__":
    main()
